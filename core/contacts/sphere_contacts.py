"""Sphere contacts shared by both solver methods (the paper's §3.3): the collision spheres and
the state of the two collision structures, detection and the paper's response, and the final
collision passes that remove what overlap the iterations leave.

Detection finds the overlapping spheres of different muscles and of a muscle sphere with a bone
sphere through the chosen structure (:mod:`~muscle_mss.core.contacts.spatial_hash`, the default, or the
paper's :mod:`~muscle_mss.core.contacts.octree_bvh`; both find the same pairs), or, given the bones as
solids, tallies the contacts :mod:`~muscle_mss.core.contacts.solid_contacts` found. The response is the
paper's: per colliding pair each sphere moves half the penetration along the centre line (the
whole when the other is fixed or a bone sphere; nothing when it is fixed itself); the
displacements are accumulated and applied after all tests, and the particles that collided
stop.

The kernels' state travels in named tuples (:class:`SphereState`, :class:`HashState`,
:class:`CandidateLists`, :class:`~muscle_mss.core.contacts.octree_bvh.OctreeBVH`,
:class:`~muscle_mss.core.contacts.solid_contacts.SolidState`): flat, because Numba cannot hand a tuple
nested in a tuple to a parallel loop.
"""
from __future__ import annotations

import time
from collections import namedtuple

import numba
import numpy as np
from numba import njit, prange

from . import octree_bvh, spatial_hash, sphere_lists
from ..model import PreparedModel
from .collision_spheres import Spheres, make_spheres
from ..settings import STRUCTURE_BVH, SolverSettings
from .solid_contacts import respond_solids, solid_contacts, solid_grid, solid_state

# The final collision passes (:func:`project`) stop after this many passes in which the sum of
# the responses' displacements did not fall below PROGRESS times its least so far.
STALLED_PASSES = 10
PROGRESS = 0.95

@njit(cache=True)
def now():
    """Wall-clock seconds (for the per-iteration timings inside kernels)."""
    with numba.objmode(t="float64"):
        t = time.perf_counter()
    return t


SphereState = namedtuple("SphereState", (
    "particle", "radius", "muscle", "fixed", "moves", "centres", "disp", "collided",
    "pair_count", "pair_pen", "sphere_ptr"))
SphereState.__doc__ = """The muscles' collision spheres and their per-iteration contact state.

``particle`` (s,) each sphere's particle (solver order); ``radius`` (s,) mm; ``muscle`` (s,);
``fixed`` (s,) bool and ``moves`` its negation; ``centres`` (3, s) mm gathered from the
particles; ``disp`` (3, s + b) mm the accumulated response and ``collided`` (s + b,) uint8 (bone
spheres after the muscle spheres); ``pair_count`` (s,) colliding pairs and ``pair_pen`` (s,) mm
the deepest of them; ``sphere_ptr`` (M + 1,) each muscle's first sphere."""

HashState = namedtuple("HashState", (
    "bone_centres", "bone_radius", "bone_object", "bone_moves", "muscle_cell", "skin",
    "mb_built", "longest", "pending"))
HashState.__doc__ = """The spatial hash's state for one solve besides its grids: the bone
spheres (``bone_centres`` (3, b) mm, ``bone_radius`` (b,) mm, ``bone_object`` (b,) their object
ids, ``bone_moves`` (b,) all False); the muscle grid's cell ``muscle_cell`` mm and the lists'
``skin`` mm; per muscle sphere the position its bone list was built at ``mb_built`` (3, s) mm
(inf: build now), that list's length ``longest`` (s,) and ``pending`` (s,) (did not fit its
room)."""

CandidateLists = namedtuple("CandidateLists", ("muscle", "mb_begin", "mb_end", "mb_idx", "room"))
CandidateLists.__doc__ = """The spatial hash's candidate lists, replaced when they outgrow their
room: ``muscle`` the muscle-muscle lists (:func:`~muscle_mss.core.contacts.sphere_lists.muscle_lists`),
and each muscle sphere's own list of bone spheres ``mb_idx[mb_begin[i]:mb_end[i]]`` in its
``room`` slots."""

