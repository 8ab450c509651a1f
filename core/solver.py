"""The relaxation loop of the paper's §3.1 and §3.3: MSS update, then collision handling.

Each iteration:

1. mass-spring update (:func:`muscle_mss.core.mss.muscle_step`: Hooke + damping along the spring,
   a viscous drag on the velocities and the pressure of each muscle's cage against a change of
   its rest volume, semi-implicit Euler, fixed particles stay);
2. collision detection among the boundary spheres of different muscles and between muscle
   spheres and bone spheres, through the chosen structure (:mod:`~muscle_mss.core.spatial_hash`,
   the default, or the paper's :mod:`~muscle_mss.core.octree_bvh`); both find the same pairs;
   or, given the bones as solids (:class:`~muscle_mss.core.bone_distance.BoneSolids`, issue
   14), muscle spheres against each bone's signed distance (:func:`_solid_contacts`): a sphere
   carried past a bone's shell of spheres is pushed on through it by the inner spheres, while
   the distance gradient takes it out by the nearer side from any depth;
3. response exactly as the paper: per colliding pair each sphere moves half the penetration along
   the centre line (the whole when the other is fixed or a bone sphere; nothing when it is fixed
   itself; against a solid, the whole way out to its radius plus the bone's clearance along the
   distance gradient); the displacements are accumulated and applied after all tests, and the
   particles that collided get zero velocity;
4. per muscle the mean displacement ``mean |x_k - x_{k-1}|`` (the paper's figures 5 and 6), the
   colliding pairs, the deepest penetration (of the pairs a response can resolve: a tendon
   attachment, fixed, sits inside its bone for good) and the elapsed seconds are recorded.

Terminations (:data:`TERMINATIONS`): a fixed number of iterations; the mean displacement below a
threshold (every muscle's, and not rising: the displacement first grows while the posed model
starts to move, so a small value in the first iterations is no sign of rest); a wall-clock
budget (checked after every iteration). ``iterations`` caps all three. A muscle whose mean
displacement is not finite or exceeds its own size in one iteration has diverged: the solve
stops with a :class:`MuscleMSSError` naming it.

After the last iteration, collision passes without the MSS update (:func:`_project`, the same
detection and response) run until no pair of spheres of different objects overlaps by more
than a tolerance (at most ``projection_passes``). One response leaves overlap behind wherever
a sphere is pressed between two objects — a muscle sphere pushed by another muscle into a
bone moves out of the bone by the whole bone penetration and back by half the muscle one —
and in every iteration the springs push such a sphere back in; on the demo thigh at the most
flexed pose a third of the mean sphere radius stays overlapped after 500 iterations without
these passes, under the 0.01 mm default tolerance with them.

The loop runs in Numba kernels of :data:`CHUNK_SECONDS` each; between chunks ``progress(f)`` is
called and may return True to abort. Every sum has a fixed order: the same inputs give
bitwise the same result on the same machine, whatever the thread count.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from . import octree_bvh, spatial_hash
from .bone_distance import BRICK, NO_SOLIDS, BoneSolids, _push_rest, _sample, _to_rest
from .errors import MuscleMSSError
from .cage import muscle_cage
from .mss import (Spheres, VolumeCages, lattice_order, make_spheres, muscle_step, now,
                  spring_layout)
from .settings import (STRUCTURE_BVH, STRUCTURE_HASH, STRUCTURES, TERMINATION_BUDGET,
                       TERMINATION_ITERATIONS, TERMINATION_THRESHOLD, TERMINATIONS,
                       SolverSettings)
from .volume import signed_volume


STALLED_PASSES = 10
PROGRESS = 0.95
CHUNK_SECONDS = 0.1

RUNNING, CONVERGED, OUT_OF_TIME, DIVERGED = range(4)


@dataclass
class MSSModel:
    """The posed mass-spring model of all muscles (arrays concatenated muscle after muscle).

    ``names`` the muscles; ``offsets`` (M+1,) their particle ranges; ``positions`` (n, 3) mm
    posed; ``fixed``, ``boundary`` (n,) bool; ``mass`` (n,) g; ``radius`` (n,) mm;
    ``fibre_id``, ``fibre_index`` (n,) int and optional ``fibre_grid`` (n, 2) (to order the
    particles for speed, and for the cages); ``springs`` (S, 2) int global particle indices;
    ``rest_length`` mm, ``stiffness`` g/s^2, ``damping`` g/s (S,); ``rest_positions`` (n, 3) mm,
    the rest pose whose cage volumes the volume force keeps (omitted: ``positions``);
    ``in_bone_at_rest`` (n,) bool, the particles inside a bone in the rest pose (the bones as
    solids leave them there; omitted: not known, and only the particles with a sphere are
    kept out of the solids).
    """

    names: list
    offsets: np.ndarray
    positions: np.ndarray
    fixed: np.ndarray
    mass: np.ndarray
    boundary: np.ndarray
    radius: np.ndarray
    fibre_id: np.ndarray
    fibre_index: np.ndarray
    springs: np.ndarray
    rest_length: np.ndarray
    stiffness: np.ndarray
    damping: np.ndarray
    fibre_grid: np.ndarray | None = None
    rest_positions: np.ndarray | None = None
    in_bone_at_rest: np.ndarray | None = None


@dataclass
class SolveResult:
    """Solved state (input particle order) and the per-iteration history.

    ``positions``, ``velocity`` (n, 3) mm, mm/s; ``collided`` (n,) bool (last iteration);
    ``mean_displacement`` (K, M) mm; ``muscle_pairs``, ``bone_pairs`` (K,) colliding pairs;
    ``max_penetration`` (K,) mm (deepest before the response, of a pair not fixed on both
    sides); ``seconds`` (K,) cumulative;
    ``phase_seconds`` MSS / muscle-muscle CD / muscle-bone CD (with the response) totals of the
    iterations, and the final projection's (against bones as solids the muscle-bone contacts
    run inside the MSS step's parallel region, so their time is in MSS, and muscle-bone CD is
    their tally only); ``stopped_by`` the termination that ended the loop;
    ``projection_passes`` the collision passes after the last iteration and
    ``remaining_penetration`` (mm) the deepest overlap the last of them found (0: none; at most
    the tolerance unless the passes ran out).
    """

    positions: np.ndarray
    velocity: np.ndarray
    collided: np.ndarray
    mean_displacement: np.ndarray
    muscle_pairs: np.ndarray
    bone_pairs: np.ndarray
    max_penetration: np.ndarray
    seconds: np.ndarray
    phase_seconds: dict = field(default_factory=dict)
    stopped_by: str = TERMINATION_ITERATIONS
    rebuilds: int = 0
    projection_passes: int = 0
    remaining_penetration: float = 0.0

    @property
    def iterations(self) -> int:
        return len(self.seconds)

    @property
    def colliding_pairs(self) -> np.ndarray:
        return self.muscle_pairs + self.bone_pairs


@dataclass
class PreparedModel:
    """What depends only on the model's topology: particle order and spring layout."""

    order: np.ndarray
    offsets: np.ndarray
    layout: object
    cages: VolumeCages
    inv_mass: np.ndarray
    radius: np.ndarray
    muscle: np.ndarray
    fixed: np.ndarray
    boundary: np.ndarray
    in_bone_at_rest: np.ndarray | None = None   # (n,) bool, solver order, or None: not known
    cache: dict = field(default_factory=dict)   # other methods' topology data (factorisations)
    stable_step: tuple | None = None            # stable_time_step(model) (springs, masses)


