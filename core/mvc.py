"""Mean value coordinates of points w.r.t. a closed triangle cage (paper §3.2).

Ju, Schaefer & Warren (2005), "Mean value coordinates for closed triangular meshes": a point
``x`` gets one weight per cage vertex so that any function given at the cage vertices, linear
over each triangle, is interpolated smoothly everywhere (inside and outside the cage), and
linear functions are reproduced exactly: ``sum_i w_i p_i = x``. The muscle surface follows its
particles by storing the weights of every rest surface vertex w.r.t. the rest cage once and
taking ``weights @ current cage positions`` at every time point.

Each triangle contributes through its mean vector ``m`` (the integral of the unit direction
over the triangle projected on the unit sphere around ``x``): ``m = sum_k theta_k / 2 * n_k``
and ``m = sum_k w_k (p_k - x)``, solved for ``w_k`` by dotting with the side normals ``n_k``.
This form (rather than the paper's trigonometric pseudocode, whose half perimeter ``h`` loses
all precision next to a triangle's plane) keeps full precision down to distances of 1e-12 of
the cage size. The degenerate cases of the robust form:

* a point on a cage vertex (within ``tolerance`` times the cage's size) gets weight 1 there;
* a point on a triangle, its edges included, gets that triangle's barycentric weights;
* a triangle whose plane passes through the point, the point outside it, contributes nothing
  (its spherical triangle has no area);

so no weight is ever NaN, and the weights of every point sum to one. For a closed cage the
total weight is positive inside and negative outside, never zero off the cage.
"""
import math

import numba
import numpy as np
from numba import prange

from .errors import MuscleMSSError
from .mesh_checks import surface_problems

DEFAULT_TOLERANCE = 1e-12
"""Tolerance of the degenerate cases: distances in units of the cage's bounding-box diagonal,
barycentric coordinates and triple products of unit directions as they are."""

# Where a point lies w.r.t. a triangle: its projection on the plane inside the triangle (off
# the plane or on the triangle), or beside the triangle (projection outside it).
_OFF_PLANE = 0
_ON_TRIANGLE = 1
_BESIDE = 2


@numba.njit(cache=True)
def _unit_to(p, x):
    dx = p[0] - x[0]
    dy = p[1] - x[1]
    dz = p[2] - x[2]
    d = math.sqrt(dx * dx + dy * dy + dz * dz)
    return dx / d, dy / d, dz / d, d


@numba.njit(cache=True)
def _arc(ax, ay, az, bx, by, bz):
    # 2 asin(|a - b| / 2) keeps full precision for nearly equal and nearly opposite directions,
    # where acos(a . b) does not.
    dx = ax - bx
    dy = ay - by
    dz = az - bz
    half = 0.5 * math.sqrt(dx * dx + dy * dy + dz * dz)
    return 2.0 * math.asin(min(half, 1.0))