Contacts = namedtuple("Contacts", ("spheres", "hashed", "bone_table", "bvh", "solids", "grid"))
Contacts.__doc__ = """Everything the contact kernels read and write in one solve:
:class:`SphereState`, :class:`HashState`, the bone spheres' grid (built once:
:func:`~muscle_mss.core.contacts.spatial_hash.grid_table`), the octree BVH
(:class:`~muscle_mss.core.contacts.octree_bvh.OctreeBVH`) and the solid contacts
(:class:`~muscle_mss.core.contacts.solid_contacts.SolidState`) with the bones' fields ``grid``
(:func:`~muscle_mss.core.contacts.solid_contacts.solid_grid`). Its parts go to parallel kernels one by
one: Numba cannot hand a tuple nested in a tuple to a parallel loop."""

ContactOptions = namedtuple("ContactOptions", ("use_bvh", "muscle_muscle", "muscle_bone"))
ContactOptions.__doc__ = """Which structure finds the pairs (``use_bvh``: the octree BVH, else
the spatial hash) and which contacts count."""


def contact_options(settings: SolverSettings) -> ContactOptions:
    """The :class:`ContactOptions` of ``settings``."""
    return ContactOptions(settings.contacts.structure == STRUCTURE_BVH, bool(settings.contacts.muscle_muscle),
                          bool(settings.contacts.muscle_bone))


def collision_spheres(prep: PreparedModel, bone_centres=None, bone_radius=None, bone_id=None):
    """The model's collision spheres and the bones' spheres (:func:`make_spheres`; no bones
    when ``bone_centres`` is None) and their :class:`SphereState`: ``(spheres, state)``."""
    if bone_centres is None:
        bone_centres, bone_radius, bone_id = np.zeros((0, 3)), np.zeros(0), np.zeros(0, int)
    spheres = make_spheres(prep.radius, prep.muscle, prep.fixed, prep.boundary, bone_centres,
                           bone_radius, bone_id)
    ns = spheres.count
    nb = len(spheres.bone_radius)
    n_muscles = len(prep.offsets) - 1
    state = SphereState(
        spheres.particle, spheres.radius, spheres.muscle, spheres.fixed, ~spheres.fixed,
        np.zeros((3, ns)), np.zeros((3, ns + nb)), np.zeros(ns + nb, dtype=np.uint8),
        np.zeros(ns, dtype=np.int64), np.zeros(ns),
        np.searchsorted(spheres.muscle, np.arange(n_muscles + 1)))
    return spheres, state


def hash_state(spheres: Spheres, used: bool):
    """``(HashState, bone table, CandidateLists)`` of the spatial hash: the bone table is built here once
    (bones do not move during a solve); the candidate lists in the first iteration
    (muscle-muscle lists then refreshed sphere by sphere,
    :func:`~muscle_mss.core.contacts.sphere_lists.muscle_contacts`). Empty when not ``used``."""
    ns = spheres.count
    skin = spatial_hash.skin_width(spheres, per_sphere=True)
    bone_object = spheres.bone + spheres.n_muscles
    centres = spheres.bone_centres if used else np.zeros((3, 0))
    table = spatial_hash.grid_table(centres, spheres.bone_radius if used else np.zeros(0),
                                    spatial_hash.bone_cell(spheres, skin),
                                    bone_object if used else np.zeros(0, np.int64))
    empty = np.zeros(ns, dtype=np.int64)
    room = spatial_hash.INITIAL_ROOM
    hashed = HashState(spheres.bone_centres, spheres.bone_radius, bone_object,
                       np.zeros(len(spheres.bone_radius), dtype=np.bool_),
                       spatial_hash.muscle_cell(spheres, skin), skin, np.full((3, ns), np.inf),
                       np.zeros(ns, dtype=np.int64), np.zeros(ns, dtype=np.uint8))
    lists = CandidateLists(sphere_lists.muscle_lists(spheres.radius if used else np.zeros(0)),
                           empty, empty.copy(), np.zeros(ns * room, np.int64), room)
    return hashed, table, lists


