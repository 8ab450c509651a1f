"""Fibres generated inside a muscle surface (DESIGN §6 "Fibre generation"), as Choi & Blemker
2013 and Ziva's zFiber do: the streamlines of a harmonic field that is 0 on the origin
attachment area, 1 on the insertion area and has no flux through the rest of the surface.

* **Cells**: the centres of a regular grid of cubes, spaced for about :data:`CELLS` inside the
  surface (:func:`inside_cells`: each column of cells along z crossed by the triangles, the
  cells between an odd number of crossings inside).
* **Field**: on the inside cells, the 6-neighbour graph Laplacian is zero; cells on the
  boundary whose nearest surface vertex belongs to the origin area are held at 0, to the
  insertion area at 1; a neighbour outside is left out (no flux). Solved by conjugate
  gradients preconditioned by the diagonal to a relative residual of :data:`RESIDUAL`; a
  cell not connected to both areas is left out.
* **Seeds**: the muscle's cross-section where the field is one half (its belly, so that a
  small tendon patch does not bunch the seeds): a rows x cols grid laid on it by the concentric
  map of the square onto the disc (Shirley & Chiu 1997: equal areas, even spacing), scaled to
  the section's outline; grid neighbours are section neighbours, so ``fibre_grid`` holds.
* **Fibres**: traced from each seed along the field's gradient (midpoint steps of half a cell,
  trilinear interpolation) down to :data:`END` and up to 1 - :data:`END` (within a cell of the
  attachment areas), joined origin to insertion and resampled to equal arc lengths.
  Streamlines of one field never cross, and the result is deterministic.

No VTK here: the Fibre Generator filter and ``muscle-mss fibres`` give the surfaces and the
areas.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy import ndimage, sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .bones.triangle_distance import closest_points, prepared_surface
from .errors import MuscleMSSError
from .scene import FibreSet

CELLS = 40_000
"""Grid cells inside a muscle (the spacing follows its volume): about 10 across the demo's most
slender muscle."""
RESIDUAL = 1e-10
"""Relative residual at which the field's conjugate gradients stop."""
END = 1e-3
"""A fibre ends where the field comes within this of 0 (origin) or 1 (insertion)."""
INSIDE_MARGIN = 0.05
"""A fibre point closer to the surface than this share of a cell is moved this far inside."""
RESEEDS, RESEED_SHRINK = 4, 0.85
"""A seed whose streamline stalls is moved this share of the way from the section's centre,
at most this many times."""
OUTLINE_BINS = 48
"""Angles at which the section's outline (its outermost cell centres, half a cell inside the
surface) is taken around its centre."""


@dataclass(frozen=True)
class HarmonicField:
    """``values`` (nx, ny, nz) at the cell centres ``origin + spacing * (i, j, k)`` (mm): the
    field inside (``inside``), outside the value of the nearest inside cell (so that the
    gradient at the surface has no normal part to first order); ``gradient`` (nx, ny, nz, 3)
    per mm."""

    origin: np.ndarray
    spacing: float
    values: np.ndarray
    inside: np.ndarray
    gradient: np.ndarray

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


def harmonic_field(points, triangles, origin_area, insertion_area, where: str,
                   volume: float, cells: int = CELLS) -> HarmonicField:
    """The field of the module docstring for the closed surface ``points`` (n, 3) mm,
    ``triangles`` (m, 3) of ``volume`` mm³, its attachment areas given as vertex masks
    ``origin_area``, ``insertion_area`` (n,) bool; ``where`` names the muscle in errors."""
    origin, spacing, shape = grid_for(points, cells, volume)
    inside = inside_cells(points, triangles, origin, spacing, shape)
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
        raise MuscleMSSError(f"{where}: its origin and insertion areas are not connected "
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
    return HarmonicField(origin, spacing, grid, inside_kept, gradient)


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


def concentric_disc(rows: int, cols: int) -> np.ndarray:
    """(rows * cols, 2): the centres of a rows x cols grid on the square [-1, 1]² carried onto
    the unit disc by Shirley & Chiu's concentric map (equal areas), row-major."""
    u = (2.0 * np.arange(rows) + 1.0) / rows - 1.0
    v = (2.0 * np.arange(cols) + 1.0) / cols - 1.0
    x, y = (a.ravel() for a in np.meshgrid(u, v, indexing="ij"))
    wide = np.abs(x) > np.abs(y)
    radius = np.where(wide, x, y)
    angle = np.where(wide, np.pi / 4 * y / np.where(wide, x, 1.0),
                     np.pi / 2 - np.pi / 4 * x / np.where(wide, 1.0, y))
    return np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=1)


