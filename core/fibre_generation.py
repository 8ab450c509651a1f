"""Fibres generated inside a muscle surface (DESIGN §6 "Fibre generation"), as Choi & Blemker
2013 and Ziva's zFiber do: the streamlines of a harmonic field that is 0 on the origin
attachment area, 1 on the insertion area and has no flux through the rest of the surface.

* **Field**: :mod:`.harmonic_field`, on the cells of a grid inside the surface.
* **Seeds**: the muscle's cross-section where the field is one half (its belly, so that a
  small tendon patch does not bunch the seeds): a rows x cols grid laid on it by the concentric
  map of the square onto the disc (Shirley & Chiu 1997: equal areas, even spacing), scaled to
  the section's outline; grid neighbours are section neighbours, so ``fibre_grid`` holds.
* **Fibres**: traced from each seed along the field's gradient (midpoint steps of half a cell,
  trilinear interpolation) down to :data:`END` and up to 1 - :data:`END` (within a cell of the
  attachment areas), joined origin to insertion, extended straight onto an area where they
  stopped short of it (a tendon thinner than a cell holds no cells) and resampled to equal arc
  lengths.
  Streamlines of one field never cross, and the result is deterministic.

No VTK here: the Fibre Generator filter and ``muscle-mss fibres`` give the surfaces and the
areas.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .bones.triangle_distance import closest_points, prepared_surface
from .errors import MuscleMSSError
from .harmonic_field import CELLS, HarmonicField, NotConnected, harmonic_field
from .scene import FibreSet

END = 1e-3
"""A fibre ends where the field comes within this of 0 (origin) or 1 (insertion)."""
INSIDE_MARGIN = 0.05
"""A fibre point closer to the surface than this share of a cell is moved this far inside."""
RESEEDS, RESEED_SHRINK = 4, 0.85
"""A seed whose streamline stalls is moved onto the section's nearest free cell, then to this
share of its distance from the section's centre, at most this many times in all."""
TENDON_CELLS = 3.0
"""Fibres ending farther than this many cells from their attachment area's vertices (in a tendon
thinner than a cell) are extended straight to it."""
END_GAP = 1e-4
"""Fibre ends closer than this share of the fibres' median length are moved apart (a hundred
times :data:`.fibre_pieces.JOIN_TOLERANCE`)."""
OUTLINE_BINS = 48
"""Angles at which the section's outline (its outermost cell centres, half a cell inside the
surface) is taken around its centre."""



def concentric_disc(rows: int, cols: int) -> np.ndarray:
    """(rows * cols, 2): the centres of a rows x cols grid on the square [-1, 1]² carried onto
    the unit disc by Shirley & Chiu's concentric map (equal areas), row-major."""
    u = (2.0 * np.arange(rows) + 1.0) / rows - 1.0
    v = (2.0 * np.arange(cols) + 1.0) / cols - 1.0
    x, y = (a.ravel() for a in np.meshgrid(u, v, indexing="ij"))
    wide = np.abs(x) > np.abs(y)
    radius = np.where(wide, x, y)
    # (the centre of an odd grid, x = y = 0, has radius 0: any angle)
    angle = np.where(wide, np.pi / 4 * y / np.where(wide, x, 1.0),
                     np.pi / 2 - np.pi / 4 * x / np.where(wide | (y == 0.0), 1.0, y))
    return np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=1)


def section_cells(field: HarmonicField) -> np.ndarray:
    """(k, 3) mm: the centres of the inside cells below the field's level one half with a
    neighbour above it (the muscle's cross-section at its belly)."""
    values, inside = field.values, field.inside
    low = inside & (values < 0.5)
    high = inside & (values >= 0.5)
    near = np.zeros_like(inside)
    for axis in range(3):
        for shift in (1, -1):
            near |= low & np.roll(high, shift, axis=axis)
    return field.origin + field.spacing * np.argwhere(near)