def bvh_state(spheres: Spheres, settings: SolverSettings) -> octree_bvh.OctreeBVH:
    """The octree BVH of ``spheres`` when ``settings`` choose it, else an empty one."""
    if settings.contacts.structure == STRUCTURE_BVH:
        return octree_bvh.octree_bvh(spheres, int(settings.contacts.bvh_max_depth),
                                     int(settings.contacts.bvh_min_primitives))
    return octree_bvh.octree_bvh(make_spheres(np.zeros(0), np.zeros(0, np.int64),
                                              np.zeros(0, bool), np.zeros(0, bool)))



def contact_setup(spheres: Spheres, sphere_state, settings: SolverSettings, bone_solids, x,
                  prep: PreparedModel):
    """``(Contacts, candidate lists)`` of one solve, both methods': the structure ``settings``
    choose over ``spheres`` and the solids' particles at ``x`` (3, n) mm."""
    hashed, bone_table, lists = hash_state(spheres,
                                           settings.contacts.structure != STRUCTURE_BVH)
    return Contacts(sphere_state, hashed, bone_table, bvh_state(spheres, settings),
                    solid_state(bone_solids, x, prep), solid_grid(bone_solids)), lists

# The parallel kernels below take the arrays of the state, not the tuples: Numba's parallel
# loops lost writes made by an inlined function to arrays taken out of a tuple.

@njit(cache=True, inline="always")
def gather_sphere(s, x, particle, centres, disp, collided):
    """Sphere ``s``'s centre from its particle; its displacement and collided flag cleared."""
    for axis in range(3):
        centres[axis, s] = x[axis, particle[s]]
        disp[axis, s] = 0.0
    collided[s] = 0


@njit(cache=True, inline="always")
def respond_sphere(s, x, v, particle, disp):
    """The response to collided sphere ``s``: its particle moves by the accumulated
    displacement (mm) and stops."""
    p = particle[s]
    for axis in range(3):
        x[axis, p] += disp[axis, s]
        v[axis, p] = 0.0


@njit(cache=True)
def tally(pair_count, pair_pen):
    """``(pairs, deepest mm)``: the sum of ``pair_count`` and the largest of ``pair_pen``."""
    count = 0
    deepest = 0.0
    for s in range(pair_count.shape[0]):
        count += pair_count[s]
        deepest = max(deepest, pair_pen[s])
    return count, deepest


@njit(cache=True)
def _bvh_contacts(spheres, bvh, options, use_solids):
    """:func:`collide` through the octree BVH: ``(muscle pairs, bone pairs, deepest mm,
    seconds of muscle CD)``."""
    t1 = now()
    centres, disp, collided = spheres.centres, spheres.disp, spheres.collided
    ns = spheres.particle.shape[0]
    mm_count, mb_count, deepest = 0, 0, 0.0
    bvh.state[1] += 1
    for g in range(ns, disp.shape[1]):
        for axis in range(3):
            disp[axis, g] = 0.0
        collided[g] = 0
    for axis in range(3):
        bvh.centres[axis, :ns] = centres[axis]
    no_pairs = np.zeros((0, 2), dtype=np.int64)
    n_pairs = np.zeros(1, dtype=np.int64)
    if options.muscle_muscle:
        mm_count, deepest = octree_bvh.bvh_pass(np.bool_(False), bvh, disp, collided, no_pairs,
                                                n_pairs)
    t2 = now()
    if options.muscle_bone and not use_solids:
        mb_count, pen = octree_bvh.bvh_pass(np.bool_(True), bvh, disp, collided, no_pairs, n_pairs)
        deepest = max(deepest, pen)
    return mm_count, mb_count, deepest, t2 - t1


