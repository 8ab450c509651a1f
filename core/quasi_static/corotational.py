"""Co-rotational springs: the quasi-static method's spring energy without negative stiffness.

A Hooke spring of rest length r stretched to length l is as stiff as k along itself and
k (1 - r / l) across: soft at rest length and negative when compressed. The slender muscles of
a flexed pose are compressed (59 % of the sartorius's springs at the thigh's most flexed pose),
so their energy has directions the spring Laplacian, the solver's initial inverse Hessian,
overestimates ten thousand times, and L-BFGS needs hundreds of iterations to find them
(docs/solver-notes.md, "Why hundreds of iterations remain").

Here spring ``s`` joining particles ``a`` and ``b`` (rest vector ``D``: the rest pose's
``X_b - X_a`` scaled to the spring's rest length) costs::

    E_s = k (|d - R_a D|^2 + |d - R_b D|^2) / 4,     d = x_b - x_a

with ``R_p`` the rotation that best fits particle ``p``'s springs, the polar rotation of
``sum k d D^T`` over them (as-rigid-as-possible, Sorkine and Alexa 2007; Liu et al. 2013). A
spring keeps its rest vector in its particles' rotated frames: for given rotations it is as
stiff as k in every direction, and the Laplacian is the exact Hessian of the spring term.
The energy is zero in the rest pose and in any rigid motion of it. A spring stretched along
itself costs what a Hooke spring does (``k (e r)^2 / 2`` for a stretch ``e r``); unlike a Hooke
spring, one turned against its particles' best-fit rotations costs too, so the lattice resists
shear (a uniform 1 % stretch of a lattice-26 block costs about 1.8 times the Hooke energy). The
gradient at the best rotations needs no derivative of them (they minimise the energy).

Each particle's rotation is computed afresh at every evaluation, in closed form up to a Newton
solve of a quartic (:func:`fit_rotation`): no iteration history, so the answer does not depend
on the states visited before.
"""
from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit, prange

# Newton steps at most for the largest eigenvalue of a particle's 4x4 fit matrix (from the
# upper bound sqrt(3) |A|_F, quadratic once near). Measured on the demo thigh's most flexed pose
# and the elbow's 130 degrees (N = 20, posed and solved): 11-12 steps on average; about 1 % of
# the particles reach the cap (fits of nearly rank one, the two largest eigenvalues within 2e-5
# of each other, where Newton converges linearly), their eigenvalue still within 1e-11.
NEWTON_STEPS = 60

CorotationalState = namedtuple("CorotationalState", ("rest_vectors", "frame"))
CorotationalState.__doc__ = """What the co-rotational spring term keeps: ``rest_vectors`` (S, 3)
mm each spring's ``D`` (in the order of the quasi-static spring table); ``frame`` (n, 9) work
space, after an evaluation each particle's best-fit rotation matrix row by row."""


def corotational_state(rest_vectors, n: int) -> CorotationalState:
    """The co-rotational term's state for springs of rest vectors ``rest_vectors`` (S, 3) mm
    (:meth:`~muscle_mss.core.model.MSSModel.spring_rest_vectors`, in the order of the springs
    it is used with) between ``n`` particles."""
    return CorotationalState(np.ascontiguousarray(rest_vectors, dtype=np.float64),
                             np.zeros((n, 9)))


@njit(cache=True)
def _largest_root(c2, c1, c0, upper):
    """The largest root of ``l^4 + c2 l^2 + c1 l + c0`` (all four roots real), by Newton's
    method from ``upper``, a bound above it (from above the iterates fall monotonically)."""
    root = upper
    for _ in range(NEWTON_STEPS):
        value = ((root * root + c2) * root + c1) * root + c0
        slope = (4.0 * root * root + 2.0 * c2) * root + c1
        if not slope > 0.0:
            break
        change = value / slope
        root -= change
        if not abs(change) > 1e-14 * abs(root):
            break
    return root


