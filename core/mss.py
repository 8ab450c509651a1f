"""The mass-spring system of the muscles (the paper's §3.1–3.2).

Particles of every muscle are held in one structure-of-arrays: positions and velocities are
``(3, n)`` float64 (mm, mm/s), the muscles one after another (``muscle_offsets``). The springs follow
Hooke's law with damping along the spring: for a spring from particle ``a`` to ``b`` with rest
length ``L0`` (mm), stiffness ``k`` (g/s^2) and damping ``c`` (g/s), ``d = x_b - x_a``,
``L = |d|``, the force on ``a`` is ::

    f_a = (k (L - L0) + c (v_b - v_a) . d / L) d / L        and  f_b = -f_a

(force unit g mm/s^2). Two terms beyond the paper's springs make the relaxation a convergent,
volume-keeping quasi-static solve (:func:`mss_steps`): a viscous drag on every particle's
velocity, integrated implicitly so that it is stable at any strength (the damping along the
springs is explicit and bounded by ``c dt n / m < 2`` for ``n`` springs per particle, far below
what converging needs), and the pressure of each muscle's closed cage (the MVC cage of
:mod:`muscle_mss.core.cage`) against a change of its volume: muscle is nearly incompressible,
while a spring lattice with long cells narrows several times faster than it stretches. The
pressure's stiff whole-cage mode is taken implicitly too (:func:`_implicit_volume_forces`), so
that a stiff BulkModulus does not shorten the stable time step. The step is semi-implicit Euler, ``v = (v + dt f / m) / (1 + dt drag)``, ``x += dt v``; fixed particles
(tendon attachments) never move.

Speed. The springs are grouped into *runs*: springs of one muscle with the same index offset
``d = b - a`` and the same stiffness and damping. A run whose springs cover at least half of
the index range they span is stored densely ("lanes": one rest length per index, -1 where that
index has no spring), so the force loop reads positions at ``a`` and ``a + d`` contiguously and
vectorises. A lattice with its particles ordered by (row, col, fibre_index) has 13 such runs per
muscle (:func:`lattice_order` gives that order). The springs in sparser runs (Delaunay, k-NN) take a
scalar loop. The muscles are independent tasks of one ``prange``; inside a muscle every sum has
a fixed order, so results are bitwise reproducible whatever the thread count.
"""
from __future__ import annotations

from collections import namedtuple
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from .errors import MuscleMSSError

# No 'nnan' / 'ninf': the solver's divergence check must still see NaN and infinity.
FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}

# A run of springs is stored densely when it has at least this many springs and they cover
# at least DENSE_FILL of the index range they span; otherwise its springs go to the scalar loop.
DENSE_MIN = 8
DENSE_FILL = 0.5
NO_SPRING = -1.0   # rest length of a dense lane without a spring


SpringLayout = namedtuple("SpringLayout", (
    "runs_int", "runs_param", "lane_rest", "run_ptr", "scattered_int", "scattered_param",
    "scattered_ptr"))
SpringLayout.__doc__ = """The springs grouped for the force kernel (see the module docstring).

``runs_int`` (R, 4) int64: first particle ``a``, number of lanes, offset ``d``, first lane.
``runs_param`` (R, 2) float64: stiffness (g/s^2) and damping (g/s) of the run.
``lane_rest`` (lanes,) float64: rest length (mm) of lane ``i``'s spring, -1 for no spring.
``scattered_int`` (Q, 2) int64 ends, ``scattered_param`` (Q, 3) rest length, stiffness,
damping of the springs in the scalar loop. ``run_ptr``, ``scattered_ptr`` (M+1,) int64: the
runs / scattered springs of muscle ``m`` are ``[ptr[m], ptr[m+1])``."""


