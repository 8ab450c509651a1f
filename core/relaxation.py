"""The relaxation loop of the paper's §3.1 and §3.3: MSS update, then collision handling.

Each iteration:

1. mass-spring update (:func:`muscle_mss.core.mss.muscle_step`: Hooke + damping along the spring,
   a viscous drag on the velocities and the pressure of each muscle's cage against a change of
   its rest volume, semi-implicit Euler, fixed particles stay);
2. collision detection among the boundary spheres of different muscles and between muscle
   spheres and bone spheres, through the chosen structure (:mod:`~muscle_mss.core.contacts.spatial_hash`,
   the default, or the paper's :mod:`~muscle_mss.core.contacts.octree_bvh`); both find the same pairs;
   or, given the bones as solids (:class:`~muscle_mss.core.bones.distance.BoneSolids`),
   muscle spheres against each bone's signed distance
   (:mod:`~muscle_mss.core.contacts.solid_contacts`): a sphere
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

Terminations (:data:`~muscle_mss.core.settings.TERMINATIONS`): a fixed number of iterations; the mean displacement below a
threshold (every muscle's, and not rising: the displacement first grows while the posed model
starts to move, so a small value in the first iterations is no sign of rest); a wall-clock
budget (checked after every iteration). ``iterations`` caps all three. A muscle whose mean
displacement is not finite or exceeds its own size in one iteration has diverged: the solve
stops with a :class:`MuscleMSSError` naming it.

After the last iteration, collision passes without the MSS update
(:func:`~muscle_mss.core.contacts.sphere_contacts.project`, the same
detection and response) run until no pair of spheres of different objects overlaps by more
than a tolerance (at most ``projection_passes``). One response leaves overlap behind wherever
a sphere is pressed between two objects — a muscle sphere pushed by another muscle into a
bone moves out of the bone by the whole bone penetration and back by half the muscle one —
and in every iteration the springs push such a sphere back in; on the demo thigh at the most
flexed pose a third of the mean sphere radius stays overlapped after 500 iterations without
these passes, under the 0.01 mm default tolerance with them.

Each stage of an iteration is one Numba kernel, the loop around them Python; about every
:data:`PROGRESS_SECONDS` ``progress(f)`` is called and may return True to abort. Every sum has
a fixed order: the same inputs give bitwise the same result on the same machine, whatever the
thread count.
"""
from __future__ import annotations

import time
from collections import namedtuple

import numpy as np
from numba import njit, prange

from .contacts.sphere_contacts import (bounding_box, collide, collision_spheres, contact_options,
                       contact_setup, final_passes, gather_sphere, respond_sphere, solved_state,
                       used_structures, world_box)
from .errors import MuscleMSSError, PoseError
from .model import (NO_BONES, Bones, MSSModel, PreparedModel, SolveResult, check_history_size,
                    prepare, stability_problem)
from .connective_tissue import tissue_stiffness, tissue_targets
from .mss import mss_state, muscle_step
from .solver_properties import name_of
from .settings import (METHOD_RELAXATION, TERMINATION_BUDGET,
                       TERMINATION_ITERATIONS, TERMINATION_THRESHOLD, TERMINATIONS,
                       SolverSettings)
from .contacts.solid_contacts import respond_solids, solid_contacts_range

PROGRESS_SECONDS = 0.1
"""How often (s) a solve calls its ``progress``: ParaView's progress bar and abort."""

RUNNING, CONVERGED, OUT_OF_TIME, DIVERGED = range(4)

IterationHistory = namedtuple("IterationHistory", (
    "mean_displacement", "muscle_pairs", "bone_pairs", "max_penetration", "seconds", "phases"))
IterationHistory.__doc__ = """One row per iteration: ``mean_displacement`` (K, M) mm,
``muscle_pairs`` and ``bone_pairs`` (K,) colliding pairs, ``max_penetration`` (K,) mm,
``seconds`` (K,) cumulative; ``phases`` (4,) s the totals of MSS, muscle CD, bone CD and the
final passes."""

RelaxationControl = namedtuple("RelaxationControl", (
    "termination", "threshold", "budget", "limit", "box"))
