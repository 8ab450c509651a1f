"""The quasi-static minimisation (see :mod:`muscle_mss.core.quasi_static`): L-BFGS iterations
with a backtracking line search on :class:`~.energy.ContactEnergy`, stopped by the residual and
its estimated distance to go, then the paper method's final collision passes."""
from __future__ import annotations

import time
from collections import namedtuple
from dataclasses import dataclass

import numpy as np

from ..bones.distance import BoneSolids, push_out_of_bones
from ..connective_tissue import tissue_targets
from ..contacts.sphere_contacts import (collision_spheres, contact_setup, final_passes, solved_state,
                                       world_box)
from ..errors import MuscleMSSError, PoseError
from ..model import (NO_BONES, Bones, MSSModel, PreparedModel, SolveResult, check_history_size,
                     prepare)
from ..divergence import scene_size
from ..solver_properties import name_of
from ..settings import (METHOD_QUASI_STATIC,
                        TERMINATION_BUDGET, TERMINATION_ITERATIONS, SolverSettings)
from .energy import ContactEnergy
from .lbfgs import LBFGSHistory, direction, inner, largest_move, settled
from .preconditioner import InitialInverseHessian, preconditioner
from .contact_preconditioner import ContactInverseHessian, inverse_columns_of

ARMIJO = 1e-4                   # sufficient decrease of the line search
BACKTRACKS = 40                 # line search halvings before the solve gives up
# The line search's first trial: at most this many times the last accepted step fraction (and
# at most the full step). The preconditioner is one block per muscle, so where muscles touch
# both spheres of a pair move to undo the whole overlap and the full step overshoots; a first
# trial that follows the last accepted fraction saves about 40 % of the energy evaluations
# (docs/solver-notes.md, "What paid").
STEP_GROWTH = 1.5
# Energies are sums of ~1e5 terms: a trial point whose energy is higher by less than this
# fraction of the energy is rounding, not an increase (the last steps of a tight solve).
ENERGY_ROUNDING = 1e-13
# Steps in a row that lower the energy by no more than its rounding before the solve stops as
# stalled (not converged): the energy can no longer tell a better point, and the plain
# preconditioned step still moves a particle more than the tolerance (else it has converged).
STALLED_STEPS = 50
TERMINATION_STALLED = "energy rounding"
# The iterations between updates of the volume gradient in the initial inverse Hessian (each update
# solves the spring matrix for it: three more columns). An initial inverse Hessian held for a
# few iterations is still positive definite; the volume term's stiff mode changes slowly.
VOLUME_REFRESH = 10
# The tolerance (mm) of the stage at softened contacts (settings' ``soft_start``): where the
# muscles have slid into place, before the contacts stiffen; tighter only makes that stage
# longer (docs/solver-notes.md, "Soft contacts first").
SOFT_STAGE_TOLERANCE = 0.5


@dataclass
class QuasiStaticResult(SolveResult):
    """:class:`~muscle_mss.core.model.SolveResult` (its ``residual`` the largest particle move
    of each iteration's quasi-Newton step, ``converged``: the loop met the tolerance and the
    final passes left no overlap above the penetration tolerance) plus ``energy`` (K,)
    g mm^2/s^2 at the start of each iteration. ``velocity`` is zero (a static solution);
    ``mean_displacement`` (K, M) is each muscle's mean particle move of the iteration (fixed
    particles count as not moving); ``muscle_pairs``, ``bone_pairs`` and ``max_penetration``
    the overlapping pairs and the deepest overlap (mm) at the start of each iteration."""

    energy: np.ndarray | None = None
    method: str = METHOD_QUASI_STATIC


IterationRecord = namedtuple("IterationRecord", (
    "residual", "energy", "mean_move", "muscle_pairs", "bone_pairs", "max_penetration",
    "seconds"))
IterationRecord.__doc__ = """One row per iteration: ``residual`` (K,) mm the largest particle
move of the quasi-Newton step, ``energy`` (K,) g mm^2/s^2 at its start, ``mean_move`` (K, M) mm
each muscle's mean particle move, ``muscle_pairs``, ``bone_pairs`` (K,) and
``max_penetration`` (K,) mm the overlaps at its start, ``seconds`` (K,) cumulative."""


LoopOutcome = namedtuple("LoopOutcome", (
    "record", "iterations", "stopped_by", "converged", "solve_seconds", "position"))
LoopOutcome.__doc__ = """How the minimisation ended: its :class:`IterationRecord` ``record``,
``iterations`` done, what ``stopped_by`` it, whether it ``converged`` (the tolerance met),
``solve_seconds`` spent computing steps, and the last accepted free positions ``position``
(f, 3) mm."""