def prepare(model: MSSModel) -> PreparedModel:
    """Order the particles (lattice neighbours at constant offsets) and group the springs;
    reusable for every pose of the same model."""
    offsets = np.asarray(model.offsets, dtype=np.int64)
    n = int(offsets[-1])
    order = np.empty(n, dtype=np.int64)
    for m in range(len(offsets) - 1):
        lo, hi = offsets[m], offsets[m + 1]
        grid = None if model.fibre_grid is None else model.fibre_grid[lo:hi]
        order[lo:hi] = lo + lattice_order(model.fibre_id[lo:hi], model.fibre_index[lo:hi], grid)
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n)
    springs = rank[np.asarray(model.springs, dtype=np.int64).reshape(-1, 2)]
    layout = spring_layout(springs, model.rest_length, model.stiffness, model.damping, offsets)
    fixed = np.asarray(model.fixed, dtype=bool)[order]
    inv_mass = np.where(fixed, 0.0, 1.0 / np.asarray(model.mass, dtype=np.float64)[order])
    muscle = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    in_bone = (None if model.in_bone_at_rest is None
                else np.asarray(model.in_bone_at_rest, dtype=bool)[order])
    return PreparedModel(order, offsets, layout, _cages(model, rank), inv_mass,
                         np.asarray(model.radius, dtype=np.float64)[order], muscle, fixed,
                         np.asarray(model.boundary, dtype=bool)[order], in_bone,
                         stable_step=stable_time_step(model))


def _cages(model: MSSModel, rank) -> VolumeCages:
    """Each muscle's MVC cage (:func:`muscle_mss.core.cage.muscle_cage`) in the solver's particle
    order, with its rest volume. A muscle whose boundary particles span no solid (a sheet, a
    line: no volume to keep) gets no cage."""
    offsets = np.asarray(model.offsets, dtype=np.int64)
    rest = np.asarray(model.positions if model.rest_positions is None else model.rest_positions,
                      dtype=np.float64).reshape(-1, 3)
    triangles, counts, volumes = [], [], []
    for m, name in enumerate(model.names):
        lo, hi = offsets[m], offsets[m + 1]
        grid = None if model.fibre_grid is None else model.fibre_grid[lo:hi]
        try:
            cage = muscle_cage(rest[lo:hi], model.boundary[lo:hi], model.fibre_id[lo:hi],
                               model.fibre_index[lo:hi], grid, where=f"muscle '{name}'")
        except MuscleMSSError:
            counts.append(0)
            volumes.append(1.0)
            continue
        corners = lo + cage.vertices
        triangles.append(rank[corners[cage.triangles]])
        counts.append(len(cage.triangles))
        volumes.append(signed_volume(rest[corners], cage.triangles))
    ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return VolumeCages(ptr, np.concatenate(triangles).astype(np.int64) if triangles
                       else np.zeros((0, 3), np.int64), np.asarray(volumes, dtype=np.float64))


# ---- the kernel ------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def _gather_sphere(s, x, particle, centres, disp, collided):
    """Sphere ``s``'s centre from its particle; its displacement and collided flag cleared."""
    for axis in range(3):
        centres[axis, s] = x[axis, particle[s]]
        disp[axis, s] = 0.0
    collided[s] = 0


@njit(cache=True, inline="always")
def _respond_sphere(s, x, v, particle, disp):
    """The response to collided sphere ``s``: its particle moves by the accumulated
    displacement (mm) and stops."""
    p = particle[s]
    for axis in range(3):
        x[axis, p] += disp[axis, s]
        v[axis, p] = 0.0


@njit(cache=True, parallel=True)
def _step_and_gather(mss, spheres, box, escaped, solids, use_solids):
    """The MSS step of every muscle (:func:`muscle_mss.core.mss.muscle_step`), each muscle's
    sphere centres then gathered for the collision tests and, with ``use_solids``, its
    particles tested against the bones as solids (:func:`_solid_points`; not timed apart: a
    clock in a parallel region takes the GIL) — one parallel region: every region costs a
    thread wake-up (~0.1 ms on a virtual machine), which is a large part of one iteration at
    N = 80.
    ``escaped[m]`` is set when a sphere centre or a particle tested against the solids of
    muscle ``m`` lies outside ``box`` (2, 3) mm or is not finite."""
    (x, v, x_prev, force, scratch, inv_mass, dt, drag, bulk_modulus, cage_ptr, cage_triangles,
     rest_volume, offsets, runs_int, runs_param, lane_rest, run_ptr, scattered_int,
     scattered_param, scattered_ptr) = mss
    particle, centres, disp, collided, sphere_ptr = (spheres[0], spheres[5], spheres[6],
                                                     spheres[7], spheres[10])
    for m in prange(offsets.shape[0] - 1):
        muscle_step(m, x, v, x_prev, force, scratch, inv_mass, dt, drag, bulk_modulus,
                    cage_ptr, cage_triangles, rest_volume, offsets, runs_int, runs_param,
                    lane_rest, run_ptr, scattered_int, scattered_param, scattered_ptr)
        inside = True
        for s in range(sphere_ptr[m], sphere_ptr[m + 1]):
            _gather_sphere(s, x, particle, centres, disp, collided)
            for axis in range(3):
                inside &= (centres[axis, s] >= box[0, axis]) & (centres[axis, s] <= box[1, axis])
        if use_solids:
            inside &= _solid_points(solids[21][m], solids[21][m + 1], solids, box)
        escaped[m] = not inside