def section_seeds(field: HarmonicField, rows: int, cols: int, where: str) -> np.ndarray:
    """(rows * cols, 3) mm: seeds on the field's level one half (the muscle's belly), laid by
    :func:`concentric_disc` on the section's outline, row-major by (row, col)."""
    values, inside = field.values, field.inside
    low = inside & (values < 0.5)
    high = inside & (values >= 0.5)
    near = np.zeros_like(inside)
    for axis in range(3):
        for shift in (1, -1):
            near |= low & np.roll(high, shift, axis=axis)
    cells = np.argwhere(near)
    if len(cells) < 3:
        raise MuscleMSSError(f"{where}: too thin for fibres at the grid's spacing")
    points = field.origin + field.spacing * cells
    centre = points.mean(axis=0)
    normal = field.direction(centre[None])[0]
    flat = (points - centre) - np.outer((points - centre) @ normal, normal)
    _, _, axes = np.linalg.svd(flat, full_matrices=False)
    e1, e2 = axes[0], axes[1]
    s1, s2 = np.std(flat @ e1) or 1.0, np.std(flat @ e2) or 1.0
    a, b = flat @ e1 / s1, flat @ e2 / s2
    bins = OUTLINE_BINS
    angle = np.arctan2(b, a)
    which = np.minimum(((angle + np.pi) / (2 * np.pi) * bins).astype(int), bins - 1)
    outline = np.zeros(bins)
    np.maximum.at(outline, which, np.hypot(a, b))
    filled = outline > 0
    centres = -np.pi + (np.arange(bins) + 0.5) * 2 * np.pi / bins
    outline = np.interp(centres, centres[filled], outline[filled], period=2 * np.pi)
    disc = concentric_disc(rows, cols)
    radius, theta = np.hypot(disc[:, 0], disc[:, 1]), np.arctan2(disc[:, 1], disc[:, 0])
    reach = radius * np.interp(theta, centres, outline, period=2 * np.pi)
    seeds = centre + np.outer(reach * np.cos(theta) * s1, e1) \
        + np.outer(reach * np.sin(theta) * s2, e2)
    for _ in range(8):          # onto the level one half: Newton steps along the gradient
        g = field.gradient_at(seeds)
        slope = np.maximum((g * g).sum(axis=1), 1e-300)
        move = (field.at(seeds) - 0.5)[:, None] * g / slope[:, None]
        length = np.linalg.norm(move, axis=1, keepdims=True)
        seeds -= move * np.minimum(1.0, field.spacing / np.maximum(length, 1e-300))
    return seeds


def _trace(field: HarmonicField, seeds, upward: bool, max_steps: int) -> list:
    """Per seed, the points (k, 3) of its streamline from the seed until the field comes within
    :data:`END` of 1 (``upward``) or 0, its last point where the last step crosses that level
    (linearly between its ends), or None where it does not within ``max_steps``."""
    step = 0.5 * field.spacing * (1.0 if upward else -1.0)
    level = 1.0 - END if upward else END
    x = seeds.copy()
    value = field.at(x)
    path = [x.copy()]
    ends = np.full(len(x), -1)
    for s in range(1, max_steps + 1):
        active = ends < 0
        if not active.any():
            break
        xa = x[active]
        middle = xa + 0.5 * step * field.direction(xa)
        x[active] = xa + step * field.direction(middle)
        before, value = value, field.at(x)
        reached = active & ((value >= level) if upward else (value <= level))
        if reached.any():
            share = (before[reached] - level) / (before[reached] - value[reached])
            x[reached] = path[-1][reached] + share[:, None] * (x[reached] - path[-1][reached])
            ends[reached] = s
        path.append(x.copy())
    path = np.stack(path)
    return [path[:e + 1, f] if e >= 0 else None for f, e in enumerate(ends)]


