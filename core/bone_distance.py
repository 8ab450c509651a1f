"""Signed distance to each bone: bones as solids, not shells of spheres (issues 12 and 14).

The paper's §3.3 turns bones into sets of spheres on their surface; a point carried past that
shell is inside the bone with nothing to tell it which way is out. Here every bone gets a signed
distance field, sampled once in the bone's rest frame from its closed triangle surface and moved
rigidly with the bone's 3x4 transform: a query point is mapped to the rest frame
(``q = R^T (x - t)``) and looked up there.

Sampling (:func:`bone_distance_field`). The bone's padded bounding box is cut into bricks of
``BRICK`` x ``BRICK`` x ``BRICK`` cells of ``spacing`` mm. A coarse grid of nodes ``COARSE *
spacing`` mm apart over the whole box holds the exact signed distance (used deep inside and far
outside); a brick whose centre is closer to the surface than ``band`` plus half its diagonal also
holds the exact distance at each of its ``(BRICK + 1)^3`` nodes (the narrow band, ``spacing``
apart), so every point within ``band`` mm of the surface is looked up in a fine brick. Values
are float32. The exact distance of a node is the distance to the nearest triangle (Ericson's
closest point on a triangle), found in a bounding volume hierarchy of the triangles (each
node starting from its neighbour's nearest triangle); its sign is that of ``(x - c) . n``
with ``c`` the closest point and ``n`` the angle-weighted pseudo-normal of the closest feature
(Baerentzen & Aanaes 2005: the face normal, the sum of the two face normals at an edge, the
angle-weighted sum at a vertex), which is exact for closed, manifold, outward-oriented
surfaces.

Lookup (:func:`signed_distances`): trilinear interpolation of the fine brick holding the point,
else of the coarse grid, and the gradient of that interpolant. Outside the sampled box (which
extends ``padding`` mm beyond the bone) the value is the box's value at the nearest box point
plus the distance to it, an upper bound no smaller than ``padding``, with the gradient pointing
away from the box. Interpolation error: nil on a flat piece of surface, about ``spacing^2 /
(8 R)`` near a surface of radius of curvature ``R``, at most about ``spacing / 2`` next to a
sharp edge of the mesh.

Pushing out (:func:`push_out_of_bones`): each point moves along the distance gradient until it
is ``radius`` outside every bone it is checked against, from whatever depth it starts (Newton
steps ``x += (radius - d) grad d``: one step for an exact distance, a few for the
interpolated one). The module stands apart from the solver; ``muscle_mss.filters`` uses it to keep
deformed muscle surfaces out of bones.

For a solver (issue 14): build the set once per rest bones (:func:`bone_field_set`, or the MVC
Surface Deformer's cached ``bone_fields``), and per pose call ``push_out_of_bones(fields,
centres, radii, transforms, active=~fixed)`` with the bones' (b, 3, 4) rest-to-posed
transforms (``muscle_mss.core.pose.pose_at``); add the returned (n, 3) displacements. Inside a
Numba loop, :func:`push_rest` / :func:`sample` take a bone index, a rest-frame point and
``*fields.arrays()``, and :func:`to_rest` maps a posed point to bone b's rest frame.
"""
from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numba
import numpy as np
from numba import njit, prange

from .disk_store import array_digest
from .errors import MuscleMSSError, checked_points
from .mesh_checks import checked_surface, surface_problems

BRICK = 8
"""Cells per brick edge: a fine brick holds ``(BRICK + 1)^3`` float32 values."""
COARSE = 4
"""Fine cells per coarse cell (the coarse grid, ``COARSE * spacing`` mm, covers the whole box)."""
DEFAULT_SPACING = 1.0
"""mm between the fine nodes of the narrow band."""
DEFAULT_BAND = 4.0
"""mm: every point closer than this to the surface (inside or out) is looked up in a fine brick.
Collision sphere radii of the demo muscles are below it."""
DEFAULT_PADDING = 8.0
"""mm the sampled box extends beyond the bone's bounding box."""
MAX_VALUES = 2 ** 26
"""Sampled values one bone's field may hold (256 MiB of float32): a finer spacing is refused
with an error rather than exhausting memory."""
PUSH_STEPS = 32
"""Newton steps per point and bone at most in :func:`push_out_of_bones`."""
PUSH_SWEEPS = 4
"""Passes over the bones per point at most (a push out of one bone may lead into another)."""

# Closest features of a triangle (a, b, c), as returned by _closest_on_triangle.
_FACE, _VERTEX_A, _VERTEX_B, _VERTEX_C, _EDGE_AB, _EDGE_BC, _EDGE_CA = range(7)


@dataclass(frozen=True)
class BoneDistanceField:
    """One bone's signed distance, sampled in its rest frame (see the module docstring).

    ``origin`` (3,) mm: the sampled box's lower corner; ``spacing`` mm between fine nodes;
    ``dims`` (3,) int64 bricks per axis (the box is ``dims * BRICK * spacing`` mm);
    ``coarse`` ((dims * BRICK // COARSE + 1).prod(),) float32 mm: the coarse nodes, x-major;
    ``brick_index`` (dims.prod(),) int32: each brick's fine block in ``bricks`` or -1;
    ``bricks`` (k, BRICK + 1, BRICK + 1, BRICK + 1) float32 mm: the fine nodes.
    """

    origin: np.ndarray
    spacing: float
    dims: np.ndarray
    coarse: np.ndarray
    brick_index: np.ndarray
    bricks: np.ndarray

    @property
    def nbytes(self) -> int:
        """Memory held by the sampled values (bytes)."""
        return self.coarse.nbytes + self.brick_index.nbytes + self.bricks.nbytes

    @property
    def error_bound(self) -> float:
        """mm: the most a looked-up value can differ from the exact signed distance. The
        distance changes by at most the move, so an interpolated value is within a cell's
        diagonal of the exact one (a coarse cell's, the larger), plus the float32 rounding of
        the values; outside the box the value is an upper bound of a positive distance."""
        return math.sqrt(3.0) * COARSE * self.spacing + 1e-6 * float(
            np.abs(self.coarse).max(initial=0.0))