def _record(cap: int, n_muscles: int) -> IterationRecord:
    return IterationRecord(np.zeros(cap), np.zeros(cap), np.zeros((cap, n_muscles)),
                           np.zeros(cap, dtype=np.int64), np.zeros(cap, dtype=np.int64),
                           np.zeros(cap), np.zeros(cap))


def contact_stiffness(model: MSSModel, prep: PreparedModel, pre, settings) -> np.ndarray:
    """(n,) g/s^2, solver order: each particle's contact stiffness ``w``, the contact weight
    times the stiffest particle's spring sum times its muscle's
    :meth:`~muscle_mss.core.model.MSSModel.resolution_scale`. A contact presses on the
    particles of a patch, and a finer lattice has more of them along each fibre and softer
    fibres: with one ``w`` for every resolution the full demo thigh's most flexed pose at 80
    particles per fibre took 1,446 iterations (134 without contacts), with the scale 497."""
    scale = model.resolution_scale()[prep.muscle]
    return float(settings.quasi_static.weight) * pre.stiffest * scale


def push_out_of_solids(x, points, radius, solids: BoneSolids) -> None:
    """Move the particles ``points`` (k,) of ``x`` (3, n) out to their ``radius`` (k,) mm plus
    the clearance from each bone solid (the penalty leaves an overlap of contact force / w at
    the minimum; :func:`~muscle_mss.core.bones.distance.push_out_of_bones`, bone by bone, twice
    over)."""
    b = len(solids.fields)
    for _ in range(2):
        for bone in range(b):
            active = np.zeros((len(points), b), dtype=bool)
            active[:, bone] = True
            centres = np.ascontiguousarray(x[:, points].T)
            push = push_out_of_bones(solids.fields, centres, radius + solids.clearance[bone],
                                     solids.transforms, active)
            x[:, points] += push.T


def solve(model: MSSModel, bones: Bones | None = None, settings: SolverSettings | None = None,
          *, prepared: PreparedModel | None = None, start=None,
          progress=None) -> QuasiStaticResult:
    """The static equilibrium of the posed model with contacts against ``bones`` (see
    :mod:`muscle_mss.core.quasi_static`).

    Arguments as :func:`muscle_mss.core.relaxation.solve`, but ``start`` (n, 3) mm, input
    particle order: the free particles' starting positions (warm start; None: the posed ones).
    Fixed particles stay at their posed positions. Against solids the bone spheres, if any,
    serve the final collision passes only.
    """
    settings = settings or SolverSettings(method=METHOD_QUASI_STATIC)
    bones = bones or NO_BONES
    bone_solids = bones.solids
    if bone_solids is not None:
        bone_solids.check()
    check_history_size(settings.iterations, len(model.names))
    prep = prepared if prepared is not None else prepare(model)
    pre = preconditioner(model, prep, settings.connective_tissue)
    n = int(prep.offsets[-1])
    posed = np.asarray(model.positions, dtype=np.float64).reshape(-1, 3)[prep.order]
    x = np.ascontiguousarray(posed.T)
    if start is not None:
        begin = np.asarray(start, dtype=np.float64).reshape(-1, 3)
        if begin.shape != (n, 3) or not np.isfinite(begin).all():
            raise MuscleMSSError(f"the solver's start positions must be {n} finite points; got "
                                 f"shape {begin.shape}")
        x[:, pre.free] = begin[prep.order][pre.free].T
    spheres, sphere_state = collision_spheres(prep, *bones.sphere_arrays)
    energy_of = ContactEnergy(model, prep, pre, spheres, settings, x,
                              contact_stiffness(model, prep, pre, settings), bone_solids,
                              tissue_targets(model, prep.order, settings.tissue_along))
    size = scene_size(model.positions, model.radius, bones)
    outcome = _minimise(prep, pre, settings, energy_of, spheres, progress, model.names, size)
    x[:, pre.free] = outcome.position.T
    return _finish(prep, settings, x, spheres, sphere_state, energy_of, bone_solids, outcome)


