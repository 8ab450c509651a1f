"""The harmonic field inside a muscle surface that its generated fibres follow (DESIGN §6 "Fibre
generation"; :mod:`.fibre_generation` traces them).

* **Cells**: the centres of a regular grid of cubes, spaced for about :data:`CELLS` inside the
  surface (:func:`inside_cells`: each column of cells along z crossed by the triangles, the
  cells between an odd number of crossings inside); pockets apart from the muscle's body left
  out; where the inside does not join the two areas (a section narrower than a cell), the
  cells the surface's edges run through are added (:func:`edge_cells`).
* **Field**: on the inside cells, the 6-neighbour graph Laplacian is zero; cells on the
  boundary whose nearest surface vertex belongs to the origin area are held at 0, to the
  insertion area at 1; a neighbour outside is left out (no flux). Solved by conjugate
  gradients preconditioned by the diagonal to a relative residual of :data:`RESIDUAL`; a
  cell not connected to both areas is left out.

Arrays only (no VTK).
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy import ndimage, sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .errors import MuscleMSSError

CELLS = 40_000
"""Grid cells inside a muscle (the spacing follows its volume): about 10 across the demo's most
slender muscle."""
RESIDUAL = 1e-10
"""Relative residual at which the field's conjugate gradients stop."""
POCKET_SHARE = 0.05
"""Parts of the inside (6-connected cells) smaller than this share of it are left out: the
demo thigh's adductor magnus encloses a pocket of 0.4 % apart from its body."""
EDGE_STEP = 0.5
"""Samples along the surface's edges, in cells, that mark the cells an edge runs through (a
muscle whose section narrows below a cell: its cells joined along its surface)."""


class NotConnected(MuscleMSSError):
    """The inside cells do not join a muscle's origin area to its insertion area."""


@dataclass(frozen=True)
class HarmonicField:
    """``values`` (nx, ny, nz) at the cell centres ``origin + spacing * (i, j, k)`` (mm): the
    field inside (``inside``), outside the value of the nearest inside cell (so that the
    gradient at the surface has no normal part to first order); ``gradient`` (nx, ny, nz, 3)
    per mm; ``nearest_inside`` (3, nx, ny, nz) the grid index of each cell's nearest inside
    cell."""

    origin: np.ndarray
    spacing: float
    values: np.ndarray
    inside: np.ndarray
    gradient: np.ndarray
    nearest_inside: np.ndarray

    def _coordinates(self, points):
        return ((np.asarray(points, dtype=np.float64) - self.origin) / self.spacing).T

    def at(self, points) -> np.ndarray:
        """(n,) the field at ``points`` (n, 3) mm, trilinear."""
        return ndimage.map_coordinates(self.values, self._coordinates(points), order=1,
                                       mode="nearest")

    def gradient_at(self, points) -> np.ndarray:
        """(n, 3) per mm: the gradient at ``points`` (n, 3) mm, trilinear."""
        c = self._coordinates(points)
        return np.stack([ndimage.map_coordinates(self.gradient[..., a], c, order=1,
                                                 mode="nearest") for a in range(3)], axis=1)

    def pulled_inside(self, points) -> np.ndarray:
        """``points`` (n, 3) mm, those whose nearest cell is outside moved by the step from
        that cell to its nearest inside cell (two points stay apart)."""
        index = np.clip(np.rint(self._coordinates(points)).astype(np.int64), 0,
                        np.array(self.inside.shape)[:, None] - 1)
        out = ~self.inside[tuple(index)]
        if not out.any():
            return points
        points = np.array(points, dtype=np.float64)
        cells = self.nearest_inside[(slice(None),) + tuple(index[:, out])]
        points[out] += self.spacing * (cells - index[:, out]).T
        return points

    def direction(self, points) -> np.ndarray:
        """(n, 3) the unit gradient at ``points`` (zero where the gradient vanishes)."""
        g = self.gradient_at(points)
        norm = np.linalg.norm(g, axis=1, keepdims=True)
        return np.divide(g, norm, out=np.zeros_like(g), where=norm > 0)


