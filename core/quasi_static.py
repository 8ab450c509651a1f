"""Quasi-static solver: the static equilibrium of the muscles' mass-spring model with contacts.

The paper's relaxation (:mod:`muscle_mss.core.solver`) stops after a fixed number of explicit
iterations, far from rest. This method solves for the state in which every free particle's
forces balance: the springs (Hooke, :func:`muscle_mss.core.mss.spring_forces`), each muscle's
volume pressure (:func:`muscle_mss.core.mss.mss_steps`'s ``bulk_modulus`` term), the tendon
attachments held at their posed positions, and the contacts between the spheres of different
muscles and between muscle and bone spheres (the same detection and response as the paper
method, :func:`muscle_mss.core.solver._collide`). Masses, damping and drag play no part in a
static equilibrium.

Energy. ``E(x) = sum_springs k (|x_b - x_a| - L0)^2 / 2 + sum_muscles B V0 (V / V0 - 1)^2 / 2
+ w sum_spheres |p_i(x)|^2 / 2`` where ``p_i`` is the paper's response of sphere ``i`` (its
share of the penetration along the centre line, one push per other object): a contact is a
penalty of stiffness ``w`` (g/s^2) pulling a penetrating sphere towards its contact-resolved
position, so the force on it is ``w p_i``. The penalty leaves an overlap of (contact force) / w
at equilibrium; the final collision passes of the paper method (:func:`solver._project`)
remove it.

Iteration (local/global, Liu et al. 2013 and Bouaziz et al. 2014 without the inertia term).
The constant matrix ``A = L + w D`` — ``L`` the spring Laplacian weighted by stiffness, ``D``
one on every particle carrying a collision sphere, rows and columns of the fixed particles
removed — is factorised once per topology (scipy ``splu``; block diagonal, one block per
muscle) and kept on the :class:`~muscle_mss.core.solver.PreparedModel`. One step is
``x <- x + A^-1 g(x)`` on the free particles, ``g`` the total force above (springs, volume,
contact pulls): for the springs this is exactly the local step (each spring's rest-length
direction) followed by the global solve, since ``L x + f_springs(x)`` is the global step's
right-hand side; the contact term's target is the contact-resolved position of a penetrating
sphere and the current position of every other sphere, so the matrix never changes when
contacts come and go. The fixed point is the equilibrium ``g(x) = 0``. The volume term's
whole-cage mode, stiff at the default BulkModulus and absent from ``A``, is added to ``A`` as a
rank-one update per muscle at the current state (:func:`_with_volume_stiffness`).

Acceleration. Anderson acceleration (Peng et al. 2018) over the last :attr:`history` steps,
restarted when the set of colliding spheres changes (the map's pieces change there) and
safeguarded: an accelerated point whose step is longer than the step before it is dropped for
the plain step, and the history restarts.

Termination by residual: the largest particle move of a plain step (mm; ``A^-1 g``, the
distance the step would move the farthest particle) and the distance still to go estimated
from its decay rate (:func:`_settled`) both below ``tolerance`` stop the loop, then
the final collision passes run; the solve has converged when the move was below the tolerance
and the passes left no overlap above ``penetration_tolerance``. ``iterations`` caps the loop
and ``time_budget`` (when set) bounds its wall-clock seconds. Warm start: ``start`` positions
(e.g. the solution of a neighbouring time point carried by the pose change) replace the posed
positions of the free particles.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sparse
import scipy.sparse.linalg as sparse_linalg
from numba import njit, prange

from . import solver as S
from .errors import MuscleMSSError
from .mss import _add_cage_gradient, _muscle_forces, _volume_forces

DEFAULT_TOLERANCE = 1e-3        # mm, largest particle move of a step
DEFAULT_HISTORY = 5             # Anderson acceleration depth
# The contact stiffness w as a multiple of the largest diagonal entry of L (the sum of the
# stiffnesses of one particle's springs, 260 g/s^2 for a lattice-26 particle at the Spring
# Builder's 10 g/s^2): stiffer contacts leave less overlap for the final passes but make
# every sphere's row of A stiffer, which slows the free boundary particles down.
DEFAULT_CONTACT_WEIGHT = 1.0
METHOD = "quasi-static"
# Anderson history restarts when more than this fraction of the colliding spheres changed
# (0: any change). On the full demo 0.05, or never restarting, left the residual stalled just
# the same (the contact chatter, see the README), so the safe choice stays.
RESTART_FRACTION = 0.0
RATE_WINDOW = 5
REST_STEP = 1e-12        # mm


@dataclass
class QuasiStaticSettings:
    """The quasi-static solver's parameters (the filter's properties)."""

    tolerance: float = DEFAULT_TOLERANCE            # mm
    iterations: int = 500                           # cap
    time_budget: float | None = None                # s, None: no budget
    bulk_modulus: float = S.DEFAULT_BULK_MODULUS    # g/(mm s^2)
    structure: str = "spatial hash"
    bvh_max_depth: int = S.octree_bvh.MAX_DEPTH
    bvh_min_primitives: int = S.octree_bvh.MIN_PRIMITIVES
    muscle_muscle: bool = True
    muscle_bone: bool = True
    projection_passes: int = S.DEFAULT_PROJECTION_PASSES
    penetration_tolerance: float = S.DEFAULT_PENETRATION_TOLERANCE    # mm
    contact_weight: float = DEFAULT_CONTACT_WEIGHT
    history: int = DEFAULT_HISTORY


@dataclass
class QuasiStaticResult(S.SolveResult):
    """:class:`~muscle_mss.core.solver.SolveResult` plus ``residual`` (K,) mm, the largest
    particle move of each iteration's plain step, and ``converged``: the last residual below
    the tolerance and no overlap above the penetration tolerance after the final passes.
    ``velocity`` is zero (a static solution); ``mean_displacement`` (K, M) is each muscle's
    mean particle move of the plain step."""

    residual: np.ndarray | None = None
    converged: bool = False
    method: str = METHOD


@dataclass
class Factor:
    """The constant matrix of the global step, factorised: ``free`` (f,) the free particles
    (solver order), ``lu`` scipy's ``SuperLU`` of ``A`` (f x f), ``weight`` w (g/s^2)."""

    free: np.ndarray
    lu: object
    weight: float


