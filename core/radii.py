"""Boundary particles and their collision spheres (the paper's §3.3, DESIGN §6 "Boundary, radii").

Only *boundary* particles take part in collisions (and form the MVC cage): with a
``fibre_grid`` they are the surface of the particle lattice — every particle of the fibres on the
grid's outer ring plus the two end faces (:func:`boundary_from_grid`); without one, the particles
nearest to the muscle surface's vertices (:func:`boundary_from_surface`).

Each boundary particle is the centre of a sphere. The paper's radius heuristic
(:func:`sphere_radii`): every surface vertex is collected by its nearest boundary particle, and a
particle's radius is the mean distance to the vertices it collected — a compromise between
covering the muscle surface and claiming little space outside it. A boundary particle that
collects no vertex (its surroundings are covered by its neighbours' spheres) gets the distance to
its nearest surface vertex: its sphere just reaches the surface. That distance is also the
simpler rule used for every boundary particle when the heuristic is off.

Then :func:`shrink_radii` removes every overlap between spheres of different muscles in the
rest pose, so that the collision handling does not push muscles apart before they move, and
:func:`clear_of_obstacles` every overlap with the bone spheres: the demo's muscles lie ~0.3 mm
from their bones, and a muscle sphere of the heuristic's radius reaching into the femur was
pushed out every iteration, crushing the lattice (vastus intermedius lost 48 % of its volume in
a solve of the unmoved rest pose).
"""
from __future__ import annotations

from itertools import chain

import numpy as np
from scipy.spatial import cKDTree

# Shrunk spheres are kept this fraction apart so that round-off cannot leave them touching
# with a sum of radii one ulp above their distance.
SHRINK_MARGIN = 1e-9


def boundary_from_grid(grid, fibre_id, fibre_index) -> np.ndarray:
    """(P,) bool: the particles on the surface of the fibre lattice.

    A particle is on it when its fibre lacks one of its four grid neighbours (row +-1, col +-1)
    — on a full rectangular grid, the outer ring of fibres — or when it is the first or last
    particle of its fibre (the two end faces). An ``R x C`` grid with ``n`` particles per fibre
    has ``2 (R + C - 2) n + 2 (R - 2)(C - 2)`` boundary particles.

    Parameters
    ----------
    grid, fibre_id, fibre_index : (P, 2) int, (P,) int, (P,) int
        Each particle's fibre's place in ``fibre_grid``, its fibre and its place along it, as
        :func:`~muscle_mss.core.springs.lattice_places` takes them (the grid need not be a
        full rectangle here).
    """
    grid = np.asarray(grid, dtype=np.int64).reshape(-1, 2)
    fibre_id = np.asarray(fibre_id, dtype=np.int64).ravel()
    fibre_index = np.asarray(fibre_index, dtype=np.int64).ravel()
    if len(fibre_id) == 0:
        return np.zeros(0, dtype=bool)
    # one code per grid place, with a free row / column on every side so neighbours stay >= 0
    low = grid.min(axis=0) - 1
    width = int(grid[:, 1].max() - low[1] + 2)
    code = (grid[:, 0] - low[0]) * width + (grid[:, 1] - low[1])
    places = np.unique(code)
    ring = np.zeros(len(code), dtype=bool)
    for step in (1, -1, width, -width):
        ring |= ~np.isin(code + step, places)
    _, inverse = np.unique(fibre_id, return_inverse=True)
    inverse = inverse.ravel()
    last = np.zeros(inverse.max() + 1, dtype=np.int64)
    np.maximum.at(last, inverse, fibre_index)
    ends = (fibre_index == 0) | (fibre_index == last[inverse])
    return ring | ends


def boundary_from_surface(particles, surface_points) -> np.ndarray:
    """(P,) bool: the particles that are the nearest particle of at least one surface vertex.

    particles (P, 3), surface_points (V, 3) float64 mm.
    """
    particles = np.asarray(particles, dtype=np.float64).reshape(-1, 3)
    _, nearest = cKDTree(particles).query(np.asarray(surface_points, dtype=np.float64))
    boundary = np.zeros(len(particles), dtype=bool)
    boundary[nearest] = True
    return boundary


def sphere_radii(particles, boundary, surface_points, heuristic: bool = True) -> np.ndarray:
    """(P,) float64 mm: the collision sphere radius of each particle, 0 where not boundary.

    Parameters
    ----------
    particles : (P, 3) float64, mm
        Rest positions.
    boundary : (P,) bool
    surface_points : (V, 3) float64, mm
        The vertices of the muscle's rest surface.
    heuristic : bool
        The paper's rule (mean distance to the collected vertices; the nearest-vertex distance
        for a particle that collects none) or, when False, the nearest-vertex distance for all.
    """
    particles = np.asarray(particles, dtype=np.float64).reshape(-1, 3)
    surface_points = np.asarray(surface_points, dtype=np.float64).reshape(-1, 3)
    centres = np.flatnonzero(np.asarray(boundary, dtype=bool))
    radii = np.zeros(len(particles))
    if len(centres) == 0:
        return radii
    to_surface, _ = cKDTree(surface_points).query(particles[centres])
    if heuristic:
        distance, collector = cKDTree(particles[centres]).query(surface_points)
        count = np.bincount(collector, minlength=len(centres))
        total = np.bincount(collector, weights=distance, minlength=len(centres))
        to_surface = np.where(count > 0, total / np.maximum(count, 1), to_surface)
    radii[centres] = to_surface
    return radii


