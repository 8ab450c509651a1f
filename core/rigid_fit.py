"""Rigid fit: the rotation and translation that carry one point set onto another (Kabsch).

Bones are rigid. The caches of bone spheres and distance fields
(:mod:`muscle_mss.filters.bone_sets`) and the MVC Surface Deformer recover each posed bone's
motion from its points at every time point, so the fit is on the time slider's path: least
squares over all points (Kabsch 1976: the SVD of the centred cross-covariance, reflections
excluded), its passes over the points in Numba (a 16,600-point femur: 0.1 ms, against 1.3-1.9 ms
for the NumPy expressions it replaces), the 3 x 3 SVD in NumPy.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .errors import MuscleMSSError, checked_points

POSED_BONE_RESIDUAL = 1e-5
"""A posed bone is a rigid motion of its rest bone when the fit leaves no point farther than
this fraction of the bone's size (its bounding box's longest side, at least 1 mm)."""


@njit(cache=True)
def _centred_cross_covariance(source, target):
    """``(source centroid (3,), target centroid (3,), H (3, 3))``, ``H = sum (s - s0)(t - t0)^T``
    over the rows of ``source`` and ``target`` (n, 3)."""
    n = source.shape[0]
    a = np.zeros(3)
    b = np.zeros(3)
    for i in range(n):
        for k in range(3):
            a[k] += source[i, k]
            b[k] += target[i, k]
    a /= n
    b /= n
    h = np.zeros((3, 3))
    for i in range(n):
        for j in range(3):
            s = source[i, j] - a[j]
            for k in range(3):
                h[j, k] += s * (target[i, k] - b[k])
    return a, b, h


@njit(cache=True)
def _largest_miss_and_size(source, target, rotation, translation):
    """``(largest |R s + t - target| mm, longest side of target's bounding box mm)``."""
    worst = 0.0
    low = np.full(3, np.inf)
    high = np.full(3, -np.inf)
    for i in range(source.shape[0]):
        d2 = 0.0
        for k in range(3):
            v = (rotation[k, 0] * source[i, 0] + rotation[k, 1] * source[i, 1]
                 + rotation[k, 2] * source[i, 2] + translation[k] - target[i, k])
            d2 += v * v
            low[k] = min(low[k], target[i, k])
            high[k] = max(high[k], target[i, k])
        worst = max(worst, d2)
    return np.sqrt(worst), (high - low).max()


def rigid_fit(source, target):
    """The least-squares rigid motion taking ``source`` to ``target`` (both (n, 3) mm, finite,
    the same points in the same order, n >= 1): ``(rotation (3, 3), translation (3,), residual
    mm, size mm)`` with ``target ~ source @ rotation.T + translation``, ``residual`` the largest
    point distance left and ``size`` the longest side of ``target``'s bounding box."""
    source = np.ascontiguousarray(source, dtype=np.float64)
    target = np.ascontiguousarray(target, dtype=np.float64)
    a, b, h = _centred_cross_covariance(source, target)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rotation = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    translation = b - rotation @ a
    residual, size = _largest_miss_and_size(source, target, rotation, translation)
    return rotation, translation, float(residual), float(size)


def fitted_rigid_transform(rest, posed, where="bone") -> np.ndarray:
    """The rigid 3x4 transform ``M`` with ``posed = rest @ M[:, :3].T + M[:, 3]``, for a bone
    given at rest and posed: (n, 3) mm each, the same vertices in the same order. Raises
    :class:`MuscleMSSError` naming ``where`` when ``posed`` is not a rigid motion of ``rest``
    (a point off by more than :data:`POSED_BONE_RESIDUAL` of the bone's size)."""
    rest = checked_points(rest, f"{where} (rest)")
    posed = checked_points(posed, f"{where} (posed)")
    if rest.shape != posed.shape or len(rest) < 3:
        raise MuscleMSSError(f"{where}: the posed bone has {len(posed)} points and the rest bone "
                             f"{len(rest)}; connect the bones the pose was made from")
    rotation, translation, off, size = rigid_fit(rest, posed)
    if off > POSED_BONE_RESIDUAL * max(size, 1.0):
        raise MuscleMSSError(f"{where}: the posed bone is not a rigid motion of the rest bone "
                             f"(off by {off:.3g} mm); connect the rest bones (bones.vtm) and the "
                             "Rigid Pose Transform's PosedBones made from them")
    return np.hstack([rotation, translation[:, None]])