def _bone_list_contacts(spheres, hashed, table, lists):
    """The muscle spheres against the bone spheres through their own candidate lists
    (:func:`~muscle_mss.core.contacts.spatial_hash.own_list_contacts`), the lists grown and the pending
    spheres tested again when one outgrew its room. Returns the lists. Python: called with the
    lists' tuple of 22 arrays, a kernel cost tens of microseconds an iteration to call."""
    room, mb_idx = lists.room, lists.mb_idx
    found = spatial_hash.own_list_contacts(spheres, hashed, table, lists.mb_begin,
                                           lists.mb_end, mb_idx, room, np.bool_(False))
    if found > room:
        # the spheres tested keep their counts; the pending ones get theirs now
        room = 2 * found
        mb_idx = np.empty(spheres.particle.shape[0] * room, dtype=np.int64)
        hashed.mb_built[:, :] = np.inf
        spatial_hash.own_list_contacts(spheres, hashed, table, lists.mb_begin, lists.mb_end,
                                       mb_idx, room, np.bool_(True))
    return CandidateLists(lists.muscle, lists.mb_begin, lists.mb_end, mb_idx, room)


def used_structures(contacts, options):
    """``(bvh, bone_table)`` for :func:`collide`: ``contacts.bvh`` when the run finds its pairs
    through the octree BVH, ``contacts.bone_table`` when the muscle spheres meet the bones as
    sphere sets through the spatial hash, None for what the run does not use: :func:`collide`
    then calls no kernel of that structure, so a run compiles (and loads) none of them."""
    use_solids = contacts.solids.transforms.shape[0] > 0
    bvh = contacts.bvh if options.use_bvh else None
    bone_table = (contacts.bone_table if not options.use_bvh and options.muscle_bone
                  and not use_solids else None)
    return bvh, bone_table


def collide(contacts, options, lists, bvh, bone_table):
    """Collision detection at the gathered sphere centres: each collided sphere's displacement
    by the paper's response into ``spheres.disp``, ``spheres.collided`` set (both cleared by
    the gather); the bones as sphere sets, or as solids (tallied from what
    :func:`~muscle_mss.core.contacts.solid_contacts.solid_contacts` found) when ``solids`` has bones.
    Returns ``(muscle pairs, bone pairs, deepest penetration before the response mm, seconds
    of muscle CD, seconds of bone CD, spheres whose lists were refreshed, lists)``; keep the
    returned :class:`CandidateLists` (grown when they outgrow their room). ``contacts`` a
    :class:`Contacts`, ``options`` :class:`ContactOptions`, ``bvh`` and ``bone_table`` from
    :func:`used_structures`. Python around the kernels, called once an iteration: compiled,
    it compiled its kernels a second time (docs/performance.md, "The first run")."""
    spheres, hashed, solids = contacts.spheres, contacts.hashed, contacts.solids
    use_solids = solids.transforms.shape[0] > 0
    t1 = time.perf_counter()
    mm_count, mb_count, deepest, refreshed = 0, 0, 0.0, 0
    if bvh is not None:
        mm_count, mb_count, deepest, mm_seconds = _bvh_contacts(spheres, bvh, options,
                                                                use_solids)
        t2 = t1 + mm_seconds
    else:
        muscle = lists.muscle
        if options.muscle_muscle:
            refreshed, muscle = sphere_lists.muscle_contacts(
                spheres.centres, spheres.radius, spheres.muscle, spheres.fixed, spheres.moves,
                hashed.skin, hashed.muscle_cell, lists.muscle, spheres.disp, spheres.collided,
                spheres.pair_count, spheres.pair_pen)
            mm_count, deepest = tally(spheres.pair_count, spheres.pair_pen)
        lists = CandidateLists(muscle, lists.mb_begin, lists.mb_end, lists.mb_idx, lists.room)
        t2 = time.perf_counter()
        if bone_table is not None:
            lists = _bone_list_contacts(spheres, hashed, bone_table, lists)
            mb_count, pen = tally(spheres.pair_count, spheres.pair_pen)
            deepest = max(deepest, pen)
    if options.muscle_bone and use_solids:
        # tested in the relaxation's step or in solid_contacts (final passes)
        mb_count, pen = tally(solids.count, solids.pen)
        deepest = max(deepest, pen)
    t3 = time.perf_counter()
    return mm_count, mb_count, deepest, t2 - t1, t3 - t2, refreshed, lists


