"""Exact signed distance to a closed triangle surface (the ground truth of the bones' sampled
fields, :mod:`.bones.distance`).

The distance of a point is that to its nearest triangle: Ericson's closest point on a triangle
(Real-Time Collision Detection §5.1.5), the nearest triangle found in a bounding volume
hierarchy of the triangles (:class:`TriangleTree`), nearer boxes first, boxes farther than the
best triangle so far skipped. Its sign is that of ``(x - c) . n`` with ``c`` the closest point
and ``n`` the angle-weighted pseudo-normal of the closest feature (Baerentzen & Aanaes 2005:
the face normal, the sum of the two face normals at an edge, the angle-weighted sum at a
vertex), which is exact for closed, manifold, outward-oriented surfaces.

A surface is prepared once (:func:`prepared_surface`: its pseudo-normals and hierarchy, kept
for the last :data:`SURFACES_KEPT` surfaces by bitwise digest) and then queried by the kernels
:func:`exact_at_queries` (any points) and :func:`exact_at_bricks` (the nodes of the bones'
fine bricks), or through the checked :func:`exact_signed_distance`, :func:`exact_closest_points`
and :func:`inside_surface`.
"""
from __future__ import annotations

import math
from collections import OrderedDict, namedtuple

import numba
import numpy as np
from numba import njit, prange

from ..disk_store import array_digest
from ..errors import MuscleMSSError
from ..mesh_checks import checked_surface, surface_problems

LEAF_SIZE = 4
"""Triangles per leaf of the bounding volume hierarchy at most."""
_STACK = 64
"""Depth of the traversal stack (a median-split tree of 2^40 leaves would need 40)."""
SURFACES_KEPT = 8
"""Prepared surfaces kept in :data:`PREPARED_SURFACES`."""

# Closest features of a triangle (a, b, c), as returned by _closest_point_on_triangle.
_FACE, _VERTEX_A, _VERTEX_B, _VERTEX_C, _EDGE_AB, _EDGE_BC, _EDGE_CA = range(7)

TriangleMesh = namedtuple("TriangleMesh", "points triangles face_normals edge_normals "
                                          "vertex_normals")
TriangleMesh.__doc__ = """A closed triangle surface with its pseudo-normals, as the kernels take
it: ``points`` (n, 3) float64 mm, ``triangles`` (m, 3) int64, unit ``face_normals`` (m, 3),
``edge_normals`` (m, 3, 3) (edge e of triangle t runs from corner e to corner e + 1; the sum of
the normals of the two triangles sharing it) and angle-weighted ``vertex_normals`` (n, 3)."""

TriangleTree = namedtuple("TriangleTree", "low high child first count order")
TriangleTree.__doc__ = """A bounding volume hierarchy of a surface's triangles (k nodes): node n
has the box ``low[n]``..``high[n]`` (k, 3) float64 mm; an inner node has the children
``child[n]`` and ``child[n] + 1`` (k,) int64, a leaf (child -1) holds the triangles
``order[first[n]:first[n] + count[n]]`` ((k,), (k,), (m,) int64)."""