@njit(cache=True)
def _tally(pair_count, pair_pen):
    count = 0
    deepest = 0.0
    for s in range(pair_count.shape[0]):
        count += pair_count[s]
        deepest = max(deepest, pair_pen[s])
    return count, deepest


# A particle whose distance to every solid bone exceeds its reach by a slack plus its move since
# that distance was sampled times SOLID_LIPSCHITZ is clear of them without sampling: the
# trilinear interpolant of a distance (1-Lipschitz) changes by at most sqrt(3) per mm within the
# narrow band of fine bricks (continuous across them). It jumps where a fine brick meets a
# coarse one, by the coarse grid's interpolation error, but those faces lie farther than the
# band (4 mm) from the surface, beyond the reach of the demo's spheres; a contact missed there
# is found once the particle has moved, and the final passes test every particle afresh.
SOLID_LIPSCHITZ = np.sqrt(3.0)
SOLID_SLACK_CELLS = 1.0         # fine cells: the slack in mm is this times the field's spacing


@njit(cache=True)
def _solid_points(first, last, solids, box):
    """Particles ``first..last-1`` of ``solids`` (:func:`solid_arguments`: every free particle
    not inside a bone at rest, each with its sphere's radius or 0) against the bones as solids:
    a particle closer to bone b's surface than its radius plus the bone's clearance, or inside
    the bone, gets the displacement that takes it out to that distance along the distance
    gradient (the whole penetration, as against a bone sphere, from whatever depth) in the
    state's ``disp``, and ``collided`` set (:func:`_respond_solids` applies them). A particle
    outside a bone's sampled box by its reach or more is clear of it (the field is at least the
    box's padding there); one that has moved little since it was last found clear of every bone
    by a margin is skipped (:data:`SOLID_LIPSCHITZ`); one outside ``box`` (2, 3) mm or not
    finite is left alone, and the return value is then False (diverged). One muscle's particles
    per call: a call passes the whole state tuple, too dear per particle."""
    (transforms, clearance, tolerance, origin, spacing, dims, coarse_start, coarse, index_start,
     brick_index, bricks, x, points, radius, anchor, margin, slack, disp, collided, count,
     pen) = solids[:21]
    inside = True
    for k in range(first, last):
        count[k] = 0
        pen[k] = 0.0
        collided[k] = 0
        p = points[k]
        cx, cy, cz = x[0, p], x[1, p], x[2, p]
        if not ((cx >= box[0, 0]) & (cx <= box[1, 0]) & (cy >= box[0, 1]) & (cy <= box[1, 1])
                & (cz >= box[0, 2]) & (cz <= box[1, 2])):
            inside = False
            continue
        ex, ey, ez = cx - anchor[0, k], cy - anchor[1, k], cz - anchor[2, k]
        room = margin[k] - slack
        if room > 0.0 and SOLID_LIPSCHITZ ** 2 * (ex * ex + ey * ey + ez * ez) < room * room:
            continue
        clear = np.inf
        for axis in range(3):
            disp[axis, k] = 0.0
        for b in range(transforms.shape[0]):
            qx, qy, qz = _to_rest(transforms, b, cx, cy, cz)
            reach = radius[k] + clearance[b]
            h = spacing[b]
            ox = max(origin[b, 0] - qx, qx - origin[b, 0] - dims[b, 0] * BRICK * h, 0.0)
            oy = max(origin[b, 1] - qy, qy - origin[b, 1] - dims[b, 1] * BRICK * h, 0.0)
            oz = max(origin[b, 2] - qz, qz - origin[b, 2] - dims[b, 2] * BRICK * h, 0.0)
            away = np.sqrt(ox * ox + oy * oy + oz * oz)
            if away > 0.0 and away >= reach:
                clear = min(clear, away - reach)
                continue
            value = _sample(b, qx, qy, qz, origin, spacing, dims, coarse_start, coarse,
                            index_start, brick_index, bricks)[0]
            if value >= reach - tolerance:
                clear = min(clear, value - reach)
                continue
            clear = -np.inf
            px, py, pz, _ = _push_rest(b, qx, qy, qz, reach, tolerance, origin, spacing, dims,
                                       coarse_start, coarse, index_start, brick_index, bricks)
            m = transforms[b]
            dx, dy, dz = px - qx, py - qy, pz - qz
            for axis in range(3):
                disp[axis, k] += m[axis, 0] * dx + m[axis, 1] * dy + m[axis, 2] * dz
            collided[k] = 1
            count[k] += 1
            pen[k] = max(pen[k], reach - value)
        anchor[0, k], anchor[1, k], anchor[2, k] = cx, cy, cz
        margin[k] = clear
    return inside


@njit(cache=True, parallel=True)
def _solid_contacts(solids, box):
    """:func:`_solid_points` for every particle of ``solids``, muscle by muscle in parallel
    (the final passes; the iterations run it inside :func:`_step_and_gather`'s region, where
    there is no thread wake-up to pay)."""
    ptr = solids[21]
    for m in prange(ptr.shape[0] - 1):
        _solid_points(ptr[m], ptr[m + 1], solids, box)


@njit(cache=True)
def _respond_solids(x, v, solids, ever):
    """The response to :func:`_solid_contacts`: each collided particle moves by its
    displacement (mm) and stops; ``ever`` (k,) gets it (the final passes' record)."""
    points, disp, collided = solids[12], solids[17], solids[18]
    for k in range(points.shape[0]):
        if collided[k]:
            p = points[k]
            for axis in range(3):
                x[axis, p] += disp[axis, k]
                v[axis, p] = 0.0
            ever[k] = 1