def global_matrix(prep: S.PreparedModel, weight: float):
    """``A = L + weight D`` restricted to the free particles (see the module docstring), CSC,
    with the free particles' indices (solver order)."""
    springs, stiffness = _springs(prep)
    n = int(prep.offsets[-1])
    a, b = springs[:, 0], springs[:, 1]
    lap = sparse.coo_matrix(
        (np.concatenate([stiffness, stiffness, -stiffness, -stiffness]),
         (np.concatenate([a, b, a, b]), np.concatenate([a, b, b, a]))), shape=(n, n)).tocsr()
    sphere = prep.boundary & (prep.radius > 0.0)
    free = np.flatnonzero(~prep.fixed)
    matrix = (lap + sparse.diags(np.where(sphere, weight, 0.0)))[free][:, free]
    return matrix.tocsc(), free


def _springs(prep: S.PreparedModel):
    """Every spring's ends (solver order) and stiffness, from the prepared layout."""
    lay = prep.layout
    ends, stiffness = [lay.scattered_int], [lay.scattered_param[:, 1]]
    for r in range(len(lay.runs_int)):
        first, lanes, d, lane0 = lay.runs_int[r]
        present = np.flatnonzero(lay.lane_rest[lane0:lane0 + lanes] >= 0.0)
        a = first + present
        ends.append(np.stack([a, a + d], axis=1))
        stiffness.append(np.full(len(a), lay.runs_param[r, 0]))
    return np.concatenate(ends).astype(np.int64), np.concatenate(stiffness)