def lattice_order(fibre_id, fibre_index, fibre_grid=None) -> np.ndarray:
    """(P,) int64: the order of one muscle's particles in which lattice neighbours sit at
    constant index offsets — by (row, col) of ``fibre_grid`` when given, else by ``fibre_id``,
    then by ``fibre_index``. Any order is correct; this one makes the spring kernel fast."""
    fibre_index = np.asarray(fibre_index).ravel()
    if fibre_grid is not None:
        grid = np.asarray(fibre_grid).reshape(len(fibre_index), -1)
        return np.lexsort((fibre_index, np.asarray(fibre_id).ravel(), grid[:, 1], grid[:, 0]))
    return np.lexsort((fibre_index, np.asarray(fibre_id).ravel()))


def spring_layout(springs, rest_length, stiffness, damping, muscle_offsets) -> SpringLayout:
    """Group the springs for the force kernel.

    Parameters
    ----------
    springs : (S, 2) int
        Particle indices of each spring's ends (global, muscles one after another); a spring
        never joins two muscles.
    rest_length, stiffness, damping : (S,) float64
        mm, g/s^2, g/s.
    muscle_offsets : (M+1,) int
        Muscle ``m`` owns particles ``[muscle_offsets[m], muscle_offsets[m+1])``.
    """
    springs = np.asarray(springs, dtype=np.int64).reshape(-1, 2)
    rest_length = np.asarray(rest_length, dtype=np.float64).ravel()
    stiffness = np.asarray(stiffness, dtype=np.float64).ravel()
    damping = np.asarray(damping, dtype=np.float64).ravel()
    offsets = np.asarray(muscle_offsets, dtype=np.int64)
    a = springs.min(axis=1)
    b = springs.max(axis=1)
    d = b - a
    muscle = np.searchsorted(offsets, a, side="right") - 1
    order = np.lexsort((a, damping, stiffness, d, muscle))
    a, d, muscle = a[order], d[order], muscle[order]
    rest, k, c = rest_length[order], stiffness[order], damping[order]
    new_group = np.ones(len(a), dtype=bool)
    new_group[1:] = ((muscle[1:] != muscle[:-1]) | (d[1:] != d[:-1]) | (k[1:] != k[:-1])
                     | (c[1:] != c[:-1]))
    starts = np.flatnonzero(new_group)
    ends = np.append(starts[1:], len(a)) if len(a) else starts
    span = a[ends - 1] - a[starts] + 1
    # a repeated spring would need two springs in one lane: its run takes the scalar loop
    repeated = np.zeros(len(a), dtype=bool)
    repeated[1:] = (a[1:] == a[:-1]) & ~new_group[1:]
    has_repeat = np.add.reduceat(repeated, starts) > 0 if len(a) else np.zeros(0, dtype=bool)
    dense = (((ends - starts) >= DENSE_MIN) & ((ends - starts) >= DENSE_FILL * span)
             & ~has_repeat)

    lane_first = np.concatenate([[0], np.cumsum(np.where(dense, span, 0))])
    lane_rest = np.full(int(lane_first[-1]), NO_SPRING)
    in_dense = np.repeat(dense, ends - starts)
    group_of = np.repeat(np.arange(len(starts)), ends - starts)
    lane = lane_first[group_of] + a - a[starts][group_of]
    lane_rest[lane[in_dense]] = rest[in_dense]
    runs_int = np.stack([a[starts], span, d[starts], lane_first[:-1]], axis=1)[dense]
    runs_param = np.stack([k[starts], c[starts]], axis=1)[dense]
    run_muscle = muscle[starts][dense]

    sparse = ~in_dense
    scattered_int = np.stack([a[sparse], a[sparse] + d[sparse]], axis=1)
    scattered_param = np.stack([rest[sparse], k[sparse], c[sparse]], axis=1)
    n_muscles = len(offsets) - 1
    return SpringLayout(
        np.ascontiguousarray(runs_int, dtype=np.int64),
        np.ascontiguousarray(runs_param, dtype=np.float64),
        lane_rest,
        np.searchsorted(run_muscle, np.arange(n_muscles + 1)).astype(np.int64),
        np.ascontiguousarray(scattered_int, dtype=np.int64).reshape(-1, 2),
        np.ascontiguousarray(scattered_param, dtype=np.float64).reshape(-1, 3),
        np.searchsorted(muscle[sparse], np.arange(n_muscles + 1)).astype(np.int64))


