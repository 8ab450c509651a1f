"""How deep the collision spheres of each object still overlap others after a solve.

A check of the result (summary.csv's ``sphere_overlap_mm`` per muscle),
run once per time point, not in the solver's loop: the paper's §3.3
response aims at spheres of different objects that just touch, so the remaining overlap
measures how far a solve is from that. It measures spheres, not the surface the user sees:
surface vertices in bones are reported by the MVC Surface Deformer.
"""
from collections import namedtuple

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

# The grid of max_penetration_pairs: cells of this many times the largest radius. On the full
# demo thigh at N = 80 (26,360 spheres, radii 2.9 mm on average, 10 mm at most): 16 ms a call
# at 1.0, 22 ms at 2.0, 25 ms at 0.5.
CELL_RADII = 1.0

Spheres = namedtuple("Spheres", "centres radii owner free")
Spheres.__doc__ = """Collision spheres as the overlap kernel takes them: ``centres`` (n, 3)
float64 mm, ``radii`` (n,) float64 mm, ``owner`` (n,) int64 (the object; -1 a bone) and ``free``
(n,) bool (the sphere may move)."""

CellGrid = namedtuple("CellGrid", "keys lower cell dims")
CellGrid.__doc__ = """Cubic cells of ``cell`` mm from ``lower`` (3,) float64 mm, ``dims`` (3,) int64
per axis, numbered x-major; ``keys`` (n,) int64 the ascending cell of each sorted sphere."""


def _spheres(centres, radii, owner, bone_centres, bone_radii, fixed):
    """The muscle spheres as arrays (centres (n, 3), radii (n,), owner (n,), free (n,)), then
    the same four over muscle and bone spheres together, the bones owned by -1 and never free."""
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    radii = np.asarray(radii, dtype=np.float64).reshape(-1)
    owner = np.asarray(owner, dtype=np.int64).reshape(-1)
    free = np.ones(len(centres), bool) if fixed is None else ~np.asarray(fixed, bool).reshape(-1)
    if bone_centres is None or not len(bone_centres):
        return centres, radii, owner, free, centres, radii, owner, free
    return (centres, radii, owner, free,
            np.concatenate([centres, np.asarray(bone_centres, dtype=np.float64)]),
            np.concatenate([radii, np.asarray(bone_radii, dtype=np.float64)]),
            np.concatenate([owner, np.full(len(bone_centres), -1)]),
            np.concatenate([free, np.zeros(len(bone_centres), bool)]))


def max_penetration_per_object(centres, radii, owner, n_objects, bone_centres=None,
                               bone_radii=None, fixed=None) -> np.ndarray:
    """Deepest overlap (mm; 0 when none) of each object's spheres with spheres of other objects,
    over the pairs a solver can resolve: at least one sphere free to move (bone spheres and
    ``fixed`` muscle spheres — tendon attachments, which sit inside their bone — cannot).

    Parameters
    ----------
    centres : (n, 3) float64 mm, radii : (n,) float64 mm
        The muscles' collision spheres (boundary particles).
    owner : (n,) int, the muscle of each sphere, in ``0 .. n_objects - 1``
    bone_centres : (k, 3) float64 mm, bone_radii : (k,) float64 mm, optional
        Bone spheres; they count as objects of their own for every muscle.
    fixed : (n,) bool, optional, muscle spheres that never move
    """
    centres, radii, owner, free, centres_all, radii_all, owner_all, free_all = _spheres(
        centres, radii, owner, bone_centres, bone_radii, fixed)
    deepest = np.zeros(n_objects)
    if len(centres) == 0:
        return deepest
    reach = radii + radii_all.max()
    neighbours = cKDTree(centres_all).query_ball_point(centres, reach)
    counts = np.fromiter((len(n) for n in neighbours), dtype=np.int64, count=len(neighbours))
    i = np.repeat(np.arange(len(centres)), counts)
    j = np.fromiter((k for n in neighbours for k in n), dtype=np.int64, count=int(counts.sum()))
    other = (owner_all[j] != owner[i]) & (free[i] | free_all[j])
    i, j = i[other], j[other]
    depth = radii[i] + radii_all[j] - np.linalg.norm(centres[i] - centres_all[j], axis=1)
    np.maximum.at(deepest, owner[i], np.maximum(depth, 0.0))
    return deepest



