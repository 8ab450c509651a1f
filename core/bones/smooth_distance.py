"""A continuously differentiable lookup of the bones' signed distance fields, for the
quasi-static solve's contact energy.

:func:`~muscle_mss.core.bones.distance.sample` interpolates trilinearly: its value is continuous
but its gradient jumps at every cell face. The quasi-static method's bone penalty ``w / 2 (r -
d)^2`` then has a gradient that jumps with it, and a particle pressed into a bone can come to
rest on a cell face where the push from one side and the other disagree: on the demo thigh at
its most flexed pose seven such particles kept 1.2-5.5 g mm/s^2 of force for thousands of
iterations (the directional derivative across the face flipping from -4.7 to +5.5), the
quasi-Newton steps chattered across the faces and no stopping test fired.

:func:`smooth_sample` evaluates instead the quadratic B-spline whose control points are the
fine nodes' values (the trilinear interpolant smoothed by a box of one cell): continuous with a
continuous gradient everywhere, exact for a linear distance (a flat bone surface), within about
``spacing^2 / (8 R)`` mm of the trilinear value near a surface of radius of curvature ``R``.
A node of a brick that holds no fine values takes the coarse grid's trilinear value there.
Outside the sampled box it continues as :func:`~muscle_mss.core.bones.distance.sample` does.
"""
from __future__ import annotations

import math

from numba import njit

from .distance import BRICK, COARSE, _trilinear


@njit(cache=True)
def _node_value(b, i, j, k, grid):
    """The value (mm) at fine node (i, j, k) of bone b (clamped to the sampled box): its
    brick's, or the coarse grid's trilinear value where the brick holds no fine nodes."""
    dims = grid.dims
    nx, ny, nz = dims[b, 0], dims[b, 1], dims[b, 2]
    i = min(max(i, 0), nx * BRICK)
    j = min(max(j, 0), ny * BRICK)
    k = min(max(k, 0), nz * BRICK)
    bi, bj, bk = min(i // BRICK, nx - 1), min(j // BRICK, ny - 1), min(k // BRICK, nz - 1)
    block = grid.brick_index[grid.index_start[b] + (bi * ny + bj) * nz + bk]
    if block >= 0:
        n = BRICK + 1
        return float(grid.bricks[block][((i - bi * BRICK) * n + (j - bj * BRICK)) * n
                                         + (k - bk * BRICK)])
    per = BRICK // COARSE
    ci, cj, ck = min(i // COARSE, nx * per - 1), min(j // COARSE, ny * per - 1), \
        min(k // COARSE, nz * per - 1)
    sy = nz * per + 1
    sx = (ny * per + 1) * sy
    return _trilinear(grid.coarse, grid.coarse_start[b] + ci * sx + cj * sy + ck, sx, sy,
                      (i - ci * COARSE) / COARSE, (j - cj * COARSE) / COARSE,
                      (k - ck * COARSE) / COARSE)[0]


@njit(cache=True)
def _bspline(u):
    """The nearest node ``c`` to coordinate ``u`` (in cells) and the quadratic B-spline
    weights of nodes c - 1, c, c + 1 and their derivatives."""
    c = int(math.floor(u + 0.5))
    t = u - c
    return (c, 0.5 * (0.5 - t) ** 2, 0.75 - t * t, 0.5 * (0.5 + t) ** 2,
            t - 0.5, -2.0 * t, t + 0.5)


@njit(cache=True)
def _smooth_inside_box(b, ux, uy, uz, grid):
    """Value and gradient (per fine cell) at (ux, uy, uz), in fine cells from the box's
    origin."""
    ci, ai0, ai1, ai2, di0, di1, di2 = _bspline(ux)
    cj, aj0, aj1, aj2, dj0, dj1, dj2 = _bspline(uy)
    ck, ak0, ak1, ak2, dk0, dk1, dk2 = _bspline(uz)
    wi, dwi = (ai0, ai1, ai2), (di0, di1, di2)
    wj, dwj = (aj0, aj1, aj2), (dj0, dj1, dj2)
    wk, dwk = (ak0, ak1, ak2), (dk0, dk1, dk2)
    value, gx, gy, gz = 0.0, 0.0, 0.0, 0.0
    for a in range(3):
        for c in range(3):
            for e in range(3):
                v = _node_value(b, ci + a - 1, cj + c - 1, ck + e - 1, grid)
                value += wi[a] * wj[c] * wk[e] * v
                gx += dwi[a] * wj[c] * wk[e] * v
                gy += wi[a] * dwj[c] * wk[e] * v
                gz += wi[a] * wj[c] * dwk[e] * v
    return value, gx, gy, gz


@njit(cache=True)
def smooth_sample(b, qx, qy, qz, grid):
    """Signed distance (mm) and its gradient at rest-frame point q of bone b of ``grid``
    (:data:`~muscle_mss.core.bones.distance.FieldGrid`), continuously differentiable (module
    docstring); outside the sampled box as :func:`~muscle_mss.core.bones.distance.sample`."""
    origin, dims = grid.origin, grid.dims
    h = grid.spacing[b]
    ux = (qx - origin[b, 0]) / h
    uy = (qy - origin[b, 1]) / h
    uz = (qz - origin[b, 2]) / h
    cx = min(max(ux, 0.0), float(dims[b, 0] * BRICK))
    cy = min(max(uy, 0.0), float(dims[b, 1] * BRICK))
    cz = min(max(uz, 0.0), float(dims[b, 2] * BRICK))
    value, gx, gy, gz = _smooth_inside_box(b, cx, cy, cz, grid)
    ox, oy, oz = (ux - cx) * h, (uy - cy) * h, (uz - cz) * h
    away = math.sqrt(ox * ox + oy * oy + oz * oz)
    if away > 0.0:
        return value + away, ox / away, oy / away, oz / away
    return value, gx / h, gy / h, gz / h
