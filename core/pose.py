"""The rigid pose (paper §3.1, DESIGN §6 "Pose").

"To process a given time point of the motion, the transformation matrices are first applied to
the bones. The muscles (the triangular surfaces as well as the particles) are transformed as well,
using an interpolated transformation matrix of the nearest bones."

This module and :mod:`.bones.weights` hold the three pieces of that sentence:

* the bone transforms at any time: :func:`pose_at` interpolates a :class:`~.scene.Motion`
  between its rows (rotation by quaternion slerp, translation linearly) and clamps outside it;
* the weights of the nearest bones: :mod:`.bones.weights` (exact point-to-triangle distance to
  each bone surface in the rest pose, and the fall-off formula);
* the blend of the bone transforms: :func:`blend_linear` (linear blend skinning) and
  :func:`blend_dual_quaternion` (Kavan et al. 2008, dual quaternion skinning), and
  :func:`transform_rigid` for the bones themselves.

Transforms are (3, 4) float64 matrices ``M`` mapping rest to posed coordinates in mm,
``x' = M[:, :3] @ x + M[:, 3]``. Quaternions are (4,) float64 ``(w, x, y, z)``.
Every blend is computed as ``x + displacement`` so that an identity transform leaves a point
bit-for-bit where it was.
"""
import math

import numba
import numpy as np
from numba import prange

from .errors import MuscleMSSError
from .scene import Motion

LINEAR = "linear"
DUAL_QUATERNION = "dual quaternion"
BLENDINGS = (LINEAR, DUAL_QUATERNION)
"""The blending methods, in the order of the filter's ``Blending`` property."""

WEIGHT_SUM_TOLERANCE = 1e-9
"""Largest allowed deviation of a point's weights from summing to 1."""


# ---- quaternions ---------------------------------------------------------------------------

