"""Closed triangle surfaces of implicit solids (DESIGN §4): the demo scenes' bones and the
attachment landmarks on them.

An implicit solid is a function of points (n, 3) mm, negative inside and roughly the signed
distance in mm near its surface (:mod:`.demo.geometry`'s primitives). It is sampled on a regular
grid (:class:`SampledField`) and meshed by marching tetrahedra on a Freudenthal (6-tetrahedra)
subdivision of the grid: the level set of a piecewise-linear function with no zero at a grid
node is a closed 2-manifold by construction (:func:`mesh_implicit`, :func:`mesh_sampled`).
:func:`project_to_surface` puts a landmark onto the implicit surface.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import map_coordinates
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..scene import Surface

# Freudenthal subdivision: one tetrahedron per permutation of the axes, walking from corner
# (0,0,0) to (1,1,1). All cubes use the same six, so the tetrahedra of neighbouring cubes share
# faces and the piecewise-linear level set has no cracks.
_CORNERS = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)])


def _freudenthal_tetrahedra():
    tets = []
    for order in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        corner = np.zeros(3, dtype=int)
        path = [0]
        for axis in order:
            corner[axis] = 1
            path.append(int(corner[0] * 4 + corner[1] * 2 + corner[2]))
        tets.append(path)
    return np.array(tets)


def _tetrahedron_cases():
    """(16, 2, 3, 2): for each inside/outside pattern of the 4 corners, up to two triangles,
    each as three crossing edges given by their two corner numbers (-1: no triangle)."""
    table = np.full((16, 2, 3, 2), -1)
    for code in range(1, 15):
        inside = [c for c in range(4) if code >> c & 1]
        outside = [c for c in range(4) if not code >> c & 1]
        if len(inside) == 2:
            (a, b), (c, d) = inside, outside
            table[code, 0] = [(a, c), (a, d), (b, d)]
            table[code, 1] = [(a, c), (b, d), (b, c)]
        else:
            lone = inside[0] if len(inside) == 1 else outside[0]
            table[code, 0] = [(lone, o) for o in range(4) if o != lone]
    return table


_TETRAHEDRA = _freudenthal_tetrahedra()
_CASES = _tetrahedron_cases()


@dataclass(frozen=True)
class SampledField:
    """An implicit function and its values on a regular grid.

    ``values`` (nx, ny, nz) float64 at the nodes ``lower + spacing * (i, j, k)`` (mm).
    """

    field: object
    lower: np.ndarray
    spacing: float
    values: np.ndarray

    @classmethod
    def sample(cls, field, lower, upper, spacing) -> "SampledField":
        lower = np.asarray(lower, dtype=np.float64)
        shape = np.ceil((np.asarray(upper) - lower) / spacing).astype(np.int64) + 1
        values = field(cls._nodes(lower, spacing, shape)).reshape(shape)
        # A zero at a node would let several crossing edges share one vertex (a non-manifold pinch).
        values[values == 0.0] = 1e-12
        return cls(field, lower, float(spacing), values)

    @staticmethod
    def _nodes(lower, spacing, shape):
        axes = [lower[d] + spacing * np.arange(shape[d]) for d in range(3)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)

    def nodes(self):
        return self._nodes(self.lower, self.spacing, self.values.shape)

    def interpolate(self, points):
        """Trilinear interpolation of the grid values at ``points`` (n, 3) mm; outside the grid
        the nearest boundary value (positive: outside the solid)."""
        coords = ((np.asarray(points) - self.lower) / self.spacing).T
        return map_coordinates(self.values, coords, order=1, mode="nearest")


def mesh_implicit(field, lower, upper, spacing) -> Surface:
    """Closed, manifold, outward triangle surface of ``{x : field(x) < 0}`` by marching tetrahedra.

    Parameters
    ----------
    field : callable, (n, 3) float64 mm -> (n,) float64, negative inside
    lower, upper : (3,) corners of a box (mm) on whose faces ``field`` is positive
    spacing : grid step (mm)

    Only the largest connected piece is kept. Vertices lie on the grid edges where the field
    changes sign, placed on its zero by regula falsi.
    """
    return mesh_sampled(SampledField.sample(field, lower, upper, spacing))


def mesh_sampled(sampled: SampledField) -> Surface:
    """:func:`mesh_implicit` of an already sampled field."""
    field, shape = sampled.field, np.array(sampled.values.shape)
    nodes = sampled.nodes()
    values = sampled.values.reshape(-1)
    inside = values < 0.0

    strides = np.array([shape[1] * shape[2], shape[2], 1])
    cube_origins = np.arange(nodes.shape[0]).reshape(shape)[:-1, :-1, :-1].reshape(-1)
    corners = cube_origins[:, None] + (_CORNERS @ strides)[None, :]
    corner_inside = inside[corners]
    mixed = corner_inside.any(axis=1) & ~corner_inside.all(axis=1)
    tets = corners[mixed][:, _TETRAHEDRA].reshape(-1, 4)
    code = (inside[tets] * (1 << np.arange(4))).sum(axis=1)

    edge_a, edge_b = [], []
    for slot in range(2):
        has = _CASES[code, slot, 0, 0] >= 0
        local = _CASES[code[has], slot]                       # (k, 3, 2)
        rows = np.arange(has.sum())[:, None]
        edge_a.append(tets[has][rows, local[:, :, 0]])
        edge_b.append(tets[has][rows, local[:, :, 1]])
    edge_a = np.concatenate(edge_a)
    edge_b = np.concatenate(edge_b)
    # Name each crossing edge by its inside node then its outside node.
    first_inside = inside[edge_a]
    inner = np.where(first_inside, edge_a, edge_b)
    outer = np.where(first_inside, edge_b, edge_a)
    keys = inner * nodes.shape[0] + outer
    unique_keys, triangles = np.unique(keys, return_inverse=True)
    triangles = triangles.reshape(-1, 3)
    n_in, n_out = unique_keys // nodes.shape[0], unique_keys % nodes.shape[0]

    lo_t, hi_t = np.zeros(len(unique_keys)), np.ones(len(unique_keys))
    lo_f, hi_f = values[n_in], values[n_out]
    p_in, p_out = nodes[n_in], nodes[n_out]
    t = lo_f / (lo_f - hi_f)
    linear = p_in + t[:, None] * (p_out - p_in)
    # Orient by the linear interpolant, whose level set in a tetrahedron is exactly the planar
    # triangle: its normal must point from the inside node to the outside node.
    normals = np.cross(linear[triangles[:, 1]] - linear[triangles[:, 0]],
                       linear[triangles[:, 2]] - linear[triangles[:, 0]])
    e = triangles[:, 0]
    flip = np.einsum("ij,ij->i", normals, p_out[e] - p_in[e]) < 0.0
    triangles[flip] = triangles[flip][:, ::-1]
    for _ in range(4):
        f = field(p_in + t[:, None] * (p_out - p_in))
        below = f < 0.0
        lo_t, lo_f = np.where(below, t, lo_t), np.where(below, f, lo_f)
        hi_t, hi_f = np.where(below, hi_t, t), np.where(below, hi_f, f)
        t = lo_t + (hi_t - lo_t) * lo_f / (lo_f - hi_f)
    points = p_in + t[:, None] * (p_out - p_in)
    return _largest_piece(points, triangles)


def _largest_piece(points, triangles) -> Surface:
    n = len(points)
    rows = np.concatenate([triangles[:, 0], triangles[:, 1]])
    cols = np.concatenate([triangles[:, 1], triangles[:, 2]])
    _, label = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)),
                                    directed=False)
    keep = label == np.argmax(np.bincount(label[triangles[:, 0]], minlength=label.max() + 1))
    new_index = np.cumsum(keep) - 1
    kept = triangles[keep[triangles[:, 0]]]
    return Surface(points[keep].copy(), new_index[kept].astype(np.int64))


def project_to_surface(field, point, steps: int = 8) -> np.ndarray:
    """The point of the implicit surface of ``field`` reached from ``point`` (mm) by Newton
    steps along the field's gradient (for landmarks within a few mm of the surface)."""
    x = np.asarray(point, dtype=np.float64).copy()
    h = 1e-4
    for _ in range(steps):
        f = field(x[None, :])[0]
        grad = (field(x + h * np.eye(3)) - f) / h
        x = x - f * grad / (grad @ grad)
    return x