RelaxationControl.__doc__ = """When the loop stops: ``termination`` the index of the
termination in :data:`~muscle_mss.core.settings.TERMINATIONS`, its ``threshold`` mm and
``budget`` s; ``limit`` (M,) mm each muscle's divergence limit (:func:`_divergence_limits`) and
``box`` (2, 3) mm the world box (:func:`~muscle_mss.core.contacts.sphere_contacts.world_box`)."""


@njit(cache=True, parallel=True)
def _step_and_gather(mss, springs, particle, centres, disp, collided, sphere_ptr, box, escaped,
                     solids, grid, use_solids):
    """The MSS step of every muscle (:func:`muscle_mss.core.mss.muscle_step` of ``mss`` and
    ``springs``), each
    muscle's sphere centres then gathered for the collision tests (the arrays of
    :class:`~muscle_mss.core.contacts.sphere_contacts.SphereState`) and, with ``use_solids``, its particles
    tested against the bones as solids (``solids`` and their fields ``grid``,
    :func:`~muscle_mss.core.contacts.solid_contacts.solid_contacts_range`; not timed apart: a clock in a
    parallel region takes the GIL) — one parallel region: every region costs a thread wake-up
    (~0.1 ms on a virtual machine), which is a large part of one iteration at N = 80.
    ``escaped[m]`` is set when a sphere centre or a particle tested against the solids of
    muscle ``m`` lies outside ``box`` or is not finite. Returns the first such muscle, or -1."""
    x, offsets, solid_ptr = mss.x, mss.offsets, solids.ptr
    for m in prange(offsets.shape[0] - 1):
        muscle_step(np.int64(m), mss, springs)
        inside = True
        for s in range(sphere_ptr[m], sphere_ptr[m + 1]):
            gather_sphere(s, x, particle, centres, disp, collided)
            for axis in range(3):
                inside &= (centres[axis, s] >= box[0, axis]) & (centres[axis, s] <= box[1, axis])
        if use_solids:
            inside &= solid_contacts_range(solid_ptr[m], solid_ptr[m + 1], solids, grid, box)
        escaped[m] = not inside
    for m in range(escaped.shape[0]):
        if escaped[m]:
            return m
    return -1


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
def _mean_steps(x, x_prev, offsets, out):
    """Each muscle's mean particle displacement since ``x_prev`` (mm) into ``out`` (M,)."""
    for m in range(out.shape[0]):
        out[m] = _mean_step(x, x_prev, offsets[m], offsets[m + 1])


@njit(cache=True)
def _status(mean_disp, seconds, it, control):
    """``(status, diverged muscle or -1)`` after iteration ``it``: diverged when a muscle's
    mean displacement exceeds its limit or is not finite, converged when every muscle's is
    below the threshold and not rising (termination ``displacement threshold``), out of time
    when the budget is spent (termination ``time budget``)."""
    top = 0.0
    for m in range(mean_disp.shape[1]):
        if not mean_disp[it, m] <= control.limit[m]:
            return DIVERGED, m
        top = max(top, mean_disp[it, m])
    if control.termination == 1 and it > 0 and top < control.threshold:
        previous = 0.0
        for m in range(mean_disp.shape[1]):
            previous = max(previous, mean_disp[it - 1, m])
        if top <= previous:
            return CONVERGED, -1
    if control.termination == 2 and seconds[it] >= control.budget:
        return OUT_OF_TIME, -1
    return RUNNING, -1


@njit(cache=True, parallel=True)
def _respond_and_measure(x, v, x_prev, offsets, particle, disp, collided, sphere_ptr,
                         mean_disp):
    """The response: the collided spheres' particles move by their displacements and stop;
    each muscle's mean particle displacement of the iteration, mean ``|x - x_prev|`` mm, into
    ``mean_disp`` (M,)."""
    for m in prange(offsets.shape[0] - 1):
        for s in range(sphere_ptr[m], sphere_ptr[m + 1]):
            if collided[s]:
                respond_sphere(s, x, v, particle, disp)
        mean_disp[m] = _mean_step(x, x_prev, offsets[m], offsets[m + 1])



def _divergence_limits(positions, offsets, reach) -> np.ndarray:
    """(M,) mm: a muscle's bounding-box diagonal plus ``reach`` (the farthest one collision
    push can move a sphere) — no sane iteration moves its particles that far on average."""
    limits = np.empty(len(offsets) - 1)
    for m in range(len(limits)):
        part = positions[offsets[m]:offsets[m + 1]]
        size = 0.0
        if len(part):
            lower, upper = bounding_box(part)
            size = float(np.linalg.norm(upper - lower))
        limits[m] = size + reach + 1.0
    return limits


