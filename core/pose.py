"""The rigid pose (paper §3.1, DESIGN §6 "Pose").

"To process a given time point of the motion, the transformation matrices are first applied to
the bones. The muscles (the triangular surfaces as well as the particles) are transformed as well,
using an interpolated transformation matrix of the nearest bones."

This module holds the three pieces of that sentence:

* the bone transforms at any time: :func:`pose_at` interpolates a :class:`~.scene.Motion`
  between its rows (rotation by quaternion slerp, translation linearly) and clamps outside it;
* the weights of the nearest bones: :func:`bone_distances` (exact point-to-triangle distance to
  each bone surface in the rest pose) and :func:`weights_from_distances` (the fall-off formula);
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
from .mesh_checks import checked_surface
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

def _check_points(points) -> np.ndarray:
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
    p = _check_points(points)
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
    p = _check_points(points)
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


# ---- weights of the nearest bones --------------------------------------------------------------

@numba.njit(cache=True)
def _segment_distance_sq(px, py, pz, ax, ay, az, bx, by, bz):
    ex = bx - ax
    ey = by - ay
    ez = bz - az
    length_sq = ex * ex + ey * ey + ez * ez
    s = 0.0
    if length_sq > 0.0:
        s = ((px - ax) * ex + (py - ay) * ey + (pz - az) * ez) / length_sq
        s = min(max(s, 0.0), 1.0)
    dx = px - (ax + s * ex)
    dy = py - (ay + s * ey)
    dz = pz - (az + s * ez)
    return dx * dx + dy * dy + dz * dz


@numba.njit(cache=True)
def _point_triangle_distance(px, py, pz, tri):
    """Euclidean distance (mm) from a point to the triangle ``tri`` (3 corners, 3).

    The nearest point is either the foot of the perpendicular on the plane (when it falls
    inside) or on one of the three edges; degenerate triangles reduce to their edges.
    """
    ax, ay, az = tri[0, 0], tri[0, 1], tri[0, 2]
    ux, uy, uz = tri[1, 0] - ax, tri[1, 1] - ay, tri[1, 2] - az
    vx, vy, vz = tri[2, 0] - ax, tri[2, 1] - ay, tri[2, 2] - az
    wx, wy, wz = px - ax, py - ay, pz - az
    uu = ux * ux + uy * uy + uz * uz
    uv = ux * vx + uy * vy + uz * vz
    vv = vx * vx + vy * vy + vz * vz
    wu = wx * ux + wy * uy + wz * uz
    wv = wx * vx + wy * vy + wz * vz
    denom = uu * vv - uv * uv
    if denom > 1e-12 * uu * vv:
        beta = (vv * wu - uv * wv) / denom
        gamma = (uu * wv - uv * wu) / denom
        if beta >= 0.0 and gamma >= 0.0 and beta + gamma <= 1.0:
            nx = uy * vz - uz * vy
            ny = uz * vx - ux * vz
            nz = ux * vy - uy * vx
            return abs(wx * nx + wy * ny + wz * nz) / math.sqrt(nx * nx + ny * ny + nz * nz)
    best = _segment_distance_sq(px, py, pz, tri[0, 0], tri[0, 1], tri[0, 2],
                                tri[1, 0], tri[1, 1], tri[1, 2])
    best = min(best, _segment_distance_sq(px, py, pz, tri[1, 0], tri[1, 1], tri[1, 2],
                                          tri[2, 0], tri[2, 1], tri[2, 2]))
    best = min(best, _segment_distance_sq(px, py, pz, tri[2, 0], tri[2, 1], tri[2, 2],
                                          tri[0, 0], tri[0, 1], tri[0, 2]))
    return math.sqrt(best)


@numba.njit(cache=True)
def _distance_to_ball(px, py, pz, centres, radii, k):
    """|p - centre_k| - radius_k: a lower bound of the distance to anything inside the ball."""
    cx = px - centres[k, 0]
    cy = py - centres[k, 1]
    cz = pz - centres[k, 2]
    return math.sqrt(cx * cx + cy * cy + cz * cz) - radii[k]


@numba.njit(cache=True)
def _distance_to_box(px, py, pz, lower, upper, g):
    """Distance to the axis-aligned box ``lower[g]``..``upper[g]`` (0 inside): a lower bound
    of the distance to anything inside it."""
    dx = max(lower[g, 0] - px, 0.0, px - upper[g, 0])
    dy = max(lower[g, 1] - py, 0.0, py - upper[g, 1])
    dz = max(lower[g, 2] - pz, 0.0, pz - upper[g, 2])
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@numba.njit(cache=True)
def _nearest_box(px, py, pz, lower, upper, first, stop):
    """Index in ``first:stop`` of the box nearest to p."""
    nearest = first
    nearest_bound = np.inf
    for g in range(first, stop):
        bound = _distance_to_box(px, py, pz, lower, upper, g)
        if bound < nearest_bound:
            nearest_bound = bound
            nearest = g
    return nearest


@numba.njit(cache=True)
def _cell_distance(px, py, pz, corners, tri_centres, tri_radii, cell_starts, c, best):
    """min(best, distance to the triangles of cell c), measuring only triangles whose ball
    is nearer than the best so far."""
    for k in range(cell_starts[c], cell_starts[c + 1]):
        if _distance_to_ball(px, py, pz, tri_centres, tri_radii, k) < best:
            best = min(best, _point_triangle_distance(px, py, pz, corners[k]))
    return best


@numba.njit(cache=True, parallel=True)
def _surface_distances(points, corners, tri_centres, tri_radii, cell_starts, cell_lower,
                       cell_upper, block_starts, block_lower, block_upper, bone_blocks, out):
    """Distance of each point to each bone's triangles.

    Three levels, each a contiguous range of the next: bones (``bone_blocks``, B + 1) hold
    blocks, blocks (``block_starts``) hold cells, cells (``cell_starts``) hold triangles. Each
    block and cell lies in a box, each triangle in a ball (centre, radius); the distance to a
    box or ball bounds the distance to its content from below. The cell nearest by that bound
    in the nearest block gives a first exact distance; after it only blocks, cells and
    triangles whose bound beats the best so far are looked into.
    """
    for i in prange(points.shape[0]):
        px = points[i, 0]
        py = points[i, 1]
        pz = points[i, 2]
        for b in range(bone_blocks.shape[0] - 1):
            seed_block = _nearest_box(px, py, pz, block_lower, block_upper, bone_blocks[b],
                                      bone_blocks[b + 1])
            seed = _nearest_box(px, py, pz, cell_lower, cell_upper, block_starts[seed_block],
                                block_starts[seed_block + 1])
            best = _cell_distance(px, py, pz, corners, tri_centres, tri_radii, cell_starts,
                                  seed, np.inf)
            for blk in range(bone_blocks[b], bone_blocks[b + 1]):
                if _distance_to_box(px, py, pz, block_lower, block_upper, blk) >= best:
                    continue
                for c in range(block_starts[blk], block_starts[blk + 1]):
                    if c != seed and _distance_to_box(px, py, pz, cell_lower, cell_upper,
                                                      c) < best:
                        best = _cell_distance(px, py, pz, corners, tri_centres, tri_radii,
                                              cell_starts, c, best)
            out[i, b] = best


TRIANGLES_PER_CELL = 32
"""Aimed-for number of triangles in one cell of the distance search."""
CELLS_PER_BLOCK_SIDE = 4
"""A block of the distance search is a cube of this many cells a side (~16 cells of surface)."""


def _starts(keys):
    """Where runs of equal sorted ``keys`` start, plus the end: (runs + 1,) int64."""
    return np.concatenate([[0], np.flatnonzero(np.diff(keys)) + 1, [len(keys)]]).astype(np.int64)


def _cells_and_blocks(corners):
    """The triangles (m, 3, 3) of one bone sorted by block, then by cell, of a cubic grid with
    about :data:`TRIANGLES_PER_CELL` triangles a cell.

    Returns ``(sorted corners, cell_starts (C + 1,) into triangles, block_starts (K + 1,) into
    cells)``.
    """
    centroids = corners.mean(axis=1)
    lower = centroids.min(axis=0)
    # A surface crosses a cube of side s in about 2 (s / edge)^2 triangles; at most 1024
    # cells a side keep the keys small whatever the triangle sizes.
    edge = float(np.median(np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1)))
    side = max(edge * math.sqrt(TRIANGLES_PER_CELL / 2.0),
               float((centroids.max(axis=0) - lower).max()) / 1024.0, 1e-9)
    cells = ((centroids - lower) / side).astype(np.int64)
    blocks = cells // CELLS_PER_BLOCK_SIDE

    def key(ijk):
        shape = ijk.max(axis=0) + 1
        return (ijk[:, 0] * shape[1] + ijk[:, 1]) * shape[2] + ijk[:, 2]

    cell_key, block_key = key(cells), key(blocks)
    order = np.lexsort((cell_key, block_key))
    cell_starts = _starts(cell_key[order])
    block_starts = _starts(block_key[order][cell_starts[:-1]])
    return corners[order], cell_starts, block_starts


def bone_distances(points, bones, labels=None) -> np.ndarray:
    """Distance from each point to each bone surface (nearest point on any of its triangles).

    Exact (no sampling): every triangle that could be nearer than the best found is measured.

    Parameters
    ----------
    points : (n, 3) float64, mm (rest pose)
    bones : sequence of B ``(vertices (v, 3) float64 mm, triangles (m, 3) int)``
    labels : B names of the bones for messages (e.g. ``"bones.vtm block 'femur'"``), or None

    Returns
    -------
    (n, B) float64, mm
    """
    p = _check_points(points)
    if len(bones) == 0:
        raise MuscleMSSError("there are no bones; the pose needs at least one bone surface")
    corners, cell_starts, block_starts, bone_blocks = [], [[0]], [[0]], [0]
    for b, (vertices, triangles) in enumerate(bones):
        label = labels[b] if labels is not None else f"bone {b}"
        v, t = checked_surface(vertices, triangles, label)
        sorted_corners, cells, blocks = _cells_and_blocks(v[t])
        # Shift this bone's ranges behind the previous bones' triangles and cells.
        cell_starts.append(cells[1:] + cell_starts[-1][-1])
        block_starts.append(blocks[1:] + block_starts[-1][-1])
        bone_blocks.append(bone_blocks[-1] + len(blocks) - 1)
        corners.append(sorted_corners)
    corners = np.ascontiguousarray(np.concatenate(corners))
    cell_starts = np.concatenate(cell_starts).astype(np.int64)
    block_starts = np.concatenate(block_starts).astype(np.int64)
    tri_centres = corners.mean(axis=1)
    tri_radii = np.linalg.norm(corners - tri_centres[:, None, :], axis=2).max(axis=1)
    flat = corners.reshape(-1, 3)
    cell_lower = np.minimum.reduceat(flat, 3 * cell_starts[:-1], axis=0)
    cell_upper = np.maximum.reduceat(flat, 3 * cell_starts[:-1], axis=0)
    block_lower = np.minimum.reduceat(cell_lower, block_starts[:-1], axis=0)
    block_upper = np.maximum.reduceat(cell_upper, block_starts[:-1], axis=0)
    out = np.empty((len(p), len(bones)))
    _surface_distances(p, corners, tri_centres, tri_radii, cell_starts, cell_lower, cell_upper,
                       block_starts, block_lower, block_upper,
                       np.asarray(bone_blocks, dtype=np.int64), out)
    return out


def weights_from_distances(distances, bones_per_point: int, fall_off: float) -> np.ndarray:
    """Blend weights of each point's ``K = bones_per_point`` nearest bones.

    With ``d_1 <= d_2 <= …`` a point's sorted bone distances and ``F = fall_off``::

        w_k = exp(-d_k / F) - exp(-d_(K+1) / F)   for the K nearest bones (k <= K)
        w_k = 0                                     for the others

    then normalised to sum 1 (the ``d_(K+1)`` term is 0 when there are at most K bones).
    ``F`` is the distance over which a farther bone's influence falls by a factor e. Subtracting
    the (K+1)-th bone's term makes a weight reach 0 exactly where its bone leaves the K
    nearest, so weights (and the rigid pose) stay continuous across the muscle. Where the K+1
    nearest bones are equally far, the K first in bone order share equally.

    Parameters
    ----------
    distances : (n, B) float64, mm, from :func:`bone_distances`
    bones_per_point : int >= 1
    fall_off : float > 0, mm

    Returns
    -------
    (n, B) float64, rows summing to 1, columns in the order of ``distances``
    """
    d = np.asarray(distances, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] == 0:
        raise MuscleMSSError(f"distances must be an (n, B) array with B >= 1, not {d.shape}")
    if int(bones_per_point) < 1:
        raise MuscleMSSError(f"bones per point is {bones_per_point}; it must be at least 1")
    if not (math.isfinite(fall_off) and fall_off > 0.0):
        raise MuscleMSSError(f"the fall-off is {fall_off} mm; it must be a positive distance")
    n, bone_count = d.shape
    k = min(int(bones_per_point), bone_count)
    order = np.argsort(d, axis=1, kind="stable")
    nearest_first = np.take_along_axis(d, order, axis=1)
    # Measured from the nearest bone so that exp() cannot underflow for all bones at once.
    closeness = np.exp(-(nearest_first - nearest_first[:, :1]) / fall_off)
    cut = closeness[:, k] if k < bone_count else np.zeros(n)
    sorted_weights = np.zeros_like(d)
    sorted_weights[:, :k] = np.maximum(closeness[:, :k] - cut[:, None], 0.0)
    total = sorted_weights.sum(axis=1)
    tied = total <= 0.0
    sorted_weights[tied, :k] = 1.0
    total[tied] = k
    sorted_weights /= total[:, None]
    weights = np.zeros_like(d)
    np.put_along_axis(weights, order, sorted_weights, axis=1)
    return weights


def bone_weights(points, bones, bones_per_point: int, fall_off: float,
                 labels=None) -> np.ndarray:
    """Blend weights (n, B) of points (n, 3) mm w.r.t. bone surfaces in the rest pose:
    :func:`weights_from_distances` of :func:`bone_distances` (same parameters)."""
    return weights_from_distances(bone_distances(points, bones, labels), bones_per_point,
                                  fall_off)