@njit(cache=True, parallel=True)
def _collide(spheres, hashed, bvh, use_bvh, muscle_muscle, muscle_bone, lists, solids):
    """Collision detection at the gathered sphere centres: each collided sphere's displacement
    by the paper's response into ``disp``, ``collided`` set (both cleared by the gather); the
    bones as sphere sets, or as solids (:func:`_solid_contacts`) when ``solids`` has bones.
    Returns ``(muscle pairs, bone pairs, deepest penetration before the response mm, seconds
    of muscle CD, seconds of bone CD, spheres whose lists were refreshed, lists)``; keep the
    returned lists (the spatial hash's candidate lists, grown when they outgrow their room)."""
    (particle, radius, muscle, fixed, moves, centres, disp, collided, pair_count,
     pair_pen, sphere_ptr) = spheres
    (bone_centres, bone_radius, bone_object, bone_moves, bone_table, muscle_cell, skin,
     mb_built, longest, pending) = hashed
    mm_lists, mb_begin, mb_end, mb_idx, room = lists
    (b_centres, b_radius, b_fixed, perm, b_scratch, object_first, static, node_int, node_box,
     node_stamp, stack, state, best_pen, best_dir, best_partner, touched, n_muscles, max_depth,
     min_primitives, no_pairs, n_pairs) = bvh
    ns = particle.shape[0]
    use_solids = solids[0].shape[0] > 0
    t1 = now()
    mm_count = 0
    mb_count = 0
    deepest = 0.0
    refreshed = 0
    if use_bvh:
        state[1] += 1
        for g in range(ns, disp.shape[1]):
            for axis in range(3):
                disp[axis, g] = 0.0
            collided[g] = 0
        for axis in range(3):
            b_centres[axis, :ns] = centres[axis]
        if muscle_muscle:
            mm_count, deepest = octree_bvh.bvh_pass(
                False, n_muscles, max_depth, min_primitives, b_centres, b_radius, b_fixed,
                perm, b_scratch, object_first, static, node_int, node_box, node_stamp, stack,
                state, best_pen, best_dir, best_partner, touched, disp, collided, no_pairs,
                n_pairs)
        t2 = now()
        if muscle_bone and not use_solids:
            mb_count, pen = octree_bvh.bvh_pass(
                True, n_muscles, max_depth, min_primitives, b_centres, b_radius, b_fixed,
                perm, b_scratch, object_first, static, node_int, node_box, node_stamp, stack,
                state, best_pen, best_dir, best_partner, touched, disp, collided, no_pairs,
                n_pairs)
            deepest = max(deepest, pen)
    else:
        if muscle_muscle:
            refreshed, mm_lists = spatial_hash.muscle_contacts(
                centres, radius, muscle, fixed, moves, skin, muscle_cell, mm_lists, disp,
                collided, pair_count, pair_pen)
            mm_count, deepest = _tally(pair_count, pair_pen)
        t2 = now()
        if muscle_bone and not use_solids:
            found = spatial_hash.own_list_contacts(
                centres, radius, fixed, muscle, bone_table, skin, mb_built, mb_begin, mb_end,
                mb_idx, room, longest, pending, False, bone_centres, bone_radius, bone_object,
                bone_moves, disp, collided, pair_count, pair_pen)
            if found > room:
                # the spheres tested keep their counts; the pending ones get theirs now
                mb_count, pen = _tally(pair_count, pair_pen)
                room = 2 * found
                mb_idx = np.empty(ns * room, dtype=np.int64)
                mb_built[:, :] = np.inf
                spatial_hash.own_list_contacts(
                    centres, radius, fixed, muscle, bone_table, skin, mb_built, mb_begin,
                    mb_end, mb_idx, room, longest, pending, True, bone_centres, bone_radius,
                    bone_object, bone_moves, disp, collided, pair_count, pair_pen)
            mb_count, pen = _tally(pair_count, pair_pen)
            deepest = max(deepest, pen)
    if muscle_bone and use_solids:
        # tested in _step_and_gather (iterations) or _solid_contacts (final passes)
        mb_count, pen = _tally(solids[19], solids[20])
        deepest = max(deepest, pen)
    t3 = now()
    return (mm_count, mb_count, deepest, t2 - t1, t3 - t2, refreshed,
            (mm_lists, mb_begin, mb_end, mb_idx, room))


@njit(cache=True, inline="always")
def _mean_step(x, x_prev, first, last):
    """Mean distance (mm) particles ``first..last-1`` moved since ``x_prev``."""
    total = 0.0
    for p in range(first, last):
        d2 = 0.0
        for axis in range(3):
            d2 += (x[axis, p] - x_prev[axis, p]) ** 2
        total += np.sqrt(d2)
    return total / max(last - first, 1)


@njit(cache=True)
def _first_set(flags):
    """Index of the first nonzero entry of ``flags``, or -1."""
    for m in range(flags.shape[0]):
        if flags[m]:
            return m
    return -1


