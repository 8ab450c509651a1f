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
* a point on a triangle, its edges included, gets that triangle's barycentric weights; "on"
  is decided by the distance to the plane and the barycentric coordinates of the projection,
  not by the pseudocode's test ``pi - h < eps``: h approaches pi only quadratically in the
  distance, so that test would snap points far off the triangle (3e-5 of its size for
  eps = 1e-9) onto it;
* a triangle whose plane passes through the point, the point outside it, contributes nothing
  (its spherical triangle has no area);

so no weight is ever NaN, and the weights of every point sum to one. For a closed cage that
does not cross itself the total weight is positive inside and negative outside, never zero off
the cage; next to a cage folded over itself it can nearly cancel, and
:func:`bounded_coordinates` then takes the nearest cage point's weights instead.
"""
import math

import numba
import numpy as np
from numba import prange

from .errors import MuscleMSSError, check_memory
from .mesh_checks import surface_problems

DEFAULT_TOLERANCE = 1e-12
"""The tolerance of the degenerate cases: distances in units of the cage's bounding-box diagonal,
barycentric coordinates and triple products of unit directions as they are."""

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
def _directions_to_vertices(cage_points, x, eps_distance, unit, distance):
    """Unit directions ``unit`` (m, 3) and distances ``distance`` (m,) mm from point ``x`` (3,)
    to the cage vertices; returns the first vertex within ``eps_distance`` mm of x (then the
    scratch is left partly filled), or -1."""
    for j in range(cage_points.shape[0]):
        dx = cage_points[j, 0] - x[0]
        dy = cage_points[j, 1] - x[1]
        dz = cage_points[j, 2] - x[2]
        d = math.sqrt(dx * dx + dy * dy + dz * dz)
        if d <= eps_distance:
            return j
        unit[j, 0] = dx / d
        unit[j, 1] = dy / d
        unit[j, 2] = dz / d
        distance[j] = d
    return -1


@numba.njit(cache=True)
def _add_triangle_weights(t, cage_triangles, normals, unit, distance, eps_distance,
                          eps_unitless, row):
    """Add triangle t's contribution to the unnormalised weights ``row`` (m,) of a point seen
    in the directions ``unit`` (m, 3) at the distances ``distance`` (m,) mm, and return False;
    or, when the point lies on the triangle (edges included), overwrite ``row`` with its
    barycentric weights and return True."""
    i0 = cage_triangles[t, 0]
    i1 = cage_triangles[t, 1]
    i2 = cage_triangles[t, 2]
    u0x, u0y, u0z, d0 = unit[i0, 0], unit[i0, 1], unit[i0, 2], distance[i0]
    u1x, u1y, u1z, d1 = unit[i1, 0], unit[i1, 1], unit[i1, 2], distance[i1]
    u2x, u2y, u2z, d2 = unit[i2, 0], unit[i2, 1], unit[i2, 2], distance[i2]
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
    det = u0x * c0x + u0y * c0y + u0z * c0z
    nx, ny, nz = normals[t, 0], normals[t, 1], normals[t, 2]
    nn = nx * nx + ny * ny + nz * nz
    beside = False
    if nn > 0.0:
        # Signed barycentric coordinates of x's projection on the plane: the areas of the
        # sub-triangles (x, p_{k+1}, p_{k+2}) = d_{k+1} d_{k+2} c_k / 2 over the area.
        b0 = d1 * d2 * (c0x * nx + c0y * ny + c0z * nz) / nn
        b1 = d2 * d0 * (c1x * nx + c1y * ny + c1z * nz) / nn
        b2 = d0 * d1 * (c2x * nx + c2y * ny + c2z * nz) / nn
        beside = b0 < -eps_unitless or b1 < -eps_unitless or b2 < -eps_unitless
        height = d0 * (u0x * nx + u0y * ny + u0z * nz) / math.sqrt(nn)
        if not beside and abs(height) <= eps_distance:
            _set_barycentric(row, i0, i1, i2, max(b0, 0.0), max(b1, 0.0), max(b2, 0.0))
            return True
    sin0 = math.sqrt(c0x * c0x + c0y * c0y + c0z * c0z)
    sin1 = math.sqrt(c1x * c1x + c1y * c1y + c1z * c1z)
    sin2 = math.sqrt(c2x * c2x + c2y * c2y + c2z * c2z)
    if sin0 == 0.0 or sin1 == 0.0 or sin2 == 0.0 or det == 0.0:
        return False
    if beside and abs(det) <= eps_unitless:
        # x beside the triangle and (almost) in its plane: the spherical triangle has
        # (almost) no area, and its mean vector below would be all rounding error.
        return False
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
    return False


@numba.njit(cache=True)
def _set_barycentric(row, i0, i1, i2, b0, b1, b2):
    """``row`` (m,): zero but the normalised non-negative barycentric weights b0, b1, b2 of the
    vertices i0, i1, i2 (a point on their triangle)."""
    total = b0 + b1 + b2
    for j in range(row.shape[0]):
        row[j] = 0.0
    row[i0] += b0 / total
    row[i1] += b1 / total
    row[i2] += b2 / total


@numba.njit(cache=True)
def _point_weights(cage_points, cage_triangles, normals, x, eps_distance, eps_unitless, unit,
                   distance, row):
    """Fill ``row`` (m,) with the normalised weights of point ``x`` (3,).

    ``normals`` (t, 3): (p1 - p0) x (p2 - p0) of each triangle; ``unit`` (m, 3) and
    ``distance`` (m,): scratch for the directions and distances from x to the cage vertices.
    """
    m = cage_points.shape[0]
    for j in range(m):
        row[j] = 0.0
    on_vertex = _directions_to_vertices(cage_points, x, eps_distance, unit, distance)
    if on_vertex >= 0:
        row[on_vertex] = 1.0
        return
    for t in range(cage_triangles.shape[0]):
        if _add_triangle_weights(t, cage_triangles, normals, unit, distance, eps_distance,
                                 eps_unitless, row):
            return
    total = 0.0
    for j in range(m):
        total += row[j]
    for j in range(m):
        row[j] /= total


@numba.njit(parallel=True, cache=True)
def _mean_value_coordinates(cage_points, cage_triangles, normals, points, eps_distance,
                            eps_unitless, chunks, weights):
    n = points.shape[0]
    m = cage_points.shape[0]
    for c in prange(chunks):
        # One scratch per chunk of points, not per point.
        unit = np.empty((m, 3))
        distance = np.empty(m)
        for q in range(c * n // chunks, (c + 1) * n // chunks):
            _point_weights(cage_points, cage_triangles, normals, points[q], eps_distance,
                           eps_unitless, unit, distance, weights[q])


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
    check_memory(f"{where}: the mean value coordinates of {len(points)} surface vertices "
                 f"on {len(cage_points)} cage vertices", 8.0 * len(points) * len(cage_points),
                 "use fewer particles per fibre (the cage holds the boundary particles)")
    weights = np.empty((len(points), len(cage_points)), dtype=np.float64)
    if len(points):
        a, b, c = (cage_points[cage_triangles[:, k]] for k in range(3))
        normals = np.cross(b - a, c - a)
        chunks = min(len(points), 8 * numba.get_num_threads())
        _mean_value_coordinates(cage_points, cage_triangles, normals, points, tolerance * size,
                                tolerance, chunks, weights)
    if not np.isfinite(weights).all():
        bad = int(np.flatnonzero(~np.isfinite(weights).all(axis=1))[0])
        raise MuscleMSSError(f"{where}: the weights of point {bad} are not finite; the cage "
                             "is degenerate around it")
    return weights


WELL_CONDITIONED = 8.0
"""Sum of absolute weights up to which a point keeps its mean value coordinates as they are: a
point whose weights' absolute values sum to S moves up to S times as far as the cage's
non-affine motion. The surface vertices of the demo scenes at 20 particles per fibre reach 7.9
(the full thigh's semimembranosus), 3.5 on the small thigh."""
ILL_CONDITIONED = 10.0
"""Sum of absolute weights from which a point takes the weights of its nearest cage point
instead (:func:`bounded_coordinates`)."""


def bounded_coordinates(cage_points, cage_triangles, points, tolerance=DEFAULT_TOLERANCE,
                        where="cage"):
    """Mean value coordinates where they are well conditioned, else the barycentric weights of
    the nearest cage point: what carries a muscle surface.

    A cage through coarse particles can fold over itself (the lattice's ring fibres cross near
    a tendon). Next to such a fold the rays from a point cross the cage leaving and entering at
    nearly the same distances, the total weight nearly cancels, and the normalised weights grow
    large and of both signs: 11,940 in absolute sum for a vertex 0.47 mm outside the small
    demo's rectus femoris cage at 8 particles per fibre, which then ended metres away. The mean
    value coordinates are exact for affine motions of the cage, but amplify its non-affine
    motion by their absolute sum S. So a point with S up to :data:`WELL_CONDITIONED` keeps its
    mean value coordinates (bitwise), one with S from :data:`ILL_CONDITIONED` takes the
    barycentric weights of the nearest point of the cage (it keeps its rest offset from that
    point), and in between the two are blended linearly in S, so that the weights stay
    continuous over the surface. The absolute sum of every row is then at most
    ``WELL_CONDITIONED``. Every row sums to 1; ``weights @ cage_points`` reproduces a point
    exactly where S <= ``WELL_CONDITIONED`` and its nearest cage point where S >=
    ``ILL_CONDITIONED``: apply the weights to the cage's displacement from rest
    (:func:`mvc_deform`), as the MVC Surface Deformer does, and the rest pose is reproduced
    exactly.

    The arguments and result as for :func:`mean_value_coordinates`.
    """
    weights = mean_value_coordinates(cage_points, cage_triangles, points, tolerance, where)
    spread = np.abs(weights).sum(axis=1)
    blend = np.clip((spread - WELL_CONDITIONED) / (ILL_CONDITIONED - WELL_CONDITIONED), 0.0, 1.0)
    rows = np.flatnonzero(blend > 0.0)
    if len(rows):
        nearest = nearest_point_weights(cage_points, cage_triangles,
                                        np.asarray(points, dtype=np.float64)[rows])
        share = blend[rows, None]
        weights[rows] = (1.0 - share) * weights[rows] + share * nearest
    return weights


def nearest_point_weights(cage_points, cage_triangles, points, chunk=4096):
    """(n, m) float64: for each of ``points`` (n, 3) mm, the barycentric weights of the nearest
    point of the triangles ``cage_triangles`` (t, 3) of ``cage_points`` (m, 3) mm (the first
    nearest triangle on ties; Ericson, Real-Time Collision Detection §5.1.5)."""
    cage_points = np.asarray(cage_points, dtype=np.float64)
    cage_triangles = np.asarray(cage_triangles, dtype=np.int64)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    a, b, c = (cage_points[cage_triangles[:, k]][None] for k in range(3))
    ab, ac = b - a, c - a
    weights = np.zeros((len(points), len(cage_points)))
    step = max(1, chunk * 64 // max(len(cage_triangles), 1))

    def dot(u, v):
        return np.einsum("ptk,ptk->pt", *np.broadcast_arrays(u, v))

    for start in range(0, len(points), step):
        p = points[start:start + step, None, :]
        ap, bp, cp = p - a, p - b, p - c
        d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), \
            dot(ab, cp), dot(ac, cp)
        va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
        with np.errstate(divide="ignore", invalid="ignore"):
            on_ab = np.nan_to_num(d1 / (d1 - d3))
            on_ac = np.nan_to_num(d2 / (d2 - d6))
            on_bc = np.nan_to_num((d4 - d3) / ((d4 - d3) + (d5 - d6)))
            inner_v = np.nan_to_num(vb / (va + vb + vc))
            inner_w = np.nan_to_num(vc / (va + vb + vc))
        # (v, w): the weights of b and c; Ericson's regions in his order, the first that holds
        regions = [
            (d1 <= 0.0) & (d2 <= 0.0),                                   # vertex a
            (d3 >= 0.0) & (d4 <= d3),                                    # vertex b
            (vc <= 0.0) & (d1 >= 0.0) & (d3 <= 0.0),                     # edge ab
            (d6 >= 0.0) & (d5 <= d6),                                    # vertex c
            (vb <= 0.0) & (d2 >= 0.0) & (d6 <= 0.0),                     # edge ac
            (va <= 0.0) & (d4 - d3 >= 0.0) & (d5 - d6 >= 0.0),           # edge bc
        ]
        zero, one = np.zeros_like(d1), np.ones_like(d1)
        v = np.select(regions, [zero, one, on_ab, zero, zero, 1.0 - on_bc], inner_v)
        w = np.select(regions, [zero, zero, zero, one, on_ac, on_bc], inner_w)
        u = 1.0 - v - w
        closest = u[..., None] * a + v[..., None] * b + w[..., None] * c
        nearest = np.argmin(((p - closest) ** 2).sum(axis=2), axis=1)
        rows = np.arange(len(nearest))
        corners = cage_triangles[nearest]
        out = weights[start:start + step]
        for k, share in enumerate((u, v, w)):
            np.add.at(out, (rows, corners[:, k]), share[rows, nearest])
    return weights


def mvc_deform(weights, cage_positions):
    """Positions (n, 3) mm of the points whose ``weights`` (n, m) were computed at rest, for
    the cage vertices at ``cage_positions`` (m, 3) mm.

    The map is linear, so the same call turns the cage's displacement from rest into the
    points' displacement: the MVC Surface Deformer keeps its weights as float32 (half the
    memory it reads every time point) and applies them to displacements, so that the rest pose
    is reproduced exactly and rounding stays about 1e-7 of the displacement. ``weights`` may be
    float64 or float32; the sums are float64.

    A Numba loop over the points, not ``weights @ cage_positions``: in ParaView's Python the
    BLAS (Debian's pthreads OpenBLAS) ran its own threads beside Numba's and the product took
    1.7 ms a demo muscle on the time slider instead of 0.5."""
    weights = np.asarray(weights)
    if weights.dtype not in (np.float32, np.float64):
        weights = weights.astype(np.float64)
    weights = np.ascontiguousarray(weights)
    cage_positions = np.ascontiguousarray(cage_positions, dtype=np.float64).reshape(-1, 3)
    out = np.empty((weights.shape[0], 3))
    _weighted_sums(weights, cage_positions, out)
    return out


@numba.njit(cache=True, parallel=True)
def _weighted_sums(weights, cage_positions, out):
    """``out[i] = sum_j weights[i, j] cage_positions[j]`` for every row ``i``."""
    for i in prange(weights.shape[0]):
        x, y, z = 0.0, 0.0, 0.0
        for j in range(weights.shape[1]):
            w = np.float64(weights[i, j])
            x += w * cage_positions[j, 0]
            y += w * cage_positions[j, 1]
            z += w * cage_positions[j, 2]
        out[i, 0] = x
        out[i, 1] = y
        out[i, 2] = z