def solve(model: MSSModel, bones: Bones | None = None, settings: SolverSettings | None = None,
          *, prepared: PreparedModel | None = None, start=None, progress=None) -> SolveResult:
    """Relax the posed model with collisions against ``bones`` (see the module docstring).

    ``prepared`` from :func:`~muscle_mss.core.model.prepare` for this model's topology;
    ``start`` must be None (the relaxation starts at rest at the posed particles);
    ``progress(fraction) -> bool`` is called about every :data:`PROGRESS_SECONDS`, True aborts
    with a :class:`MuscleMSSError`.
    """
    settings = settings or SolverSettings(method=METHOD_RELAXATION)
    if start is not None:
        raise MuscleMSSError("the paper relaxation starts from the posed particles; it "
                             "takes no start positions")
    bones = bones or NO_BONES
    bone_solids = bones.solids
    if bone_solids is not None:
        bone_solids.check()
    prep = prepared if prepared is not None else prepare(model)
    problem = stability_problem(model, settings.relaxation.time_step, prep.stable_step)
    if problem:
        raise MuscleMSSError(problem)
    check_history_size(settings.iterations, len(model.names))
    offsets = prep.offsets
    n = int(offsets[-1])
    posed = np.asarray(model.positions, dtype=np.float64).reshape(-1, 3)[prep.order]
    x = np.ascontiguousarray(posed.T)
    v = np.zeros_like(x)
    relaxation = settings.relaxation
    tissue = ((tissue_stiffness(model, prep.order, prep.fixed, settings.connective_tissue),
               tissue_targets(model, prep.order, settings.tissue_along))
              if settings.connective_tissue > 0.0 else ())
    mss = mss_state(x, v, np.zeros((3, 3, n)), prep.inv_mass, relaxation.time_step,
                    relaxation.drag, settings.bulk_modulus, prep.cages, offsets, *tissue)
    spheres, sphere_state = collision_spheres(prep, *bones.sphere_arrays)
    contacts, lists = contact_setup(spheres, sphere_state, settings, bone_solids, x, prep)
    reach = (2.0 * (max(spheres.radius, default=0.0) + max(spheres.bone_radius, default=0.0))
             + (bone_solids.reach if bone_solids is not None else 0.0))
    control = RelaxationControl(
        TERMINATIONS.index(settings.termination), float(relaxation.displacement_threshold),
        float(settings.time_budget), _divergence_limits(posed, offsets, reach),
        world_box(posed, spheres.bone_centres))
    history, status, rebuilds, lists = _iterate(model, settings, mss, prep.layout, contacts,
                                                control, lists, progress)
    return _result(prep, settings, mss, spheres, contacts, control.box, lists, history, status,
                   rebuilds)