@numba.njit(cache=True)
def _point_weights(cage_points, cage_triangles, x, eps_distance, eps_unitless, row):
    """Fill ``row`` (m,) with the normalised weights of point ``x`` (3,)."""
    m = cage_points.shape[0]
    eps_d2 = eps_distance * eps_distance
    for j in range(m):
        row[j] = 0.0
    for j in range(m):
        dx = cage_points[j, 0] - x[0]
        dy = cage_points[j, 1] - x[1]
        dz = cage_points[j, 2] - x[2]
        if dx * dx + dy * dy + dz * dz <= eps_d2:
            row[j] = 1.0
            return
    for t in range(cage_triangles.shape[0]):
        i0 = cage_triangles[t, 0]
        i1 = cage_triangles[t, 1]
        i2 = cage_triangles[t, 2]
        place = _place_on_plane(cage_points[i0], cage_points[i1], cage_points[i2], x,
                                eps_distance, eps_unitless, row, i0, i1, i2)
        if place == _ON_TRIANGLE:
            return
        u0x, u0y, u0z, d0 = _unit_to(cage_points[i0], x)
        u1x, u1y, u1z, d1 = _unit_to(cage_points[i1], x)
        u2x, u2y, u2z, d2 = _unit_to(cage_points[i2], x)
        # c_k = u_{k+1} x u_{k+2}: normal of the spherical triangle's side opposite vertex k,
        # of length sin(theta_k).
        c0x = u1y * u2z - u1z * u2y
        c0y = u1z * u2x - u1x * u2z
        c0z = u1x * u2y - u1y * u2x
        c1x = u2y * u0z - u2z * u0y
        c1y = u2z * u0x - u2x * u0z
        c1z = u2x * u0y - u2y * u0x
        c2x = u0y * u1z - u0z * u1y
        c2y = u0z * u1x - u0x * u1z
        c2z = u0x * u1y - u0y * u1x
        sin0 = math.sqrt(c0x * c0x + c0y * c0y + c0z * c0z)
        sin1 = math.sqrt(c1x * c1x + c1y * c1y + c1z * c1z)
        sin2 = math.sqrt(c2x * c2x + c2y * c2y + c2z * c2z)
        det = u0x * c0x + u0y * c0y + u0z * c0z
        if sin0 == 0.0 or sin1 == 0.0 or sin2 == 0.0 or det == 0.0:
            continue
        if place == _BESIDE and abs(det) <= eps_unitless:
            # x beside the triangle and (almost) in its plane: the spherical triangle has
            # (almost) no area, and its mean vector below would be all rounding error.
            continue
        # Mean vector (the integral of the unit direction over the spherical triangle, its
        # sign that of det): sum_k theta_k / 2 * c_k / |c_k|, theta_k the arc opposite k.
        a0 = 0.5 * _arc(u1x, u1y, u1z, u2x, u2y, u2z) / sin0
        a1 = 0.5 * _arc(u2x, u2y, u2z, u0x, u0y, u0z) / sin1
        a2 = 0.5 * _arc(u0x, u0y, u0z, u1x, u1y, u1z) / sin2
        mx = a0 * c0x + a1 * c1x + a2 * c2x
        my = a0 * c0y + a1 * c1y + a2 * c2y
        mz = a0 * c0z + a1 * c1z + a2 * c2z
        # m = sum_k w_k d_k u_k; dotting with c_k isolates w_k. The signed det makes faces
        # seen from outside count negatively, as the closed-surface integral requires.
        row[i0] += (c0x * mx + c0y * my + c0z * mz) / (d0 * det)
        row[i1] += (c1x * mx + c1y * my + c1z * mz) / (d1 * det)
        row[i2] += (c2x * mx + c2y * my + c2z * mz) / (d2 * det)
    total = 0.0
    for j in range(m):
        total += row[j]
    for j in range(m):
        row[j] /= total


@numba.njit(cache=True)
def _place_on_plane(p0, p1, p2, x, eps_distance, eps_unitless, row, i0, i1, i2):
    """Where ``x`` lies w.r.t. triangle (p0, p1, p2): on it (edges included: then its
    barycentric weights are put in ``row``), beside it (its projection on the plane falls
    outside the triangle), or off the plane over the triangle.

    Decided by distances, not by the spherical angles of the paper's pseudocode: the half
    perimeter of the spherical triangle approaches pi only quadratically in the distance to
    the plane, so an angle tolerance would snap points far off the triangle onto it.
    """
    ex = p1[0] - p0[0]
    ey = p1[1] - p0[1]
    ez = p1[2] - p0[2]
    fx = p2[0] - p0[0]
    fy = p2[1] - p0[1]
    fz = p2[2] - p0[2]
    nx = ey * fz - ez * fy
    ny = ez * fx - ex * fz
    nz = ex * fy - ey * fx
    nn = nx * nx + ny * ny + nz * nz
    if nn == 0.0:
        return _OFF_PLANE
    # Signed barycentric coordinates of x's projection: sub-triangle areas over the area.
    b0 = _sub_area(p1, p2, x, nx, ny, nz) / nn
    b1 = _sub_area(p2, p0, x, nx, ny, nz) / nn
    b2 = _sub_area(p0, p1, x, nx, ny, nz) / nn
    if b0 < -eps_unitless or b1 < -eps_unitless or b2 < -eps_unitless:
        return _BESIDE
    height = (nx * (x[0] - p0[0]) + ny * (x[1] - p0[1]) + nz * (x[2] - p0[2])) / math.sqrt(nn)
    if abs(height) > eps_distance:
        return _OFF_PLANE
    b0 = max(b0, 0.0)
    b1 = max(b1, 0.0)
    b2 = max(b2, 0.0)
    total = b0 + b1 + b2
    for j in range(row.shape[0]):
        row[j] = 0.0
    row[i0] += b0 / total
    row[i1] += b1 / total
    row[i2] += b2 / total
    return _ON_TRIANGLE