@dataclass(frozen=True)
class BoneFieldSet:
    """The fields of several bones packed for the kernels: bone ``b``'s arrays start at
    ``coarse_start[b]``, ``index_start[b]``; ``brick_index`` entries are global rows of
    ``bricks`` (k, (BRICK + 1)^3) float32."""

    names: tuple
    origin: np.ndarray
    spacing: np.ndarray
    dims: np.ndarray
    coarse_start: np.ndarray
    coarse: np.ndarray
    index_start: np.ndarray
    brick_index: np.ndarray
    bricks: np.ndarray

    @classmethod
    def pack(cls, fields, names=None) -> "BoneFieldSet":
        """Pack :class:`BoneDistanceField` objects (in bone order) into one set."""
        fields = list(fields)
        names = tuple(names) if names is not None else tuple(str(i) for i in range(len(fields)))
        coarse_start = np.cumsum([0] + [len(f.coarse) for f in fields])[:-1].astype(np.int64)
        index_start = np.cumsum([0] + [len(f.brick_index) for f in fields])[:-1].astype(np.int64)
        brick_start = np.cumsum([0] + [len(f.bricks) for f in fields])[:-1]
        indices = [np.where(f.brick_index >= 0, f.brick_index + s, -1).astype(np.int32)
                   for f, s in zip(fields, brick_start)]
        nodes = (BRICK + 1) ** 3
        return cls(
            names=names,
            origin=np.array([f.origin for f in fields], dtype=np.float64).reshape(-1, 3),
            spacing=np.array([f.spacing for f in fields], dtype=np.float64),
            dims=np.array([f.dims for f in fields], dtype=np.int64).reshape(-1, 3),
            coarse_start=coarse_start,
            coarse=np.concatenate([f.coarse for f in fields] + [np.zeros(0, np.float32)]),
            index_start=index_start,
            brick_index=np.concatenate(indices + [np.zeros(0, np.int32)]),
            bricks=np.concatenate([f.bricks.reshape(-1, nodes) for f in fields]
                                  + [np.zeros((0, nodes), np.float32)]))

    def __len__(self):
        return len(self.names)

    def arrays(self):
        """The packed arrays in the order the kernels take them."""
        return (self.origin, self.spacing, self.dims, self.coarse_start, self.coarse,
                self.index_start, self.brick_index, self.bricks)


@dataclass
class BoneSolids:
    """Bones as solids for the solvers' muscle-bone contacts (instead of their sphere sets):
    ``fields`` a :class:`BoneFieldSet` of b bones sampled in their own frames, ``transforms``
    (b, 3, 4) each bone's field frame to its posed place, and ``clearance`` (b,) mm that every
    muscle sphere keeps from the bone's surface beyond its own radius (the radius of the bone's
    spheres, the paper's bone thickness: a sphere clear of the solid is clear of the sphere set
    too). Particles inside a bone at rest have no sphere (the Rigid Pose Transform clears them,
    :func:`muscle_mss.filters.bone_sets.clear_of_bones`), so no solid pushes them."""

    fields: BoneFieldSet
    transforms: np.ndarray
    clearance: np.ndarray

    def check(self) -> None:
        """Raise :class:`MuscleMSSError` unless there is one finite 3x4 transform and one finite
        clearance of 0 mm or more per bone."""
        b = len(self.fields)
        transforms = np.asarray(self.transforms)
        clearance = np.asarray(self.clearance)
        if transforms.shape != (b, 3, 4) or not np.isfinite(transforms).all():
            raise MuscleMSSError(f"the bone solids need one finite 3x4 transform per bone ({b}); "
                                 f"got shape {transforms.shape}")
        if clearance.shape != (b,) or not (np.isfinite(clearance).all()
                                           and (clearance >= 0).all()):
            raise MuscleMSSError(f"the bone solids need one finite clearance of 0 mm or more per "
                                 f"bone ({b}); got {clearance}")

    @property
    def reach(self) -> float:
        """mm: the farthest a push out of a bone can move a point (half the largest sampled
        box's diagonal plus the largest clearance; 0 without bones)."""
        if not len(self.fields):
            return 0.0
        boxes = self.fields.dims * BRICK * self.fields.spacing[:, None]
        return float(0.5 * np.linalg.norm(boxes, axis=1).max() + np.max(self.clearance))

    def kernel_arguments(self) -> tuple:
        """``(transforms, clearance, push tolerance mm, *fields.arrays())`` for the kernels;
        :data:`NO_SOLIDS` has the same types and no bone."""
        tolerance = 1e-3 * float(self.fields.spacing.min()) if len(self.fields) else 0.0
        return ((np.ascontiguousarray(self.transforms, dtype=np.float64),
                 np.ascontiguousarray(self.clearance, dtype=np.float64), tolerance)
                + self.fields.arrays())


# ---- exact distance to a triangle surface --------------------------------------------------