def _minimise(prep, pre, settings, energy_of, spheres, progress, names, size):
    """The L-BFGS iterations from the positions ``energy_of`` holds, in stages
    (:func:`_stages`: one by default; with ``soft_start`` the contacts softened first, then at
    their full stiffness), until the last stage's tolerance, the cap, the budget or a failed
    line search (:class:`LoopOutcome`, the stages' iterations in one record). Raises
    :class:`~muscle_mss.core.errors.PoseError` naming the muscle (of ``names``) when the energy
    at the start is not finite or a particle gets farther from a stage's start than ``size``
    mm (:func:`~muscle_mss.core.divergence.scene_size`, :func:`_check_reach`): the energy has
    no minimum near the pose."""
    loop = LoopOutcome(_record(int(settings.iterations), len(prep.offsets) - 1), 0, None,
                       False, 0.0, np.ascontiguousarray(energy_of.x[:, pre.free].T))
    stages = _stages(settings, energy_of)
    started = time.perf_counter()
    for number, (fraction, tolerance) in enumerate(stages):
        energy_of.soften(fraction)
        first = loop.iterations
        stage = _iterate(prep, pre, settings, energy_of, spheres, progress, names, size,
                         loop, tolerance, started)
        loop = stage._replace(solve_seconds=loop.solve_seconds + stage.solve_seconds)
        if number == len(stages) - 1:
            break
        if stage.stopped_by == TERMINATION_BUDGET or stage.iterations >= int(settings.iterations):
            return loop._replace(converged=False)   # out of iterations before the last stage
        if stage.converged and _met_untouched(loop.record, first, stage.iterations,
                                              settings.quasi_static.tolerance):
            break
    return loop


def _met_untouched(record, first, done, tolerance) -> bool:
    """Whether the stage of ``record``'s rows ``first:done`` ended where no contact touches
    (the softened energy equals the full one around it) with a step and a distance to go
    within ``tolerance``: the full problem's convergence (a model at rest ends in one
    iteration)."""
    last = done - 1
    return bool(record.muscle_pairs[last] == 0 and record.bone_pairs[last] == 0
                and record.residual[last] <= tolerance
                and settled(record.residual[first:done], tolerance))


def _stages(settings, energy_of) -> list:
    """``[(contact stiffness fraction, tolerance mm), ...]`` of the minimisation's stages: with
    contacts and ``soft_start`` below 1, first at that fraction to
    :data:`SOFT_STAGE_TOLERANCE` (or the tolerance, if looser), then at the full stiffness."""
    tolerance = settings.quasi_static.tolerance
    soft = settings.quasi_static.soft_start
    if soft < 1.0 and energy_of.has_contacts():
        return [(soft, max(SOFT_STAGE_TOLERANCE, tolerance)), (1.0, tolerance)]
    return [(1.0, tolerance)]


def _iterate(prep, pre, settings, energy_of, spheres, progress, names, size, loop, tolerance,
             started):
    """One stage of :func:`_minimise`: the iterations from ``loop.position`` (its
    ``iterations`` done before, their rows of ``loop.record`` filled) until ``tolerance`` mm
    or the others' ends; the history starts empty. ``started``: the minimisation's start
    (``time.perf_counter()``), from which the record counts seconds."""
    budget = settings.budget
    free_muscle = prep.muscle[pre.free]
    has_cage = np.diff(prep.cages.ptr) > 0
    volume_stiffness = np.where(has_cage, float(settings.bulk_modulus)
                                / prep.cages.rest_volume, 0.0)     # (M,) g/(mm^4 s^2)
    step_limit = float(spheres.radius.max()) if spheres.count else np.inf
    n_muscles = len(prep.offsets) - 1
    sizes = np.maximum(np.diff(prep.offsets), 1)
    cap = int(settings.iterations)
    record = loop.record
    solve_seconds = 0.0
    position = loop.position
    energy, gradient, volume_gradient = energy_of.evaluate(position)
    if not np.isfinite(energy):
        _not_finite(gradient, free_muscle, names)
    begin = position
    # an upper bound of the farthest particle move since the start: the sum of the accepted
    # steps' largest moves; the moves themselves are measured only when the bound passes the
    # scene's size (rarely; never on the demo motions)
    travelled = 0.0
    history = LBFGSHistory(int(settings.quasi_static.history), len(pre.free))
    first = done = loop.iterations
    converged, stopped_by = False, TERMINATION_ITERATIONS
    accepted = 1.0                  # the last accepted step fraction
    stalled = 0     # steps in a row that lowered the energy by no more than its rounding
    while done < cap:
        record.muscle_pairs[done], record.bone_pairs[done], record.max_penetration[done] = \
            energy_of.contact_figures()
        record.energy[done] = energy
        tick = time.perf_counter()
        if (done - first) % VOLUME_REFRESH == 0:
            h0 = InitialInverseHessian(pre, free_muscle, volume_stiffness, volume_gradient)
        step, largest, slope = _step(gradient, history, _with_contacts(h0, energy_of, settings),
                                     record.residual[first:], done - first, tolerance,
                                     stalled > 0)
        solve_seconds += time.perf_counter() - tick
        done += 1
        if largest <= tolerance:
            converged, stopped_by = True, "tolerance"
            record.seconds[done - 1] = time.perf_counter() - started
            break
        trial = _line_search(energy_of, position, energy, step, slope,
                             min(1.0, step_limit / largest, STEP_GROWTH * accepted))
        if trial is None:
            energy_of.evaluate(position)
            stopped_by = "line search"
            record.seconds[done - 1] = time.perf_counter() - started
            break
        trial, trial_energy, trial_gradient, trial_volume, accepted = trial
        moved = trial - position
        change = trial_gradient - gradient
        curvature = inner(moved, change)
        stalled = stalled + 1 if energy - trial_energy <= ENERGY_ROUNDING * abs(energy) else 0
        if settings.quasi_static.history and curvature > 1e-12 * np.sqrt(
                inner(moved, moved) * inner(change, change)):
            history.add(moved, change, 1.0 / curvature)
        record.mean_move[done - 1] = np.bincount(free_muscle, np.sqrt(np.einsum(
            "ij,ij->i", moved, moved)), minlength=n_muscles) / sizes
        position, energy, gradient, volume_gradient = (trial, trial_energy, trial_gradient,
                                                       trial_volume)
        travelled += accepted * largest
        if travelled > size:
            travelled = _check_reach(position, begin, size, free_muscle, names, done)
        record.seconds[done - 1] = time.perf_counter() - started
        if stalled >= STALLED_STEPS:
            stopped_by = TERMINATION_STALLED
            break
        if budget is not None and record.seconds[done - 1] >= budget:
            stopped_by = TERMINATION_BUDGET
            break
        if progress is not None and progress(done / cap):
            raise MuscleMSSError(f"the solve was stopped by the user after {done} iterations")
    return LoopOutcome(record, done, stopped_by, converged, solve_seconds, position)