def max_penetration_pairs(centres, radii, owner, n_objects, bone_centres=None,
                          bone_radii=None, fixed=None) -> np.ndarray:
    """:func:`max_penetration_per_object` as a Numba grid search instead of Python lists per
    sphere (the reference's generator took 0.2 s a time point over ~0.4 M pairs at N = 80). All spheres are binned into cubic
    cells (:data:`CELL_RADII`), and each muscle sphere scans the cells within its radius
    plus the largest radius, where every sphere it overlaps lies. Same arguments and the
    same result, bitwise
    (the same depth formula over a superset of the reference's pairs, the extra ones farther
    apart than their radii); :func:`max_penetration_per_object` stays as its slow reference."""
    centres, radii, owner, free, centres_all, radii_all, owner_all, free_all = _spheres(
        centres, radii, owner, bone_centres, bone_radii, fixed)
    deepest = np.zeros(n_objects)
    if len(centres) == 0:
        return deepest
    # at most a million cells per axis, so that the cell numbers fit int64
    cell = max(CELL_RADII * float(radii_all.max()),
               1e-6 * float(np.ptp(centres_all, axis=0).max()), 1e-12)
    lower = centres_all.min(axis=0)
    dims = np.floor((centres_all.max(axis=0) - lower) / cell).astype(np.int64) + 1
    keys = _cell_keys(centres_all, lower, cell, dims)
    order = np.argsort(keys, kind="stable")
    per_sphere = np.empty(len(centres))
    _deepest_per_sphere(Spheres(centres, radii, owner, free),
                        Spheres(centres_all[order], radii_all[order], owner_all[order],
                                free_all[order]),
                        CellGrid(keys[order], lower, cell, dims), per_sphere)
    np.maximum.at(deepest, owner, per_sphere)
    return deepest


def _cell_keys(points, lower, cell, dims) -> np.ndarray:
    """(n,) int64: the grid cell of each point, numbered x-major."""
    index = np.minimum(np.floor((points - lower) / cell).astype(np.int64), dims - 1)
    return (index[:, 0] * dims[1] + index[:, 1]) * dims[2] + index[:, 2]


@njit(cache=True, inline="always")
def _first_at_least(keys, value):
    """Index of the first of the sorted ``keys`` that is >= ``value`` (len(keys) if none)."""
    low, high = 0, len(keys)
    while low < high:
        middle = (low + high) // 2
        if keys[middle] < value:
            low = middle + 1
        else:
            high = middle
    return low


@njit(cache=True, inline="always")
def _cell_span(centre, reach, lower, cell, dims):
    """The first and last cell (along one axis) within ``reach`` of ``centre``."""
    return (max(int(np.floor((centre - reach - lower) / cell)), 0),
            min(int(np.floor((centre + reach - lower) / cell)), dims - 1))


@njit(cache=True)
def _deepest_per_sphere(muscle, everyone, grid, out):
    """``out[i]``: deepest overlap (mm, >= 0) of sphere ``i`` of ``muscle`` (:class:`Spheres`)
    with the spheres ``everyone`` (all spheres sorted by their cell ``grid.keys``,
    :class:`CellGrid`) of other objects, pairs with a free sphere only; scans the cells within
    ``radii[i]`` plus the largest radius of sphere ``i``'s centre, a run of consecutive keys per
    row of cells. Serial: it runs once a time point, for the statistics (milliseconds), and a
    parallel loop doubled its compile (2.2 s against 1.0 s)."""
    centres, radii, owner, free = muscle.centres, muscle.radii, muscle.owner, muscle.free
    sorted_centres, sorted_radii = everyone.centres, everyone.radii
    sorted_owner, sorted_free, sorted_keys = everyone.owner, everyone.free, grid.keys
    lower, cell, dims = grid.lower, grid.cell, grid.dims
    reach_all = sorted_radii.max() if len(sorted_radii) else 0.0
    for i in range(len(centres)):
        reach = radii[i] + reach_all
        a0, a1 = _cell_span(centres[i, 0], reach, lower[0], cell, dims[0])
        b0, b1 = _cell_span(centres[i, 1], reach, lower[1], cell, dims[1])
        c0, c1 = _cell_span(centres[i, 2], reach, lower[2], cell, dims[2])
        best = 0.0
        for a in range(a0, a1 + 1):
            for b in range(b0, b1 + 1):
                row = (a * dims[1] + b) * dims[2]
                last = row + c1
                s = _first_at_least(sorted_keys, row + c0)
                while s < len(sorted_keys) and sorted_keys[s] <= last:
                    if sorted_owner[s] != owner[i] and (free[i] or sorted_free[s]):
                        dx = centres[i, 0] - sorted_centres[s, 0]
                        dy = centres[i, 1] - sorted_centres[s, 1]
                        dz = centres[i, 2] - sorted_centres[s, 2]
                        depth = radii[i] + sorted_radii[s] - np.sqrt(dx * dx + dy * dy
                                                                     + dz * dz)
                        if depth > best:
                            best = depth
                    s += 1
        out[i] = best
