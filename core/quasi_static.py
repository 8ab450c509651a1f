"""Quasi-static solver: the static equilibrium of the muscles' mass-spring model with contacts.

The paper's relaxation (:mod:`muscle_mss.core.solver`) stops after a fixed number of explicit
iterations, far from rest. This method minimises the model's energy over the free particles
(tendon particles stay at their posed positions); at the minimum every free particle's forces
balance. Masses, damping and drag play no part in a static equilibrium.

Energy (g mm^2 / s^2)::

    E(x) = sum_springs k (|x_b - x_a| - L0)^2 / 2                 (Hooke, as mss.spring_forces)
         + sum_muscles B V0 (V / V0 - 1)^2 / 2                    (volume pressure, BulkModulus B)
         + w / 2 sum_pairs max(0, r_i + r_j - |c_i - c_j|)^2      (contacts)

The contact term is a penalty on every overlapping pair of spheres of different muscles and of
a muscle sphere with a bone sphere (tendon spheres against bones are exempt, as in the paper),
or, given :class:`~muscle_mss.core.bone_distance.BoneSolids`, of a muscle particle with a bone
as a solid (``max(0, r_i + clearance - d(c_i))`` with ``d`` the bone's signed distance: a
particle is pushed out along the distance gradient from any depth, where a sphere past a bone's
shell of spheres is pulled on through it by the springs: on the full demo at the most flexed
pose the sphere-set solve was still drifting after thousands of iterations, its particles up to
85 mm apart between 250 and 4,000 iterations):
each sphere of an overlapping pair is pushed along the centre line by ``w`` times the overlap,
the whole push going to the free sphere when the other is fixed or a bone. Unlike the paper's
response (the deepest pair of each other object) the sum over all pairs is continuously
differentiable, so the minimisation converges where the paper's rule makes contacts chatter.
``w`` is :attr:`QuasiStaticSettings.contact_weight` times the largest sum of one particle's
spring stiffnesses (260 g/s^2 for a lattice-26 particle at the Spring Builder's defaults). The
penalty leaves an overlap of (contact force) / w at the minimum; the final collision passes of
the paper method (:func:`muscle_mss.core.solver._project`, against the solids when given)
remove it, after the free spheres are pushed out of the bone solids
(:func:`_push_out_of_solids`). Against the solids the penalty holds every free particle that
is not inside a bone at rest (``MSSModel.in_bone_at_rest``), with its sphere's radius or none
(:func:`muscle_mss.core.solver.solid_points`): an interior particle dragged into a bone is
pushed out as well.

Minimisation: L-BFGS (Liu, Bouaziz and Kavan 2017, "Quasi-Newton methods for real-time
simulation of hyperelastic materials") whose initial inverse Hessian is ``(A + K)^-1``: ``A = L``
the spring Laplacian weighted by stiffness, fixed particles' rows and columns removed,
factorised once per topology (one banded Cholesky factor per muscle, :class:`Preconditioner`),
and ``K`` each muscle's rank-one volume stiffness ``(B / V0) g g^T``, ``g = dV/dx`` at the
current state (Sherman-Morrison). A step of ``A^-1`` alone is the local/global step of Liu et
al. 2013; the history of the last :attr:`~QuasiStaticSettings.history` steps corrects it
towards Newton's. Contacts are left out of ``A``: a diagonal ``w`` on every sphere particle
pins the free surface (the walking pose of the full demo then did not converge in 500
iterations), refactorising ``A`` with each iteration's contacts cost 0.1 s per iteration at
N = 20, and Newton steps solved by conjugate gradients preconditioned with ``A`` needed 80
products each (74 s for the walking pose against 12.6 s). A backtracking line search
(Armijo) makes every iteration lower the energy, and a step moves no particle farther than the
largest muscle sphere radius (a longer step could jump over a contact). Contacts are found
from candidate lists (spheres of other objects within their radii plus a skin,
:func:`muscle_mss.core.spatial_hash.candidate_lists`) rebuilt whenever a sphere has moved half
the skin since: the energy is that of all overlapping pairs.

Termination by residual: the residual of an iteration is the largest particle move of its
quasi-Newton step (mm, before the line search), the L-BFGS estimate of the distance to the
minimum. The loop stops when it is below ``tolerance`` and so is the distance still to go
estimated from its decay (:func:`distance_to_go`), and the plain preconditioned step ``(A + K)^-1
grad E`` is below ``tolerance`` as well (it bounds the force: ``|f| <= |A + K| tolerance``);
then the final collision passes run. The solve has converged when the loop stopped so and
the passes left no overlap above ``penetration_tolerance``. ``iterations`` caps the loop and
``time_budget`` (when set) bounds its wall-clock seconds. Warm start: ``start`` positions (e.g.
the solution of a neighbouring time point carried by the pose change) replace the posed
positions of the free particles.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg as linalg
import scipy.sparse as sparse
from numba import njit, prange
from scipy.sparse.csgraph import reverse_cuthill_mckee

from . import solver as S
from . import spatial_hash
from .errors import MuscleMSSError
from .bone_distance import BoneSolids, _sample, _to_rest, push_out_of_bones
from .mss import _add_cage_gradient, _cage_volume
from .settings import (METHOD_QUASI_STATIC, STRUCTURE_BVH, STRUCTURES, TERMINATION_BUDGET,
                       TERMINATION_ITERATIONS, SolverSettings)

ARMIJO = 1e-4                   # sufficient decrease of the line search
BACKTRACKS = 40                 # line search halvings before the solve gives up
# Energies are sums of ~1e5 terms: a trial point whose energy is higher by less than this
# fraction of the energy is rounding, not an increase (the last steps of a tight solve).
ENERGY_ROUNDING = 1e-13
# Iterations over which the residual's decay is measured. With 10, the walking pose of the full
# demo thigh (N = 20) stopped as converged after 1,292 iterations 0.020 / 1.14 mm (mean / max)
# from a solve to 1e-5 mm: the last ten steps shrank faster than the slow bending modes behind
# them. With 30 it stops after 1,945 iterations 0.0035 / 0.083 mm from it (60: the same).
RATE_WINDOW = 30
REST_STEP = 1e-12               # mm: a residual below it is rest (rounding of mm coordinates)
SKIN_FRACTION = 1.0             # contact list skin, times the mean muscle sphere radius


@dataclass
class QuasiStaticResult(S.SolveResult):
    """:class:`~muscle_mss.core.solver.SolveResult` plus ``residual`` (K,) mm, the largest
    particle move of each iteration's quasi-Newton step, ``energy`` (K,) g mm^2/s^2 at the start
    of each iteration, and ``converged``: the loop met the tolerance and the final passes left
    no overlap above the penetration tolerance. ``velocity`` is zero (a static solution);
    ``mean_displacement`` (K, M) is each muscle's mean particle move of the iteration (fixed
    particles count as not moving); ``muscle_pairs``, ``bone_pairs`` and ``max_penetration``
    the overlapping pairs and the deepest overlap (mm) at the start of each iteration."""

    residual: np.ndarray | None = None
    energy: np.ndarray | None = None
    converged: bool = False
    method: str = METHOD_QUASI_STATIC


# ---- the constant part of the Hessian ----------------------------------------------------------

@dataclass
class Preconditioner:
    """The spring Laplacian ``L`` on the free particles, factorised muscle by muscle.

    ``free`` (f,) the free particles (solver order); ``blocks`` per muscle ``(rows, factor)``:
    ``rows`` (k,) positions in ``free`` in the factor's order (the smaller bandwidth of the
    particles ordered slice by slice along the fibres and of reverse Cuthill-McKee), ``factor``
    the lower banded Cholesky factor (LAPACK layout); ``stiffest`` (g/s^2) the largest sum of
    one particle's spring stiffnesses (the contact stiffness's unit); ``bandwidth`` the largest
    block's."""

    free: np.ndarray
    blocks: list
    stiffest: float
    bandwidth: int

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``A^-1 rhs`` for ``rhs`` (f, c)."""
        out = np.empty_like(rhs)
        for rows, factor_ in self.blocks:
            out[rows] = linalg.cho_solve_banded((factor_, True), rhs[rows], check_finite=False)
        return out


def _springs(model: S.MSSModel, prep: S.PreparedModel):
    """Every spring's ends (solver order), rest length and stiffness, grouped by muscle:
    ``(ends (S, 2), rest (S,), stiffness (S,), ptr (M + 1,))``."""
    rank = np.empty(len(prep.order), dtype=np.int64)
    rank[prep.order] = np.arange(len(prep.order))
    ends = rank[np.asarray(model.springs, dtype=np.int64).reshape(-1, 2)]
    muscle = prep.muscle[ends[:, 0]]
    order = np.argsort(muscle, kind="stable")
    ptr = np.searchsorted(muscle[order], np.arange(len(prep.offsets))).astype(np.int64)
    return (np.ascontiguousarray(ends[order]),
            np.asarray(model.rest_length, dtype=np.float64)[order].copy(),
            np.asarray(model.stiffness, dtype=np.float64)[order].copy(), ptr)


def _bandwidth(matrix, order) -> int:
    coo = matrix.tocoo()
    place = np.empty(len(order), dtype=np.int64)
    place[order] = np.arange(len(order))
    return int(np.abs(place[coo.row] - place[coo.col]).max(initial=0))


def preconditioner(model: S.MSSModel, prep: S.PreparedModel) -> Preconditioner:
    """The factorised ``L`` for ``prep``'s topology, cached on ``prep``. A muscle whose free
    particles are not all joined to a fixed particle through springs would float: the solve
    refuses it."""
    key = "quasi-static preconditioner"
    if key in prep.cache:
        return prep.cache[key]
    ends, _, stiffness, _ = model_springs(model, prep)
    n = int(prep.offsets[-1])
    diagonal = np.bincount(ends.ravel(), np.repeat(stiffness, 2), minlength=n)
    stiffest = float(diagonal.max(initial=0.0) or 1.0)
    a, b = ends[:, 0], ends[:, 1]
    lap = sparse.coo_matrix(
        (np.concatenate([stiffness, stiffness, -stiffness, -stiffness]),
         (np.concatenate([a, b, a, b]), np.concatenate([a, b, b, a]))), shape=(n, n)).tocsr()
    free = np.flatnonzero(~prep.fixed)
    matrix = lap[free][:, free].tocsr()
    along = np.asarray(model.fibre_index).ravel()[prep.order][free]
    free_muscle = prep.muscle[free]
    blocks, widest = [], 0
    for m in range(len(prep.offsets) - 1):
        rows = np.flatnonzero(free_muscle == m)
        if not len(rows):
            continue
        block = matrix[rows][:, rows]
        candidates = [np.lexsort((np.arange(len(rows)), along[rows])),
                      np.asarray(reverse_cuthill_mckee(block, symmetric_mode=True), np.int64)]
        widths = [_bandwidth(block, c) for c in candidates]
        order = candidates[int(np.argmin(widths))]
        width = min(widths)
        ordered = block[order][:, order].tocoo()
        keep = ordered.row >= ordered.col
        banded = np.zeros((width + 1, len(rows)))
        banded[(ordered.row - ordered.col)[keep], ordered.col[keep]] = ordered.data[keep]
        try:
            factor_ = linalg.cholesky_banded(banded, lower=True, check_finite=False)
        except linalg.LinAlgError:
            raise MuscleMSSError(
                f"the quasi-static solver cannot factorise the springs of muscle "
                f"'{model.names[m]}': some of its free particles are joined to no fixed "
                "particle through springs (they would float away); fix its tendon ends or use "
                "the paper relaxation") from None
        blocks.append((rows[order], factor_))
        widest = max(widest, width)
    result = Preconditioner(free, blocks, stiffest, widest)
    prep.cache[key] = result
    return result


def model_springs(model: S.MSSModel, prep: S.PreparedModel):
    """:func:`_springs`, cached on ``prep`` (the topology's)."""
    key = "quasi-static springs"
    if key not in prep.cache:
        prep.cache[key] = _springs(model, prep)
    return prep.cache[key]


# ---- kernels ---------------------------------------------------------------------------------

@njit(cache=True, parallel=True)
def _elastic(x, gradient, volume_gradient, energy, ends, rest, stiffness, spring_ptr,
             bulk_modulus, cage_ptr, cage_triangles, rest_volume, offsets):
    """The spring and volume energy of every muscle into ``energy`` (M,), its gradient into
    ``gradient`` (3, n) (overwritten), each muscle's cage volume gradient ``dV/dx`` into
    ``volume_gradient`` (3, n) (zero off the cages and when ``bulk_modulus`` is 0), at ``x``
    (3, n) mm. One parallel region over the muscles (a spring never joins two)."""
    for m in prange(offsets.shape[0] - 1):
        for axis in range(3):
            for p in range(offsets[m], offsets[m + 1]):
                gradient[axis, p] = 0.0
                volume_gradient[axis, p] = 0.0
        e = 0.0
        for s in range(spring_ptr[m], spring_ptr[m + 1]):
            a, b = ends[s, 0], ends[s, 1]
            dx = x[0, b] - x[0, a]
            dy = x[1, b] - x[1, a]
            dz = x[2, b] - x[2, a]
            length = np.sqrt(dx * dx + dy * dy + dz * dz)
            stretch = length - rest[s]
            e += 0.5 * stiffness[s] * stretch * stretch
            if length > 0.0:
                f = stiffness[s] * stretch / length
                gradient[0, b] += f * dx
                gradient[1, b] += f * dy
                gradient[2, b] += f * dz
                gradient[0, a] -= f * dx
                gradient[1, a] -= f * dy
                gradient[2, a] -= f * dz
        if bulk_modulus > 0.0 and cage_ptr[m + 1] > cage_ptr[m]:
            strain = _cage_volume(m, x, cage_ptr, cage_triangles) / (6.0 * rest_volume[m]) - 1.0
            e += 0.5 * bulk_modulus * rest_volume[m] * strain * strain
            _add_cage_gradient(m, x, gradient, bulk_modulus * strain / 6.0, cage_ptr,
                               cage_triangles)
            _add_cage_gradient(m, x, volume_gradient, 1.0 / 6.0, cage_ptr, cage_triangles)
        energy[m] = e


@njit(cache=True, parallel=True)
def _contacts(x, gradient, weight, particle, radius, fixed, mm_begin, mm_end, mm_idx,
              mb_begin, mb_end, mb_idx, bone_centres, bone_radius, sphere_energy, overlaps,
              deepest):
    """The contact penalty of every muscle sphere against the spheres in its candidate lists
    (``mm_*`` other muscles' spheres, ``mb_*`` bone spheres, CSR as
    :func:`~muscle_mss.core.spatial_hash.candidate_lists`): its gradient added to ``gradient``
    (3, n) at the sphere's particle (a free sphere only), per sphere the energy of its pairs
    (a muscle pair counted by its lower sphere) into ``sphere_energy`` (s,), the overlapping
    pairs into ``overlaps`` (s, 2) (muscle, bone; a muscle pair by its lower sphere) and the
    deepest overlap of its pairs into ``deepest`` (s,) (0: it touches nothing). Sphere ``i``
    writes only its own entries."""
    for i in prange(particle.shape[0]):
        p = particle[i]
        xi, yi, zi = x[0, p], x[1, p], x[2, p]
        gx, gy, gz = 0.0, 0.0, 0.0
        e = 0.0
        n_mm, n_mb = 0, 0
        worst = 0.0
        for k in range(mm_begin[i], mm_end[i]):
            j = mm_idx[k]
            q = particle[j]
            dx, dy, dz = xi - x[0, q], yi - x[1, q], zi - x[2, q]
            d = np.sqrt(dx * dx + dy * dy + dz * dz)
            pen = radius[i] + radius[j] - d
            if pen > 0.0 and not (fixed[i] and fixed[j]):
                worst = max(worst, pen)
                if j > i:
                    e += 0.5 * weight * pen * pen
                    n_mm += 1
                if d > 0.0:
                    gx -= weight * pen * dx / d
                    gy -= weight * pen * dy / d
                    gz -= weight * pen * dz / d
        if not fixed[i]:
            for k in range(mb_begin[i], mb_end[i]):
                j = mb_idx[k]
                dx = xi - bone_centres[0, j]
                dy = yi - bone_centres[1, j]
                dz = zi - bone_centres[2, j]
                d = np.sqrt(dx * dx + dy * dy + dz * dz)
                pen = radius[i] + bone_radius[j] - d
                if pen > 0.0:
                    e += 0.5 * weight * pen * pen
                    n_mb += 1
                    worst = max(worst, pen)
                    if d > 0.0:
                        gx -= weight * pen * dx / d
                        gy -= weight * pen * dy / d
                        gz -= weight * pen * dz / d
        if not fixed[i]:
            gradient[0, p] += gx
            gradient[1, p] += gy
            gradient[2, p] += gz
        sphere_energy[i] = e
        overlaps[i, 0] = n_mm
        overlaps[i, 1] = n_mb
        deepest[i] = worst


@njit(cache=True, parallel=True)
def _field_contacts(x, gradient, weight, particle, radius, fixed, clearance, transforms,
                    origin, spacing, dims, coarse_start, coarse, index_start, brick_index,
                    bricks, sphere_energy, overlaps, deepest):
    """The contact penalty of every free muscle sphere against the bones as solids: ``w / 2
    max(0, r_i + clearance_b - d_b(c_i))^2`` per bone ``b``, ``d_b`` its signed distance
    (:mod:`muscle_mss.core.bone_distance`, sampled in the bone's rest frame, ``transforms``
    (b, 3, 4) rest to posed), pushing along the distance gradient from whatever depth. Added
    to ``gradient``, ``sphere_energy``, ``overlaps[:, 1]`` and ``deepest`` (after
    :func:`_contacts`)."""
    for i in prange(particle.shape[0]):
        if fixed[i]:
            continue
        p = particle[i]
        gx, gy, gz = 0.0, 0.0, 0.0
        e = 0.0
        count = 0
        worst = deepest[i]
        for b in range(transforms.shape[0]):
            qx, qy, qz = _to_rest(transforms, b, x[0, p], x[1, p], x[2, p])
            value, hx, hy, hz = _sample(b, qx, qy, qz, origin, spacing, dims, coarse_start,
                                        coarse, index_start, brick_index, bricks)
            pen = radius[i] + clearance[b] - value
            if pen > 0.0:
                e += 0.5 * weight * pen * pen
                count += 1
                worst = max(worst, pen)
                m = transforms[b]
                gx -= weight * pen * (m[0, 0] * hx + m[0, 1] * hy + m[0, 2] * hz)
                gy -= weight * pen * (m[1, 0] * hx + m[1, 1] * hy + m[1, 2] * hz)
                gz -= weight * pen * (m[2, 0] * hx + m[2, 1] * hy + m[2, 2] * hz)
        gradient[0, p] += gx
        gradient[1, p] += gy
        gradient[2, p] += gz
        sphere_energy[i] += e
        overlaps[i, 1] += count
        deepest[i] = worst


@njit(cache=True, parallel=True)
def _near_solids(x, particle, radius, reach, transforms, origin, spacing, dims, coarse_start,
                 coarse, index_start, brick_index, bricks, near):
    """``near[i]``: whether particle ``particle[i]`` lies within its ``radius[i]`` plus
    ``reach[b]`` (mm) of some bone ``b`` as a solid (its sampled signed distance)."""
    for i in prange(particle.shape[0]):
        p = particle[i]
        near[i] = False
        for b in range(transforms.shape[0]):
            qx, qy, qz = _to_rest(transforms, b, x[0, p], x[1, p], x[2, p])
            value = _sample(b, qx, qy, qz, origin, spacing, dims, coarse_start, coarse,
                            index_start, brick_index, bricks)[0]
            if value < radius[i] + reach[b]:
                near[i] = True
                break


@njit(cache=True)
def _moved_more(x, particle, built, limit):
    """Whether a sphere's particle is farther than ``limit`` mm from ``built`` (3, s)."""
    for i in range(particle.shape[0]):
        p = particle[i]
        d2 = 0.0
        for axis in range(3):
            d2 += (x[axis, p] - built[axis, i]) ** 2
        if not d2 <= limit * limit:
            return True
    return False


# ---- the energy --------------------------------------------------------------------------------

class _Energy:
    """The energy of one posed model as a function of the free particles' positions, with the
    contact candidate lists it keeps up to date (see the module docstring)."""

    def __init__(self, model, prep, pre: Preconditioner, spheres, settings, x, weight,
                 solids=None):
        self.prep, self.pre, self.weight = prep, pre, weight
        self.x = x                                  # (3, n) mm, fixed particles posed
        self.free = pre.free
        n = x.shape[1]
        self.gradient = np.zeros((3, n))
        self.volume_gradient = np.zeros((3, n))
        self.muscle_energy = np.zeros(len(prep.offsets) - 1)
        self.springs = model_springs(model, prep)
        self.bulk_modulus = float(settings.bulk_modulus)
        self.spheres = spheres
        ns = spheres.count
        self.muscle_muscle = bool(settings.muscle_muscle)
        self.solids = solids if settings.muscle_bone else None
        self.muscle_bone = (bool(settings.muscle_bone) and self.solids is None
                            and len(spheres.bone_radius) > 0)
        self.skin = SKIN_FRACTION * float(spheres.radius.mean()) if ns else 0.0
        self.sphere_energy = np.zeros(ns)
        self.overlaps = np.zeros((ns, 2), dtype=np.int64)
        self.deepest = np.zeros(ns)
        # the solids' penalty over every free particle not inside a bone at rest
        self.solid_points = S.solid_points(prep) if self.solids is not None \
            else np.zeros(0, dtype=np.int64)
        k = len(self.solid_points)
        self.solid_radius = prep.radius[self.solid_points].copy()
        self.solid_energy = np.zeros(k)
        self.solid_overlaps = np.zeros((k, 2), dtype=np.int64)
        self.solid_deepest = np.zeros(k)
        self.solid_fixed = np.zeros(k, dtype=np.bool_)
        # the solid points within their radius plus clearance plus the skin of a bone when
        # the list was built (at positions solid_built): the others cannot touch a bone
        # before one of them moves half the skin (a sampled distance changes by at most sqrt(3)
        # times a move), so the penalty skips them
        self.solid_built = np.zeros((3, k))
        self.solid_mask = np.zeros(k, dtype=np.bool_)
        self.near = None                 # (indices into solid_points, their particles, ...)
        self.built = np.zeros((3, ns))
        self.bone_table = None
        if self.muscle_bone:
            self.bone_table = spatial_hash.grid_table(
                spheres.bone_centres, spheres.bone_radius,
                spatial_hash.bone_cell(spheres, self.skin), spheres.bone + spheres.n_muscles)
        none = np.zeros(ns, dtype=np.int64)
        self.mm = self.mb = (none, none, np.zeros(0, dtype=np.int64))
        self.lists_built = False
        self.rebuilds = 0
        self.seconds = np.zeros(3)       # elastic, muscle contacts, bone contacts

    def _refresh_lists(self):
        """Rebuild the contact candidate lists when a sphere moved half the skin."""
        sp = self.spheres
        if not sp.count or not (self.muscle_muscle or self.muscle_bone):
            return
        if self.lists_built and not _moved_more(self.x, sp.particle, self.built,
                                                0.5 * self.skin):
            return
        self.built[:] = self.x[:, sp.particle]
        tick = time.perf_counter()
        if self.muscle_muscle:
            table = spatial_hash.grid_table(self.built, sp.radius,
                                            spatial_hash.muscle_cell(sp, self.skin), sp.muscle)
            self.mm = spatial_hash.candidate_lists(self.built, sp.radius, sp.muscle, table,
                                                   self.skin)
        tock = time.perf_counter()
        if self.muscle_bone:
            self.mb = spatial_hash.candidate_lists(self.built, sp.radius, sp.muscle,
                                                   self.bone_table, self.skin)
        self.seconds[1] += tock - tick
        self.seconds[2] += time.perf_counter() - tock
        self.lists_built = True
        self.rebuilds += 1

    def _refresh_near_solids(self):
        """Rebuild the list of solid points near a bone when one of them moved half the skin
        since (see ``solid_built``)."""
        if self.near is not None and not _moved_more(self.x, self.solid_points,
                                                     self.solid_built, 0.5 * self.skin):
            return
        solids = self.solids
        self.solid_built[:] = self.x[:, self.solid_points]
        _near_solids(self.x, self.solid_points, self.solid_radius,
                     solids.clearance + self.skin, solids.transforms, *solids.fields.arrays(),
                     self.solid_mask)
        index = np.flatnonzero(self.solid_mask)
        k = len(index)
        self.near = (index, self.solid_points[index], self.solid_radius[index],
                     self.solid_fixed[index], np.zeros(k), np.zeros((k, 2), dtype=np.int64),
                     np.zeros(k))

    def evaluate(self, free_positions):
        """Set the free particles to ``free_positions`` (f, 3) and return ``(energy, gradient
        (f, 3), volume gradient (f, 3))``; the contact statistics stay on the object."""
        self.x[:, self.free] = free_positions.T
        tick = time.perf_counter()
        springs = self.springs
        cages = self.prep.cages
        _elastic(self.x, self.gradient, self.volume_gradient, self.muscle_energy, springs[0],
                 springs[1], springs[2], springs[3], self.bulk_modulus, cages.ptr,
                 cages.triangles, cages.rest_volume, self.prep.offsets)
        self.seconds[0] += time.perf_counter() - tick
        self._refresh_lists()
        tick = time.perf_counter()
        sp = self.spheres
        if sp.count:
            _contacts(self.x, self.gradient, self.weight, sp.particle, sp.radius, sp.fixed,
                      *self.mm, *self.mb, sp.bone_centres, sp.bone_radius, self.sphere_energy,
                      self.overlaps, self.deepest)
        if self.solids is not None and len(self.solid_points):
            solids = self.solids
            self._refresh_near_solids()
            index, points, radius, fixed, energy, overlaps, deepest = self.near
            for array in (self.solid_energy, self.solid_overlaps, self.solid_deepest, energy,
                          overlaps, deepest):
                array[:] = 0
            _field_contacts(self.x, self.gradient, self.weight, points, radius, fixed,
                            solids.clearance, solids.transforms, *solids.fields.arrays(),
                            energy, overlaps, deepest)
            self.solid_energy[index] = energy
            self.solid_overlaps[index] = overlaps
            self.solid_deepest[index] = deepest
        self.seconds[1] += time.perf_counter() - tick
        energy = float(self.muscle_energy.sum() + self.sphere_energy.sum()
                       + self.solid_energy.sum())
        return (energy, np.ascontiguousarray(self.gradient[:, self.free].T),
                np.ascontiguousarray(self.volume_gradient[:, self.free].T))

    def contact_figures(self):
        """``(muscle pairs, bone pairs, deepest overlap mm)`` at the last evaluation."""
        totals = self.overlaps.sum(axis=0)
        return (int(totals[0]), int(totals[1] + self.solid_overlaps[:, 1].sum()),
                float(max(self.deepest.max(initial=0.0), self.solid_deepest.max(initial=0.0))))


# ---- the driver ------------------------------------------------------------------------------

def _check(settings: SolverSettings) -> None:
    if settings.structure not in STRUCTURES:
        raise MuscleMSSError(f"collision structure {settings.structure!r} is not one of "
                             f"{', '.join(STRUCTURES)}")
    for name, value, least in (("iterations", settings.iterations, 1),
                               ("projection passes", settings.projection_passes, 0),
                               ("history", settings.quasi_static.history, 0)):
        if not (value >= least and int(value) == value):
            raise MuscleMSSError(f"solver {name} is {value}; it must be a whole number, "
                                 f"{least} or more")
    for name, value in (("tolerance", settings.quasi_static.tolerance),
                        ("penetration tolerance", settings.penetration_tolerance),
                        ("bulk modulus", settings.bulk_modulus)):
        if not (value >= 0.0 and np.isfinite(value)):
            raise MuscleMSSError(f"solver {name} is {value}; it must be finite and 0 or more")
    weight = settings.quasi_static.contact_weight
    if not (weight > 0.0 and np.isfinite(weight)):
        raise MuscleMSSError(f"solver contact weight is {weight}; it must be "
                             "finite and positive")
    if settings.budget is not None and not settings.budget >= 0.0:
        raise MuscleMSSError(f"solver time budget is {settings.budget}; it must be 0 or "
                             "more")


def _largest_move(step) -> float:
    """The largest particle move (mm) of ``step`` (f, 3)."""
    return float(np.sqrt(np.einsum("ij,ij->i", step, step).max(initial=0.0)))


class _Hessian0:
    """``(A + K)^-1`` at one state: ``A`` the :class:`Preconditioner`, ``K`` each muscle's
    rank-one volume stiffness ``(B / V0) g g^T`` for the volume gradient ``g`` (f, 3) of that
    state (Sherman-Morrison per muscle, ``A`` being block diagonal). ``A`` alone leaves the
    volume term's stiff whole-cage mode out: at BulkModulus 50 its steps overshoot that mode
    many times."""

    def __init__(self, pre: Preconditioner, free_muscle, volume_stiffness, volume_gradient):
        self.pre, self.free_muscle, self.c = pre, free_muscle, volume_stiffness
        self.g = volume_gradient
        self.solved_g = None
        self.self_term = None

    def __call__(self, rhs):
        if not self.c.any():
            return self.pre.solve(rhs)
        if self.solved_g is None:
            both = self.pre.solve(np.concatenate([rhs, self.g], axis=1))
            out, self.solved_g = both[:, :3], both[:, 3:]
            self.self_term = np.bincount(self.free_muscle, np.einsum(
                "ij,ij->i", self.g, self.solved_g), minlength=len(self.c))
        else:
            out = self.pre.solve(rhs)
        along = np.bincount(self.free_muscle, np.einsum("ij,ij->i", self.g, out),
                            minlength=len(self.c))
        scale = self.c * along / (1.0 + self.c * self.self_term)
        out -= self.solved_g * scale[self.free_muscle, None]
        return out


def _push_out_of_solids(x, points, radius, solids: BoneSolids) -> None:
    """Move the particles ``points`` (k,) of ``x`` (3, n) out to their ``radius`` (k,) mm plus
    the clearance from each bone solid (the penalty leaves an overlap of contact force / w at
    the minimum; :func:`~muscle_mss.core.bone_distance.push_out_of_bones`, bone by bone, twice
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


def distance_to_go(residual) -> float:
    """The distance (mm) the particles still have to go after the iterations whose residuals
    are ``residual`` (K,), estimated as ``r rho / (1 - rho)``: ``r`` the last residual, ``rho``
    its mean decay per iteration over the last :data:`RATE_WINDOW` iterations (a step
    shrinking by ``rho`` per iteration has that much left in its geometric tail; the last step
    alone understated the distance to the minimum 50 times on the small demo, where a solve
    stopped at 0.01 mm ended 0.55 mm from one started elsewhere). ``inf`` when the residual is
    not shrinking or there is one only; 0 below :data:`REST_STEP` (rest)."""
    last = float(residual[-1])
    if last < REST_STEP:
        return 0.0
    if len(residual) < 2:
        return np.inf
    window = min(RATE_WINDOW, len(residual) - 1)
    rate = (last / residual[-1 - window]) ** (1.0 / window)
    return last * rate / (1.0 - rate) if rate < 1.0 else np.inf


def _settled(residual, tolerance) -> bool:
    """Whether :func:`distance_to_go` is below ``tolerance`` (mm)."""
    return distance_to_go(residual) < tolerance


class _History:
    """The last ``size`` L-BFGS pairs ``(s, y, 1 / y.s)`` of (f, 3) arrays, in ring buffers
    (no arrays made per iteration)."""

    def __init__(self, size: int, free: int):
        self.s = np.zeros((max(size, 1), 3 * free))
        self.y = np.zeros_like(self.s)
        self.rho = np.zeros(max(size, 1))
        self.alpha = np.zeros(max(size, 1))
        self.size, self.count, self.next = size, 0, 0

    def __len__(self):
        return self.count

    def clear(self):
        self.count = 0

    def add(self, s, y, rho):
        """Keep the pair ``s``, ``y`` (f, 3) (copied), dropping the oldest when full."""
        if self.size == 0:
            return
        self.s[self.next] = s.ravel()
        self.y[self.next] = y.ravel()
        self.rho[self.next] = rho
        self.next = (self.next + 1) % self.size
        self.count = min(self.count + 1, self.size)

    def order(self) -> np.ndarray:
        """The slots of the pairs kept, oldest first."""
        return (self.next - self.count + np.arange(self.count)) % max(self.size, 1)


@njit(cache=True)
def _lbfgs_back(q, s, y, rho, order, alpha):
    """The first loop of the two-loop recursion on ``q`` (in place), newest pair first."""
    for t in range(order.shape[0] - 1, -1, -1):
        k = order[t]
        a = 0.0
        for i in range(q.shape[0]):
            a += s[k, i] * q[i]
        a *= rho[k]
        alpha[k] = a
        for i in range(q.shape[0]):
            q[i] -= a * y[k, i]


@njit(cache=True)
def _lbfgs_forward(r, s, y, rho, order, alpha):
    """The second loop of the two-loop recursion on ``r`` (in place), oldest pair first."""
    for t in range(order.shape[0]):
        k = order[t]
        b = 0.0
        for i in range(r.shape[0]):
            b += y[k, i] * r[i]
        c = alpha[k] - rho[k] * b
        for i in range(r.shape[0]):
            r[i] += c * s[k, i]


def _direction(gradient, history: _History, h0):
    """The L-BFGS step ``-H gradient`` (f, 3) (two-loop recursion, Nocedal and Wright
    algorithm 7.4) for the pairs of ``history`` and the initial inverse Hessian ``h0``."""
    q = gradient.copy()
    order = history.order()
    _lbfgs_back(q.reshape(-1), history.s, history.y, history.rho, order, history.alpha)
    r = np.ascontiguousarray(h0(q))
    _lbfgs_forward(r.reshape(-1), history.s, history.y, history.rho, order, history.alpha)
    return -r


def solve(model: S.MSSModel, bone_centres=None, bone_radius=None, bone_id=None,
          settings: SolverSettings | None = None, progress=None,
          prepared: S.PreparedModel | None = None, start=None,
          bone_solids: BoneSolids | None = None) -> QuasiStaticResult:
    """The static equilibrium of the posed model with contacts (see the module docstring).

    Arguments as :func:`muscle_mss.core.solver.solve`; ``start`` (n, 3) mm, input particle
    order: the free particles' starting positions (warm start; omitted: the posed ones). Fixed
    particles stay at their posed positions. ``bone_solids``: the bones as solids for the
    muscle-bone contacts of the minimisation (the bone spheres then serve the final collision
    passes only).
    """
    settings = settings or SolverSettings(method=METHOD_QUASI_STATIC)
    _check(settings)
    tolerance = settings.quasi_static.tolerance
    budget = settings.budget
    if bone_solids is not None:
        bone_solids.check()
    S.check_history_size(settings.iterations, len(model.names))
    prep = prepared if prepared is not None else S.prepare(model)
    pre = preconditioner(model, prep)
    offsets = prep.offsets
    n = int(offsets[-1])
    n_muscles = len(offsets) - 1
    posed = np.asarray(model.positions, dtype=np.float64).reshape(-1, 3)[prep.order]
    x = np.ascontiguousarray(posed.T)
    free = pre.free
    if start is not None:
        begin = np.asarray(start, dtype=np.float64).reshape(-1, 3)
        if begin.shape != (n, 3) or not np.isfinite(begin).all():
            raise MuscleMSSError(f"the solver's start positions must be {n} finite points; got "
                                 f"shape {begin.shape}")
        x[:, free] = begin[prep.order][free].T
    free_muscle = prep.muscle[free]
    has_cage = np.diff(prep.cages.ptr) > 0
    volume_stiffness = np.where(has_cage, float(settings.bulk_modulus)
                                / prep.cages.rest_volume, 0.0)     # (M,) g/(mm^4 s^2)
    spheres, sphere_state = S.collision_spheres(prep, bone_centres, bone_radius, bone_id)
    ns = spheres.count
    energy_of = _Energy(model, prep, pre, spheres, settings, x,
                        float(settings.quasi_static.contact_weight) * pre.stiffest, bone_solids)
    step_limit = float(spheres.radius.max()) if ns else np.inf
    sizes = np.maximum(np.diff(offsets), 1)

    cap = int(settings.iterations)
    residual = np.zeros(cap)
    energies = np.zeros(cap)
    mean_move = np.zeros((cap, n_muscles))
    muscle_pairs = np.zeros(cap, dtype=np.int64)
    bone_pairs = np.zeros(cap, dtype=np.int64)
    max_pen = np.zeros(cap)
    seconds = np.zeros(cap)
    solve_seconds = 0.0

    started = time.perf_counter()
    position = np.ascontiguousarray(x[:, free].T)
    energy, gradient, volume_gradient = energy_of.evaluate(position)
    history = _History(int(settings.quasi_static.history), len(free))
    done = 0
    converged_loop = False
    stopped_by = TERMINATION_ITERATIONS
    while done < cap:
        muscle_pairs[done], bone_pairs[done], max_pen[done] = energy_of.contact_figures()
        energies[done] = energy
        tick = time.perf_counter()
        h0 = _Hessian0(pre, free_muscle, volume_stiffness, volume_gradient)
        step = _direction(gradient, history, h0)
        largest = _largest_move(step)
        if not np.isfinite(largest):
            raise MuscleMSSError(f"the quasi-static solve diverged at iteration {done + 1}: a "
                                 "particle's step is not finite; check stiffness and bulk "
                                 "modulus")
        residual[done] = largest
        if largest <= tolerance and not _settled(residual[:done + 1], tolerance):
            largest = max(largest, 2.0 * tolerance)     # not yet: keep going
        elif largest <= tolerance and history:
            # confirm with the plain step, which bounds the force
            plain = -h0(gradient)
            if _largest_move(plain) > tolerance:
                history.clear()
                step, largest = plain, _largest_move(plain)
        slope = float(np.vdot(gradient, step))
        if slope >= 0.0 and largest > 0.0:
            history.clear()
            step = -h0(gradient)
            largest = _largest_move(step)
            slope = float(np.vdot(gradient, step))
        solve_seconds += time.perf_counter() - tick
        done += 1
        if largest <= tolerance:
            converged_loop = True
            stopped_by = "tolerance"
            seconds[done - 1] = time.perf_counter() - started
            break
        # backtracking line search on the energy (Armijo)
        alpha = min(1.0, step_limit / largest)
        accepted = False
        for _ in range(BACKTRACKS):
            trial = position + alpha * step
            trial_energy, trial_gradient, trial_volume = energy_of.evaluate(trial)
            rise = trial_energy - energy
            if rise <= ARMIJO * alpha * slope + ENERGY_ROUNDING * abs(energy):
                accepted = True
                break
            # the minimum of the quadratic through E(0), E'(0) and E(alpha), kept in
            # [alpha / 10, alpha / 2]
            curve = rise - alpha * slope
            guess = -slope * alpha * alpha / (2.0 * curve) if curve > 0.0 else 0.5 * alpha
            alpha = min(max(guess, 0.1 * alpha), 0.5 * alpha)
        if not accepted:
            energy_of.evaluate(position)
            stopped_by = "line search"
            seconds[done - 1] = time.perf_counter() - started
            break
        moved = trial - position
        change = trial_gradient - gradient
        curvature = float(np.vdot(moved, change))
        if settings.quasi_static.history and curvature > 1e-12 * float(np.linalg.norm(moved)
                                                           * np.linalg.norm(change)):
            history.add(moved, change, 1.0 / curvature)
        mean_move[done - 1] = np.bincount(free_muscle, np.sqrt(np.einsum(
            "ij,ij->i", moved, moved)), minlength=n_muscles) / sizes
        position, energy, gradient, volume_gradient = (trial, trial_energy, trial_gradient,
                                                       trial_volume)
        seconds[done - 1] = time.perf_counter() - started
        if budget is not None and seconds[done - 1] >= budget:
            stopped_by = TERMINATION_BUDGET
            break
        if progress is not None and progress(done / cap):
            raise MuscleMSSError(f"the solve was stopped by the user after {done} iterations")

    x[:, free] = position.T
    touching = energy_of.deepest > 0.0
    touching_solid = energy_of.solid_deepest > 0.0
    if len(energy_of.solid_points):
        _push_out_of_solids(x, energy_of.solid_points, energy_of.solid_radius, bone_solids)
    # the final collision passes of the paper method remove the penalty's overlap
    use_bvh = settings.structure == STRUCTURE_BVH
    hashed = S._hash_state(spheres, not use_bvh)
    bvh = S._bvh_state(spheres, settings)
    fixed_state, lists = hashed[:-5], hashed[-5:]
    solids = S.solid_arguments(bone_solids, x, prep)
    solid_collided = np.zeros(len(solids[12]), dtype=np.uint8)
    if len(energy_of.solid_points):     # the same particles, the same order
        solid_collided[:] = touching_solid
    collided_spheres = touching.astype(np.uint8)
    passes, left, projection_seconds = 0, 0.0, 0.0
    if settings.projection_passes > 0 and (settings.muscle_muscle or settings.muscle_bone):
        tick = time.perf_counter()
        passes, left, lists = S._project(
            x, np.zeros_like(x), sphere_state, fixed_state, bvh, use_bvh,
            bool(settings.muscle_muscle), bool(settings.muscle_bone),
            int(settings.projection_passes), float(settings.penetration_tolerance), lists,
            collided_spheres, solids, solid_collided, S._world_box(x.T, spheres.bone_centres.T))
        projection_seconds = time.perf_counter() - tick
    rank = np.empty(n, dtype=np.int64)
    rank[prep.order] = np.arange(n)
    collided_out = np.zeros(n, dtype=bool)
    collided_out[spheres.particle] = collided_spheres[:ns] > 0
    collided_out[solids[12]] |= solid_collided > 0
    phases = {"mss": float(energy_of.seconds[0] + solve_seconds),
              "muscle_cd": float(energy_of.seconds[1]), "bone_cd": float(energy_of.seconds[2]),
              "projection": projection_seconds}
    return QuasiStaticResult(
        positions=x.T[rank].copy(), velocity=np.zeros((n, 3)), collided=collided_out[rank],
        mean_displacement=mean_move[:done].copy(), muscle_pairs=muscle_pairs[:done].copy(),
        bone_pairs=bone_pairs[:done].copy(), max_penetration=max_pen[:done].copy(),
        seconds=seconds[:done].copy(), phase_seconds=phases, stopped_by=stopped_by,
        rebuilds=energy_of.rebuilds, projection_passes=passes, remaining_penetration=left,
        residual=residual[:done].copy(), energy=energies[:done].copy(),
        converged=converged_loop and left <= settings.penetration_tolerance)