@njit(cache=True, parallel=True)
def _solve_chunk(mss, spheres, hashed, bvh, history, control, first, last, started, lists,
                 solids):
    """Iterations ``first`` up to ``last`` (fewer when a termination stops the loop): the MSS
    step, :func:`_collide`, the response; each iteration's row of ``history``. Returns
    ``(status, iterations done, diverged muscle or -1, list refreshes, lists)``."""
    x, v, x_prev, offsets = mss[0], mss[1], mss[2], mss[12]
    particle, disp, collided, sphere_ptr = spheres[0], spheres[6], spheres[7], spheres[10]
    scratch = np.zeros(solids[12].shape[0], dtype=np.uint8)
    mean_disp, muscle_pairs, bone_pairs, max_pen, seconds, phases = history
    (use_bvh, muscle_muscle, muscle_bone, termination, threshold, budget, limit, box) = control
    use_solids = solids[0].shape[0] > 0
    escaped = np.zeros(offsets.shape[0] - 1, dtype=np.bool_)
    status = RUNNING
    bad = -1
    rebuilds = 0
    it = first
    while it < last and status == RUNNING:
        t0 = now()
        _step_and_gather(mss, spheres, box, escaped, solids, muscle_bone and use_solids)
        t1 = now()
        bad = _first_set(escaped)
        if bad >= 0:
            # a sphere left the world box (or is not finite): stop before any collision
            # structure indexes its grid or tree with it
            for m in range(mean_disp.shape[1]):
                mean_disp[it, m] = _mean_step(x, x_prev, offsets[m], offsets[m + 1])
            seconds[it] = now() - started
            status = DIVERGED
            it += 1
            break
        mm_count, mb_count, deepest, mm_seconds, mb_seconds, refreshed, lists = _collide(
            spheres, hashed, bvh, use_bvh, muscle_muscle, muscle_bone, lists, solids)
        rebuilds += refreshed
        t3 = now()
        # the response: apply the displacements, stop the collided particles; each muscle's
        # mean particle displacement of the iteration, mean |x - x_prev|
        if muscle_bone:
            _respond_solids(x, v, solids, scratch)
        for m in prange(offsets.shape[0] - 1):
            for s in range(sphere_ptr[m], sphere_ptr[m + 1]):
                if collided[s]:
                    _respond_sphere(s, x, v, particle, disp)
            mean_disp[it, m] = _mean_step(x, x_prev, offsets[m], offsets[m + 1])
        t4 = now()
        phases[0] += (t1 - t0) + (t4 - t3)
        phases[1] += mm_seconds
        phases[2] += mb_seconds
        muscle_pairs[it] = mm_count
        bone_pairs[it] = mb_count
        max_pen[it] = deepest
        seconds[it] = t4 - started
        top = 0.0
        for m in range(mean_disp.shape[1]):
            if not mean_disp[it, m] <= limit[m]:
                status = DIVERGED
                bad = m
                break
            top = max(top, mean_disp[it, m])
        if status == RUNNING and termination == 1 and it > 0 and top < threshold:
            previous = 0.0
            for m in range(mean_disp.shape[1]):
                previous = max(previous, mean_disp[it - 1, m])
            if top <= previous:
                status = CONVERGED
        if status == RUNNING and termination == 2 and seconds[it] >= budget:
            status = OUT_OF_TIME
        it += 1
    return status, it, bad, rebuilds, lists


@njit(cache=True, parallel=True)
def _project(x, v, spheres, hashed, bvh, use_bvh, muscle_muscle, muscle_bone, passes,
             tolerance, lists, ever_collided, solids, solid_ever, box):
    """Collision passes without the MSS step (:func:`_collide` and the response) until no
    pair penetrates more than ``tolerance`` mm, at most ``passes``. A response moves the
    spheres of a pair apart as measured before it; when a sphere is pressed between two
    objects (a muscle against a bone, say) one pass leaves half the overlap, so the passes
    repeat it the way the iterations would, without the springs pushing back in between (the
    deepest overlap then halves every two passes). They also stop after
    :data:`STALLED_PASSES` passes in which the sum of the responses' displacements did not fall
    below :data:`PROGRESS` times its least so far: a sphere wedged between two bones (a knee
    joint gap narrower than the sphere) is pushed back and forth and cannot be freed, while the
    pushes of the overlaps that can be resolved shrink geometrically.
    ``ever_collided`` (n_spheres,) gets the spheres that collided in any pass, ``solid_ever``
    the particles of ``solids`` (as for :func:`_collide`) that met a solid bone (``box`` as for
    :func:`_solid_points`). Returns
    ``(passes run, deepest penetration left mm, lists)``: the deepest left is that found by
    the last pass before its response, 0 when nothing collided."""
    particle, centres, disp, collided = spheres[0], spheres[5], spheres[6], spheres[7]
    solids[15][:] = -np.inf     # every particle tested afresh by the first pass
    done = 0
    deepest = 0.0
    best = np.inf
    since_best = 0
    while done < passes:
        for s in prange(particle.shape[0]):
            _gather_sphere(s, x, particle, centres, disp, collided)
        if muscle_bone and solids[0].shape[0] > 0:
            _solid_contacts(solids, box)
        mm_count, mb_count, deepest, mm_seconds, mb_seconds, refreshed, lists = _collide(
            spheres, hashed, bvh, use_bvh, muscle_muscle, muscle_bone, lists, solids)
        done += 1
        for s in prange(particle.shape[0]):
            if collided[s]:
                ever_collided[s] = 1
                _respond_sphere(s, x, v, particle, disp)
        if muscle_bone:
            _respond_solids(x, v, solids, solid_ever)
        if deepest <= tolerance:
            break
        push = 0.0
        for s in range(particle.shape[0]):
            if collided[s]:
                push += np.sqrt(disp[0, s] ** 2 + disp[1, s] ** 2 + disp[2, s] ** 2)
        solid_disp, solid_collided = solids[17], solids[18]
        for k in range(solid_collided.shape[0]):
            if muscle_bone and solid_collided[k]:
                push += np.sqrt(solid_disp[0, k] ** 2 + solid_disp[1, k] ** 2
                                + solid_disp[2, k] ** 2)
        if push < PROGRESS * best:
            best = push
            since_best = 0
        else:
            since_best += 1
            if since_best >= STALLED_PASSES:
                break
    return done, deepest, lists


# ---- the driver ------------------------------------------------------------------------------

def _check_settings(settings: SolverSettings) -> None:
    if settings.termination not in TERMINATIONS:
        raise MuscleMSSError(f"termination {settings.termination!r} is not one of "
                             f"{', '.join(TERMINATIONS)}")
    if settings.structure not in STRUCTURES:
        raise MuscleMSSError(f"collision structure {settings.structure!r} is not one of "
                             f"{', '.join(STRUCTURES)}")
    if not (settings.projection_passes >= 0 and int(settings.projection_passes)
            == settings.projection_passes):
        raise MuscleMSSError(f"solver projection passes is {settings.projection_passes}; it "
                             "must be a whole number, 0 or more")
    for name, value in (("iterations", settings.iterations),
                        ("time step", settings.relaxation.time_step),
                        ("BVH max depth", settings.bvh_max_depth),
                        ("BVH min primitives", settings.bvh_min_primitives)):
        if not value > 0:
            raise MuscleMSSError(f"solver {name} is {value}; it must be positive")
    for name, value in (("displacement threshold", settings.relaxation.displacement_threshold),
                        ("time budget", settings.time_budget),
                        ("drag", settings.relaxation.drag),
                        ("penetration tolerance", settings.penetration_tolerance),
                        ("bulk modulus", settings.bulk_modulus)):
        if not (value >= 0.0 and np.isfinite(value)):
            raise MuscleMSSError(f"solver {name} is {value}; it must be finite and 0 or more")