def section_seeds(field: HarmonicField, rows: int, cols: int, where: str) -> np.ndarray:
    """(rows * cols, 3) mm: seeds on the field's level one half (the muscle's belly), laid by
    :func:`concentric_disc` on the section's outline, row-major by (row, col)."""
    points = section_cells(field)
    if len(points) < 3:
        raise MuscleMSSError(f"{where}: too thin for fibres at the grid's spacing")
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
        # a step out across the curved surface to where the field outside is flat: back in
        stalled = active & (np.abs(value - before) < 1e-12)
        if stalled.any():
            x[stalled] = field.pulled_inside(x[stalled])
            value[stalled] = field.at(x[stalled])
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
    try:
        field = harmonic_field(points, triangles, origin_area, insertion_area, where, volume,
                               cells)
    except NotConnected:
        field = harmonic_field(points, triangles, origin_area, insertion_area, where, volume,
                               cells, bridged=True)
    seeds = section_seeds(field, rows, cols, where)
    centre = seeds.mean(axis=0)
    max_steps = int(8 * np.ptp(points, axis=0).sum() / field.spacing)
    down, up = [None] * len(seeds), [None] * len(seeds)
    lost, first = np.arange(len(seeds)), True
    for _ in range(RESEEDS + 1):
        # a seed at the section's rim may start where the field is flat (outside a crescent
        # section, a fold of the surface, a corner of the cells): it is moved onto the
        # section's nearest free cell, then towards the section's centre
        for f, d, u in zip(lost, _trace(field, seeds[lost], False, max_steps),
                           _trace(field, seeds[lost], True, max_steps)):
            down[f], up[f] = d, u
        lost = np.array([f for f in lost if down[f] is None or up[f] is None], dtype=int)
        if not len(lost):
            break
        if first:
            seeds[lost] = _into_section(seeds, lost, section_cells(field), field.spacing)
            first = False
        else:
            seeds[lost] = centre + RESEED_SHRINK * (seeds[lost] - centre)
    else:
        raise MuscleMSSError(f"{where}: {len(lost)} of {len(seeds)} fibres do not reach both "
                             "attachment areas along the field (fibre grid cells "
                             f"{[divmod(int(f), cols) for f in lost[:4]]})")
    traced = _reaching_areas([np.concatenate([d[::-1], u[1:]]) for d, u in zip(down, up)],
                             points, (origin_area, insertion_area), TENDON_CELLS * field.spacing)
    fibres = np.stack([resample(f, samples) for f in traced])
    _keep_inside(fibres, seeds, prepared_surface(points, triangles, where),
                 INSIDE_MARGIN * field.spacing)
    _separate_ends(fibres)
    grid = np.stack(np.divmod(np.arange(rows * cols), cols), axis=1)
    return FibreSet.from_polylines(list(fibres), grid)


def _into_section(seeds, lost, cells, spacing: float) -> np.ndarray:
    """(len(lost), 3) mm: for each of the seeds ``lost`` (indices into ``seeds`` (F, 3) mm),
    the nearest section cell centre (``cells`` (k, 3) mm) farther than half a cell from every
    other seed."""
    kept = np.setdiff1d(np.arange(len(seeds)), lost)
    free = cells
    if len(kept):
        free = cells[cKDTree(seeds[kept]).query(cells)[0] > 0.5 * spacing]
    moved = seeds[lost].copy()
    for k in range(len(moved)):
        if not len(free):
            break
        nearest = int(np.argmin(np.linalg.norm(free - moved[k], axis=1)))
        moved[k] = free[nearest]
        free = free[np.linalg.norm(free - moved[k], axis=1) > 0.5 * spacing]
    return moved


def _reaching_areas(fibres: list, points, areas, limit: float) -> list:
    """The traced ``fibres`` (each (k, 3) mm, origin first), each end extended by a straight
    piece to its area (``areas``: the origin and insertion vertex masks of ``points`` (n, 3)
    mm) where the fibres stop farther than ``limit`` mm from it (their median): a tendon
    thinner than the cells holds no cells, so the traced fibres stop where it starts. The
    pieces end on the fibres' pattern of ends shrunk onto the area around its centre, so
    that no two fibres share an end."""
    fibres = list(fibres)
    for end, area in ((0, areas[0]), (-1, areas[1])):
        area_points = points[np.asarray(area, dtype=bool)]
        ends = np.array([f[end] for f in fibres])
        if np.median(cKDTree(area_points).query(ends)[0]) <= limit:
            continue
        centre, middle = area_points.mean(axis=0), ends.mean(axis=0)
        spread = np.sqrt(((ends - middle) ** 2).sum(axis=1).mean())
        room = np.sqrt(((area_points - centre) ** 2).sum(axis=1).mean())
        targets = centre + min(1.0, room / max(spread, 1e-300)) * (ends - middle)
        fibres = [np.concatenate([t[None], f] if end == 0 else [f, t[None]])
                  for f, t in zip(fibres, targets)]
    return fibres