@njit(cache=True)
def _closest_on_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Closest point of triangle (a, b, c) to p and its feature (_FACE, _VERTEX_*, _EDGE_*):
    ``(squared distance, x, y, z, feature)`` (Ericson, Real-Time Collision Detection §5.1.5)."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    qx, qy, qz, feature = ax, ay, az, _VERTEX_A
    if not (d1 <= 0.0 and d2 <= 0.0):
        bpx, bpy, bpz = px - bx, py - by, pz - bz
        d3 = abx * bpx + aby * bpy + abz * bpz
        d4 = acx * bpx + acy * bpy + acz * bpz
        cpx, cpy, cpz = px - cx, py - cy, pz - cz
        d5 = abx * cpx + aby * cpy + abz * cpz
        d6 = acx * cpx + acy * cpy + acz * cpz
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d3 >= 0.0 and d4 <= d3:
            qx, qy, qz, feature = bx, by, bz, _VERTEX_B
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            v = d1 / (d1 - d3) if d1 - d3 > 0.0 else 0.0
            qx, qy, qz, feature = ax + v * abx, ay + v * aby, az + v * abz, _EDGE_AB
        elif d6 >= 0.0 and d5 <= d6:
            qx, qy, qz, feature = cx, cy, cz, _VERTEX_C
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
            w = d2 / (d2 - d6) if d2 - d6 > 0.0 else 0.0
            qx, qy, qz, feature = ax + w * acx, ay + w * acy, az + w * acz, _EDGE_CA
        elif va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
            den = (d4 - d3) + (d5 - d6)
            w = (d4 - d3) / den if den > 0.0 else 0.0
            qx, qy, qz, feature = bx + w * (cx - bx), by + w * (cy - by), bz + w * (cz - bz), \
                _EDGE_BC
        else:
            den = va + vb + vc
            v = vb / den if den != 0.0 else 0.0
            w = vc / den if den != 0.0 else 0.0
            qx, qy, qz = ax + v * abx + w * acx, ay + v * aby + w * acy, az + v * abz + w * acz
            feature = _FACE
    dx, dy, dz = px - qx, py - qy, pz - qz
    return dx * dx + dy * dy + dz * dz, qx, qy, qz, feature


LEAF_SIZE = 4
"""Triangles per leaf of the bounding volume hierarchy at most."""
_STACK = 64
"""Depth of the traversal stack (a median-split tree of 2^40 leaves would need 40)."""


@njit(cache=True)
def _box_distance_sq(px, py, pz, low, high, node):
    gx = max(max(low[node, 0] - px, px - high[node, 0]), 0.0)
    gy = max(max(low[node, 1] - py, py - high[node, 1]), 0.0)
    gz = max(max(low[node, 2] - pz, pz - high[node, 2]), 0.0)
    return gx * gx + gy * gy + gz * gz


@njit(cache=True)
def _nearest_signed(px, py, pz, hint, stack, points, triangles, face_normals, edge_normals,
                    vertex_normals, low, high, child, first, count, order):
    """Exact signed distance (mm, negative inside) of p to the surface and its nearest
    triangle, found in the bounding volume hierarchy (node n: box ``low[n]``..``high[n]``;
    inner nodes have children ``child[n]`` and ``child[n] + 1``, leaves (child -1) hold
    ``order[first[n]:first[n] + count[n]]``), nearer child first, boxes farther than the best
    triangle so far skipped. A ``hint`` triangle (>= 0; a neighbouring point's nearest) starts
    the search with a tight bound. ``stack`` (_STACK,) int64 is scratch."""
    best = np.inf
    bx = by = bz = 0.0
    bt = -1
    bf = 0
    if hint >= 0:
        a, b, e = triangles[hint, 0], triangles[hint, 1], triangles[hint, 2]
        best, bx, by, bz, bf = _closest_on_triangle(
            px, py, pz, points[a, 0], points[a, 1], points[a, 2], points[b, 0], points[b, 1],
            points[b, 2], points[e, 0], points[e, 1], points[e, 2])
        bt = hint
    top = 0
    stack[0] = 0
    while top >= 0:
        node = stack[top]
        top -= 1
        if _box_distance_sq(px, py, pz, low, high, node) >= best:
            continue
        if child[node] < 0:
            for s in range(first[node], first[node] + count[node]):
                t = order[s]
                a, b, e = triangles[t, 0], triangles[t, 1], triangles[t, 2]
                d2, qx, qy, qz, f = _closest_on_triangle(
                    px, py, pz, points[a, 0], points[a, 1], points[a, 2],
                    points[b, 0], points[b, 1], points[b, 2],
                    points[e, 0], points[e, 1], points[e, 2])
                if d2 < best:
                    best, bx, by, bz, bt, bf = d2, qx, qy, qz, t, f
            continue
        left = child[node]
        near, far = left, left + 1
        if _box_distance_sq(px, py, pz, low, high, far) < \
                _box_distance_sq(px, py, pz, low, high, near):
            near, far = far, near
        stack[top + 1] = far
        stack[top + 2] = near
        top += 2
    if bf == _FACE:
        nx, ny, nz = face_normals[bt, 0], face_normals[bt, 1], face_normals[bt, 2]
    elif bf <= _VERTEX_C:
        v = triangles[bt, bf - _VERTEX_A]
        nx, ny, nz = vertex_normals[v, 0], vertex_normals[v, 1], vertex_normals[v, 2]
    else:
        e = bf - _EDGE_AB
        nx, ny, nz = edge_normals[bt, e, 0], edge_normals[bt, e, 1], edge_normals[bt, e, 2]
    distance = math.sqrt(best)
    if (px - bx) * nx + (py - by) * ny + (pz - bz) * nz < 0.0:
        return -distance, bt
    return distance, bt