def _world_box(positions, bone_centres) -> np.ndarray:
    """(2, 3) mm: the box no sphere centre may leave during a solve — the bounding box of the
    posed particles and the bone spheres grown by its own diagonal on every side. A sphere
    outside it has diverged (a step of the explicit integration too long for the springs):
    the solve stops before the collision structures index a grid or tree with it."""
    boxes = [_box(points) for points in (np.asarray(p, dtype=np.float64).reshape(-1, 3)
                                         for p in (positions, bone_centres)) if len(points)]
    lower = np.min([low for low, _ in boxes], axis=0) if boxes else np.zeros(3)
    upper = np.max([high for _, high in boxes], axis=0) if boxes else np.zeros(3)
    grow = max(float(np.linalg.norm(upper - lower)), 1.0)
    return np.stack([lower - grow, upper + grow])


@njit(cache=True)
def _box(points):
    """``(lower (3,), upper (3,))`` mm: the bounding box of ``points`` (n >= 1, 3) (NumPy's
    ``min(axis=0)`` took 4 ms on the 66,560 particles of the demo thigh at N = 80)."""
    lower = points[0].copy()
    upper = points[0].copy()
    for i in range(1, points.shape[0]):
        for k in range(3):
            lower[k] = min(lower[k], points[i, k])
            upper[k] = max(upper[k], points[i, k])
    return lower, upper


# The Gershgorin bounds of stable_time_step overestimate the stiffest mode (a checkerboard
# mode of lattice-26 reaches 0.67 of the bound's omega^2), and the implicit drag and the
# collision response (collided particles stop) widen the stable range: the 3x3x8 lattices of
# the solver tests still settle at 2.2 times the bound's step and diverge from 2.5 times (in 65
# iterations; 7 at 3 times). Steps up to this many times the bound's run (a divergence then
# stops the solve with an error); longer ones are refused before the solve.
STABILITY_MARGIN = 3.0
# The per-iteration history (mean displacement of each muscle and four columns) is refused above
# this size: Iterations caps a time budget's solve, and 1e9 would ask for tens of GiB.
MAX_HISTORY_BYTES = 2 * 1024 ** 3


def stable_time_step(model: MSSModel):
    """``(dt s, muscle index, particle, kind)``: the longest semi-implicit Euler step that the
    stiffest particle of the model takes without growing (``kind`` "stiffness" or
    "damping"), from a Gershgorin bound on the mass-scaled spring stiffness matrix
    ``M^-1/2 K M^-1/2`` (row i: ``sum_j k_ij (1/m_i + 1/sqrt(m_i m_j))``, fixed particles do
    not move) and the same bound on the springs' (explicit) damping: ``dt = 2 / omega_max``
    and ``dt = 2 / gamma_max``. ``inf`` when no free particle has a spring."""
    springs = np.asarray(model.springs, dtype=np.int64).reshape(-1, 2)
    mass = np.asarray(model.mass, dtype=np.float64)
    free = ~np.asarray(model.fixed, dtype=bool)
    if len(springs) == 0 or not free.any():
        return np.inf, 0, 0, "stiffness"
    with np.errstate(divide="ignore"):
        inv = np.where(free, 1.0 / mass, 0.0)
    root = np.sqrt(inv)
    a, b = springs[:, 0], springs[:, 1]
    best = (np.inf, 0, 0, "stiffness")
    for kind, coefficient, scale in (("stiffness", model.stiffness, np.sqrt),
                                     ("damping", model.damping, lambda r: r)):
        c = np.asarray(coefficient, dtype=np.float64)
        cross = c * root[a] * root[b]
        row = (np.bincount(a, c * inv[a] + cross, minlength=len(mass))
               + np.bincount(b, c * inv[b] + cross, minlength=len(mass)))
        p = int(np.argmax(row))
        if row[p] > 0.0:
            dt = 2.0 / float(scale(row[p]))
            if dt < best[0]:
                muscle = int(np.searchsorted(model.offsets, p, side="right") - 1)
                best = (dt, muscle, p - int(model.offsets[muscle]), kind)
    return best


def stability_problem(model: MSSModel, time_step: float, stable_step=None) -> str | None:
    """Why ``time_step`` cannot give a meaningful solve of ``model`` (the explicit integration
    grows without bound: particles jump ~1e8 mm in the first iteration), or None. Refused
    above :data:`STABILITY_MARGIN` times :func:`stable_time_step` (``stable_step``: its result
    for this model when known, e.g. :attr:`PreparedModel.stable_step`)."""
    dt, m, p, kind = stable_step if stable_step is not None else stable_time_step(model)
    if not time_step > STABILITY_MARGIN * dt:
        return None
    lo = int(model.offsets[m])
    springs = np.asarray(model.springs, dtype=np.int64).reshape(-1, 2)
    mine = (springs == lo + p).any(axis=1)
    total = float(np.asarray(model.stiffness if kind == "stiffness" else model.damping,
                             dtype=np.float64)[mine].sum())
    unit = "g/s^2" if kind == "stiffness" else "g/s"
    fix = ("raise the Spring Builder's Mass or lower its Stiffness" if kind == "stiffness"
           else "raise the Spring Builder's Mass or lower its Damping")
    return (f"the model cannot be solved with TimeStep {time_step:g} s: particle {p} of "
            f"muscle '{model.names[m]}' (mass {float(model.mass[lo + p]):.3g} g, springs of "
            f"total {kind} {total:.3g} {unit}) is stable only below {dt:.3g} s, and explicit "
            f"integration would blow up ({time_step / dt:.3g} times too long); lower the "
            f"MSS Collision Solver's TimeStep below {dt:.3g} s, or {fix}")


