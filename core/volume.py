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