@njit(cache=True)
def _closest_point_on_triangle(px, py, pz, points, triangles, t):
    """Closest point of triangle t (corners a, b, c) to p and its feature (_FACE, _VERTEX_*,
    _EDGE_*): ``(squared distance mm^2, x, y, z, feature)`` (Ericson §5.1.5)."""
    a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
    ax, ay, az = points[a, 0], points[a, 1], points[a, 2]
    bx, by, bz = points[b, 0], points[b, 1], points[b, 2]
    cx, cy, cz = points[c, 0], points[c, 1], points[c, 2]
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    qx, qy, qz, feature = ax, ay, az, _VERTEX_A
    if not (d1 <= 0.0 and d2 <= 0.0):
        bpx, bpy, bpz = px - bx, py - by, pz - bz
        d3 = abx * bpx + aby * bpy + abz * bpz
        d4 = acx * bpx + acy * bpy + acz * bpz
        cpx, cpy, cpz = px - cx, py - cy, pz - cz
        d5 = abx * cpx + aby * cpy + abz * cpz
        d6 = acx * cpx + acy * cpy + acz * cpz
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d3 >= 0.0 and d4 <= d3:
            qx, qy, qz, feature = bx, by, bz, _VERTEX_B
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            v = d1 / (d1 - d3) if d1 - d3 > 0.0 else 0.0
            qx, qy, qz, feature = ax + v * abx, ay + v * aby, az + v * abz, _EDGE_AB
        elif d6 >= 0.0 and d5 <= d6:
            qx, qy, qz, feature = cx, cy, cz, _VERTEX_C
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
            w = d2 / (d2 - d6) if d2 - d6 > 0.0 else 0.0
            qx, qy, qz, feature = ax + w * acx, ay + w * acy, az + w * acz, _EDGE_CA
        elif va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
            den = (d4 - d3) + (d5 - d6)
            w = (d4 - d3) / den if den > 0.0 else 0.0
            qx, qy, qz, feature = bx + w * (cx - bx), by + w * (cy - by), bz + w * (cz - bz), \
                _EDGE_BC
        else:
            den = va + vb + vc
            v = vb / den if den != 0.0 else 0.0
            w = vc / den if den != 0.0 else 0.0
            qx, qy, qz = ax + v * abx + w * acx, ay + v * aby + w * acy, az + v * abz + w * acz
            feature = _FACE
    dx, dy, dz = px - qx, py - qy, pz - qz
    return dx * dx + dy * dy + dz * dz, qx, qy, qz, feature


@njit(cache=True)
def _box_distance_sq(px, py, pz, low, high, node):
    """Squared distance (mm^2) of p to the box ``low[node]``..``high[node]`` (0 inside)."""
    gx = max(max(low[node, 0] - px, px - high[node, 0]), 0.0)
    gy = max(max(low[node, 1] - py, py - high[node, 1]), 0.0)
    gz = max(max(low[node, 2] - pz, pz - high[node, 2]), 0.0)
    return gx * gx + gy * gy + gz * gz


@njit(cache=True)
def _feature_normal(mesh, triangle, feature):
    """The pseudo-normal (3 floats) of the closest ``feature`` of ``triangle``."""
    if feature == _FACE:
        normal = mesh.face_normals[triangle]
    elif feature <= _VERTEX_C:
        normal = mesh.vertex_normals[mesh.triangles[triangle, feature - _VERTEX_A]]
    else:
        normal = mesh.edge_normals[triangle, feature - _EDGE_AB]
    return normal[0], normal[1], normal[2]


@njit(cache=True)
def _nearest_signed(px, py, pz, hint, stack, mesh, tree):
    """Exact signed distance (mm, negative inside) of p to the surface ``mesh``, its nearest
    triangle and the closest point on it (3 floats, mm): ``(distance, triangle, x, y, z)``,
    found in ``tree``, nearer child first, boxes farther than the best triangle so far
    skipped. A ``hint`` triangle (>= 0; a neighbouring point's nearest) starts the search with a
    tight bound. ``stack`` (_STACK,) int64 is scratch."""
    low, high, child = tree.low, tree.high, tree.child
    best = np.inf
    bx = by = bz = 0.0
    bt = -1
    bf = 0
    if hint >= 0:
        best, bx, by, bz, bf = _closest_point_on_triangle(px, py, pz, mesh.points,
                                                          mesh.triangles, hint)
        bt = hint
    top = 0
    stack[0] = 0
    while top >= 0:
        node = stack[top]
        top -= 1
        if _box_distance_sq(px, py, pz, low, high, node) >= best:
            continue
        if child[node] < 0:
            for s in range(tree.first[node], tree.first[node] + tree.count[node]):
                t = tree.order[s]
                d2, qx, qy, qz, f = _closest_point_on_triangle(px, py, pz, mesh.points,
                                                               mesh.triangles, t)
                if d2 < best:
                    best, bx, by, bz, bt, bf = d2, qx, qy, qz, t, f
            continue
        left = child[node]
        near, far = left, left + 1
        if _box_distance_sq(px, py, pz, low, high, far) < \
                _box_distance_sq(px, py, pz, low, high, near):
            near, far = far, near
        stack[top + 1] = far
        stack[top + 2] = near
        top += 2
    nx, ny, nz = _feature_normal(mesh, bt, bf)
    distance = math.sqrt(best)
    if (px - bx) * nx + (py - by) * ny + (pz - bz) * nz < 0.0:
        return -distance, bt, bx, by, bz
    return distance, bt, bx, by, bz