def _separate_ends(fibres) -> None:
    """Move the ends of ``fibres`` (F, S, 3) mm that lie within :data:`END_GAP` of their
    length of another fibre's end back along their last segment, each by its own share of
    it (up to a tenth), in place: streamlines funnelled into a small tendon patch can end a
    hair apart, and fibres sharing an end read as the pieces of one fibre
    (:mod:`.fibre_pieces`)."""
    lengths = np.linalg.norm(np.diff(fibres, axis=1), axis=2).sum(axis=1)
    gap = END_GAP * float(np.median(lengths))
    for end, before in ((0, 1), (-1, -2)):
        pairs = cKDTree(fibres[:, end]).query_pairs(gap, output_type="ndarray")
        crowded = np.unique(pairs)
        for rank, f in enumerate(crowded):
            share = 0.1 * (rank + 1) / len(crowded)
            fibres[f, end] += share * (fibres[f, before] - fibres[f, end])


def _keep_inside(fibres, seeds, surface, margin: float) -> None:
    """Move the points of ``fibres`` (F, S, 3) mm closer than ``margin`` mm to the surface, or
    outside it (a last step across a curved end, half a cell), to ``margin`` inside the
    surface from their closest point on it, in place (a point on the surface itself: towards
    its fibre's seed, on the muscle's belly)."""
    flat = fibres.reshape(-1, 3)
    for _ in range(3):      # a point moved at a sharp tip of the surface may still be out
        distance, closest = closest_points(surface, flat)
        out = distance > -0.5 * margin
        if not out.any():
            break
        inward = np.where(distance[out, None] < 0.0, 1.0, -1.0) * (flat[out] - closest[out])
        length = np.linalg.norm(inward, axis=1, keepdims=True)
        seed = np.repeat(seeds, fibres.shape[1], axis=0)[out] - closest[out]
        inward = np.where(length > 1e-6 * margin, inward, seed)
        inward /= np.maximum(np.linalg.norm(inward, axis=1, keepdims=True), 1e-300)
        flat[out] = closest[out] + margin * inward


def fibre_grid_shape(count: int) -> tuple:
    """``(rows, cols)`` of ``count`` fibres: the most nearly square grid (64: 8 x 8, 60: 6 x
    10)."""
    if count < 1:
        raise MuscleMSSError(f"the fibre count is {count}; a muscle needs at least one fibre")
    rows = max(r for r in range(1, int(np.sqrt(count)) + 1) if count % r == 0)
    return rows, count // rows


def generate_scene_fibres(muscles: dict, bones: dict, named: dict, count: int = 64,
                          samples: int = 30, progress=None) -> dict:
    """``{muscle: FibreSet}``: ``count`` fibres of ``samples`` points for every muscle of
    ``muscles`` (``{name: Surface}``, rest pose, mm) between its attachment areas on
    ``bones`` (:func:`.attachment_areas.scene_areas`, ``named`` the bones the scene names),
    each FibreSet naming its origin and insertion bone. ``progress(done, total)`` is called
    after each muscle."""
    from .attachment_areas import scene_areas
    from .scene import MUSCLES_FILE
    rows, cols = fibre_grid_shape(count)
    areas = scene_areas(muscles, bones, named)
    out = {}
    for done, (muscle, surface) in enumerate(muscles.items()):
        area = areas[muscle]
        fibres = generate_fibres(surface.points, surface.triangles, area.origin, area.insertion,
                                 rows, cols, samples, f"{MUSCLES_FILE} block '{muscle}'")
        fibres.origin_bone, fibres.insertion_bone = area.origin_bone, area.insertion_bone
        out[muscle] = fibres
        if progress is not None:
            progress(done + 1, len(muscles))
    return out