@njit(cache=True)
def _adjugate_column(m00, m01, m02, m03, m11, m12, m13, m22, m23, m33):
    """The column of largest norm of the adjugate of the symmetric 4x4 matrix ``m`` (its upper
    triangle given): for ``m = N - l I`` with ``l`` a simple eigenvalue of ``N``, a multiple of
    that eigenvalue's eigenvector. Returns the column and its squared norm."""
    m10, m20, m30, m21, m31, m32 = m01, m02, m03, m12, m13, m23
    s0 = m00 * m11 - m10 * m01
    s1 = m00 * m12 - m10 * m02
    s2 = m00 * m13 - m10 * m03
    s3 = m01 * m12 - m11 * m02
    s4 = m01 * m13 - m11 * m03
    s5 = m02 * m13 - m12 * m03
    c5 = m22 * m33 - m32 * m23
    c4 = m21 * m33 - m31 * m23
    c3 = m21 * m32 - m31 * m22
    c2 = m20 * m33 - m30 * m23
    c1 = m20 * m32 - m30 * m22
    c0 = m20 * m31 - m30 * m21
    columns = ((m11 * c5 - m12 * c4 + m13 * c3, -m10 * c5 + m12 * c2 - m13 * c1,
                m10 * c4 - m11 * c2 + m13 * c0, -m10 * c3 + m11 * c1 - m12 * c0),
               (-m01 * c5 + m02 * c4 - m03 * c3, m00 * c5 - m02 * c2 + m03 * c1,
                -m00 * c4 + m01 * c2 - m03 * c0, m00 * c3 - m01 * c1 + m02 * c0),
               (m31 * s5 - m32 * s4 + m33 * s3, -m30 * s5 + m32 * s2 - m33 * s1,
                m30 * s4 - m31 * s2 + m33 * s0, -m30 * s3 + m31 * s1 - m32 * s0),
               (-m21 * s5 + m22 * s4 - m23 * s3, m20 * s5 - m22 * s2 + m23 * s1,
                -m20 * s4 + m21 * s2 - m23 * s0, m20 * s3 - m21 * s1 + m22 * s0))
    best, size = columns[0], -1.0
    for column in columns:
        norm = column[0] ** 2 + column[1] ** 2 + column[2] ** 2 + column[3] ** 2
        if norm > size:
            best, size = column, norm
    return best, size


@njit(cache=True)
def fit_rotation(frame, p):
    """Replace ``frame[p]`` (a 3x3 matrix ``A`` row by row) with the rotation ``R`` maximising
    ``trace(R^T A)`` (the polar rotation of ``A``, a reflection never): the unit quaternion of
    the largest eigenvalue of Horn's symmetric 4x4 matrix of ``A^T`` (Horn 1987), the eigenvalue
    by Newton's method on the characteristic polynomial and the vector from the adjugate
    (Theobald 2005, "Rapid calculation of RMSDs using a quaternion-based characteristic
    polynomial"). Where that eigenvalue is not simple (``A`` of rank one or less) every rotation
    of a family fits as well; the identity's nearest is not sought, the identity is kept when the
    adjugate vanishes."""
    # Horn's S = A^T: s_xy = a_yx
    sxx, syx, szx = frame[p, 0], frame[p, 1], frame[p, 2]
    sxy, syy, szy = frame[p, 3], frame[p, 4], frame[p, 5]
    sxz, syz, szz = frame[p, 6], frame[p, 7], frame[p, 8]
    n00 = sxx + syy + szz
    n01, n02, n03 = syz - szy, szx - sxz, sxy - syx
    n11, n12, n13 = sxx - syy - szz, sxy + syx, szx + sxz
    n22, n23 = -sxx + syy - szz, syz + szy
    n33 = -sxx - syy + szz
    squares = (sxx * sxx + sxy * sxy + sxz * sxz + syx * syx + syy * syy + syz * syz
               + szx * szx + szy * szy + szz * szz)
    det_s = (sxx * (syy * szz - syz * szy) - sxy * (syx * szz - syz * szx)
             + sxz * (syx * szy - syy * szx))
    det_n = _determinant(n00, n01, n02, n03, n11, n12, n13, n22, n23, n33)
    root = _largest_root(-2.0 * squares, -8.0 * det_s, det_n, np.sqrt(3.0 * squares))
    (w, x, y, z), size = _adjugate_column(n00 - root, n01, n02, n03, n11 - root, n12, n13,
                                          n22 - root, n23, n33 - root)
    if not size > 1e-28 * squares ** 3 or not size > 0.0:
        w, x, y, z, size = 1.0, 0.0, 0.0, 0.0, 1.0
    norm = 1.0 / np.sqrt(size)
    w, x, y, z = w * norm, x * norm, y * norm, z * norm
    frame[p, 0] = 1.0 - 2.0 * (y * y + z * z)
    frame[p, 1] = 2.0 * (x * y - w * z)
    frame[p, 2] = 2.0 * (x * z + w * y)
    frame[p, 3] = 2.0 * (x * y + w * z)
    frame[p, 4] = 1.0 - 2.0 * (x * x + z * z)
    frame[p, 5] = 2.0 * (y * z - w * x)
    frame[p, 6] = 2.0 * (x * z - w * y)
    frame[p, 7] = 2.0 * (y * z + w * x)
    frame[p, 8] = 1.0 - 2.0 * (x * x + y * y)


@njit(cache=True)
def _determinant(m00, m01, m02, m03, m11, m12, m13, m22, m23, m33):
    """The determinant of the symmetric 4x4 matrix ``m`` (its upper triangle given)."""
    s0 = m00 * m11 - m01 * m01
    s1 = m00 * m12 - m01 * m02
    s2 = m00 * m13 - m01 * m03
    s3 = m01 * m12 - m11 * m02
    s4 = m01 * m13 - m11 * m03
    s5 = m02 * m13 - m12 * m03
    c5 = m22 * m33 - m23 * m23
    c4 = m12 * m33 - m13 * m23
    c3 = m12 * m23 - m13 * m22
    c2 = m02 * m33 - m03 * m23
    c1 = m02 * m23 - m03 * m22
    c0 = m02 * m13 - m03 * m12
    return s0 * c5 - s1 * c4 + s2 * c3 + s3 * c2 - s4 * c1 + s5 * c0