def factor(prep: S.PreparedModel, contact_weight: float = DEFAULT_CONTACT_WEIGHT) -> Factor:
    """The factorised global matrix for ``prep``'s topology, cached on ``prep`` per contact
    weight (a muscle without a fixed particle and without springs to one is singular: it
    floats, and the solve refuses it)."""
    key = ("quasi-static factor", float(contact_weight))
    if key in prep.cache:
        return prep.cache[key]
    springs, stiffness = _springs(prep)
    n = int(prep.offsets[-1])
    diagonal = np.bincount(springs.ravel(), np.repeat(stiffness, 2), minlength=n)
    weight = float(contact_weight) * float(diagonal.max(initial=0.0) or 1.0)
    matrix, free = global_matrix(prep, weight)
    try:
        lu = sparse_linalg.splu(matrix, permc_spec="MMD_AT_PLUS_A")
    except RuntimeError as err:
        raise MuscleMSSError(
            f"the quasi-static solver cannot factorise the spring system ({err}): a muscle "
            "has free particles joined to no fixed particle through springs (it would float "
            "away); fix its tendon ends or use the paper relaxation") from None
    result = Factor(free, lu, weight)
    prep.cache[key] = result
    return result


# ---- kernels ---------------------------------------------------------------------------------

@njit(cache=True, parallel=True)
def _forces_and_gather(x, still, force, scratch, gradient, bulk_modulus, cage_ptr,
                       cage_triangles, rest_volume, offsets, runs_int, runs_param, lane_rest,
                       run_ptr, scattered_int, scattered_param, scattered_ptr, spheres):
    """Spring and volume forces on every particle into ``force`` (3, n) (``still`` (3, n)
    zeros: velocities, so the springs' damping adds nothing), each muscle's cage volume
    gradient ``dV/dx`` into ``gradient`` (3, n) (zero off the cages, and everywhere when
    ``bulk_modulus`` is 0), each muscle's sphere centres gathered for the collision tests —
    one parallel region over the muscles."""
    particle, centres, disp, collided, sphere_ptr = (spheres[0], spheres[5], spheres[6],
                                                     spheres[7], spheres[10])
    for m in prange(offsets.shape[0] - 1):
        _muscle_forces(m, x, still, force, scratch, offsets, runs_int, runs_param, lane_rest,
                       run_ptr, scattered_int, scattered_param, scattered_ptr)
        _volume_forces(m, x, force, cage_ptr, cage_triangles, rest_volume, bulk_modulus)
        for axis in range(3):
            gradient[axis, offsets[m]:offsets[m + 1]] = 0.0
        if bulk_modulus > 0.0 and cage_ptr[m + 1] > cage_ptr[m]:
            _add_cage_gradient(m, x, gradient, 1.0 / 6.0, cage_ptr, cage_triangles)
        for s in range(sphere_ptr[m], sphere_ptr[m + 1]):
            S._gather_sphere(s, x, particle, centres, disp, collided)


@njit(cache=True, parallel=True)
def _add_pulls(force, weight, particle, disp, collided):
    """The contact pull ``weight * response`` of every collided sphere added to ``force``."""
    for s in prange(particle.shape[0]):
        if collided[s]:
            p = particle[s]
            for axis in range(3):
                force[axis, p] += weight * disp[axis, s]


@njit(cache=True, parallel=True)
def _muscle_moves(step, free, muscle, n_muscles, out):
    """Mean particle move (mm) of each muscle for ``step`` (f, 3) on the free particles
    (fixed particles count as not moving); returns the largest move."""
    f = free.shape[0]
    length = np.empty(f)
    for i in prange(f):
        length[i] = np.sqrt(step[i, 0] ** 2 + step[i, 1] ** 2 + step[i, 2] ** 2)
    for m in range(n_muscles):
        out[m] = 0.0
    largest = 0.0
    for i in range(f):
        out[muscle[free[i]]] += length[i]
        largest = max(largest, length[i])
    return largest