def check_history_size(iterations, muscles: int) -> None:
    """Refuse an iteration cap whose per-iteration history would not fit
    :data:`MAX_HISTORY_BYTES` (it is allocated before the solve starts)."""
    size = float(iterations) * (muscles + 4) * 8
    if size > MAX_HISTORY_BYTES:
        most = int(MAX_HISTORY_BYTES // ((muscles + 4) * 8))
        raise MuscleMSSError(
            f"Iterations {int(iterations)} would need a {size / 1024 ** 3:.3g} GiB history "
            f"({muscles} muscles + 4 values per iteration); at most "
            f"{MAX_HISTORY_BYTES / 1024 ** 3:.3g} GiB ({most} iterations) are allowed; lower "
            "Iterations (it caps every termination)")


def _divergence_limits(positions, offsets, reach) -> np.ndarray:
    """(M,) mm: a muscle's bounding-box diagonal plus ``reach`` (the farthest one collision
    push can move a sphere) — no sane iteration moves its particles that far on average."""
    limits = np.empty(len(offsets) - 1)
    for m in range(len(limits)):
        part = positions[offsets[m]:offsets[m + 1]]
        size = 0.0
        if len(part):
            lower, upper = _box(part)
            size = float(np.linalg.norm(upper - lower))
        limits[m] = size + reach + 1.0
    return limits


def collision_spheres(prep: PreparedModel, bone_centres=None, bone_radius=None, bone_id=None):
    """The model's collision spheres and bones' spheres (:func:`make_spheres`; no bones when
    ``bone_centres`` is None) and the contact kernels' per-sphere state: ``(spheres, (particle,
    radius, muscle, fixed, moves, centres (3, s), displacements (3, s + b), collided (s + b,),
    pair counts, deepest pair penetrations, each muscle's first sphere (M + 1,)))``, shared by
    the paper relaxation and the quasi-static method."""
    if bone_centres is None:
        bone_centres, bone_radius, bone_id = np.zeros((0, 3)), np.zeros(0), np.zeros(0, int)
    spheres = make_spheres(prep.radius, prep.muscle, prep.fixed, prep.boundary, bone_centres,
                           bone_radius, bone_id)
    ns = spheres.count
    nb = len(spheres.bone_radius)
    n_muscles = len(prep.offsets) - 1
    state = (spheres.particle, spheres.radius, spheres.muscle, spheres.fixed, ~spheres.fixed,
             np.zeros((3, ns)), np.zeros((3, ns + nb)), np.zeros(ns + nb, dtype=np.uint8),
             np.zeros(ns, dtype=np.int64), np.zeros(ns),
             np.searchsorted(spheres.muscle, np.arange(n_muscles + 1)))
    return spheres, state


def solve(model: MSSModel, bone_centres=None, bone_radius=None, bone_id=None,
          settings: SolverSettings | None = None, progress=None,
          prepared: PreparedModel | None = None,
          bone_solids: BoneSolids | None = None) -> SolveResult:
    """Relax the posed model with collisions (see the module docstring).

    ``bone_centres`` (b, 3) mm, ``bone_radius`` (b,) mm, ``bone_id`` (b,) int, sorted, from
    :func:`muscle_mss.core.bone_spheres.bone_spheres` on the posed bones (omit for no bones);
    ``progress(fraction) -> bool`` is called between chunks, True aborts with a
    :class:`MuscleMSSError`; ``prepared`` from :func:`prepare` for this model's topology;
    ``bone_solids``: the bones as solids for the muscle-bone contacts, of the iterations and
    the final passes (then give no bone spheres: they would be ignored).
    """
    settings = settings or SolverSettings()
    _check_settings(settings)
    if bone_solids is not None:
        bone_solids.check()
    prep = prepared if prepared is not None else prepare(model)
    problem = stability_problem(model, settings.relaxation.time_step, prep.stable_step)
    if problem:
        raise MuscleMSSError(problem)
    check_history_size(settings.iterations, len(model.names))
    offsets = prep.offsets
    n = int(offsets[-1])
    n_muscles = len(offsets) - 1
    posed = np.asarray(model.positions, dtype=np.float64).reshape(-1, 3)[prep.order]
    x = np.ascontiguousarray(posed.T)
    v = np.zeros_like(x)
    work = np.zeros((3, 3, n))
    relaxation = settings.relaxation
    mss = ((x, v, work[0], work[1], work[2], prep.inv_mass, float(relaxation.time_step),
            float(relaxation.drag), float(settings.bulk_modulus)) + prep.cages.arrays
           + (offsets,) + prep.layout.arrays)

    spheres, sphere_state = collision_spheres(prep, bone_centres, bone_radius, bone_id)
    ns = spheres.count
    solids = solid_arguments(bone_solids, x, prep)
    hashed = _hash_state(spheres, settings.structure == STRUCTURE_HASH)
    bvh = _bvh_state(spheres, settings)

    cap = int(settings.iterations)
    history = (np.zeros((cap, n_muscles)), np.zeros(cap, dtype=np.int64),
               np.zeros(cap, dtype=np.int64), np.zeros(cap), np.zeros(cap), np.zeros(4))
    control = (settings.structure == STRUCTURE_BVH,
               bool(settings.muscle_muscle), bool(settings.muscle_bone),
               TERMINATIONS.index(settings.termination),
               float(relaxation.displacement_threshold),
               float(settings.time_budget),
               _divergence_limits(posed, offsets, 2.0 * (max(spheres.radius, default=0.0)
                                                         + max(spheres.bone_radius, default=0.0))
                                  + (bone_solids.reach if bone_solids is not None else 0.0)),
               _world_box(posed, spheres.bone_centres))

    started = time.perf_counter()
    done = 0
    chunk = 1
    status = RUNNING
    rebuilds = 0
    fixed_state, lists = hashed[:-5], hashed[-5:]
    while done < cap and status == RUNNING:
        before = done
        tick = time.perf_counter()
        status, done, bad, more, lists = _solve_chunk(
            mss, sphere_state, fixed_state, bvh, history, control, done, min(cap, done + chunk),
            started, lists, solids)
        rebuilds += more
        per_iteration = (time.perf_counter() - tick) / max(done - before, 1)
        chunk = int(min(max(CHUNK_SECONDS / max(per_iteration, 1e-9), 1), 1000))
        if status == DIVERGED:
            raise MuscleMSSError(
                f"muscle '{model.names[bad]}' diverged at iteration {done}: its mean particle "
                f"displacement was {history[0][done - 1, bad]:.3g} mm in one iteration; lower "
                f"the TimeStep (now {relaxation.time_step} s) or check stiffness and mass")
        fraction = done / cap
        if settings.termination == TERMINATION_BUDGET and settings.time_budget > 0:
            fraction = max(fraction, history[4][done - 1] / settings.time_budget)
        if progress is not None and status == RUNNING and done < cap and progress(fraction):
            raise MuscleMSSError(f"the solve was stopped by the user after {done} iterations")

    mean_disp, muscle_pairs, bone_pairs, max_pen, seconds, phases = history
    collided_spheres = sphere_state[7][:ns].copy()
    solid_collided = solids[18].copy()
    passes, left = 0, 0.0
    if settings.projection_passes > 0 and (settings.muscle_muscle or settings.muscle_bone):
        tick = time.perf_counter()
        passes, left, lists = _project(
            x, v, sphere_state, fixed_state, bvh, control[0], control[1], control[2],
            int(settings.projection_passes), float(settings.penetration_tolerance), lists,
            collided_spheres, solids, solid_collided, control[-1])
        phases[3] += time.perf_counter() - tick

    rank = np.empty(n, dtype=np.int64)
    rank[prep.order] = np.arange(n)
    collided = np.zeros(n, dtype=bool)
    collided[spheres.particle] = collided_spheres > 0
    collided[solids[12]] |= solid_collided > 0
    stopped_by = {RUNNING: TERMINATION_ITERATIONS, CONVERGED: TERMINATION_THRESHOLD,
                  OUT_OF_TIME: TERMINATION_BUDGET}[status]
    return SolveResult(
        x.T[rank].copy(), v.T[rank].copy(), collided[rank], mean_disp[:done].copy(),
        muscle_pairs[:done].copy(), bone_pairs[:done].copy(), max_pen[:done].copy(),
        seconds[:done].copy(),
        {"mss": float(phases[0]), "muscle_cd": float(phases[1]), "bone_cd": float(phases[2]),
         "projection": float(phases[3])},
        stopped_by, rebuilds, passes, left)


def solid_points(prep: PreparedModel) -> np.ndarray:
    """(k,) int64, solver order: the particles the bones as solids keep out — every free
    particle not inside a bone at rest (``in_bone_at_rest``; a particle embedded in its
    attachment bone belongs there), with or without a sphere; when the model does not say
    which particles are inside a bone at rest, the free particles with a sphere."""
    if prep.in_bone_at_rest is None:
        keep = prep.boundary & (prep.radius > 0.0)
    else:
        keep = ~prep.in_bone_at_rest
    return np.flatnonzero(keep & ~prep.fixed).astype(np.int64)


def solid_arguments(bone_solids: BoneSolids | None, x: np.ndarray,
                    prep: PreparedModel) -> tuple:
    """The kernels' ``solids`` argument: ``bone_solids`` (checked; None: no bone as a solid),
    the positions ``x`` (3, n) mm they read, the particles of :func:`solid_points` with their
    sphere radii (0: none), the skip state of :func:`_solid_points` (each particle's position
    (3, k) mm when last sampled and its least clearance of the bones then, mm), the slack (mm),
    the contact state (displacement (3, k) mm, collided (k,), contacts (k,), deepest (k,) mm)
    and each muscle's first particle among them (M + 1,)."""
    points = solid_points(prep) if bone_solids is not None else np.zeros(0, np.int64)
    if bone_solids is None:
        bone_solids = NO_SOLIDS
    bone_solids.check()
    k = len(points)
    slack = (SOLID_SLACK_CELLS * float(bone_solids.fields.spacing.max())
             if len(bone_solids.fields) else 0.0)
    return bone_solids.kernel_arguments() + (
        x, points, prep.radius[points].copy(), np.zeros((3, k)), np.full(k, -np.inf), slack,
        np.zeros((3, k)), np.zeros(k, dtype=np.uint8), np.zeros(k, dtype=np.int64),
        np.zeros(k), np.searchsorted(points, prep.offsets).astype(np.int64))


def _hash_state(spheres: Spheres, used: bool) -> tuple:
    """The spatial hash's arrays for the kernel: the bone table is built here once (bones do
    not move during a solve); the candidate lists in the first iteration (muscle-muscle lists
    then refreshed sphere by sphere, :func:`spatial_hash.muscle_contacts`)."""
    ns = spheres.count
    skin = spatial_hash.skin_width(spheres, per_sphere=True)
    bone_object = spheres.bone + spheres.n_muscles
    centres = spheres.bone_centres if used else np.zeros((3, 0))
    table = spatial_hash.grid_table(centres, spheres.bone_radius if used else np.zeros(0),
                                    spatial_hash.bone_cell(spheres, skin),
                                    bone_object if used else np.zeros(0, np.int64))
    empty = np.zeros(ns, dtype=np.int64)
    room = spatial_hash.INITIAL_ROOM
    return (spheres.bone_centres, spheres.bone_radius, bone_object,
            np.zeros(len(spheres.bone_radius), dtype=np.bool_), table,
            spatial_hash.muscle_cell(spheres, skin), skin, np.full((3, ns), np.inf),
            np.zeros(ns, dtype=np.int64), np.zeros(ns, dtype=np.uint8),
            spatial_hash.muscle_lists(spheres.radius if used else np.zeros(0)),
            empty, empty.copy(), np.zeros(ns * room, np.int64), room)


def _bvh_state(spheres: Spheres, settings: SolverSettings) -> tuple:
    if settings.structure == STRUCTURE_BVH:
        tree = octree_bvh.octree_bvh(spheres, int(settings.bvh_max_depth),
                                     int(settings.bvh_min_primitives))
    else:
        tree = octree_bvh.octree_bvh(make_spheres(np.zeros(0), np.zeros(0, np.int64),
                                                  np.zeros(0, bool), np.zeros(0, bool)))
    return tree.arrays + (tree.n_muscles, tree.max_depth, tree.min_primitives,
                          np.zeros((0, 2), dtype=np.int64), np.zeros(1, dtype=np.int64))