@njit(cache=True, inline="always")
def add_spring_frames(x, ends, stiffness, vectors, first, last, frame):
    """Add the springs ``first:last`` of ``ends`` (S, 2) to their particles' fit matrices
    ``frame`` (n, 9): ``k d D^T`` row by row on both ends, ``d`` the spring at ``x`` (3, n) mm,
    ``D`` its rest vector (``vectors`` (S, 3)), ``k`` its ``stiffness`` (S,) g/s^2."""
    for s in range(first, last):
        a, b = ends[s, 0], ends[s, 1]
        k = stiffness[s]
        for i in range(3):
            kd = k * (x[i, b] - x[i, a])
            for j in range(3):
                frame[a, 3 * i + j] += kd * vectors[s, j]
                frame[b, 3 * i + j] += kd * vectors[s, j]


@njit(cache=True, parallel=True)
def add_corotational_energy(x, gradient, energy, ends, stiffness, spring_ptr, offsets, state):
    """Add the co-rotational spring energy of every muscle to ``energy`` (M,) and its gradient
    to ``gradient`` (3, n), at ``x`` (3, n) mm, for the springs ``ends`` (S, 2), ``stiffness``
    (S,) g/s^2 grouped by muscle (``spring_ptr`` (M + 1,)), the particles by ``offsets``
    (M + 1,); ``state`` a :class:`CorotationalState` (its rotations written). One parallel
    region over the muscles (a spring never joins two)."""
    vectors, frame = state.rest_vectors, state.frame
    for m in prange(offsets.shape[0] - 1):
        for p in range(offsets[m], offsets[m + 1]):
            for i in range(9):
                frame[p, i] = 0.0
        add_spring_frames(x, ends, stiffness, vectors, spring_ptr[m], spring_ptr[m + 1], frame)
        for p in range(offsets[m], offsets[m + 1]):
            fit_rotation(frame, p)
        e = 0.0
        for s in range(spring_ptr[m], spring_ptr[m + 1]):
            a, b = ends[s, 0], ends[s, 1]
            k = stiffness[s]
            for i in range(3):
                d = x[i, b] - x[i, a]
                ra = d - (frame[a, 3 * i] * vectors[s, 0] + frame[a, 3 * i + 1] * vectors[s, 1]
                          + frame[a, 3 * i + 2] * vectors[s, 2])
                rb = d - (frame[b, 3 * i] * vectors[s, 0] + frame[b, 3 * i + 1] * vectors[s, 1]
                          + frame[b, 3 * i + 2] * vectors[s, 2])
                e += 0.25 * k * (ra * ra + rb * rb)
                f = 0.5 * k * (ra + rb)
                gradient[i, b] += f
                gradient[i, a] -= f
        energy[m] += e


@njit(cache=True, parallel=True)
def fit_rotations(frame):
    """:func:`fit_rotation` of every row of ``frame`` (n, 9)."""
    for p in prange(frame.shape[0]):
        fit_rotation(frame, np.int64(p))


@njit(cache=True)
def _spring_tension(x, ends, stiffness, vectors, frame, tension):
    """``tension`` (S,) g mm/s^2 of :func:`spring_tension` at ``x`` (3, n); ``frame`` (n, 9)
    zeros, left holding each particle's rotation."""
    add_spring_frames(x, ends, stiffness, vectors, np.int64(0), ends.shape[0], frame)
    fit_rotations(frame)
    for s in range(ends.shape[0]):
        a, b, k = ends[s, 0], ends[s, 1], stiffness[s]
        total = 0.0
        for i in range(3):
            turned = 0.0
            for j in range(3):
                turned += (frame[a, 3 * i + j] + frame[b, 3 * i + j]) * vectors[s, j]
            pull = k * ((x[i, b] - x[i, a]) - 0.5 * turned)
            total += pull * pull
        tension[s] = np.sqrt(total)


def spring_tension(model, positions) -> np.ndarray:
    """(S,) g mm/s^2: the size of each co-rotational spring's pull ``k (d - (R_a + R_b) D /
    2)`` at ``positions`` (n, 3) mm (input order), for the model's springs and rest pose."""
    x = np.ascontiguousarray(np.asarray(positions, dtype=np.float64).reshape(-1, 3).T)
    ends = np.ascontiguousarray(model.springs, dtype=np.int64).reshape(-1, 2)
    k = np.ascontiguousarray(model.stiffness, dtype=np.float64)
    state = corotational_state(model.spring_rest_vectors(), x.shape[1])
    tension = np.empty(len(ends))
    _spring_tension(x, ends, k, state.rest_vectors, state.frame, tension)
    return tension