@dataclass
class VolumeCages:
    """The closed cage of each muscle for the volume force (:func:`mss_steps`).

    ``triangles`` (T, 3) int64 global particle indices, outward in the rest pose; ``ptr``
    (M+1,) int64: muscle ``m``'s triangles are ``[ptr[m], ptr[m+1])`` (none: no volume force
    on that muscle); ``rest_volume`` (M,) float64 mm^3, positive where the muscle has a cage.
    """

    ptr: np.ndarray
    triangles: np.ndarray
    rest_volume: np.ndarray

    @property
    def arrays(self) -> tuple:
        """The arrays in the order the kernels take them."""
        return self.ptr, self.triangles, self.rest_volume


def no_cages(n_muscles: int) -> VolumeCages:
    """No muscle has a cage: no volume force."""
    return VolumeCages(np.zeros(n_muscles + 1, dtype=np.int64), np.zeros((0, 3), np.int64),
                       np.ones(n_muscles))


MSSState = namedtuple("MSSState", (
    "x", "v", "x_prev", "force", "scratch", "inv_mass", "dt", "drag", "bulk_modulus", "cage_ptr",
    "cage_triangles", "rest_volume", "offsets", "tissue", "target"))
MSSState.__doc__ = """The mass-spring system's state and parameters for the step kernels; the
springs travel beside it (:class:`SpringLayout`). Both are flat and have fewer than 16 fields:
they go to parallel loops, which take no nested tuple, and Numba 0.56 lowers no named tuple of
16 fields or more there.

``x``, ``v`` (3, n) float64 mm, mm/s; ``x_prev`` (3, n) receives x before the step; ``force``,
``scratch`` (3, n) work arrays; ``inv_mass`` (n,) 1/g, 0 for fixed particles (so they never
move); ``dt`` s; ``drag`` 1/s and ``bulk_modulus`` g/(mm s^2) as in :func:`mss_steps`;
``cage_ptr``, ``cage_triangles``, ``rest_volume`` the :class:`VolumeCages`; ``offsets`` (M+1,)
the muscles' particle ranges; ``tissue`` (n,) g/s^2 and ``target`` (3 or 6, n) mm the
connective tissue's stiffness and targets (:mod:`muscle_mss.core.connective_tissue`), both empty
(length 0) for none."""


def mss_state(x, v, work, inv_mass, dt, drag, bulk_modulus, cages: VolumeCages,
              offsets, tissue=None, target=None) -> MSSState:
    """The :class:`MSSState` of positions and velocities ``x``, ``v`` (3, n), work space
    ``work`` (3, 3, n) (previous positions, forces, scratch) and the parameters; ``tissue``
    (n,) and ``target`` (3, n) the connective tissue (omitted: none)."""
    if tissue is None:
        tissue, target = np.zeros(0), np.zeros((3, 0))
    return MSSState(x, v, work[0], work[1], work[2], inv_mass, float(dt), float(drag),
                    float(bulk_modulus), *cages.arrays, offsets,
                    np.ascontiguousarray(tissue, dtype=np.float64),
                    np.ascontiguousarray(target, dtype=np.float64))