@numba.njit(cache=True)
def _sub_area(a, b, x, nx, ny, nz):
    # ((a - x) x (b - x)) . n: twice the signed area of (x, a, b) times |n|.
    ax = a[0] - x[0]
    ay = a[1] - x[1]
    az = a[2] - x[2]
    bx = b[0] - x[0]
    by = b[1] - x[1]
    bz = b[2] - x[2]
    return (ay * bz - az * by) * nx + (az * bx - ax * bz) * ny + (ax * by - ay * bx) * nz


@numba.njit(parallel=True, cache=True)
def _mean_value_coordinates(cage_points, cage_triangles, points, eps_distance, eps_unitless,
                            weights):
    for q in prange(points.shape[0]):
        _point_weights(cage_points, cage_triangles, points[q], eps_distance, eps_unitless,
                       weights[q])


def mean_value_coordinates(cage_points, cage_triangles, points, tolerance=DEFAULT_TOLERANCE,
                           where="cage"):
    """Mean value coordinates of ``points`` w.r.t. a closed triangle cage.

    Parameters
    ----------
    cage_points : (m, 3) float64, mm
        The cage vertices (rest pose).
    cage_triangles : (t, 3) int
        A closed, manifold, consistently oriented triangulation of ``cage_points``.
    points : (n, 3) float64, mm
        The points to express (inside, outside or on the cage).
    tolerance : float
        Relative tolerance of the degenerate cases (see the module docstring).
    where : str
        Names the cage in error messages, e.g. ``"muscle 'gracilis': cage"``.

    Returns
    -------
    (n, m) float64
        Row ``q`` holds the weights of ``points[q]``; every row sums to 1 and
        ``weights @ cage_points == points`` up to rounding. Memory: ``8 n m`` bytes.
    """
    cage_points = np.ascontiguousarray(cage_points, dtype=np.float64)
    cage_triangles = np.ascontiguousarray(cage_triangles, dtype=np.int64)
    points = np.ascontiguousarray(points, dtype=np.float64)
    if cage_points.ndim != 2 or cage_points.shape[1] != 3 or len(cage_points) < 4:
        raise MuscleMSSError(f"{where}: needs at least 4 points of 3 coordinates, "
                             f"got shape {cage_points.shape}")
    if cage_triangles.ndim != 2 or cage_triangles.shape[1] != 3:
        raise MuscleMSSError(f"{where}: triangles must be an (t, 3) array, "
                             f"got shape {cage_triangles.shape}")
    if points.ndim != 2 or points.shape[1] != 3:
        raise MuscleMSSError(f"{where}: the points to express must be an (n, 3) array, "
                             f"got shape {points.shape}")
    if not np.isfinite(points).all():
        bad = int(np.flatnonzero(~np.isfinite(points).all(axis=1))[0])
        raise MuscleMSSError(f"{where}: point {bad} to express has a NaN or infinite "
                             "coordinate; every coordinate must be finite")
    problems = surface_problems(cage_points, cage_triangles)
    if problems:
        raise MuscleMSSError(f"{where} {problems[0]}; mean value coordinates need a closed, "
                             "outward-oriented cage")
    low, high = cage_points.min(axis=0), cage_points.max(axis=0)
    size = float(np.linalg.norm(high - low))
    # The weights are translation invariant; centring keeps rounding relative to the cage size
    # for muscles far from the origin.
    centre = 0.5 * (low + high)
    cage_points = cage_points - centre
    points = points - centre
    weights = np.empty((len(points), len(cage_points)), dtype=np.float64)
    if len(points):
        _mean_value_coordinates(cage_points, cage_triangles, points, tolerance * size,
                                tolerance, weights)
    if not np.isfinite(weights).all():
        bad = int(np.flatnonzero(~np.isfinite(weights).all(axis=1))[0])
        raise MuscleMSSError(f"{where}: the weights of point {bad} are not finite; the cage "
                             "is degenerate around it")
    return weights


def mvc_deform(weights, cage_positions):
    """Positions (n, 3) mm of the points whose ``weights`` (n, m) were computed at rest, for
    the cage vertices at ``cage_positions`` (m, 3) mm."""
    return np.asarray(weights) @ np.asarray(cage_positions, dtype=np.float64)
