"""Bones as sets of spheres on their surface (the paper's §3.3: "the bones are also converted to a
set of spheres that approximates their surface").

:func:`bone_spheres` samples a closed triangle surface into sphere centres with Poisson-disc
spacing: a dense set of candidate points (a barycentric grid on every triangle, at most
spacing / 2 apart along its edges) is visited in a fixed pseudo-random order and a candidate is
kept when no kept centre lies closer than ``spacing``. Every candidate, and so the surface up to
spacing / 2, then lies within ``spacing`` of a centre; each sphere gets radius ``spacing``, so
the spheres cover the surface without holes a muscle sphere could slip through. The same surface and spacing always
give the same spheres.

How the count follows from the spacing: such a random-order Poisson-disc set on a surface of
area ``A`` has about ``SPHERES_PER_AREA * A / spacing**2`` centres (``SPHERES_PER_AREA`` = 0.62,
measured on the demo bones; a hexagonal packing would give 1.15). The demo pelvis (58,000 mm^2)
at the default spacing ``DEFAULT_SPACING`` = 2.05 mm gets about 8,600 spheres, the paper's
8527 for its pelvis. :func:`bone_spheres` also takes a ``count`` instead and finds the spacing
that gives exactly that many (the benchmark's 8527 / 1568 / 1709).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from ..errors import MuscleMSSError, check_memory
from ..mesh_checks import checked_surface
from ..settings import DEFAULT_BONE_SPHERE_SPACING as DEFAULT_SPACING
from ..solver_properties import name_of
SPHERES_PER_AREA = 0.62         # centres ~ SPHERES_PER_AREA * area / spacing^2
CANDIDATES_PER_SPACING = 2      # candidate grid step = spacing / 2
ORDER_BLOCK = 4096              # candidates shuffled within blocks of this many (cache locality)
ORDER_SEED = 20140301           # fixed visiting order: same surface, same spheres
# The largest spacing, as a fraction of the bone's smallest bounding-box side: each sphere's
# radius is the spacing, so the spheres stand that far off the bone and hold the muscles there.
# A spacing of 1e6 mm made one sphere per bone that held every muscle 1e6 mm out (the
# small demo thigh's quasi-static solve wrote volume errors of 3e14 %). The demo bones' smallest
# sides are 23.5 mm (the ulna) to 133 mm (the pelvis): 5.9-33 mm allowed, 2.05 by default.
MAX_SPACING_SHARE = 0.25


@njit(cache=True)
def _subdivisions(points, triangles, step):
    """(m,) int64: grid subdivisions per triangle so that its longest edge is cut into pieces
    no longer than ``step``."""
    q = np.empty(triangles.shape[0], dtype=np.int64)
    for t in range(triangles.shape[0]):
        longest = 0.0
        for e in range(3):
            a = triangles[t, e]
            b = triangles[t, (e + 1) % 3]
            d2 = 0.0
            for axis in range(3):
                d2 += (points[a, axis] - points[b, axis]) ** 2
            longest = max(longest, np.sqrt(d2))
        q[t] = max(1, int(np.ceil(longest / step)))
    return q


@njit(cache=True)
def _candidates(points, triangles, q, first, out):
    """The barycentric grid points of every triangle into ``out[first[t]:first[t + 1]]``."""
    for t in range(triangles.shape[0]):
        k = first[t]
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        for i in range(q[t] + 1):
            for j in range(q[t] + 1 - i):
                u = i / q[t]
                w = j / q[t]
                for axis in range(3):
                    out[k, axis] = (points[a, axis] + u * (points[b, axis] - points[a, axis])
                                    + w * (points[c, axis] - points[a, axis]))
                k += 1


@njit(cache=True)
def _poisson_disc(candidates, order, spacing, limit):
    """Indices of the kept candidates (in visiting order): each kept one is at least
    ``spacing`` from all kept before it. Stops after ``limit`` kept."""
    lower = np.empty(3)
    dims = np.empty(3, dtype=np.int64)
    for axis in range(3):
        lower[axis] = candidates[:, axis].min()
        dims[axis] = int((candidates[:, axis].max() - lower[axis]) / spacing) + 1
    head = np.full(dims[0] * dims[1] * dims[2], -1, dtype=np.int64)
    nxt = np.full(candidates.shape[0], -1, dtype=np.int64)
    kept = np.empty(min(limit, candidates.shape[0]), dtype=np.int64)
    n_kept = 0
    s2 = spacing * spacing
    # the candidate's own cell first: almost every candidate is refused there
    near = np.empty((27, 3), dtype=np.int64)
    n = 0
    for ring in range(4):
        for i in range(-1, 2):
            for j in range(-1, 2):
                for k in range(-1, 2):
                    if abs(i) + abs(j) + abs(k) == ring:
                        near[n, 0], near[n, 1], near[n, 2] = i, j, k
                        n += 1
    for c in order:
        if n_kept == kept.shape[0]:
            break
        ci = min(int((candidates[c, 0] - lower[0]) / spacing), dims[0] - 1)
        cj = min(int((candidates[c, 1] - lower[1]) / spacing), dims[1] - 1)
        ck = min(int((candidates[c, 2] - lower[2]) / spacing), dims[2] - 1)
        free = True
        for n in range(27):
            i = ci + near[n, 0]
            j = cj + near[n, 1]
            k = ck + near[n, 2]
            if not free:
                break
            if i < 0 or j < 0 or k < 0 or i >= dims[0] or j >= dims[1] or k >= dims[2]:
                continue
            other = head[(i * dims[1] + j) * dims[2] + k]
            while other >= 0 and free:
                d2 = 0.0
                for axis in range(3):
                    d2 += (candidates[c, axis] - candidates[other, axis]) ** 2
                free = d2 >= s2
                other = nxt[other]
        if free:
            slot = (ci * dims[1] + cj) * dims[2] + ck
            nxt[c] = head[slot]
            head[slot] = c
            kept[n_kept] = c
            n_kept += 1
    return kept[:n_kept]


def surface_area(points, triangles) -> float:
    """Area of a triangle surface, mm^2."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    return float(0.5 * np.linalg.norm(np.cross(p[t[:, 1]] - p[t[:, 0]],
                                                p[t[:, 2]] - p[t[:, 0]]), axis=1).sum())