@njit(cache=True, inline="always", error_model="numpy", fastmath=FASTMATH)
def _spring_factor(dx, dy, dz, dvx, dvy, dvz, rest, k, c):
    """Force on the spring's first end divided by ``d``: (k (L - L0) + c dv.d / L) / L; zero for
    a spring of zero length, whose direction is undefined."""
    length = np.sqrt(dx * dx + dy * dy + dz * dz)
    inv = 1.0 / length if length > 0.0 else 0.0
    return (k * (length - rest) + c * (dvx * dx + dvy * dy + dvz * dz) * inv) * inv


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _run_forces(x0, x1, x2, v0, v1, v2, t0, t1, t2, first, lanes, d, lane0, lane_rest, k, c):
    # Unsigned indices: Numba then drops its negative-index wraparound, which blocks SIMD.
    for i in range(lanes):
        a = np.uint64(first + i)
        b = a + np.uint64(d)
        rest = lane_rest[np.uint64(lane0 + i)]
        f = _spring_factor(x0[b] - x0[a], x1[b] - x1[a], x2[b] - x2[a],
                           v0[b] - v0[a], v1[b] - v1[a], v2[b] - v2[a], rest, k, c)
        f = f if rest >= 0.0 else 0.0
        t0[a] = f * (x0[b] - x0[a])
        t1[a] = f * (x1[b] - x1[a])
        t2[a] = f * (x2[b] - x2[a])


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _run_scatter(f0, f1, f2, t0, t1, t2, first, lanes, d):
    # Two loops: within one, a write to a + d could meet a later lane's a and block SIMD.
    for i in range(lanes):
        a = np.uint64(first + i)
        f0[a] += t0[a]
        f1[a] += t1[a]
        f2[a] += t2[a]
    for i in range(lanes):
        a = np.uint64(first + i)
        b = a + np.uint64(d)
        f0[b] -= t0[a]
        f1[b] -= t1[a]
        f2[b] -= t2[a]


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _muscle_forces(m, state, springs):
    """Spring forces (``springs``: :class:`SpringLayout`) on the particles of muscle ``m`` into
    ``state.force`` (3, n)."""
    x, v, force, scratch, muscle_offsets = (state.x, state.v, state.force, state.scratch,
                                            state.offsets)
    runs_int, runs_param, lane_rest, run_ptr = (springs.runs_int, springs.runs_param,
                                                springs.lane_rest, springs.run_ptr)
    scattered_int, scattered_param, scattered_ptr = (springs.scattered_int,
                                                     springs.scattered_param,
                                                     springs.scattered_ptr)
    for axis in range(3):
        force[axis, muscle_offsets[m]:muscle_offsets[m + 1]] = 0.0
    x0, x1, x2 = x[0], x[1], x[2]
    v0, v1, v2 = v[0], v[1], v[2]
    f0, f1, f2 = force[0], force[1], force[2]
    t0, t1, t2 = scratch[0], scratch[1], scratch[2]
    for r in range(run_ptr[m], run_ptr[m + 1]):
        _run_forces(x0, x1, x2, v0, v1, v2, t0, t1, t2, runs_int[r, 0], runs_int[r, 1],
                    runs_int[r, 2], runs_int[r, 3], lane_rest, runs_param[r, 0], runs_param[r, 1])
        _run_scatter(f0, f1, f2, t0, t1, t2, runs_int[r, 0], runs_int[r, 1], runs_int[r, 2])
    for s in range(scattered_ptr[m], scattered_ptr[m + 1]):
        a = scattered_int[s, 0]
        b = scattered_int[s, 1]
        dx = x0[b] - x0[a]
        dy = x1[b] - x1[a]
        dz = x2[b] - x2[a]
        f = _spring_factor(dx, dy, dz, v0[b] - v0[a], v1[b] - v1[a], v2[b] - v2[a],
                           scattered_param[s, 0], scattered_param[s, 1], scattered_param[s, 2])
        f0[a] += f * dx
        f1[a] += f * dy
        f2[a] += f * dz
        f0[b] -= f * dx
        f1[b] -= f * dy
        f2[b] -= f * dz


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def cage_volume(m, x, cage_ptr, cage_triangles):
    """Six times the volume (mm^3) of muscle ``m``'s cage at ``x`` (3, n).

    Coordinates are taken relative to one cage vertex ``o``: the volume of a closed cage is
    ``sum (a - o).((b - o) x (c - o)) / 6`` for any ``o``, and near the cage the products keep
    their digits (absolute coordinates are hundreds of mm, the cage tens)."""
    first, stop = cage_ptr[m], cage_ptr[m + 1]
    x0, x1, x2 = x[0], x[1], x[2]
    corner = np.uint64(cage_triangles[first, 0])
    ox, oy, oz = x0[corner], x1[corner], x2[corner]
    volume = 0.0
    for t in range(np.uint64(first), np.uint64(stop)):
        a = np.uint64(cage_triangles[t, 0])
        b = np.uint64(cage_triangles[t, 1])
        c = np.uint64(cage_triangles[t, 2])
        ay, az = x1[a] - oy, x2[a] - oz
        by, bz = x1[b] - oy, x2[b] - oz
        cy, cz = x1[c] - oy, x2[c] - oz
        volume += ((x0[a] - ox) * (by * cz - bz * cy) + (x0[b] - ox) * (cy * az - cz * ay)
                   + (x0[c] - ox) * (ay * bz - az * by))
    return volume


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def add_cage_gradient(m, x, out, scale, cage_ptr, cage_triangles):
    """Add ``scale`` times six times the gradient of muscle ``m``'s cage volume to ``out`` (3, n):
    the gradient of ``sum a.(b x c) / 6`` with respect to ``a`` is ``(b x c) / 6``."""
    first, stop = cage_ptr[m], cage_ptr[m + 1]
    x0, x1, x2 = x[0], x[1], x[2]
    f0, f1, f2 = out[0], out[1], out[2]
    corner = np.uint64(cage_triangles[first, 0])
    ox, oy, oz = x0[corner], x1[corner], x2[corner]
    for t in range(np.uint64(first), np.uint64(stop)):
        a = np.uint64(cage_triangles[t, 0])
        b = np.uint64(cage_triangles[t, 1])
        c = np.uint64(cage_triangles[t, 2])
        ax, ay, az = x0[a] - ox, x1[a] - oy, x2[a] - oz
        bx, by, bz = x0[b] - ox, x1[b] - oy, x2[b] - oz
        cx, cy, cz = x0[c] - ox, x1[c] - oy, x2[c] - oz
        f0[a] += scale * (by * cz - bz * cy)
        f1[a] += scale * (bz * cx - bx * cz)
        f2[a] += scale * (bx * cy - by * cx)
        f0[b] += scale * (cy * az - cz * ay)
        f1[b] += scale * (cz * ax - cx * az)
        f2[b] += scale * (cx * ay - cy * ax)
        f0[c] += scale * (ay * bz - az * by)
        f1[c] += scale * (az * bx - ax * bz)
        f2[c] += scale * (ax * by - ay * bx)


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _volume_forces(m, x, force, cage_ptr, cage_triangles, rest_volume, bulk_modulus):
    """Add the pressure force of muscle ``m``'s cage to ``force`` (3, n): ``-bulk_modulus
    (V / V_rest - 1) dV/dx``, minus the gradient of the energy ``bulk_modulus V_rest
    (V / V_rest - 1)^2 / 2`` (see :func:`mss_steps`)."""
    if cage_ptr[m + 1] == cage_ptr[m] or bulk_modulus == 0.0:
        return
    volume = cage_volume(m, x, cage_ptr, cage_triangles)
    pressure = -bulk_modulus * (volume / (6.0 * rest_volume[m]) - 1.0) / 6.0
    add_cage_gradient(m, x, force, pressure, cage_ptr, cage_triangles)


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _implicit_volume_forces(m, state):
    """Add muscle ``m``'s pressure force to ``force`` (3, n) so that the semi-implicit Euler
    step that follows takes the volume term implicitly (backward Euler on its stiffness).

    The volume energy's Hessian is dominated by the rank-one ``K = (bulk_modulus / V_rest)
    g g^T``, ``g = dV/dx`` over the whole cage: one stiff mode (every cage vertex moving along
    its normal at once) whose explicit step is stable only below ``dt = 2 / sqrt(bulk_modulus /
    V_rest g^T M^-1 g)`` (0.03 s for the small demo's thigh at BulkModulus 50, below the
    default time step). The backward Euler velocity change ``(M + dt^2 K) dv = dt (f - dt K v)``
    is solved in closed form (Sherman-Morrison): the force handed to the integration becomes
    ``r - g (c g^T M^-1 r) / (1 + c g^T M^-1 g)``, ``r = f - dt K v``, ``c = dt^2 bulk_modulus
    / V_rest``. Stable at any BulkModulus; the equilibria (``f = 0``, ``v = 0``) are unchanged.
    ``state.scratch`` (3, n) is work space (muscle ``m``'s entries are overwritten)."""
    x, v, force, gradient, inv_mass, dt = (state.x, state.v, state.force, state.scratch,
                                           state.inv_mass, state.dt)
    cage_ptr, cage_triangles, rest_volume, bulk_modulus = (state.cage_ptr, state.cage_triangles,
                                                           state.rest_volume, state.bulk_modulus)
    first, stop = state.offsets[m], state.offsets[m + 1]
    if cage_ptr[m + 1] == cage_ptr[m] or bulk_modulus == 0.0:
        return
    for axis in range(3):
        gradient[axis, first:stop] = 0.0
    add_cage_gradient(m, x, gradient, 1.0 / 6.0, cage_ptr, cage_triangles)
    volume = cage_volume(m, x, cage_ptr, cage_triangles) / 6.0
    stiffness = bulk_modulus / rest_volume[m]
    g_v = 0.0
    for axis in range(3):
        for p in range(first, stop):
            g_v += gradient[axis, p] * v[axis, p]
    along = -bulk_modulus * (volume / rest_volume[m] - 1.0) - dt * stiffness * g_v
    g_m_r = 0.0
    g_m_g = 0.0
    for axis in range(3):
        for p in range(first, stop):
            force[axis, p] += along * gradient[axis, p]
            g_m_r += inv_mass[p] * gradient[axis, p] * force[axis, p]
            g_m_g += inv_mass[p] * gradient[axis, p] * gradient[axis, p]
    c = dt * dt * stiffness
    correction = c * g_m_r / (1.0 + c * g_m_g)
    for axis in range(3):
        for p in range(first, stop):
            force[axis, p] -= correction * gradient[axis, p]