@njit(cache=True)
def _push_total(spheres, solids, muscle_bone):
    """The sum of the lengths (mm) of the responses' displacements of one pass."""
    push = 0.0
    disp = spheres.disp
    for s in range(spheres.particle.shape[0]):
        if spheres.collided[s]:
            push += np.sqrt(disp[0, s] ** 2 + disp[1, s] ** 2 + disp[2, s] ** 2)
    for k in range(solids.collided.shape[0]):
        if muscle_bone and solids.collided[k]:
            push += np.sqrt(solids.disp[0, k] ** 2 + solids.disp[1, k] ** 2
                            + solids.disp[2, k] ** 2)
    return push


@njit(cache=True, parallel=True)
def _gather_all(x, particle, centres, disp, collided):
    for s in prange(particle.shape[0]):
        gather_sphere(s, x, particle, centres, disp, collided)


@njit(cache=True, parallel=True)
def _respond_all(x, v, particle, disp, collided, ever_collided):
    for s in prange(particle.shape[0]):
        if collided[s]:
            ever_collided[s] = 1
            respond_sphere(s, x, v, particle, disp)


def project(x, v, contacts, options, passes, tolerance, lists, ever_collided, solid_ever, box,
            bvh, bone_table):
    """Collision passes without the MSS step (:func:`collide` and the response) until no pair
    penetrates more than ``tolerance`` mm, at most ``passes`` (``contacts``, ``options``,
    ``lists``, ``bvh``, ``bone_table`` as for :func:`collide`).

    A response moves the spheres of a pair apart as measured before it; when a sphere is
    pressed between two objects (a muscle against a bone, say) one pass leaves half the
    overlap, so the passes repeat it the way the iterations would, without the springs pushing
    back in between (the deepest overlap then halves every two passes). They also stop after
    :data:`STALLED_PASSES` passes in which the sum of the responses' displacements did not fall
    below :data:`PROGRESS` times its least so far: a sphere wedged between two bones (a knee
    joint gap narrower than the sphere) is pushed back and forth and cannot be freed, while the
    pushes of the overlaps that can be resolved shrink geometrically.
    ``ever_collided`` (n_spheres,) gets the spheres that collided in any pass, ``solid_ever``
    the solid-contact particles that met a solid bone (``box`` (2, 3) mm: the world box, as
    for :func:`~muscle_mss.core.contacts.solid_contacts.solid_contacts`). Returns ``(passes run,
    deepest penetration left mm, lists)``: the deepest left is that found by the last pass
    before its response, 0 when nothing collided. A Python loop around the kernels: passes are
    few, and a compiled loop compiled :func:`collide` a second time."""
    spheres, solids = contacts.spheres, contacts.solids
    solids.margin[:] = -np.inf     # every particle tested afresh by the first pass
    done = 0
    deepest = 0.0
    best = np.inf
    since_best = 0
    while done < passes:
        _gather_all(x, spheres.particle, spheres.centres, spheres.disp, spheres.collided)
        if options.muscle_bone and solids.transforms.shape[0] > 0:
            solid_contacts(solids, contacts.grid, box)
        mm_count, mb_count, deepest, mm_seconds, mb_seconds, refreshed, lists = collide(
            contacts, options, lists, bvh, bone_table)
        done += 1
        _respond_all(x, v, spheres.particle, spheres.disp, spheres.collided, ever_collided)
        if options.muscle_bone:
            respond_solids(x, v, solids, solid_ever)
        # measured before the test below, so that the warm-up's passes compile it too
        push = _push_total(spheres, solids, options.muscle_bone)
        if deepest <= tolerance:
            break
        if push < PROGRESS * best:
            best = push
            since_best = 0
        else:
            since_best += 1
            if since_best >= STALLED_PASSES:
                break
    return done, deepest, lists