@numba.njit(cache=True)
def _column_crossings(points, triangles, origin, spacing, flips):
    """Toggle ``flips[i, j, k]`` for each crossing of the column of cells (i, j) by a
    triangle, at the first cell above the crossing (serial: two triangles may toggle one
    cell; a muscle's triangles take milliseconds)."""
    nx, ny, nz = flips.shape
    for t in range(len(triangles)):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        ax, ay, az = points[a, 0], points[a, 1], points[a, 2]
        bx, by, bz = points[b, 0], points[b, 1], points[b, 2]
        cx, cy, cz = points[c, 0], points[c, 1], points[c, 2]
        area = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay)
        if area == 0.0:
            continue
        i0 = max(int(np.ceil((min(ax, bx, cx) - origin[0]) / spacing)), 0)
        i1 = min(int(np.floor((max(ax, bx, cx) - origin[0]) / spacing)), nx - 1)
        j0 = max(int(np.ceil((min(ay, by, cy) - origin[1]) / spacing)), 0)
        j1 = min(int(np.floor((max(ay, by, cy) - origin[1]) / spacing)), ny - 1)
        for i in range(i0, i1 + 1):
            x = origin[0] + i * spacing
            for j in range(j0, j1 + 1):
                y = origin[1] + j * spacing
                wa = ((bx - x) * (cy - y) - (cx - x) * (by - y)) / area
                wb = ((cx - x) * (ay - y) - (ax - x) * (cy - y)) / area
                wc = 1.0 - wa - wb
                if wa < 0.0 or wb < 0.0 or wc < 0.0:
                    continue
                z = wa * az + wb * bz + wc * cz
                k = int(np.floor((z - origin[2]) / spacing)) + 1
                if 0 <= k < nz:
                    flips[i, j, k] ^= 1


def grid_for(points, cells: int = CELLS, volume: float | None = None):
    """``(origin, spacing, shape)`` of a grid of cubes over the box of ``points`` (n, 3) mm with
    two cells to spare on each side, spaced for about ``cells`` inside a solid of ``volume``
    mm³ (default: the box's). The origin is shifted by an irrational share of a cell, so that
    no column of cell centres runs through a mesh edge or vertex of a surface on round
    coordinates."""
    low, high = points.min(axis=0), points.max(axis=0)
    volume = float(np.prod(high - low)) if volume is None else volume
    spacing = float(np.cbrt(volume / cells))
    origin = low - (2.0 - 0.5 * (np.sqrt(2.0) - 1.0)) * spacing
    shape = tuple(int(n) for n in np.ceil((high - origin) / spacing) + 3)
    return origin, spacing, shape


def inside_cells(points, triangles, origin, spacing, shape) -> np.ndarray:
    """(nx, ny, nz) bool: the cell centres inside the closed surface (``points`` (n, 3) mm,
    ``triangles`` (m, 3)), by the parity of its crossings along each column."""
    flips = np.zeros(shape, dtype=np.uint8)
    _column_crossings(np.ascontiguousarray(points, dtype=np.float64),
                      np.ascontiguousarray(triangles, dtype=np.int64),
                      np.asarray(origin, dtype=np.float64), float(spacing), flips)
    return (np.bitwise_xor.accumulate(flips, axis=2) == 1)


def edge_cells(points, triangles, origin, spacing, shape) -> np.ndarray:
    """(nx, ny, nz) bool: the cells that an edge of the surface (``points`` (n, 3) mm,
    ``triangles`` (m, 3)) runs through, sampled every :data:`EDGE_STEP` cells, and their
    face neighbours."""
    edges = np.unique(np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]],
                                              triangles[:, [2, 0]]]), axis=1), axis=0)
    a, b = points[edges[:, 0]], points[edges[:, 1]]
    steps = np.ceil(np.linalg.norm(b - a, axis=1) / (EDGE_STEP * spacing)).astype(np.int64) + 1
    edge = np.repeat(np.arange(len(edges)), steps)
    share = (np.arange(len(edge)) - np.repeat(np.cumsum(steps) - steps, steps)) \
        / np.repeat(steps - 1, steps)
    samples = a[edge] + share[:, None] * (b - a)[edge]
    index = np.clip(np.rint((samples - origin) / spacing).astype(np.int64), 0,
                    np.array(shape) - 1)
    touched = np.zeros(shape, dtype=bool)
    touched[tuple(index.T)] = True
    # consecutive samples may share only an edge or a corner of their cells: widened by a
    # face-neighbour, they share faces (the graph below is 6-connected)
    return ndimage.binary_dilation(touched)