@njit(cache=True, inline="always")
def along_part(x, target, p):
    """``d . g`` of particle ``p`` (:mod:`~muscle_mss.core.connective_tissue`): the part of its
    displacement from its target along its fibre, times ``sqrt(1 - along)``; 0 for (3, n)
    targets."""
    dot = 0.0
    if target.shape[0] == 6:
        for axis in range(3):
            dot += (x[axis, p] - target[axis, p]) * target[3 + axis, p]
    return dot


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _tissue_forces(m, state):
    """Add the connective tissue's pull ``-k_i (x_i - t_i)`` (weaker along the fibres for
    (6, n) targets, :mod:`~muscle_mss.core.connective_tissue`) on the particles of muscle ``m``
    to ``state.force`` (none when ``state.tissue`` is empty)."""
    if state.tissue.shape[0] == 0:
        return
    x, force, tissue, target = state.x, state.force, state.tissue, state.target
    if target.shape[0] == 6:
        for p in range(state.offsets[m], state.offsets[m + 1]):
            dot = along_part(x, target, p)
            for axis in range(3):
                force[axis, p] -= tissue[p] * (x[axis, p] - target[axis, p]
                                               - dot * target[3 + axis, p])
        return
    for axis in range(3):
        for p in range(state.offsets[m], state.offsets[m + 1]):
            force[axis, p] -= tissue[p] * (x[axis, p] - target[axis, p])


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def _integrate(x, v, x_prev, force, inv_mass, first, stop, dt, keep):
    """One coordinate of the semi-implicit Euler step with implicit drag for particles
    ``[first, stop)``; ``keep = 1 / (1 + dt drag)``."""
    for p in range(np.uint64(first), np.uint64(stop)):
        x_prev[p] = x[p]
        v[p] = (v[p] + dt * inv_mass[p] * force[p]) * keep
        x[p] += dt * v[p]