# ---- the driver ------------------------------------------------------------------------------

def _with_volume_stiffness(delta, fac: Factor, gradient, free_muscle, volume_stiffness):
    """Turn the step ``delta = A^-1 f`` (f, 3) into ``(A + K)^-1 f`` in place, ``K`` the volume
    energy's stiff part, ``(BulkModulus / V_rest) g g^T`` per muscle with ``g = dV/dx``
    (``gradient`` (f, 3) on the free particles). ``A`` alone leaves that whole-cage mode out:
    at BulkModulus 50 a step of ``A^-1 f`` overshoots it and the iteration diverges. Sherman-
    Morrison per muscle (``A`` is block diagonal): ``delta - A^-1 g c (g . delta) / (1 + c
    g . A^-1 g)``, one more solve with ``A`` for all muscles at once."""
    solved = fac.lu.solve(gradient)
    n_muscles = len(volume_stiffness)
    along = np.bincount(free_muscle, np.einsum("ij,ij->i", gradient, delta), minlength=n_muscles)
    self_ = np.bincount(free_muscle, np.einsum("ij,ij->i", gradient, solved),
                        minlength=n_muscles)
    scale = volume_stiffness * along / (1.0 + volume_stiffness * self_)
    delta -= solved * scale[free_muscle, None]


def _settled(residual, tolerance) -> bool:
    """Whether the iteration has reached the tolerance: the last step moved no particle more
    than ``tolerance`` (mm) and neither does the distance still to go, estimated as
    ``r rho / (1 - rho)`` with ``rho`` the mean decay of the step over the last
    :data:`RATE_WINDOW` steps (a step shrinking by ``rho`` per iteration has that much left in
    its geometric tail; a step alone understates it by ``1 / (1 - rho)``, 65 times on a
    stretched lattice). A step below :data:`REST_STEP` is rest (rounding of mm coordinates)."""
    last = residual[-1]
    if last < REST_STEP:
        return True
    if len(residual) < 2 or not last < tolerance:
        return False
    window = min(RATE_WINDOW, len(residual) - 1)
    rate = (last / residual[-1 - window]) ** (1.0 / window)
    return rate < 1.0 and last * rate / (1.0 - rate) < tolerance

def _check(settings: QuasiStaticSettings) -> None:
    if settings.structure not in S.STRUCTURES:
        raise MuscleMSSError(f"collision structure {settings.structure!r} is not one of "
                             f"{', '.join(S.STRUCTURES)}")
    if not (settings.iterations >= 1 and int(settings.iterations) == settings.iterations):
        raise MuscleMSSError(f"solver iterations is {settings.iterations}; it must be a whole "
                             "number, 1 or more")
    if not (settings.projection_passes >= 0
            and int(settings.projection_passes) == settings.projection_passes):
        raise MuscleMSSError(f"solver projection passes is {settings.projection_passes}; it "
                             "must be a whole number, 0 or more")
    for name, value in (("tolerance", settings.tolerance),
                        ("penetration tolerance", settings.penetration_tolerance),
                        ("bulk modulus", settings.bulk_modulus)):
        if not (value >= 0.0 and np.isfinite(value)):
            raise MuscleMSSError(f"solver {name} is {value}; it must be finite and 0 or more")
    if not (settings.contact_weight > 0.0 and np.isfinite(settings.contact_weight)):
        raise MuscleMSSError(f"solver contact weight is {settings.contact_weight}; it must be "
                             "finite and positive")
    if settings.time_budget is not None and not settings.time_budget >= 0.0:
        raise MuscleMSSError(f"solver time budget is {settings.time_budget}; it must be 0 or "
                             "more")


