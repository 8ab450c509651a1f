"""Enclosed volume of closed triangle surfaces by the divergence theorem (paper §4.2).

``V = 1/6 * sum_t p0 . (p1 x p2)``: positive for an outward-oriented closed surface. The
volume error of a deformed muscle is ``|V - V_rest| / V_rest``.
"""
import numba
import numpy as np


@numba.njit(cache=True)
def _signed_volume(points, triangles):
    total = 0.0
    for t in range(triangles.shape[0]):
        a = points[triangles[t, 0]]
        b = points[triangles[t, 1]]
        c = points[triangles[t, 2]]
        total += (a[0] * (b[1] * c[2] - b[2] * c[1])
                  + a[1] * (b[2] * c[0] - b[0] * c[2])
                  + a[2] * (b[0] * c[1] - b[1] * c[0]))
    return total / 6.0


def signed_volume(points, triangles) -> float:
    """Signed volume (mm³) of a closed triangle surface.

    Parameters
    ----------
    points : (n, 3) float64, mm
    triangles : (m, 3) int, vertex indices, counter-clockwise seen from outside
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    if len(triangles) == 0:
        return 0.0
    # Shift to the centroid: the sum is then far less prone to cancellation.
    return float(_signed_volume(points - points.mean(axis=0), triangles))


def volume_error(volume: float, rest_volume: float) -> float:
    """Relative volume error ``|V - V_rest| / V_rest`` (a fraction, not %)."""
    return abs(volume - rest_volume) / abs(rest_volume)


@numba.njit(cache=True, inline="always")
def vector_between(head, i, tail, j):
    """The components (mm) of ``head[i] - tail[j]`` (rows of (n, 3) point arrays)."""
    return head[i, 0] - tail[j, 0], head[i, 1] - tail[j, 1], head[i, 2] - tail[j, 2]


@numba.njit(cache=True, parallel=True)
def _winding_numbers(points, surface_points, triangles, out):
    for q in numba.prange(points.shape[0]):
        total = 0.0
        for t in range(triangles.shape[0]):
            i, j, k = triangles[t, 0], triangles[t, 1], triangles[t, 2]
            ax, ay, az = vector_between(surface_points, i, points, q)
            bx, by, bz = vector_between(surface_points, j, points, q)
            cx, cy, cz = vector_between(surface_points, k, points, q)
            la = np.sqrt(ax * ax + ay * ay + az * az)
            lb = np.sqrt(bx * bx + by * by + bz * bz)
            lc = np.sqrt(cx * cx + cy * cy + cz * cz)
            numerator = (ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz)
                         + az * (bx * cy - by * cx))
            denominator = (la * lb * lc + (ax * bx + ay * by + az * bz) * lc
                           + (ax * cx + ay * cy + az * cz) * lb
                           + (bx * cx + by * cy + bz * cz) * la)
            total += 2.0 * np.arctan2(numerator, denominator)
        out[q] = total / (4.0 * np.pi)


def winding_numbers(points, surface_points, triangles) -> np.ndarray:
    """(p,) float64: the winding number of a closed, outward-oriented triangle surface around
    each of ``points`` (p, 3) mm — 1 inside, 0 outside (up to rounding) — the sum of the solid
    angles of its triangles over 4 pi (Van Oosterom and Strackee's formula). For the few
    sample points of the scene checks: O(points x triangles)."""
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.zeros(len(points))
    if len(points) and len(triangles):
        _winding_numbers(points, np.ascontiguousarray(surface_points, dtype=np.float64),
                         np.ascontiguousarray(triangles, dtype=np.int64), out)
    return out