@njit(parallel=True, cache=True)
def exact_at_queries(queries, chunks, mesh, tree, out, closest):
    """Exact signed distances (mm) of ``queries`` (q, 3) mm to ``mesh`` into ``out`` (q,) and
    the closest surface points into ``closest`` (q, 3) mm, in ``chunks`` runs of consecutive
    queries (:func:`query_chunks`); within a run each query starts from the previous one's
    nearest triangle (fast for grid-ordered queries, exact for any order)."""
    n = queries.shape[0]
    for c in prange(chunks):
        stack = np.empty(_STACK, dtype=np.int64)
        hint = np.int64(-1)
        for q in range(c * n // chunks, (c + 1) * n // chunks):
            out[q], hint, closest[q, 0], closest[q, 1], closest[q, 2] = _nearest_signed(
                queries[q, 0], queries[q, 1], queries[q, 2], hint, stack, mesh, tree)


@njit(parallel=True, cache=True)
def exact_at_bricks(bricks, origin, spacing, mesh, tree, out):
    """Fill ``out`` (k, B + 1, B + 1, B + 1) with the exact signed distances (mm) at the nodes,
    ``spacing`` mm apart from ``origin`` (3,) mm, of the bricks of B cells a side at brick
    coordinates ``bricks`` (k, 3) int64; each node starts from its neighbour's nearest
    triangle."""
    n = out.shape[1]
    brick = n - 1
    for s in prange(bricks.shape[0] * n):
        stack = np.empty(_STACK, dtype=np.int64)
        b = s // n
        a = s - b * n
        x = origin[0] + (bricks[b, 0] * brick + a) * spacing
        row = np.int64(-1)
        for j in range(n):
            y = origin[1] + (bricks[b, 1] * brick + j) * spacing
            hint = row
            for k in range(n):
                z = origin[2] + (bricks[b, 2] * brick + k) * spacing
                out[b, a, j, k], hint, _, _, _ = _nearest_signed(x, y, z, hint, stack, mesh,
                                                                  tree)
                if k == 0:
                    row = hint


def query_chunks(n) -> int:
    """Runs of consecutive queries for :func:`exact_at_queries` of ``n`` queries: a few per
    thread."""
    return max(1, min(n, 8 * numba.get_num_threads()))


def _hierarchy(points, triangles) -> TriangleTree:
    """A bounding volume hierarchy of the triangles: each node's triangles split at the median
    of their centroids along their longest extent, leaves of at most LEAF_SIZE, the two
    children of a node stored side by side."""
    m = len(triangles)
    corners = points[triangles]                       # (m, 3, 3)
    size = 2 * m + 1
    low, high = np.empty((size, 3)), np.empty((size, 3))
    child = np.full(size, -1, dtype=np.int64)
    first, count = np.zeros(size, dtype=np.int64), np.zeros(size, dtype=np.int64)
    order = np.arange(m, dtype=np.int64)
    nodes = _split_nodes(corners.min(axis=1), corners.max(axis=1), corners.mean(axis=1),
                         LEAF_SIZE, TriangleTree(low, high, child, first, count, order))
    return TriangleTree(low[:nodes], high[:nodes], child[:nodes], first[:nodes],
                        count[:nodes], order)


@njit(cache=True)
def _split_nodes(tri_low, tri_high, centroid, leaf_size, tree):
    """Build :func:`_hierarchy`'s nodes in place in ``tree`` (room for 2 m + 1 nodes) from the
    triangles' boxes ``tri_low``, ``tri_high`` and ``centroid`` (m, 3); returns the number of
    nodes (a Python loop over the nodes took 0.3 s a bone of the demo thigh)."""
    low, high, child, first, count, order = tree
    m = centroid.shape[0]
    count[0] = m
    pending = np.empty(low.shape[0], dtype=np.int64)
    pending[0] = 0
    top, nodes = 1, 1
    lowest = np.empty(3)
    highest = np.empty(3)
    c_low = np.empty(3)
    c_high = np.empty(3)
    while top > 0:
        top -= 1
        node = pending[top]
        start, n = first[node], count[node]
        lowest[:] = np.inf
        highest[:] = -np.inf
        c_low[:] = np.inf
        c_high[:] = -np.inf
        for i in range(start, start + n):
            t = order[i]
            for axis in range(3):
                lowest[axis] = min(lowest[axis], tri_low[t, axis])
                highest[axis] = max(highest[axis], tri_high[t, axis])
                c_low[axis] = min(c_low[axis], centroid[t, axis])
                c_high[axis] = max(c_high[axis], centroid[t, axis])
        low[node] = lowest
        high[node] = highest
        if n <= leaf_size:
            continue
        axis = int(np.argmax(c_high - c_low))
        middle = n // 2
        keys = np.empty(n)
        for i in range(n):
            keys[i] = centroid[order[start + i], axis]
        members = order[start:start + n][np.argsort(keys, kind="mergesort")]
        order[start:start + n] = members
        child[node] = nodes
        first[nodes], count[nodes] = start, middle
        first[nodes + 1], count[nodes + 1] = start + middle, n - middle
        pending[top] = nodes
        pending[top + 1] = nodes + 1
        top += 2
        nodes += 2
    return nodes


def _pseudo_normals(points, triangles):
    """Unit face normals (m, 3), edge pseudo-normals (m, 3, 3) and angle-weighted vertex
    pseudo-normals (n, 3) of a closed manifold surface (see :class:`TriangleMesh`)."""
    a, b, c = (points[triangles[:, k]] for k in range(3))
    cross = np.cross(b - a, c - a)
    length = np.linalg.norm(cross, axis=1, keepdims=True)
    face = np.divide(cross, length, out=np.zeros_like(cross), where=length > 0)
    corners = np.stack([a, b, c], axis=1)
    vertex = np.zeros_like(points)
    for k in range(3):
        u = corners[:, (k + 1) % 3] - corners[:, k]
        w = corners[:, (k + 2) % 3] - corners[:, k]
        nu = np.linalg.norm(u, axis=1)
        nw = np.linalg.norm(w, axis=1)
        ok = (nu > 0) & (nw > 0)
        cosine = np.ones(len(u))
        cosine[ok] = np.einsum("ij,ij->i", u[ok], w[ok]) / (nu[ok] * nw[ok])
        angle = np.arccos(np.clip(cosine, -1.0, 1.0))
        np.add.at(vertex, triangles[:, k], angle[:, None] * face)
    m = len(triangles)
    start = triangles.reshape(-1)
    end = triangles[:, [1, 2, 0]].reshape(-1)
    key = np.minimum(start, end) * len(points) + np.maximum(start, end)
    order = np.argsort(key, kind="stable")
    # A closed manifold surface has every edge exactly twice (surface_problems checked it).
    first, second = order[0::2], order[1::2]
    other = np.empty(3 * m, dtype=np.int64)
    other[first] = second // 3
    other[second] = first // 3
    edge = (face[:, None, :] + face[other.reshape(m, 3)]).copy()
    return face, edge, vertex


def surface_digest(points, triangles) -> str:
    """A digest of a triangle surface, bitwise: its points (n, 3) float64 and triangles (m, 3)
    int64 (:func:`~muscle_mss.core.disk_store.array_digest`)."""
    return array_digest(np.asarray(triangles, dtype=np.int64),
                        np.asarray(points, dtype=np.float64))


class PreparedSurface:
    """A closed triangle surface ready for exact signed distances: ``mesh``, its
    :class:`TriangleMesh` (pseudo-normals), and ``tree``, its :class:`TriangleTree`."""

    def __init__(self, points, triangles, where):
        points, triangles = checked_surface(points, triangles, where)
        problems = surface_problems(points, triangles)
        if problems:
            raise MuscleMSSError(f"{where} {problems[0]}; a signed distance needs a closed, "
                                 "outward-oriented surface")
        self.mesh = TriangleMesh(points, triangles, *_pseudo_normals(points, triangles))
        self.tree = _hierarchy(points, triangles)


PREPARED_SURFACES = OrderedDict()
"""The last surfaces prepared for exact distances (digest -> :class:`PreparedSurface`): the
Spring Builder and the Rigid Pose Transform both test the same rest bones, and the hierarchy
costs 0.3 s a bone of the demo thigh."""


def prepared_surface(points, triangles, where) -> PreparedSurface:
    """:class:`PreparedSurface` of ``points`` (n, 3) mm, ``triangles`` (m, 3), the same one
    while the surface is the same bitwise (errors are raised each time); ``where`` names the
    surface in errors."""
    points, triangles = checked_surface(points, triangles, where)
    key = surface_digest(points, triangles)
    if key in PREPARED_SURFACES:
        PREPARED_SURFACES.move_to_end(key)
        return PREPARED_SURFACES[key]
    surface = PreparedSurface(points, triangles, where)
    PREPARED_SURFACES[key] = surface
    while len(PREPARED_SURFACES) > SURFACES_KEPT:
        PREPARED_SURFACES.popitem(last=False)
    return surface


def exact_signed_distance(points, triangles, queries, where="surface") -> np.ndarray:
    """Exact signed distance (mm, negative inside) of ``queries`` (q, 3) mm to the closed,
    outward-oriented triangle surface ``points`` (n, 3) mm, ``triangles`` (m, 3): the nearest
    triangle through a bounding volume hierarchy, the sign by pseudo-normals. Returns (q,)
    float64."""
    return exact_closest_points(points, triangles, queries, where)[0]


def exact_closest_points(points, triangles, queries, where="surface"):
    """:func:`exact_signed_distance` of ``queries`` (q, 3) mm and the closest point of the
    surface to each: ``(distance (q,) mm, closest (q, 3) mm)``."""
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    return closest_points(prepared_surface(points, triangles, where), queries, where)


def closest_points(surface: PreparedSurface, queries, where="surface"):
    """:func:`exact_closest_points` on a :class:`PreparedSurface`: ``(distance (q,) mm,
    closest (q, 3) mm)`` of ``queries`` (q, 3) mm."""
    queries = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(queries).all():
        raise MuscleMSSError(f"{where}: the query points must have finite coordinates")
    out, closest = np.empty(len(queries)), np.empty((len(queries), 3))
    if len(queries):
        exact_at_queries(queries, query_chunks(len(queries)), surface.mesh, surface.tree, out,
                         closest)
    return out, closest


def unsigned_distance(points, triangles, queries, where="surface") -> np.ndarray:
    """(q,) mm: the distance of ``queries`` (q, 3) mm to the nearest triangle of ``points``
    (n, 3) mm, ``triangles`` (m, 3), a surface that need not be closed or oriented (a cage
    carried by the particles): no pseudo-normals (without them every distance comes out
    positive), the hierarchy built for this call only."""
    queries = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
    points, triangles = checked_surface(points, triangles, where)
    m = len(triangles)
    mesh = TriangleMesh(points, triangles, np.zeros((m, 3)), np.zeros((m, 3, 3)),
                        np.zeros((len(points), 3)))
    out = np.empty(len(queries))
    if len(queries):
        exact_at_queries(queries, query_chunks(len(queries)), mesh,
                         _hierarchy(points, triangles), out, np.empty((len(queries), 3)))
    return out


def inside_surface(points, triangles, queries, sampled, error_bound, where="surface"):
    """(q,) bool: which ``queries`` (q, 3) mm are inside the closed surface ``points``,
    ``triangles`` (its exact signed distance below 0), given ``sampled`` (q,) mm, their distance
    looked up in the surface's field, whose
    :attr:`~muscle_mss.core.bones.distance.BoneDistanceField.error_bound` is ``error_bound`` mm:
    only the queries that the sampled value does not place farther out than that are measured
    exactly (the Spring Builder and the Rigid Pose Transform test every particle of the model
    against every bone: 0.6 s of the first time point at N = 80)."""
    queries = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
    sampled = np.asarray(sampled, dtype=np.float64).reshape(-1)
    inside = np.zeros(len(queries), dtype=bool)
    near = np.flatnonzero(~(sampled > error_bound))          # NaN is measured too
    if len(near):
        inside[near] = exact_signed_distance(points, triangles, queries[near], where) < 0.0
    return inside
