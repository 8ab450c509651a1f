"""The weights of the nearest bones for the rigid pose (paper §3.1, DESIGN §6 "Pose").

"The muscles (the triangular surfaces as well as the particles) are transformed as well, using
an interpolated transformation matrix of the nearest bones." Each point's weight of a bone
falls off with its distance to the bone's surface in the rest pose: :func:`bone_distances`
measures that distance exactly (the nearest point on any triangle, triangles sorted into
blocks and cells whose boxes prune the search) and :func:`weights_from_distances` turns the
distances into weights; :mod:`.pose` blends the bone transforms with them.
"""
import math
from collections import namedtuple

import numba
import numpy as np
from numba import prange

from ..errors import MuscleMSSError
from ..mesh_checks import checked_surface
from ..pose import checked_positions

TRIANGLES_PER_CELL = 32
"""Aimed-for number of triangles in one cell of the distance search."""
CELLS_PER_BLOCK_SIDE = 4
"""A block of the distance search is a cube of this many cells a side (~16 cells of surface)."""

BoneSurfaces = namedtuple("BoneSurfaces", "corners tri_centres tri_radii cell_starts cell_lower "
                                          "cell_upper block_starts block_lower block_upper "
                                          "bone_blocks")
BoneSurfaces.__doc__ = """The triangles of all bones sorted for the distance search, in three
levels, each a contiguous range of the next: bones (``bone_blocks`` (B + 1,) int64) hold blocks,
blocks (``block_starts`` (K + 1,) int64) hold cells, cells (``cell_starts`` (C + 1,) int64) hold
triangles (``corners`` (m, 3, 3) float64 mm). Each block and cell lies in a box
(``block_lower``, ``block_upper`` (K, 3); ``cell_lower``, ``cell_upper`` (C, 3) mm), each
triangle in a ball (``tri_centres`` (m, 3) mm, ``tri_radii`` (m,) mm)."""

@numba.njit(cache=True)
def _segment_distance_sq(px, py, pz, ax, ay, az, bx, by, bz):
    """Squared distance (mm^2) from p to the segment a-b (a point when a == b)."""
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
def _cell_distance(px, py, pz, surfaces, c, best):
    """min(best, distance (mm) to the triangles of cell c of ``surfaces``), measuring only
    triangles whose ball is nearer than the best so far."""
    for k in range(surfaces.cell_starts[c], surfaces.cell_starts[c + 1]):
        if _distance_to_ball(px, py, pz, surfaces.tri_centres, surfaces.tri_radii, k) < best:
            best = min(best, _point_triangle_distance(px, py, pz, surfaces.corners[k]))
    return best


@numba.njit(cache=True, parallel=True)
def _surface_distances(points, surfaces, out):
    """Distance (mm) of each point (n, 3) mm to each bone's triangles of ``surfaces``
    (:class:`BoneSurfaces`) into ``out`` (n, B).

    The distance to a box or ball bounds the distance to its content from below. The cell
    nearest by that bound in the nearest block gives a first exact distance; after it only
    blocks, cells and triangles whose bound beats the best so far are looked into.
    """
    bone_blocks, block_starts = surfaces.bone_blocks, surfaces.block_starts
    block_lower, block_upper = surfaces.block_lower, surfaces.block_upper
    cell_lower, cell_upper = surfaces.cell_lower, surfaces.cell_upper
    for i in prange(points.shape[0]):
        px = points[i, 0]
        py = points[i, 1]
        pz = points[i, 2]
        for b in range(bone_blocks.shape[0] - 1):
            seed_block = _nearest_box(px, py, pz, block_lower, block_upper, bone_blocks[b],
                                      bone_blocks[b + 1])
            seed = _nearest_box(px, py, pz, cell_lower, cell_upper, block_starts[seed_block],
                                block_starts[seed_block + 1])
            best = _cell_distance(px, py, pz, surfaces, seed, np.inf)
            for blk in range(bone_blocks[b], bone_blocks[b + 1]):
                if _distance_to_box(px, py, pz, block_lower, block_upper, blk) >= best:
                    continue
                for c in range(block_starts[blk], block_starts[blk + 1]):
                    if c != seed and _distance_to_box(px, py, pz, cell_lower, cell_upper,
                                                      c) < best:
                        best = _cell_distance(px, py, pz, surfaces, c, best)
            out[i, b] = best


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
    p = checked_positions(points)
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
    _surface_distances(p, BoneSurfaces(corners, tri_centres, tri_radii, cell_starts, cell_lower,
                                       cell_upper, block_starts, block_lower, block_upper,
                                       np.asarray(bone_blocks, dtype=np.int64)), out)
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