def _sample(points, triangles, spacing, limit, where="bone"):
    q = _subdivisions(points, triangles, spacing / CANDIDATES_PER_SPACING)
    first = np.concatenate([[0], np.cumsum((q + 1) * (q + 2) // 2)])
    # candidates with their shuffle keys and links (8 doubles each) and the Poisson-disc grid
    # of spacing-sized cells over the bounding box (one int64 each), counted before allocating
    cells = float(np.prod(np.floor((points.max(axis=0) - points.min(axis=0)) / spacing) + 1.0))
    check_memory(f"{where}: bone spheres {spacing:g} mm apart ({int(first[-1])} candidate "
                 f"points, a grid of {cells:.3g} cells)", 64.0 * first[-1] + 8.0 * cells,
                 f"raise the MSS Collision Solver's {name_of('contacts.bone_sphere_spacing')}")
    candidates = np.empty((int(first[-1]), 3))
    _candidates(points, triangles, q, first, candidates)
    # shuffled within blocks of neighbouring candidates: random enough for an even
    # Poisson-disc set, local enough to stay in cache
    key = (np.arange(len(candidates)) // ORDER_BLOCK
           + np.random.default_rng(ORDER_SEED).random(len(candidates)))
    order = np.argsort(key, kind="stable")
    return candidates[_poisson_disc(candidates, order, spacing, limit)]


def bone_spheres(points, triangles, spacing: float | None = None, count: int | None = None,
                 where: str = "bone"):
    """Spheres on a bone surface: ``(centres (k, 3) float64 mm, radii (k,) float64 mm)``.

    Give ``spacing`` (mm, the least distance between centres and the radius of every sphere;
    default :data:`DEFAULT_SPACING`) or ``count`` (exactly that many spheres: the spacing is
    found by bisection, and the last-placed surplus centres are dropped).
    points (n, 3) mm and triangles (m, 3) int of a triangle surface; ``where`` names it in
    errors.
    """
    points, triangles = checked_surface(points, triangles, where)
    if count is None:
        spacing = DEFAULT_SPACING if spacing is None else float(spacing)
        if not spacing > 0.0:
            raise MuscleMSSError(f"{where}: bone sphere spacing is {spacing}; it must be positive")
        side = float(np.ptp(points, axis=0).min()) if len(points) else 0.0
        if spacing > MAX_SPACING_SHARE * side:
            raise MuscleMSSError(
                f"{where}: bone spheres {spacing:g} mm apart are too large for a bone whose "
                f"bounding box is {side:.3g} mm at its thinnest: each sphere's radius is the "
                "spacing, and spheres larger than a quarter of that "
                f"({MAX_SPACING_SHARE * side:.3g} mm) hold the muscles that far off the bone; "
                f"lower the MSS Collision Solver's {name_of('contacts.bone_sphere_spacing')} "
                f"(default {DEFAULT_SPACING:g} "
                "mm)")
        centres = _sample(points, triangles, spacing, len(points) + 10 ** 9, where)
        return centres, np.full(len(centres), spacing)
    count = int(count)
    if count < 1:
        raise MuscleMSSError(f"{where}: bone sphere count is {count}; it must be at least 1")
    area = surface_area(points, triangles)
    # count(spacing) falls as spacing grows; keep `low` giving >= count, `high` giving fewer
    low = high = np.sqrt(SPHERES_PER_AREA * area / count)
    while len(_sample(points, triangles, low, count)) < count:
        low *= 0.8
        if low < 1e-9 * high:
            raise MuscleMSSError(f"{where}: cannot place {count} spheres on this surface")
    while len(_sample(points, triangles, high, count + 1)) > count:
        high *= 1.25
    for _ in range(20):
        middle = 0.5 * (low + high)
        if len(_sample(points, triangles, middle, count)) >= count:
            low = middle
        else:
            high = middle
    centres = _sample(points, triangles, low, count)
    return centres, np.full(count, low)