def harmonic_field(points, triangles, origin_area, insertion_area, where: str,
                   volume: float, cells: int = CELLS, bridged: bool = False) -> HarmonicField:
    """The field of the module docstring for the closed surface ``points`` (n, 3) mm,
    ``triangles`` (m, 3) of ``volume`` mm³, its attachment areas given as vertex masks
    ``origin_area``, ``insertion_area`` (n,) bool; ``where`` names the muscle in errors.
    ``bridged``: the cells the surface's edges run through count as inside too, for a muscle
    whose section narrows below a cell (the demo thigh's biceps femoris short head narrows to
    a line for 35 mm)."""
    origin, spacing, shape = grid_for(points, cells, volume)
    inside = inside_cells(points, triangles, origin, spacing, shape)
    if bridged:
        inside |= edge_cells(points, triangles, origin, spacing, shape)
    # a pocket of the surface apart from the muscle's body (a fold, a stray closed piece of
    # a segmentation) holds no fibres and must not take the areas' cells
    label, _ = ndimage.label(inside)
    sizes = np.bincount(label.ravel())
    sizes[0] = 0
    inside &= sizes[label] >= POCKET_SHARE * sizes.sum()
    index = np.full(shape, -1, dtype=np.int64)
    cell = np.argwhere(inside)
    index[inside] = np.arange(len(cell))
    pairs = []
    for axis in range(3):
        step = np.zeros(3, dtype=np.int64)
        step[axis] = 1
        a = index[tuple(slice(0, n - s) for n, s in zip(shape, step))]
        b = index[tuple(slice(s, n) for n, s in zip(shape, step))]
        both = (a >= 0) & (b >= 0)
        pairs.append(np.stack([a[both], b[both]], axis=1))
    pairs = np.concatenate(pairs)
    degree = np.bincount(pairs.ravel(), minlength=len(cell))
    boundary = degree < 6
    centres = origin + spacing * cell
    tree = cKDTree(points)
    nearest = np.full(len(cell), -1)
    nearest[boundary] = tree.query(centres[boundary])[1]
    held = np.full(len(cell), np.nan)
    for mask, value in ((origin_area, 0.0), (insertion_area, 1.0)):
        mask = np.asarray(mask, dtype=bool)
        on = boundary & (nearest >= 0)
        on[on] = mask[nearest[on]]
        # each area vertex holds its nearest boundary cell too (a patch finer than the cells)
        boundary_ids = np.flatnonzero(boundary)
        if mask.any() and len(boundary_ids):
            near = cKDTree(centres[boundary_ids]).query(points[mask])[1]
            on[boundary_ids[near]] = True
        if not on.any():
            raise MuscleMSSError(f"{where}: no part of its surface lies on its "
                                 f"{'origin' if value == 0.0 else 'insertion'} area")
        held[on & np.isnan(held)] = value
    # keep the cells connected to both areas
    graph = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                              shape=(len(cell), len(cell)))
    _, label = connected_components(graph, directed=False)
    kept_labels = np.intersect1d(label[held == 0.0], label[held == 1.0])
    if not len(kept_labels):
        raise NotConnected(f"{where}: its origin and insertion areas are not connected "
                             "through its inside")
    kept = np.isin(label, kept_labels)
    values = _solve_laplace(pairs, held, kept, where)
    grid = np.zeros(shape)
    inside_kept = np.zeros(shape, dtype=bool)
    inside_kept[tuple(cell[kept].T)] = True
    grid[tuple(cell[kept].T)] = values[kept]
    _, nearest_inside = ndimage.distance_transform_edt(~inside_kept, return_indices=True)
    grid = grid[tuple(nearest_inside)]
    gradient = np.stack(np.gradient(grid, spacing), axis=-1)
    return HarmonicField(origin, spacing, grid, inside_kept, gradient, nearest_inside)


def _solve_laplace(pairs, held, kept, where: str) -> np.ndarray:
    """The cells' values: ``held`` where not NaN, elsewhere (of the ``kept`` cells) the
    harmonic values of the graph of ``pairs``."""
    n = len(held)
    free = kept & np.isnan(held)
    values = np.where(np.isnan(held), 0.5, held)
    unknown = np.full(n, -1)
    unknown[free] = np.arange(free.sum())
    a, b = pairs[:, 0], pairs[:, 1]
    use = kept[a] & kept[b]
    a, b = a[use], b[use]
    degree = np.bincount(np.concatenate([a, b]), minlength=n).astype(np.float64)
    rows, cols = [], []
    rhs = np.zeros(free.sum())
    for u, v in ((a, b), (b, a)):
        both = free[u] & free[v]
        rows.append(unknown[u[both]])
        cols.append(unknown[v[both]])
        fixed = free[u] & ~free[v]
        np.add.at(rhs, unknown[u[fixed]], values[v[fixed]])
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    m = free.sum()
    diagonal = degree[free]
    matrix = sparse.csr_matrix((np.full(len(rows), -1.0), (rows, cols)), shape=(m, m)) \
        + sparse.diags(diagonal)
    x = np.full(m, 0.5)
    r = rhs - matrix @ x
    z = r / diagonal
    p = z.copy()
    rz = r @ z
    target = RESIDUAL * np.linalg.norm(rhs)
    for _ in range(20 * m):
        if np.linalg.norm(r) <= target:
            break
        q = matrix @ p
        alpha = rz / (p @ q)
        x += alpha * p
        r -= alpha * q
        z = r / diagonal
        rz, previous = r @ z, rz
        p = z + (rz / previous) * p
    else:
        raise MuscleMSSError(f"{where}: the fibre field did not converge")
    values[free] = x
    return values