@njit(cache=True)
def bounding_box(points):
    """``(lower (3,), upper (3,))`` mm: the bounding box of ``points`` (n >= 1, 3) (NumPy's
    ``min(axis=0)`` took 4 ms on the 66,560 particles of the demo thigh at N = 80)."""
    lower = points[0].copy()
    upper = points[0].copy()
    for i in range(1, points.shape[0]):
        for k in range(3):
            lower[k] = min(lower[k], points[i, k])
            upper[k] = max(upper[k], points[i, k])
    return lower, upper


def world_box(positions, bone_centres) -> np.ndarray:
    """(2, 3) mm: the box no sphere centre may leave during a solve — the bounding box of the
    posed particles and the bone spheres grown by its own diagonal on every side. A sphere
    outside it has diverged (a step of the explicit integration too long for the springs):
    the solve stops before the collision structures index a grid or tree with it."""
    points = (np.ascontiguousarray(p, dtype=np.float64).reshape(-1, 3)
              for p in (positions, bone_centres))
    boxes = [bounding_box(part) for part in points if len(part)]
    lower = np.min([low for low, _ in boxes], axis=0) if boxes else np.zeros(3)
    upper = np.max([high for _, high in boxes], axis=0) if boxes else np.zeros(3)
    grow = max(float(np.linalg.norm(upper - lower)), 1.0)
    return np.stack([lower - grow, upper + grow])


def final_passes(x, v, contacts, settings: SolverSettings, lists, collided_spheres,
                 solid_collided, box):
    """The final collision passes of a solve (:func:`project`) when ``settings`` ask for them
    and any contact counts; ``collided_spheres`` and ``solid_collided`` (as :func:`project`'s
    ``ever_collided`` and ``solid_ever``) arrive with the contacts of the solve and leave with
    those of the passes too. Returns ``(passes run, deepest overlap left mm, seconds)``."""
    if not (settings.contacts.projection_passes > 0 and (settings.contacts.muscle_muscle or settings.contacts.muscle_bone)):
        return 0, 0.0, 0.0
    tick = time.perf_counter()
    options = contact_options(settings)
    passes, left, _ = project(x, v, contacts, options,
                              int(settings.contacts.projection_passes),
                              float(settings.contacts.penetration_tolerance), lists, collided_spheres,
                              solid_collided, box, *used_structures(contacts, options))
    return passes, left, time.perf_counter() - tick


def solved_state(prep: PreparedModel, x, v, spheres: Spheres, solid_points, collided_spheres,
                 solid_collided) -> dict:
    """The solve's positions (n, 3) mm, velocities (n, 3) mm/s and collided flags (n,) in the
    input particle order (``x``, ``v`` (3, n) in the solver's; the collided spheres
    (``spheres.particle``) and solid-contact particles ``solid_points``), as
    :class:`~muscle_mss.core.model.SolveResult` fields."""
    n = x.shape[1]
    rank = np.empty(n, dtype=np.int64)
    rank[prep.order] = np.arange(n)
    collided = np.zeros(n, dtype=bool)
    collided[spheres.particle] = collided_spheres[:spheres.count] > 0
    collided[solid_points] |= solid_collided > 0
    return {"positions": x.T[rank].copy(), "velocity": v.T[rank].copy(),
            "collided": collided[rank]}