@numba.njit(cache=True)
def _rotation_to_quaternion(r, q):
    """Write the unit quaternion of the rotation ``r`` (3, 3) into ``q`` (4,), with w >= 0.

    Shepperd's choice of the largest diagonal term keeps the square root away from zero.
    """
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    if trace > 0.0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q[0] = 0.25 * s
        q[1] = (r[2, 1] - r[1, 2]) / s
        q[2] = (r[0, 2] - r[2, 0]) / s
        q[3] = (r[1, 0] - r[0, 1]) / s
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q[0] = (r[2, 1] - r[1, 2]) / s
        q[1] = 0.25 * s
        q[2] = (r[0, 1] + r[1, 0]) / s
        q[3] = (r[0, 2] + r[2, 0]) / s
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q[0] = (r[0, 2] - r[2, 0]) / s
        q[1] = (r[0, 1] + r[1, 0]) / s
        q[2] = 0.25 * s
        q[3] = (r[1, 2] + r[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q[0] = (r[1, 0] - r[0, 1]) / s
        q[1] = (r[0, 2] + r[2, 0]) / s
        q[2] = (r[1, 2] + r[2, 1]) / s
        q[3] = 0.25 * s
    norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    sign = 1.0 if q[0] >= 0.0 else -1.0
    for k in range(4):
        q[k] = sign * q[k] / norm


@numba.njit(cache=True)
def _quaternion_to_rotation(q, r):
    """Write the rotation of the unit quaternion ``q`` (4,) into ``r`` (3, 3)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    r[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    r[0, 1] = 2.0 * (x * y - w * z)
    r[0, 2] = 2.0 * (x * z + w * y)
    r[1, 0] = 2.0 * (x * y + w * z)
    r[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    r[1, 2] = 2.0 * (y * z - w * x)
    r[2, 0] = 2.0 * (x * z - w * y)
    r[2, 1] = 2.0 * (y * z + w * x)
    r[2, 2] = 1.0 - 2.0 * (x * x + y * y)


@numba.njit(cache=True)
def _slerp(q0, q1, s, out):
    """Write the spherical linear interpolation of unit quaternions at ``s`` in [0, 1] into ``out``.

    ``q`` and ``-q`` are the same rotation: the shorter arc is taken.
    """
    dot = q0[0] * q1[0] + q0[1] * q1[1] + q0[2] * q1[2] + q0[3] * q1[3]
    sign = 1.0
    if dot < 0.0:
        sign = -1.0
        dot = -dot
    if dot > 1.0 - 1e-12:
        # Nearly equal rotations: sin(theta) ~ 0, the chord is the arc.
        a = 1.0 - s
        b = sign * s
    else:
        theta = math.acos(dot)
        sin_theta = math.sin(theta)
        a = math.sin((1.0 - s) * theta) / sin_theta
        b = sign * math.sin(s * theta) / sin_theta
    norm = 0.0
    for k in range(4):
        out[k] = a * q0[k] + b * q1[k]
        norm += out[k] * out[k]
    norm = math.sqrt(norm)
    for k in range(4):
        out[k] /= norm


@numba.njit(cache=True)
def _rotations_to_quaternions(rotations, out):
    for i in range(rotations.shape[0]):
        _rotation_to_quaternion(rotations[i], out[i])


@numba.njit(cache=True)
def _quaternions_to_rotations(quaternions, out):
    for i in range(quaternions.shape[0]):
        _quaternion_to_rotation(quaternions[i], out[i])


@numba.njit(cache=True)
def _slerp_many(q0, q1, s, out):
    for i in range(q0.shape[0]):
        _slerp(q0[i], q1[i], s, out[i])


def rotation_to_quaternion(rotations) -> np.ndarray:
    """Unit quaternions ``(w, x, y, z)`` with ``w >= 0`` of rotations.

    Parameters
    ----------
    rotations : (3, 3) or (k, 3, 3) float64, proper rotation matrices

    Returns
    -------
    (4,) or (k, 4) float64
    """
    r = np.asarray(rotations, dtype=np.float64)
    flat = np.ascontiguousarray(r.reshape(-1, 3, 3))
    out = np.empty((len(flat), 4))
    _rotations_to_quaternions(flat, out)
    return out.reshape(r.shape[:-2] + (4,))


def quaternion_to_rotation(quaternions) -> np.ndarray:
    """Rotation matrices of unit quaternions ``(w, x, y, z)``:
    (4,) → (3, 3), (k, 4) → (k, 3, 3)."""
    q = np.asarray(quaternions, dtype=np.float64)
    flat = np.ascontiguousarray(q.reshape(-1, 4))
    out = np.empty((len(flat), 3, 3))
    _quaternions_to_rotations(flat, out)
    return out.reshape(q.shape[:-1] + (3, 3))


def slerp(q0, q1, s: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions, (4,) or (k, 4), at ``s`` in [0, 1]
    (0 gives ``q0``, 1 gives ``q1`` up to sign), along the shorter arc."""
    a = np.asarray(q0, dtype=np.float64)
    b = np.asarray(q1, dtype=np.float64)
    if a.shape != b.shape or a.shape[-1] != 4:
        raise MuscleMSSError(f"slerp: quaternion shapes {a.shape} and {b.shape} differ or are "
                             "not (..., 4)")
    out = np.empty((int(np.prod(a.shape[:-1], dtype=np.int64)), 4))
    _slerp_many(np.ascontiguousarray(a.reshape(-1, 4)), np.ascontiguousarray(b.reshape(-1, 4)),
                float(s), out)
    return out.reshape(a.shape)


# ---- the bone transforms at a time -----------------------------------------------------------

@numba.njit(cache=True)
def _interpolate_transforms(m0, m1, s, out):
    """Bone transforms (B, 3, 4) a fraction ``s`` of the way from ``m0`` to ``m1``."""
    q0 = np.empty(4)
    q1 = np.empty(4)
    q = np.empty(4)
    r = np.empty((3, 3))
    for b in range(m0.shape[0]):
        _rotation_to_quaternion(m0[b, :, :3], q0)
        _rotation_to_quaternion(m1[b, :, :3], q1)
        _slerp(q0, q1, s, q)
        _quaternion_to_rotation(q, r)
        for i in range(3):
            for j in range(3):
                out[b, i, j] = r[i, j]
            out[b, i, 3] = (1.0 - s) * m0[b, i, 3] + s * m1[b, i, 3]


def clamp_time(motion: Motion, time: float) -> float:
    """``time`` (s) clamped to the motion's range ``[times[0], times[-1]]``."""
    if not math.isfinite(time):
        raise MuscleMSSError(f"the requested time {time} is not a finite number")
    return min(max(float(time), float(motion.times[0])), float(motion.times[-1]))


def pose_at(motion: Motion, time: float):
    """The bone transforms at ``time`` and the time they belong to.

    At a row's time the transforms are that row's matrices exactly. Between two rows the
    rotation is the quaternion slerp and the translation the linear interpolation of the two
    rows. Outside the motion's range the time is clamped to it (the caller warns).

    Parameters
    ----------
    motion : Motion, ``times`` (T,) s ascending, ``matrices`` (T, B, 3, 4)
    time : float, s

    Returns
    -------
    matrices : (B, 3, 4) float64, rest → posed, in ``motion.bones`` order
    used_time : float, s, ``time`` clamped to the range
    """
    used = clamp_time(motion, time)
    times = motion.times
    i = int(np.searchsorted(times, used, side="right")) - 1
    if times[i] == used:
        return np.array(motion.matrices[i], dtype=np.float64), used
    s = (used - times[i]) / (times[i + 1] - times[i])
    out = np.empty(motion.matrices.shape[1:])
    _interpolate_transforms(np.ascontiguousarray(motion.matrices[i], dtype=np.float64),
                            np.ascontiguousarray(motion.matrices[i + 1], dtype=np.float64),
                            s, out)
    return out, used


# ---- blending ------------------------------------------------------------------------------

def checked_positions(points) -> np.ndarray:
    """``points`` as a contiguous (n, 3) float64 array (mm); raise :class:`MuscleMSSError` when
    they are not (n, 3) or a coordinate is NaN or infinite."""
    p = np.ascontiguousarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise MuscleMSSError(f"points must be an (n, 3) array, not {p.shape}")
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        raise MuscleMSSError(f"point {int(np.flatnonzero(bad)[0])} has a NaN or infinite "
                             "coordinate; every coordinate must be finite")
    return p


def _check_matrices(matrices) -> np.ndarray:
    m = np.ascontiguousarray(matrices, dtype=np.float64)
    if m.ndim != 3 or m.shape[1:] != (3, 4):
        raise MuscleMSSError(f"bone transforms must be a (B, 3, 4) array, not {m.shape}")
    if not np.isfinite(m).all():
        raise MuscleMSSError("a bone transform has a NaN or infinite entry")
    return m


def _check_weights(weights, n, bone_count) -> np.ndarray:
    w = np.ascontiguousarray(weights, dtype=np.float64)
    if w.shape != (n, bone_count):
        raise MuscleMSSError(f"weights must be an (n, B) = ({n}, {bone_count}) array, "
                             f"not {w.shape}")
    if n and not (np.isfinite(w).all() and (w >= 0.0).all()):
        raise MuscleMSSError("weights must be finite and non-negative")
    if n and np.abs(w.sum(axis=1) - 1.0).max() > WEIGHT_SUM_TOLERANCE:
        row = int(np.argmax(np.abs(w.sum(axis=1) - 1.0)))
        raise MuscleMSSError(f"the weights of point {row} sum to {w[row].sum():.12g}; "
                             "each point's weights must sum to 1")
    return w


def transform_rigid(points, matrix) -> np.ndarray:
    """Points moved by one rigid transform: (n, 3) mm, (3, 4) → (n, 3) mm, as a new array."""
    p = checked_positions(points)
    m = _check_matrices(np.asarray(matrix, dtype=np.float64)[None])[0]
    # x + ((R - I) x + t): an identity leaves x exactly unchanged.
    return p + (p @ (m[:, :3] - np.eye(3)).T + m[:, 3])


@numba.njit(cache=True, parallel=True)
def _blend_linear(points, weights, matrices, out):
    for i in prange(points.shape[0]):
        x = points[i, 0]
        y = points[i, 1]
        z = points[i, 2]
        dx = 0.0
        dy = 0.0
        dz = 0.0
        for b in range(weights.shape[1]):
            w = weights[i, b]
            if w == 0.0:
                continue
            m = matrices[b]
            dx += w * ((m[0, 0] - 1.0) * x + m[0, 1] * y + m[0, 2] * z + m[0, 3])
            dy += w * (m[1, 0] * x + (m[1, 1] - 1.0) * y + m[1, 2] * z + m[1, 3])
            dz += w * (m[2, 0] * x + m[2, 1] * y + (m[2, 2] - 1.0) * z + m[2, 3])
        out[i, 0] = x + dx
        out[i, 1] = y + dy
        out[i, 2] = z + dz


def _checked_blend(points, weights, matrices):
    """The arguments of a blend, checked: (points (n, 3), weights (n, B), matrices (B, 3, 4))."""
    p = checked_positions(points)
    m = _check_matrices(matrices)
    return p, _check_weights(weights, len(p), len(m)), m


def blend_linear(points, weights, matrices) -> np.ndarray:
    """Linear blend skinning: ``x' = sum_b w_b (R_b x + t_b)``.

    Blending matrices shortens vectors between rotations (the "candy wrapper" collapse at
    large joint angles); :func:`blend_dual_quaternion` does not.

    Parameters
    ----------
    points : (n, 3) float64, rest positions, mm
    weights : (n, B) float64, non-negative, each row summing to 1
    matrices : (B, 3, 4) float64, rest → posed bone transforms

    Returns
    -------
    (n, 3) float64, posed positions, mm (a new array)
    """
    p, w, m = _checked_blend(points, weights, matrices)
    out = np.empty_like(p)
    _blend_linear(p, w, m, out)
    return out


@numba.njit(cache=True)
def _dual_quaternions(matrices, real, dual):
    """Unit dual quaternions ``real + eps dual`` of rigid transforms (B, 3, 4):
    ``dual = 1/2 (0, t) real``."""
    for b in range(matrices.shape[0]):
        _rotation_to_quaternion(matrices[b, :, :3], real[b])
        tx = matrices[b, 0, 3]
        ty = matrices[b, 1, 3]
        tz = matrices[b, 2, 3]
        w, x, y, z = real[b, 0], real[b, 1], real[b, 2], real[b, 3]
        dual[b, 0] = -0.5 * (tx * x + ty * y + tz * z)
        dual[b, 1] = 0.5 * (w * tx + ty * z - tz * y)
        dual[b, 2] = 0.5 * (w * ty + tz * x - tx * z)
        dual[b, 3] = 0.5 * (w * tz + tx * y - ty * x)


@numba.njit(cache=True, parallel=True)
def _blend_dual_quaternion(points, weights, real, dual, out):
    bone_count = weights.shape[1]
    for i in prange(points.shape[0]):
        pivot = 0
        for b in range(1, bone_count):
            if weights[i, b] > weights[i, pivot]:
                pivot = b
        r0 = 0.0
        r1 = 0.0
        r2 = 0.0
        r3 = 0.0
        d0 = 0.0
        d1 = 0.0
        d2 = 0.0
        d3 = 0.0
        for b in range(bone_count):
            w = weights[i, b]
            if w == 0.0:
                continue
            # q and -q are the same rotation: blend on the pivot's hemisphere, or two bones
            # turned by nearly 180 degrees apart would cancel instead of averaging.
            if (real[b, 0] * real[pivot, 0] + real[b, 1] * real[pivot, 1]
                    + real[b, 2] * real[pivot, 2] + real[b, 3] * real[pivot, 3]) < 0.0:
                w = -w
            r0 += w * real[b, 0]
            r1 += w * real[b, 1]
            r2 += w * real[b, 2]
            r3 += w * real[b, 3]
            d0 += w * dual[b, 0]
            d1 += w * dual[b, 1]
            d2 += w * dual[b, 2]
            d3 += w * dual[b, 3]
        norm = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2 + r3 * r3)
        r0 /= norm
        r1 /= norm
        r2 /= norm
        r3 /= norm
        d0 /= norm
        d1 /= norm
        d2 /= norm
        d3 /= norm
        # Translation = vector part of 2 dual conj(real); the component of dual along real
        # (left by blending) drops out of it.
        tx = 2.0 * (r0 * d1 - d0 * r1 + r2 * d3 - r3 * d2)
        ty = 2.0 * (r0 * d2 - d0 * r2 + r3 * d1 - r1 * d3)
        tz = 2.0 * (r0 * d3 - d0 * r3 + r1 * d2 - r2 * d1)
        x = points[i, 0]
        y = points[i, 1]
        z = points[i, 2]
        # (R - I) x written out, so that the identity adds exactly zero.
        dx = (-2.0 * (r2 * r2 + r3 * r3) * x + 2.0 * (r1 * r2 - r0 * r3) * y
              + 2.0 * (r1 * r3 + r0 * r2) * z)
        dy = (2.0 * (r1 * r2 + r0 * r3) * x - 2.0 * (r1 * r1 + r3 * r3) * y
              + 2.0 * (r2 * r3 - r0 * r1) * z)
        dz = (2.0 * (r1 * r3 - r0 * r2) * x + 2.0 * (r2 * r3 + r0 * r1) * y
              - 2.0 * (r1 * r1 + r2 * r2) * z)
        out[i, 0] = x + (dx + tx)
        out[i, 1] = y + (dy + ty)
        out[i, 2] = z + (dz + tz)


def blend_dual_quaternion(points, weights, matrices) -> np.ndarray:
    """Dual quaternion skinning (Kavan, Collins, Zara, O'Sullivan 2008).

    Each bone transform becomes a unit dual quaternion; a point's are summed with its weights
    (on one hemisphere), divided by the norm of the real part, and the resulting rigid
    transform is applied. The blend of rigid transforms is rigid, so vectors between nearby
    points keep their length where :func:`blend_linear` shortens them.

    Parameters
    ----------
    points : (n, 3) float64, rest positions, mm
    weights : (n, B) float64, non-negative, each row summing to 1
    matrices : (B, 3, 4) float64, rest → posed rigid bone transforms

    Returns
    -------
    (n, 3) float64, posed positions, mm (a new array)
    """
    p, w, m = _checked_blend(points, weights, matrices)
    real = np.empty((len(m), 4))
    dual = np.empty((len(m), 4))
    _dual_quaternions(m, real, dual)
    out = np.empty_like(p)
    _blend_dual_quaternion(p, w, real, dual, out)
    return out


def blend(points, weights, matrices, blending: str = DUAL_QUATERNION) -> np.ndarray:
    """:func:`blend_linear` or :func:`blend_dual_quaternion`, by the name in :data:`BLENDINGS`."""
    if blending == LINEAR:
        return blend_linear(points, weights, matrices)
    if blending == DUAL_QUATERNION:
        return blend_dual_quaternion(points, weights, matrices)
    raise MuscleMSSError(f"blending {blending!r} is not one of {', '.join(BLENDINGS)}")