def _with_contacts(h0, energy_of, settings):
    """The initial inverse Hessian ``h0`` with the contacts between muscles at the last
    evaluation of ``energy_of`` when the settings ask for them
    (:class:`~.contact_preconditioner.ContactInverseHessian`), else ``h0``."""
    if not settings.quasi_static.contact_preconditioner:
        return h0
    return ContactInverseHessian(h0, *energy_of.contact_columns(), h0.free_muscle,
                                 inverse_columns_of(h0.pre))


def _check_reach(position, begin, size, free_muscle, names, done) -> float:
    """The farthest any particle of ``position`` (f, 3) mm has moved from ``begin`` (mm);
    :class:`~muscle_mss.core.errors.PoseError` naming its muscle when that is more than
    ``size`` mm (the scene's size) after iteration ``done``."""
    moved = np.einsum("ij,ij->i", position - begin, position - begin)
    k = int(np.argmax(moved))
    farthest = float(np.sqrt(moved[k]))
    if not farthest <= size:
        raise PoseError(names[free_muscle[k]], f" diverged in the quasi-static solve: after "
                        f"iteration {done} a particle of it lay {farthest:.3g} mm from its "
                        f"posed place, farther than the scene's size ({size:.3g} mm): "
                        "the model has no equilibrium near this pose; check the motion at "
                        f"this time, the springs' stiffness, {name_of('bulk_modulus')}, "
                        f"{name_of('connective_tissue')} and the bone contact "
                        f"({name_of('contacts.bone_sphere_spacing')})")
    return farthest


def _not_finite(gradient, free_muscle, names):
    """Raise the :class:`~muscle_mss.core.errors.PoseError` (or, where no particle's force is
    to blame, the :class:`MuscleMSSError`) of an energy that is not finite at the start."""
    bad = np.flatnonzero(~np.isfinite(gradient).all(axis=1))
    text = ("the quasi-static energy of the posed model is not finite: check the motion at "
            f"this time and the springs' rest lengths, stiffness and {name_of('bulk_modulus')}")
    if len(bad):
        raise PoseError(names[free_muscle[bad[0]]], f": {text} (a force on a particle of it "
                        "is not finite)")
    raise MuscleMSSError(text)