def _iterate(model, settings, mss, springs, contacts, control, lists, progress):
    """The iterations, until a termination stops them (``progress`` called about every
    :data:`PROGRESS_SECONDS`). Returns ``(history, status, rebuilds, lists)``, ``history``
    trimmed to the iterations run.

    The loop is Python calling one kernel per stage: a compiled loop around them compiled
    and linked every stage a second time (10 s of a first run's compile), to save
    what the calls cost (about 40 microseconds an iteration, against 0.5-1 ms for a thigh
    iteration at N = 20; docs/performance.md)."""
    cap = int(settings.iterations)
    history = IterationHistory(np.zeros((cap, len(model.names))), np.zeros(cap, np.int64),
                               np.zeros(cap, np.int64), np.zeros(cap), np.zeros(cap),
                               np.zeros(4))
    mean_disp, muscle_pairs, bone_pairs, max_pen, seconds, phases = history
    options = contact_options(settings)
    bvh, bone_table = used_structures(contacts, options)
    spheres, solids = contacts.spheres, contacts.solids
    x, v, x_prev, offsets = mss.x, mss.v, mss.x_prev, mss.offsets
    particle, disp, collided, sphere_ptr = (spheres.particle, spheres.disp, spheres.collided,
                                            spheres.sphere_ptr)
    gather = (particle, spheres.centres, disp, collided, sphere_ptr, control.box,
              np.zeros(len(model.names), dtype=np.bool_), solids, contacts.grid,
              options.muscle_bone and solids.transforms.shape[0] > 0)
    muscle_bone = options.muscle_bone
    touched = np.zeros(solids.points.shape[0], dtype=np.uint8)
    clock = time.perf_counter
    started = clock()
    report_at = started + PROGRESS_SECONDS
    status, it, rebuilds = RUNNING, 0, 0
    while it < cap and status == RUNNING:
        t0 = clock()
        bad = _step_and_gather(mss, springs, *gather)
        t1 = clock()
        if bad >= 0:
            # a sphere left the world box (or is not finite): stop before any collision
            # structure indexes its grid or tree with it
            _mean_steps(x, x_prev, offsets, mean_disp[it])
            _diverged(model, settings, history, it + 1, bad)
        mm_count, mb_count, deepest, mm_seconds, mb_seconds, refreshed, lists = collide(
            contacts, options, lists, bvh, bone_table)
        rebuilds += refreshed
        t3 = clock()
        if muscle_bone:
            respond_solids(x, v, solids, touched)
        _respond_and_measure(x, v, x_prev, offsets, particle, disp, collided, sphere_ptr,
                             mean_disp[it])
        t4 = clock()
        phases[0] += (t1 - t0) + (t4 - t3)
        phases[1] += mm_seconds
        phases[2] += mb_seconds
        muscle_pairs[it] = mm_count
        bone_pairs[it] = mb_count
        max_pen[it] = deepest
        seconds[it] = t4 - started
        status, bad = _status(mean_disp, seconds, it, control)
        it += 1
        if status == DIVERGED:
            _diverged(model, settings, history, it, bad)
        if t4 >= report_at and progress is not None and status == RUNNING and it < cap:
            report_at = t4 + PROGRESS_SECONDS
            fraction = it / cap
            if settings.termination == TERMINATION_BUDGET and settings.time_budget > 0:
                fraction = max(fraction, seconds[it - 1] / settings.time_budget)
            if progress(fraction):
                raise MuscleMSSError(f"the solve was stopped by the user after {it} iterations")
    trimmed = IterationHistory(*(column[:it].copy() for column in history[:-1]), phases)
    return trimmed, status, rebuilds, lists


def _diverged(model, settings, history, done, bad):
    """Raise the :class:`MuscleMSSError` of muscle ``bad`` diverging in iteration ``done``."""
    raise PoseError(
        model.names[bad], f" diverged at iteration {done}: its mean particle "
        f"displacement was {history.mean_displacement[done - 1, bad]:.3g} mm in one "
        f"iteration; lower the {name_of('relaxation.time_step')} (now "
        f"{settings.relaxation.time_step} s) or "
        "check stiffness and mass")


def _result(prep, settings, mss, spheres, contacts, box, lists, history, status, rebuilds):
    """The final collision passes (in the world ``box``), then the :class:`SolveResult` in the
    input order."""
    collided_spheres = contacts.spheres.collided[:spheres.count].copy()
    solid_collided = contacts.solids.collided.copy()
    passes, left, seconds = final_passes(mss.x, mss.v, contacts, settings, lists,
                                         collided_spheres, solid_collided, box)
    phases = history.phases
    phases[3] += seconds
    stopped_by = {RUNNING: TERMINATION_ITERATIONS, CONVERGED: TERMINATION_THRESHOLD,
                  OUT_OF_TIME: TERMINATION_BUDGET}[status]
    return SolveResult(
        **solved_state(prep, mss.x, mss.v, spheres, contacts.solids.points, collided_spheres,
                       solid_collided),
        mean_displacement=history.mean_displacement, muscle_pairs=history.muscle_pairs,
        bone_pairs=history.bone_pairs, max_penetration=history.max_penetration,
        seconds=history.seconds,
        phase_seconds={"mss": float(phases[0]), "muscle_cd": float(phases[1]),
                       "bone_cd": float(phases[2]), "projection": float(phases[3])},
        stopped_by=stopped_by, rebuilds=rebuilds, projection_passes=passes,
        remaining_penetration=left, converged=stopped_by == TERMINATION_THRESHOLD)