def solve(model: S.MSSModel, bone_centres=None, bone_radius=None, bone_id=None,
          settings: QuasiStaticSettings | None = None, progress=None,
          prepared: S.PreparedModel | None = None, start=None) -> QuasiStaticResult:
    """The static equilibrium of the posed model with contacts (see the module docstring).

    Arguments as :func:`muscle_mss.core.solver.solve`; ``start`` (n, 3) mm, input particle
    order: the free particles' starting positions (warm start; omitted: the posed ones). Fixed
    particles stay at their posed positions.
    """
    settings = settings or QuasiStaticSettings()
    _check(settings)
    prep = prepared if prepared is not None else S.prepare(model)
    fac = factor(prep, settings.contact_weight)
    offsets = prep.offsets
    n = int(offsets[-1])
    n_muscles = len(offsets) - 1
    posed = np.asarray(model.positions, dtype=np.float64).reshape(-1, 3)[prep.order]
    x = np.ascontiguousarray(posed.T)
    if start is not None:
        begin = np.asarray(start, dtype=np.float64).reshape(-1, 3)
        if begin.shape != (n, 3) or not np.isfinite(begin).all():
            raise MuscleMSSError(f"the solver's start positions must be {n} finite points; got "
                                 f"shape {begin.shape}")
        begin = begin[prep.order]
        x[:, fac.free] = begin[fac.free].T
    still = np.zeros_like(x)
    force = np.zeros_like(x)
    scratch = np.zeros_like(x)
    gradient = np.zeros_like(x)
    free = fac.free
    free_muscle = prep.muscle[free]
    volume_stiffness = float(settings.bulk_modulus) / prep.cages.rest_volume   # (M,) g/(mm^4 s^2)

    spheres, sphere_state = S.collision_spheres(prep, bone_centres, bone_radius, bone_id)
    ns = spheres.count
    use_bvh = settings.structure == "octree BVH"
    hashed = S._hash_state(spheres, not use_bvh)
    bvh = S._bvh_state(spheres, S.SolverSettings(
        structure=settings.structure, bvh_max_depth=settings.bvh_max_depth,
        bvh_min_primitives=settings.bvh_min_primitives))
    fixed_state, lists = hashed[:-5], hashed[-5:]
    mss = (float(settings.bulk_modulus),) + prep.cages.arrays + (offsets,) + prep.layout.arrays
    collided = sphere_state[7]
    muscle_cd, bone_cd = bool(settings.muscle_muscle), bool(settings.muscle_bone)

    cap = int(settings.iterations)
    residual = np.zeros(cap)
    mean_move = np.zeros((cap, n_muscles))
    muscle_pairs = np.zeros(cap, dtype=np.int64)
    bone_pairs = np.zeros(cap, dtype=np.int64)
    max_pen = np.zeros(cap)
    seconds = np.zeros(cap)
    phases = np.zeros(4)
    sizes = np.maximum(np.diff(offsets), 1)

    def step(state, lists):
        """The plain step at ``state`` (3, n): ``(A^-1 g (f, 3), largest move, lists,
        pairs...)``."""
        tick = time.perf_counter()
        _forces_and_gather(state, still, force, scratch, gradient, *mss, sphere_state)
        mm_count, mb_count, deepest, t_mm, t_mb, _, lists = S._collide(
            sphere_state, fixed_state, bvh, use_bvh, muscle_cd, bone_cd, lists)
        _add_pulls(force, fac.weight, spheres.particle, sphere_state[6], collided)
        delta = fac.lu.solve(np.ascontiguousarray(force[:, free].T))
        if settings.bulk_modulus > 0.0:
            _with_volume_stiffness(delta, fac, np.ascontiguousarray(gradient[:, free].T),
                                   free_muscle, volume_stiffness)
        phases[0] += time.perf_counter() - tick - t_mm - t_mb
        phases[1] += t_mm
        phases[2] += t_mb
        return delta, lists, mm_count, mb_count, deepest

    started = time.perf_counter()
    history_x, history_f = [], []
    contact_set = None
    previous_move = np.inf
    fallback = None          # the plain step's result from the last point, for the safeguard
    done = 0
    converged_loop = False
    stopped_by = "iterations"
    while done < cap:
        delta, lists, mm_count, mb_count, deepest = step(x, lists)
        largest = _muscle_moves(delta, free, prep.muscle, n_muscles, mean_move[done])
        if not np.isfinite(largest):
            raise MuscleMSSError(f"the quasi-static solve diverged at iteration {done + 1}: a "
                                 "particle's step is not finite; check stiffness and bulk "
                                 "modulus")
        if fallback is not None and largest > previous_move:
            # the accelerated point made things worse: take the plain step instead
            x[:, free] = fallback
            history_x.clear()
            history_f.clear()
            delta, lists, mm_count, mb_count, deepest = step(x, lists)
            largest = _muscle_moves(delta, free, prep.muscle, n_muscles, mean_move[done])
        mean_move[done] /= sizes
        residual[done] = largest
        muscle_pairs[done] = mm_count
        bone_pairs[done] = mb_count
        max_pen[done] = deepest
        seconds[done] = time.perf_counter() - started
        done += 1
        current = x[:, free].T.ravel()
        plain = current + delta.ravel()
        if _settled(residual[:done], settings.tolerance):
            x[:, free] = plain.reshape(-1, 3).T
            converged_loop = True
            stopped_by = "tolerance"
            break
        touching = collided[:ns].astype(bool)
        if contact_set is None or (np.count_nonzero(touching != contact_set)
                                   > RESTART_FRACTION * max(np.count_nonzero(touching), 1)):
            history_x.clear()
            history_f.clear()
            contact_set = touching.copy()
        history_x.append(plain)
        history_f.append(delta.ravel().copy())
        if len(history_x) > settings.history + 1:
            history_x.pop(0)
            history_f.pop(0)
        fallback = None
        if len(history_x) >= 2:
            d_f = np.stack([history_f[i + 1] - history_f[i] for i in range(len(history_f) - 1)],
                           axis=1)
            d_x = np.stack([history_x[i + 1] - history_x[i] for i in range(len(history_x) - 1)],
                           axis=1)
            gamma = np.linalg.lstsq(d_f, history_f[-1], rcond=None)[0]
            x[:, free] = (plain - d_x @ gamma).reshape(-1, 3).T
            fallback = plain.reshape(-1, 3).T
        else:
            x[:, free] = plain.reshape(-1, 3).T
        previous_move = largest
        if settings.time_budget is not None and seconds[done - 1] >= settings.time_budget:
            stopped_by = "time budget"
            break
        if progress is not None and progress(done / cap):
            raise MuscleMSSError(f"the solve was stopped by the user after {done} iterations")

    v = np.zeros_like(x)
    collided_spheres = collided[:ns].copy()
    passes, left = 0, 0.0
    if settings.projection_passes > 0 and (muscle_cd or bone_cd):
        tick = time.perf_counter()
        passes, left, lists = S._project(
            x, v, sphere_state, fixed_state, bvh, use_bvh, muscle_cd, bone_cd,
            int(settings.projection_passes), float(settings.penetration_tolerance), lists,
            collided_spheres)
        phases[3] += time.perf_counter() - tick
    rank = np.empty(n, dtype=np.int64)
    rank[prep.order] = np.arange(n)
    collided_out = np.zeros(n, dtype=bool)
    collided_out[spheres.particle] = collided_spheres > 0
    converged = converged_loop and left <= settings.penetration_tolerance
    return QuasiStaticResult(
        x.T[rank].copy(), np.zeros((n, 3)), collided_out[rank], mean_move[:done].copy(),
        muscle_pairs[:done].copy(), bone_pairs[:done].copy(), max_pen[:done].copy(),
        seconds[:done].copy(),
        {"mss": float(phases[0]), "muscle_cd": float(phases[1]), "bone_cd": float(phases[2]),
         "projection": float(phases[3])},
        stopped_by, 0, passes, left, residual[:done].copy(), converged)