@njit(cache=True, error_model="numpy", fastmath=FASTMATH)
def muscle_step(m, state, springs):
    """One semi-implicit Euler step of muscle ``m`` of ``state`` (:class:`MSSState`) with the
    springs ``springs`` (:class:`SpringLayout`), in place. Muscles are independent: callers run
    them as the tasks of one ``prange``."""
    _muscle_forces(m, state, springs)
    _tissue_forces(m, state)
    # the spring kernels are done with scratch's entries of muscle m: the volume term reuses them
    _implicit_volume_forces(m, state)
    keep = 1.0 / (1.0 + state.dt * state.drag)
    first, stop = state.offsets[m], state.offsets[m + 1]
    for axis in range(3):
        _integrate(state.x[axis], state.v[axis], state.x_prev[axis], state.force[axis],
                   state.inv_mass, first, stop, state.dt, keep)


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FASTMATH)
def mss_step(state, springs):
    """One semi-implicit Euler step of every muscle of ``state`` (:class:`MSSState`) with the
    springs ``springs`` (:class:`SpringLayout`), in place."""
    for m in prange(state.offsets.shape[0] - 1):
        muscle_step(np.int64(m), state, springs)


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FASTMATH)
def _forces_all(state, springs):
    for m in prange(state.offsets.shape[0] - 1):
        _muscle_forces(np.int64(m), state, springs)