def _step(gradient, history, h0, residual, done, tolerance, at_rounding=False):
    """The quasi-Newton step of iteration ``done``: ``(step (f, 3) mm, its largest particle
    move mm, slope of the energy along it)``, its largest move recorded in ``residual``. The
    step counts as within the tolerance only once the distance still to go is too, and when
    the plain preconditioned step (which bounds the force) is; a step that does not descend
    is replaced by the plain one (the history dropped). ``at_rounding``: the last step lowered
    the energy by no more than its rounding; then the plain step within the tolerance is
    enough (the force is bounded and the energy flat: the distance still to go, estimated from
    steps that no longer lower it, is noise)."""
    if at_rounding:
        plain = -h0(gradient)
        if largest_move(plain) <= tolerance:
            residual[done] = largest_move(plain)
            return plain, residual[done], inner(gradient, plain)
    step = direction(gradient, history, h0)
    largest = largest_move(step)
    if not np.isfinite(largest):
        raise MuscleMSSError(f"the quasi-static solve diverged at iteration {done + 1}: a "
                             "particle's step is not finite; check stiffness and bulk "
                             "modulus")
    residual[done] = largest
    if largest <= tolerance and not settled(residual[:done + 1], tolerance):
        largest = max(largest, 2.0 * tolerance)     # not yet: keep going
    elif largest <= tolerance and history:
        # confirm with the plain step, which bounds the force
        plain = -h0(gradient)
        if largest_move(plain) > tolerance:
            history.clear()
            step, largest = plain, largest_move(plain)
    slope = inner(gradient, step)
    if slope >= 0.0 and largest > 0.0:
        history.clear()
        step = -h0(gradient)
        largest = largest_move(step)
        slope = inner(gradient, step)
    return step, largest, slope


def _line_search(energy_of, position, energy, step, slope, alpha):
    """Backtracking line search on the energy (Armijo) from ``alpha``: ``(trial positions,
    energy, gradient, volume gradient, step fraction)`` of the accepted step, or None after
    :data:`BACKTRACKS` halvings."""
    for _ in range(BACKTRACKS):
        trial = position + alpha * step
        trial_energy, trial_gradient, trial_volume = energy_of.evaluate(trial)
        rise = trial_energy - energy
        if rise <= ARMIJO * alpha * slope + ENERGY_ROUNDING * abs(energy):
            return trial, trial_energy, trial_gradient, trial_volume, alpha
        # the minimum of the quadratic through E(0), E'(0) and E(alpha), kept in
        # [alpha / 10, alpha / 2]
        curve = rise - alpha * slope
        guess = -slope * alpha * alpha / (2.0 * curve) if curve > 0.0 else 0.5 * alpha
        alpha = min(max(guess, 0.1 * alpha), 0.5 * alpha)
    return None


def _finish(prep, settings, x, spheres, sphere_state, energy_of, bone_solids,
            outcome: LoopOutcome) -> QuasiStaticResult:
    """The solids' push and the paper method's final collision passes (they remove the
    penalty's overlap) after the minimisation's ``outcome``, then the
    :class:`QuasiStaticResult`."""
    touching = energy_of.deepest > 0.0
    touching_solid = energy_of.solid_deepest > 0.0
    if len(energy_of.solid_points):
        push_out_of_solids(x, energy_of.solid_points, energy_of.solid_radius, bone_solids)
    contacts, lists = contact_setup(spheres, sphere_state, settings, bone_solids, x, prep)
    solids = contacts.solids
    solid_collided = np.zeros(len(solids.points), dtype=np.uint8)
    if len(energy_of.solid_points):     # the same particles, the same order
        solid_collided[:] = touching_solid
    collided_spheres = touching.astype(np.uint8)
    v = np.zeros_like(x)
    passes, left, projection_seconds = final_passes(
        x, v, contacts, settings, lists, collided_spheres, solid_collided,
        world_box(x.T, spheres.bone_centres.T))
    phases = {"mss": float(energy_of.seconds[0] + outcome.solve_seconds),
              "muscle_cd": float(energy_of.seconds[1]), "bone_cd": float(energy_of.seconds[2]),
              "projection": projection_seconds}
    record, done = outcome.record, outcome.iterations
    return QuasiStaticResult(
        **solved_state(prep, x, v, spheres, solids.points, collided_spheres, solid_collided),
        mean_displacement=record.mean_move[:done].copy(),
        muscle_pairs=record.muscle_pairs[:done].copy(),
        bone_pairs=record.bone_pairs[:done].copy(),
        max_penetration=record.max_penetration[:done].copy(),
        seconds=record.seconds[:done].copy(), phase_seconds=phases,
        stopped_by=outcome.stopped_by, rebuilds=energy_of.rebuilds, projection_passes=passes,
        remaining_penetration=left,
        residual=record.residual[:done].copy(), energy=record.energy[:done].copy(),
        converged=outcome.converged and left <= settings.contacts.penetration_tolerance)