def overlapping_pairs(centres, radii, object_id):
    """Pairs of spheres of different objects that overlap: ``(a, b, distance)``.

    ``a``, ``b`` (m,) int64 index the spheres (a pair may appear in both orders), distance (m,)
    float64 mm; only spheres with a positive radius count. centres (P, 3) mm, radii (P,) mm,
    object_id (P,) int.
    """
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    radii = np.asarray(radii, dtype=np.float64).ravel()
    object_id = np.asarray(object_id).ravel()
    spheres = np.flatnonzero(radii > 0)
    empty = np.zeros(0, dtype=np.int64)
    if len(spheres) < 2:
        return empty, empty, np.zeros(0)
    # two spheres overlap only if their distance is below twice the larger radius, so each
    # overlapping pair is found from its larger sphere
    found = cKDTree(centres[spheres]).query_ball_point(centres[spheres], 2.0 * radii[spheres])
    counts = np.fromiter(map(len, found), dtype=np.int64, count=len(found))
    a = spheres[np.repeat(np.arange(len(spheres)), counts)]
    b = spheres[np.fromiter(chain.from_iterable(found), dtype=np.int64, count=int(counts.sum()))]
    a, b = a[object_id[a] != object_id[b]], b[object_id[a] != object_id[b]]
    distance = np.linalg.norm(centres[a] - centres[b], axis=1)
    overlap = distance < radii[a] + radii[b]
    return a[overlap], b[overlap], distance[overlap]


def shrink_radii(centres, radii, object_id) -> np.ndarray:
    """(P,) float64 mm: radii shrunk until no two spheres of different objects overlap.

    For an overlapping pair at distance ``d`` the larger sphere gives way first: both radii are
    capped at the ``t`` with ``min(r_a, t) + min(r_b, t) = d`` (so one huge sphere shrinks
    instead of its small neighbour; two equal spheres end at ``d / 2`` each). Each sphere takes
    the smallest cap of all its pairs. Caps only lower radii, so the pair giving a sphere its
    cap stays separated whatever its partner's other pairs do: one pass removes every overlap
    and no new overlap can appear. Spheres of the same object may overlap and are not changed
    for each other; particles of two objects at the same place end with radius 0.

    Parameters
    ----------
    centres : (P, 3) float64, mm
    radii : (P,) float64, mm
        0 for particles without a sphere.
    object_id : (P,) int
        Which muscle (object) each sphere belongs to.
    """
    radii = np.array(radii, dtype=np.float64).ravel()
    a, b, distance = overlapping_pairs(centres, radii, object_id)
    if len(a) == 0:
        return radii
    small = np.minimum(radii[a], radii[b])
    cap = np.where(distance >= 2.0 * small, distance - small, 0.5 * distance)
    cap *= 1.0 - SHRINK_MARGIN
    limit = np.full(len(radii), np.inf)
    np.minimum.at(limit, a, cap)
    np.minimum.at(limit, b, cap)
    return np.minimum(radii, limit)


def clear_of_obstacles(centres, radii, obstacle_centres, obstacle_radii) -> np.ndarray:
    """(P,) float64 mm: radii lowered until no sphere overlaps an obstacle sphere (a bone
    sphere, which never gives way); a particle closer to an obstacle than its radius gets 0
    (no sphere). Only spheres with a positive radius are looked at.

    centres (P, 3) mm, radii (P,) mm; obstacle_centres (B, 3) mm, obstacle_radii (B,) mm.
    """
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    radii = np.array(radii, dtype=np.float64).ravel()
    obstacle_centres = np.asarray(obstacle_centres, dtype=np.float64).reshape(-1, 3)
    obstacle_radii = np.asarray(obstacle_radii, dtype=np.float64).ravel()
    spheres = np.flatnonzero(radii > 0)
    if len(spheres) == 0 or len(obstacle_radii) == 0:
        return radii
    found = cKDTree(obstacle_centres).query_ball_point(centres[spheres],
                                                       radii[spheres] + obstacle_radii.max())
    counts = np.fromiter(map(len, found), dtype=np.int64, count=len(found))
    a = np.repeat(spheres, counts)
    b = np.fromiter(chain.from_iterable(found), dtype=np.int64, count=int(counts.sum()))
    room = np.linalg.norm(centres[a] - obstacle_centres[b], axis=1) - obstacle_radii[b]
    limit = np.full(len(radii), np.inf)
    np.minimum.at(limit, a, np.maximum(room, 0.0) * (1.0 - SHRINK_MARGIN))
    return np.minimum(radii, limit)