def _soa(points, n, what):
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) != n:
        raise MuscleMSSError(f"{what} has {len(points)} rows; expected {n}")
    return np.ascontiguousarray(points.T)


def spring_forces(positions, velocities, layout: SpringLayout, muscle_offsets) -> np.ndarray:
    """(n, 3) float64: the spring force on every particle (g mm/s^2).

    positions (n, 3) mm, velocities (n, 3) mm/s; ``layout`` from :func:`spring_layout`.
    """
    offsets = np.asarray(muscle_offsets, dtype=np.int64)
    n = int(offsets[-1])
    x = _soa(positions, n, "positions")
    v = _soa(velocities, n, "velocities")
    work = np.zeros((3, 3, n))
    state = mss_state(x, v, work, np.zeros(n), 0.0, 0.0, 0.0, no_cages(len(offsets) - 1),
                      offsets)
    _forces_all(state, layout)
    return state.force.T.copy()


def mss_steps(positions, velocities, masses, fixed, layout: SpringLayout, muscle_offsets,
              dt: float, steps: int, drag: float = 0.0, bulk_modulus: float = 0.0,
              cages: VolumeCages | None = None):
    """Advance the mass-spring system ``steps`` semi-implicit Euler steps of ``dt`` s without
    collisions; returns new ``(positions, velocities)`` (n, 3). masses (n,) g, fixed (n,) bool.

    ``drag`` (1/s) is a viscous drag on every particle's velocity, force ``-drag m v``, taken
    implicitly (``v <- (v + dt f / m) / (1 + dt drag)``) so that it is stable at any strength.
    ``bulk_modulus`` (g/(mm s^2), a pressure) with ``cages`` adds the pressure of each muscle's
    closed cage, ``p = -bulk_modulus (V / V_rest - 1)``, as the force ``p dV/dx`` on its
    vertices (the gradient of the energy ``bulk_modulus V_rest (V / V_rest - 1)^2 / 2``),
    its stiffness along ``dV/dx`` taken implicitly (:func:`_implicit_volume_forces`).
    """
    offsets = np.asarray(muscle_offsets, dtype=np.int64)
    n = int(offsets[-1])
    x = _soa(positions, n, "positions")
    v = _soa(velocities, n, "velocities")
    inv_mass = np.where(np.asarray(fixed, dtype=bool), 0.0, 1.0 / np.asarray(masses, float))
    v[:, inv_mass == 0.0] = 0.0
    work = np.zeros((3, 3, n))
    cages = cages if cages is not None else no_cages(len(offsets) - 1)
    state = mss_state(x, v, work, inv_mass, dt, drag, bulk_modulus, cages, offsets)
    for _ in range(int(steps)):
        mss_step(state, layout)
    return x.T.copy(), v.T.copy()