def resample(polyline, count: int) -> np.ndarray:
    """(count, 3): ``polyline`` (k, 3) at equal arc lengths, its ends kept."""
    lengths = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(polyline, axis=0),
                                                              axis=1))])
    at = np.linspace(0.0, lengths[-1], count)
    return np.stack([np.interp(at, lengths, polyline[:, a]) for a in range(3)], axis=1)


def generate_fibres(points, triangles, origin_area, insertion_area, rows: int = 8,
                    cols: int = 8, samples: int = 30, where: str = "muscle",
                    cells: int = CELLS) -> FibreSet:
    """The fibres of the muscle with the closed, outward surface ``points`` (n, 3) mm,
    ``triangles`` (m, 3) and the attachment areas ``origin_area``, ``insertion_area`` (n,)
    bool vertex masks: rows x cols fibres of ``samples`` points from origin to insertion, their
    ``grid`` the (row, col) of their seed; ``where`` names the muscle in errors."""
    from .volume import signed_volume
    points = np.asarray(points, dtype=np.float64)
    volume = signed_volume(points, triangles)
    if not volume > 0.0:
        raise MuscleMSSError(f"{where}: its surface encloses no volume (open, or inward)")
    field = harmonic_field(points, triangles, origin_area, insertion_area, where, volume,
                           cells)
    seeds = section_seeds(field, rows, cols, where)
    centre = seeds.mean(axis=0)
    max_steps = int(8 * np.ptp(points, axis=0).sum() / field.spacing)
    down, up = [None] * len(seeds), [None] * len(seeds)
    lost = np.arange(len(seeds))
    for _ in range(RESEEDS + 1):
        # a seed at the section's rim may start where the field is flat (a fold of the
        # surface, a corner of the cells): it is moved towards the section's centre
        for f, d, u in zip(lost, _trace(field, seeds[lost], False, max_steps),
                           _trace(field, seeds[lost], True, max_steps)):
            down[f], up[f] = d, u
        lost = np.array([f for f in lost if down[f] is None or up[f] is None], dtype=int)
        if not len(lost):
            break
        seeds[lost] = centre + RESEED_SHRINK * (seeds[lost] - centre)
    else:
        raise MuscleMSSError(f"{where}: {len(lost)} of {len(seeds)} fibres do not reach both "
                             "attachment areas along the field (fibre grid cells "
                             f"{[divmod(int(f), cols) for f in lost[:4]]})")
    fibres = np.stack([resample(np.concatenate([d[::-1], u[1:]]), samples)
                       for d, u in zip(down, up)])
    _keep_inside(fibres, seeds, prepared_surface(points, triangles, where),
                 INSIDE_MARGIN * field.spacing)
    grid = np.stack(np.divmod(np.arange(rows * cols), cols), axis=1)
    return FibreSet.from_polylines(list(fibres), grid)


def _keep_inside(fibres, seeds, surface, margin: float) -> None:
    """Move the points of ``fibres`` (F, S, 3) mm closer than ``margin`` mm to the surface, or
    outside it (a last step across a curved end, half a cell), to ``margin`` inside the
    surface from their closest point on it, in place (a point on the surface itself: towards
    its fibre's seed, on the muscle's belly)."""
    flat = fibres.reshape(-1, 3)
    distance, closest = closest_points(surface, flat)
    out = distance > -margin
    if out.any():
        inward = np.where(distance[out, None] < 0.0, 1.0, -1.0) * (flat[out] - closest[out])
        length = np.linalg.norm(inward, axis=1, keepdims=True)
        seed = np.repeat(seeds, fibres.shape[1], axis=0)[out] - closest[out]
        inward = np.where(length > 1e-6 * margin, inward, seed)
        inward /= np.maximum(np.linalg.norm(inward, axis=1, keepdims=True), 1e-300)
        flat[out] = closest[out] + margin * inward