@njit(parallel=True, cache=True)
def _exact_at(queries, chunks, points, triangles, face_normals, edge_normals, vertex_normals,
              low, high, child, first, count, order, out):
    """Exact values at ``queries`` (q, 3), in ``chunks`` runs of consecutive queries; within a
    run each query starts from the previous one's nearest triangle (fast for grid-ordered
    queries, exact for any order)."""
    n = queries.shape[0]
    for c in prange(chunks):
        stack = np.empty(_STACK, dtype=np.int64)
        hint = -1
        for q in range(c * n // chunks, (c + 1) * n // chunks):
            out[q], hint = _nearest_signed(queries[q, 0], queries[q, 1], queries[q, 2], hint,
                                           stack, points, triangles, face_normals, edge_normals,
                                           vertex_normals, low, high, child, first, count, order)


@njit(parallel=True, cache=True)
def _exact_at_bricks(bricks, origin, spacing, points, triangles, face_normals, edge_normals,
                     vertex_normals, low, high, child, first, count, order, out):
    """Fill ``out`` (k, BRICK + 1, BRICK + 1, BRICK + 1) with the exact values at the fine
    nodes of the bricks ``bricks`` (k, 3) int (brick coordinates); each node starts from its
    neighbour's nearest triangle."""
    n = BRICK + 1
    for s in prange(bricks.shape[0] * n):
        stack = np.empty(_STACK, dtype=np.int64)
        b = s // n
        a = s - b * n
        x = origin[0] + (bricks[b, 0] * BRICK + a) * spacing
        row = -1
        for j in range(n):
            y = origin[1] + (bricks[b, 1] * BRICK + j) * spacing
            hint = row
            for k in range(n):
                z = origin[2] + (bricks[b, 2] * BRICK + k) * spacing
                out[b, a, j, k], hint = _nearest_signed(x, y, z, hint, stack, points, triangles,
                                                        face_normals, edge_normals,
                                                        vertex_normals, low, high, child, first,
                                                        count, order)
                if k == 0:
                    row = hint


def _hierarchy(points, triangles):
    """A bounding volume hierarchy of the triangles: each node's triangles split at the median
    of their centroids along their longest extent, leaves of at most LEAF_SIZE, the two
    children of a node stored side by side. Returns ``(low, high, child, first, count,
    order)`` as :func:`_nearest_signed` takes them."""
    m = len(triangles)
    corners = points[triangles]                       # (m, 3, 3)
    size = 2 * m + 1
    low, high = np.empty((size, 3)), np.empty((size, 3))
    child = np.full(size, -1, dtype=np.int64)
    first, count = np.zeros(size, dtype=np.int64), np.zeros(size, dtype=np.int64)
    order = np.arange(m, dtype=np.int64)
    nodes = _split_nodes(corners.min(axis=1), corners.max(axis=1), corners.mean(axis=1),
                         LEAF_SIZE, low, high, child, first, count, order)
    return low[:nodes], high[:nodes], child[:nodes], first[:nodes], count[:nodes], order


@njit(cache=True)
def _split_nodes(tri_low, tri_high, centroid, leaf_size, low, high, child, first, count,
                 order):
    """Build :func:`_hierarchy`'s nodes in place from the triangles' boxes ``tri_low``,
    ``tri_high`` and ``centroid`` (m, 3); returns the number of nodes (a Python loop over the
    nodes took 0.3 s a bone of the demo thigh)."""
    m = centroid.shape[0]
    count[0] = m
    pending = np.empty(low.shape[0], dtype=np.int64)
    pending[0] = 0
    top, nodes = 1, 1
    lowest = np.empty(3)
    highest = np.empty(3)
    c_low = np.empty(3)
    c_high = np.empty(3)
    while top > 0:
        top -= 1
        node = pending[top]
        start, n = first[node], count[node]
        lowest[:] = np.inf
        highest[:] = -np.inf
        c_low[:] = np.inf
        c_high[:] = -np.inf
        for i in range(start, start + n):
            t = order[i]
            for axis in range(3):
                lowest[axis] = min(lowest[axis], tri_low[t, axis])
                highest[axis] = max(highest[axis], tri_high[t, axis])
                c_low[axis] = min(c_low[axis], centroid[t, axis])
                c_high[axis] = max(c_high[axis], centroid[t, axis])
        low[node] = lowest
        high[node] = highest
        if n <= leaf_size:
            continue
        axis = int(np.argmax(c_high - c_low))
        middle = n // 2
        keys = np.empty(n)
        for i in range(n):
            keys[i] = centroid[order[start + i], axis]
        members = order[start:start + n][np.argsort(keys, kind="mergesort")]
        order[start:start + n] = members
        child[node] = nodes
        first[nodes], count[nodes] = start, middle
        first[nodes + 1], count[nodes + 1] = start + middle, n - middle
        pending[top] = nodes
        pending[top + 1] = nodes + 1
        top += 2
        nodes += 2
    return nodes


def _pseudo_normals(points, triangles):
    """Unit face normals (m, 3), edge pseudo-normals (m, 3, 3) (edge e of triangle t runs from
    corner e to corner e + 1; the sum of the normals of the two triangles sharing it) and
    angle-weighted vertex pseudo-normals (n, 3) of a closed manifold surface."""
    a, b, c = (points[triangles[:, k]] for k in range(3))
    cross = np.cross(b - a, c - a)
    length = np.linalg.norm(cross, axis=1, keepdims=True)
    face = np.divide(cross, length, out=np.zeros_like(cross), where=length > 0)
    corners = np.stack([a, b, c], axis=1)
    vertex = np.zeros_like(points)
    for k in range(3):
        u = corners[:, (k + 1) % 3] - corners[:, k]
        w = corners[:, (k + 2) % 3] - corners[:, k]
        nu = np.linalg.norm(u, axis=1)
        nw = np.linalg.norm(w, axis=1)
        ok = (nu > 0) & (nw > 0)
        cosine = np.ones(len(u))
        cosine[ok] = np.einsum("ij,ij->i", u[ok], w[ok]) / (nu[ok] * nw[ok])
        angle = np.arccos(np.clip(cosine, -1.0, 1.0))
        np.add.at(vertex, triangles[:, k], angle[:, None] * face)
    m = len(triangles)
    start = triangles.reshape(-1)
    end = triangles[:, [1, 2, 0]].reshape(-1)
    key = np.minimum(start, end) * len(points) + np.maximum(start, end)
    order = np.argsort(key, kind="stable")
    # A closed manifold surface has every edge exactly twice (surface_problems checked it).
    first, second = order[0::2], order[1::2]
    other = np.empty(3 * m, dtype=np.int64)
    other[first] = second // 3
    other[second] = first // 3
    edge = (face[:, None, :] + face[other.reshape(m, 3)]).copy()
    return face, edge, vertex


def surface_digest(points, triangles) -> str:
    """A digest of a triangle surface, bitwise: its points (n, 3) float64 and triangles (m, 3)
    int64 (:func:`~muscle_mss.core.disk_store.array_digest`)."""
    return array_digest(np.asarray(triangles, dtype=np.int64),
                        np.asarray(points, dtype=np.float64))


# The last surfaces prepared for exact distances (digest -> _Surface): the Spring Builder and
# the Rigid Pose Transform both test the same rest bones, and the hierarchy costs 0.3 s a bone
# of the demo thigh.
_SURFACES = OrderedDict()
SURFACES_KEPT = 8


def _prepared_surface(points, triangles, where) -> "_Surface":
    """:class:`_Surface` of ``points``, ``triangles``, the same one while the surface is the
    same bitwise (errors are raised each time)."""
    points, triangles = checked_surface(points, triangles, where)
    key = surface_digest(points, triangles)
    if key in _SURFACES:
        _SURFACES.move_to_end(key)
        return _SURFACES[key]
    surface = _Surface(points, triangles, where)
    _SURFACES[key] = surface
    while len(_SURFACES) > SURFACES_KEPT:
        _SURFACES.popitem(last=False)
    return surface


class _Surface:
    """A closed triangle surface ready for exact signed distances: pseudo-normals and a
    bounding volume hierarchy of its triangles."""

    def __init__(self, points, triangles, where):
        self.points, self.triangles = checked_surface(points, triangles, where)
        problems = surface_problems(self.points, self.triangles)
        if problems:
            raise MuscleMSSError(f"{where} {problems[0]}; a signed distance needs a closed, "
                                 "outward-oriented surface")
        self.normals = _pseudo_normals(self.points, self.triangles)
        self.hierarchy = _hierarchy(self.points, self.triangles)

    def kernel_arguments(self):
        return (self.points, self.triangles) + self.normals + self.hierarchy


def exact_signed_distance(points, triangles, queries, where="surface") -> np.ndarray:
    """Exact signed distance (mm, negative inside) of ``queries`` (q, 3) mm to the closed,
    outward-oriented triangle surface ``points`` (n, 3) mm, ``triangles`` (m, 3): the nearest
    triangle through a bounding volume hierarchy, the sign by pseudo-normals. Returns (q,)
    float64."""
    queries = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(queries).all():
        raise MuscleMSSError(f"{where}: the query points must have finite coordinates")
    surface = _prepared_surface(points, triangles, where)
    out = np.empty(len(queries))
    if len(queries):
        _exact_at(queries, _chunks(len(queries)), *surface.kernel_arguments(), out)
    return out


def inside_surface(points, triangles, queries, sampled, error_bound, where="surface"):
    """(q,) bool: which ``queries`` (q, 3) mm are inside the closed surface ``points``,
    ``triangles`` (its exact signed distance below 0), given ``sampled`` (q,) mm, their distance
    looked up in the surface's field, whose :attr:`BoneDistanceField.error_bound` is
    ``error_bound``: only the queries that the sampled value does not place farther out than
    that are measured exactly (the Spring Builder and the Rigid Pose Transform test every
    particle of the model against every bone: 0.6 s of the first time point at N = 80)."""
    queries = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
    sampled = np.asarray(sampled, dtype=np.float64).reshape(-1)
    inside = np.zeros(len(queries), dtype=bool)
    near = np.flatnonzero(~(sampled > error_bound))          # NaN is measured too
    if len(near):
        inside[near] = exact_signed_distance(points, triangles, queries[near], where) < 0.0
    return inside


def _chunks(n):
    """Runs of consecutive queries for :func:`_exact_at`: a few per thread."""
    return max(1, min(n, 8 * numba.get_num_threads()))


def bone_distance_field(points, triangles, spacing=DEFAULT_SPACING, band=DEFAULT_BAND,
                        padding=DEFAULT_PADDING, where="bone") -> BoneDistanceField:
    """Sample the signed distance of one bone in its rest frame (see the module docstring).

    Parameters
    ----------
    points : (n, 3) float64 mm, triangles : (m, 3) int
        The bone's closed, manifold, outward-oriented rest surface.
    spacing : float, mm
        Distance between the fine nodes near the surface.
    band : float, mm
        Every point closer than ``band`` to the surface is interpolated from fine nodes.
    padding : float, mm
        How far the sampled box extends beyond the bone's bounding box.
    where : str
        Names the bone in error messages, e.g. ``"bones.vtm block 'femur'"``.
    """
    for name, value in (("spacing", spacing), ("band", band), ("padding", padding)):
        if not (np.isfinite(value) and value > 0):
            raise MuscleMSSError(f"{where}: the distance field's {name} is {value}; it must be "
                                 "a positive number of mm")
    points, triangles = checked_surface(points, triangles, where)
    spacing = float(spacing)
    size = BRICK * spacing
    lower = points.min(axis=0) - padding
    dims = np.ceil((points.max(axis=0) + padding - lower) / size).astype(np.int64)
    surface = _prepared_surface(points, triangles, where)
    args = surface.kernel_arguments()
    _check_size(int(np.prod(dims * (BRICK // COARSE) + 1)), "coarse", spacing, where)
    axes = [lower[k] + COARSE * spacing * np.arange(dims[k] * BRICK // COARSE + 1)
            for k in range(3)]
    corners = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    coarse = np.empty(len(corners))
    _exact_at(corners, _chunks(len(corners)), *args, coarse)
    # Every point of a brick is within half a coarse cell's diagonal of one of the brick's
    # coarse nodes, and distance is 1-Lipschitz: a brick whose nodes are all farther than
    # band + that from the surface holds no point within band of it.
    per = BRICK // COARSE
    nodes = np.abs(coarse).reshape(tuple(dims * per + 1))
    nearest = np.full(tuple(dims), np.inf)
    for a in range(per + 1):
        for b in range(per + 1):
            for c in range(per + 1):
                nearest = np.minimum(nearest, nodes[a::per, b::per, c::per][:dims[0], :dims[1],
                                                                            :dims[2]])
    near = (nearest <= band + 0.5 * math.sqrt(3.0) * COARSE * spacing).reshape(-1)
    _check_size(int(near.sum()) * (BRICK + 1) ** 3, "fine", spacing, where)
    brick_index = np.full(len(near), -1, dtype=np.int32)
    brick_index[near] = np.arange(int(near.sum()), dtype=np.int32)
    coords = np.stack(np.unravel_index(np.flatnonzero(near), tuple(dims)), axis=1) \
        .astype(np.int64)
    fine = np.empty((len(coords), BRICK + 1, BRICK + 1, BRICK + 1), dtype=np.float64)
    if len(coords):
        _exact_at_bricks(coords, lower, spacing, *args, fine)
    return BoneDistanceField(origin=lower, spacing=spacing, dims=dims,
                             coarse=coarse.astype(np.float32), brick_index=brick_index,
                             bricks=fine.astype(np.float32))


def _check_size(values, kind, spacing, where):
    if values > MAX_VALUES:
        raise MuscleMSSError(f"{where}: a distance field with spacing {spacing:g} mm would hold "
                             f"{values:,} {kind} values (at most {MAX_VALUES:,}); choose a "
                             "larger spacing")


def bone_field_set(bones, spacing=DEFAULT_SPACING, band=DEFAULT_BAND, padding=DEFAULT_PADDING,
                   labels=None) -> BoneFieldSet:
    """Fields of every bone of ``bones`` (a list of ``(points, triangles)`` rest surfaces),
    packed; ``labels`` name the bones in errors and in ``BoneFieldSet.names``."""
    labels = list(labels) if labels is not None else [f"bone {i}" for i in range(len(bones))]
    return BoneFieldSet.pack([bone_distance_field(p, t, spacing, band, padding, where=label)
                              for (p, t), label in zip(bones, labels)], labels)


# ---- lookup ----------------------------------------------------------------------------------

@njit(cache=True)
def _trilinear(values, base, sx, sy, fx, fy, fz):
    """Value and gradient (per cell) of the trilinear interpolant of the cell whose corner
    (0, 0, 0) is ``values[base]`` (strides ``sx``, ``sy``, 1) at fractions (fx, fy, fz)."""
    c000 = values[base]
    c001 = values[base + 1]
    c010 = values[base + sy]
    c011 = values[base + sy + 1]
    c100 = values[base + sx]
    c101 = values[base + sx + 1]
    c110 = values[base + sx + sy]
    c111 = values[base + sx + sy + 1]
    gx0, gy0, gz0 = 1.0 - fx, 1.0 - fy, 1.0 - fz
    c00 = c000 * gz0 + c001 * fz
    c01 = c010 * gz0 + c011 * fz
    c10 = c100 * gz0 + c101 * fz
    c11 = c110 * gz0 + c111 * fz
    c0 = c00 * gy0 + c01 * fy
    c1 = c10 * gy0 + c11 * fy
    value = c0 * gx0 + c1 * fx
    dx = c1 - c0
    dy = (c01 - c00) * gx0 + (c11 - c10) * fx
    dz = ((c001 - c000) * gy0 + (c011 - c010) * fy) * gx0 \
        + ((c101 - c100) * gy0 + (c111 - c110) * fy) * fx
    return value, dx, dy, dz


@njit(cache=True)
def _sample_inside_box(b, ux, uy, uz, spacing, dims, coarse_start, coarse, index_start,
                       brick_index, bricks):
    """Value and rest-frame gradient at (ux, uy, uz), in fine cells from the box's origin
    (inside the box)."""
    nx, ny, nz = dims[b, 0], dims[b, 1], dims[b, 2]
    bi = min(int(ux / BRICK), nx - 1)
    bj = min(int(uy / BRICK), ny - 1)
    bk = min(int(uz / BRICK), nz - 1)
    block = brick_index[index_start[b] + (bi * ny + bj) * nz + bk]
    h = spacing[b]
    if block >= 0:
        lx, ly, lz = ux - bi * BRICK, uy - bj * BRICK, uz - bk * BRICK
        i = min(int(lx), BRICK - 1)
        j = min(int(ly), BRICK - 1)
        k = min(int(lz), BRICK - 1)
        n = BRICK + 1
        value, dx, dy, dz = _trilinear(bricks[block], (i * n + j) * n + k, n * n, n,
                                       lx - i, ly - j, lz - k)
        return value, dx / h, dy / h, dz / h
    per = BRICK // COARSE
    cx, cy, cz = ux / COARSE, uy / COARSE, uz / COARSE
    i = min(int(cx), nx * per - 1)
    j = min(int(cy), ny * per - 1)
    k = min(int(cz), nz * per - 1)
    sy = nz * per + 1
    sx = (ny * per + 1) * sy
    value, dx, dy, dz = _trilinear(coarse, coarse_start[b] + i * sx + j * sy + k, sx, sy,
                                   cx - i, cy - j, cz - k)
    size = COARSE * h
    return value, dx / size, dy / size, dz / size


@njit(cache=True)
def sample(b, qx, qy, qz, origin, spacing, dims, coarse_start, coarse, index_start,
            brick_index, bricks):
    """Signed distance (mm) and its gradient at rest-frame point q of bone b."""
    h = spacing[b]
    ux = (qx - origin[b, 0]) / h
    uy = (qy - origin[b, 1]) / h
    uz = (qz - origin[b, 2]) / h
    mx = dims[b, 0] * BRICK
    my = dims[b, 1] * BRICK
    mz = dims[b, 2] * BRICK
    cx = min(max(ux, 0.0), float(mx))
    cy = min(max(uy, 0.0), float(my))
    cz = min(max(uz, 0.0), float(mz))
    value, gx, gy, gz = _sample_inside_box(b, cx, cy, cz, spacing, dims, coarse_start, coarse,
                                           index_start, brick_index, bricks)
    ox, oy, oz = (ux - cx) * h, (uy - cy) * h, (uz - cz) * h
    away = math.sqrt(ox * ox + oy * oy + oz * oz)
    if away > 0.0:
        return value + away, ox / away, oy / away, oz / away
    return value, gx, gy, gz


@njit(cache=True)
def to_rest(transforms, b, x, y, z):
    """``R^T (x - t)`` for bone b's rest-to-posed transform ``transforms[b]`` (3, 4)."""
    m = transforms[b]
    dx, dy, dz = x - m[0, 3], y - m[1, 3], z - m[2, 3]
    return (m[0, 0] * dx + m[1, 0] * dy + m[2, 0] * dz,
            m[0, 1] * dx + m[1, 1] * dy + m[2, 1] * dz,
            m[0, 2] * dx + m[1, 2] * dy + m[2, 2] * dz)


@njit(parallel=True, cache=True)
def _signed_distances(points, transforms, origin, spacing, dims, coarse_start, coarse,
                      index_start, brick_index, bricks, distance, gradient):
    for p in prange(points.shape[0]):
        for b in range(transforms.shape[0]):
            qx, qy, qz = to_rest(transforms, b, points[p, 0], points[p, 1], points[p, 2])
            value, gx, gy, gz = sample(b, qx, qy, qz, origin, spacing, dims, coarse_start,
                                        coarse, index_start, brick_index, bricks)
            distance[p, b] = value
            m = transforms[b]
            for axis in range(3):
                gradient[p, b, axis] = m[axis, 0] * gx + m[axis, 1] * gy + m[axis, 2] * gz


def _checked_transforms(fields: BoneFieldSet, transforms) -> np.ndarray:
    if transforms is None:
        transforms = np.tile(np.eye(3, 4), (len(fields), 1, 1))
    transforms = np.ascontiguousarray(transforms, dtype=np.float64)
    if transforms.shape != (len(fields), 3, 4):
        raise MuscleMSSError(f"bone transforms must be ({len(fields)}, 3, 4), one rigid 3x4 "
                             f"per bone; got shape {transforms.shape}")
    if not np.isfinite(transforms).all():
        raise MuscleMSSError("bone transforms have NaN or infinite values")
    return transforms


def signed_distances(fields: BoneFieldSet, points, transforms=None):
    """Signed distance of ``points`` (n, 3) mm to every posed bone, and its gradient.

    ``transforms`` (b, 3, 4): each bone's rest-to-posed rigid transform ``x' = M[:, :3] x +
    M[:, 3]`` (None: the rest pose). Returns ``distance`` (n, b) float64 mm (negative inside)
    and ``gradient`` (n, b, 3) float64, unit length up to interpolation, in posed coordinates.
    """
    points = checked_points(points)
    transforms = _checked_transforms(fields, transforms)
    distance = np.empty((len(points), len(fields)))
    gradient = np.empty((len(points), len(fields), 3))
    if len(points) and len(fields):
        _signed_distances(points, transforms, *fields.arrays(), distance, gradient)
    return distance, gradient


# ---- pushing points out ----------------------------------------------------------------------

@njit(cache=True)
def push_rest(b, qx, qy, qz, radius, tolerance, origin, spacing, dims, coarse_start, coarse,
               index_start, brick_index, bricks):
    """Move rest-frame point q of bone b along the distance gradient until its distance is at
    least ``radius - tolerance``; returns the new q and whether it moved."""
    moved = False
    for _ in range(PUSH_STEPS):
        value, gx, gy, gz = sample(b, qx, qy, qz, origin, spacing, dims, coarse_start, coarse,
                                    index_start, brick_index, bricks)
        if value >= radius - tolerance:
            break
        norm = math.sqrt(gx * gx + gy * gy + gz * gz)
        if norm < 1e-9:
            # A point on a ridge of the field (e.g. a box's centre): the gradient cancels; go
            # the way, of the six axis directions one node away, the distance grows most.
            h = spacing[b]
            best = -np.inf
            for axis in range(6):
                sign = 1.0 if axis < 3 else -1.0
                ex = sign * h if axis % 3 == 0 else 0.0
                ey = sign * h if axis % 3 == 1 else 0.0
                ez = sign * h if axis % 3 == 2 else 0.0
                trial = sample(b, qx + ex, qy + ey, qz + ez, origin, spacing, dims,
                                coarse_start, coarse, index_start, brick_index, bricks)[0]
                if trial > best:
                    best, gx, gy, gz = trial, ex / h, ey / h, ez / h
            norm = 1.0
        step = (radius - value + 0.5 * tolerance) / norm
        qx += step * gx
        qy += step * gy
        qz += step * gz
        moved = True
    return qx, qy, qz, moved


@njit(parallel=True, cache=True)
def _push_out_of_bones(points, radii, active, transforms, tolerance, origin, spacing, dims,
                       coarse_start, coarse, index_start, brick_index, bricks, displacement):
    for p in prange(points.shape[0]):
        x, y, z = points[p, 0], points[p, 1], points[p, 2]
        for _ in range(PUSH_SWEEPS):
            any_moved = False
            for b in range(transforms.shape[0]):
                if active[p, b] == 0:
                    continue
                qx, qy, qz = to_rest(transforms, b, x, y, z)
                qx, qy, qz, moved = push_rest(b, qx, qy, qz, radii[p], tolerance, origin,
                                               spacing, dims, coarse_start, coarse, index_start,
                                               brick_index, bricks)
                if moved:
                    m = transforms[b]
                    x = m[0, 0] * qx + m[0, 1] * qy + m[0, 2] * qz + m[0, 3]
                    y = m[1, 0] * qx + m[1, 1] * qy + m[1, 2] * qz + m[1, 3]
                    z = m[2, 0] * qx + m[2, 1] * qy + m[2, 2] * qz + m[2, 3]
                    any_moved = True
            if not any_moved:
                break
        displacement[p, 0] = x - points[p, 0]
        displacement[p, 1] = y - points[p, 1]
        displacement[p, 2] = z - points[p, 2]


def push_out_of_bones(fields: BoneFieldSet, points, radii=None, transforms=None, active=None,
                      tolerance=None) -> np.ndarray:
    """Displacements that put every point ``radius`` outside every posed bone it is checked
    against, along the distance gradient, from whatever depth it starts.

    Parameters
    ----------
    fields : BoneFieldSet
        The bones' fields (:func:`bone_field_set`), b bones.
    points : (n, 3) float64 mm
        Posed positions: collision sphere centres, or surface vertices.
    radii : (n,) float64 mm, optional
        Clearance each point needs (its sphere radius); None or 0 puts a point on the surface.
    transforms : (b, 3, 4) float64, optional
        Each bone's rest-to-posed rigid transform (None: the rest pose).
    active : (n,) or (n, b) bool, optional
        Which points (or which point-bone pairs) to push; the others get a zero displacement
        (tendon attachments that belong inside their bone, surface vertices already inside a
        bone at rest). None: all.
    tolerance : float, mm, optional
        A point counts as out when its interpolated distance is at least ``radius -
        tolerance`` (default 1e-3 of the finest spacing).

    Returns
    -------
    (n, 3) float64 mm
        ``points + displacement`` is out of every checked bone (the interpolated distance at
        least ``radius - tolerance``) unless a point is held between two bones closer together
        than twice its radius; the displacement of a point already out is exactly 0.

    A point deeper than half the bone's thickness leaves by the nearer side, which is then the
    far side from where it came in: callers that move points into bones by small steps (a
    solver iteration) push them every step.
    """
    points = checked_points(points)
    n, b = len(points), len(fields)
    radii = np.zeros(n) if radii is None else \
        np.ascontiguousarray(np.broadcast_to(np.asarray(radii, dtype=np.float64), (n,)))
    if not np.isfinite(radii).all() or (radii < 0).any():
        raise MuscleMSSError("push out of bones: radii must be finite and 0 or more (mm)")
    transforms = _checked_transforms(fields, transforms)
    if active is None:
        mask = np.ones((n, b), dtype=np.uint8)
    else:
        active = np.asarray(active, dtype=bool)
        if active.shape not in ((n,), (n, b)):
            raise MuscleMSSError(f"push out of bones: active must have shape ({n},) or "
                                 f"({n}, {b}); got {active.shape}")
        mask = np.ascontiguousarray(np.broadcast_to(active.reshape(n, -1), (n, b)),
                                    dtype=np.uint8)
    if tolerance is None:
        tolerance = 1e-3 * float(fields.spacing.min()) if b else 0.0
    displacement = np.zeros((n, 3))
    if n and b:
        _push_out_of_bones(points, radii, mask, transforms, float(tolerance), *fields.arrays(),
                           displacement)
    return displacement


# ---- slow, obvious references for the tests ---------------------------------------------------

def reference_signed_distance(points, triangles, queries) -> np.ndarray:
    """Brute force: the distance to every triangle (projection on the plane when it falls inside
    the triangle, else the nearest point of the three edges), the smallest kept; inside where
    the generalized winding number (sum of the triangles' solid angles / 4 pi) exceeds 1/2.
    (q,) float64 mm, negative inside."""
    points = np.asarray(points, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    a, b, c = (points[triangles[:, k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    out = np.empty(len(queries))
    for q, x in enumerate(np.asarray(queries, dtype=np.float64)):
        height = np.einsum("ij,ij->i", x - a, normal)
        foot = x - height[:, None] * normal
        inside = np.ones(len(a), bool)
        for p0, p1 in ((a, b), (b, c), (c, a)):
            inside &= np.einsum("ij,ij->i", np.cross(p1 - p0, foot - p0), normal) >= 0
        best = np.where(inside, np.abs(height), np.inf)
        for p0, p1 in ((a, b), (b, c), (c, a)):
            edge = p1 - p0
            s = np.clip(np.einsum("ij,ij->i", x - p0, edge) / np.einsum("ij,ij->i", edge, edge),
                        0.0, 1.0)
            best = np.minimum(best, np.linalg.norm(x - (p0 + s[:, None] * edge), axis=1))
        ra, rb, rc = a - x, b - x, c - x
        la, lb, lc = (np.linalg.norm(r, axis=1) for r in (ra, rb, rc))
        numerator = np.einsum("ij,ij->i", ra, np.cross(rb, rc))
        denominator = (la * lb * lc + np.einsum("ij,ij->i", ra, rb) * lc
                       + np.einsum("ij,ij->i", rb, rc) * la + np.einsum("ij,ij->i", rc, ra) * lb)
        winding = np.sum(2.0 * np.arctan2(numerator, denominator)) / (4.0 * np.pi)
        out[q] = -best.min() if winding > 0.5 else best.min()
    return out


def reference_push_out(points, triangles, queries, radii) -> np.ndarray:
    """Brute force on the exact distance: each query moves to its nearest surface point plus
    ``radius`` along the outward direction there (the pseudo-normal's side), as often as it
    still lies closer than ``radius - 1e-9`` (at most 8 times). Rest frame, one bone; (q, 3)
    mm positions after the push."""
    points = np.asarray(points, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    out = np.array(queries, dtype=np.float64)
    for q in range(len(out)):
        for _ in range(8):
            d = reference_signed_distance(points, triangles, out[q:q + 1])[0]
            if d >= radii[q] - 1e-9:
                break
            h = 1e-5
            grad = np.array([(reference_signed_distance(points, triangles,
                                                        out[q:q + 1] + h * e)[0] - d) / h
                             for e in np.eye(3)])
            out[q] += (radii[q] - d) * grad / np.linalg.norm(grad)
    return out


NO_SOLIDS = BoneSolids(BoneFieldSet.pack([]), np.zeros((0, 3, 4)), np.zeros(0))
"""No bone as a solid (the kernels' argument when the bones are sphere sets)."""
