"""The paper's collision structure: one octree of axis-aligned boxes per object (§3.3, after
Larsson & Akenine-Möller 2006).

Each muscle and each bone gets a tree over its spheres. A new tree is only its root box; a node
is split into the (non-empty) octants around its box's midpoint the first time a traversal needs
it, and its children keep their spheres from then on: boxes are refitted to the spheres' current
positions (once per iteration, when a traversal first visits the node), never rebuilt. Bone
trees are static: each of their boxes is fitted once.

Each muscle is tested against every other muscle and every bone by a simultaneous descent of the
two trees: overlapping boxes are split (the larger box first) until a node is at the maximum
depth or holds at most the minimum number of spheres (the paper's 8 and 10); two such nodes are
tested sphere against sphere. Boxes bound the spheres (centre +- radius), so no colliding pair is
missed: this finds exactly the pairs of :mod:`muscle_mss.core.contacts.spatial_hash`.

Like the paper's, this structure runs on one thread. The response is that of
:mod:`muscle_mss.core.mss` (one push per sphere and other object, from its deepest pair), added
object by object in increasing object order — the order of the spatial hash, so both structures
give bitwise the same displacements.
"""
from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from .collision_spheres import Spheres, deeper, push_share, sphere_push

MAX_DEPTH = 8
MIN_PRIMITIVES = 10
STATIC = np.iinfo(np.int64).max     # stamp of a static (bone) box: always current

# rows of OctreeBVH.node_int
START, COUNT, CHILD, N_CHILDREN, DEPTH, OBJECT = range(6)


OctreeBVH = namedtuple("OctreeBVH", (
    "centres", "radius", "fixed", "perm", "scratch", "object_first", "static", "node_int",
    "node_box", "node_stamp", "stack", "state", "best_pen", "best_dir", "best_partner", "touched",
    "n_muscles", "n_muscle_spheres", "max_depth", "min_primitives"))
OctreeBVH.__doc__ = """The trees of all objects in one node pool; primitives are global sphere
ids ``g``: muscle spheres ``0 .. m-1`` then bone spheres.

``centres`` (3, G) mm (muscle part refreshed every iteration), ``radius`` (G,),
``fixed`` (G,) bool (fixed particles and all bone spheres), ``object_first`` (K + 1,): object
``k``'s spheres are ``perm[object_first[k]:object_first[k + 1]]`` and its root is node ``k``;
``static`` (K,) bool. ``node_int`` (6, capacity) int64 rows START, COUNT, CHILD (first child,
-1 = not split), N_CHILDREN, DEPTH, OBJECT; ``node_box`` (6, capacity) lower and upper
corners; ``node_stamp`` (capacity,); ``state`` [nodes in use, current stamp, spheres
touched]. ``best_pen`` (G,), ``best_dir`` (3, G), ``best_partner`` (G,), ``touched`` (G,):
each sphere's deepest pair with the object being tested. ``n_muscles`` objects are muscles,
holding ``n_muscle_spheres`` spheres; ``max_depth`` and ``min_primitives`` bound the
subdivision."""


def _node_bound(n: int, max_depth: int, min_primitives: int) -> int:
    """Most nodes a tree over ``n`` spheres can grow: split nodes hold more than
    ``min_primitives`` spheres each, so at most ``n // (min_primitives + 1)`` per level."""
    split = sum(min(8 ** level, n // (min_primitives + 1)) for level in range(max_depth))
    return 1 + 8 * split


def octree_bvh(spheres: Spheres, max_depth: int = MAX_DEPTH,
               min_primitives: int = MIN_PRIMITIVES) -> OctreeBVH:
    """The root boxes of every muscle and bone (no subdivision yet)."""
    m = spheres.count
    g = m + len(spheres.bone_radius)
    n_muscles = max(spheres.n_muscles, 0)
    n_bones = spheres.n_bones
    muscle_first = np.searchsorted(spheres.muscle, np.arange(n_muscles + 1))
    bone_first = m + np.searchsorted(spheres.bone, np.arange(1, n_bones + 1))
    object_first = np.concatenate([muscle_first, bone_first]).astype(np.int64)
    k = n_muscles + n_bones
    sizes = np.diff(object_first)
    capacity = k + sum(_node_bound(int(s), max_depth, min_primitives) for s in sizes)
    centres = np.zeros((3, g))
    centres[:, m:] = spheres.bone_centres
    node_int = np.zeros((6, capacity), dtype=np.int64)
    node_int[START, :k] = object_first[:-1]
    node_int[COUNT, :k] = sizes
    node_int[CHILD, :] = -1
    node_int[OBJECT, :k] = np.arange(k)
    return OctreeBVH(
        centres, np.concatenate([spheres.radius, spheres.bone_radius]),
        np.concatenate([spheres.fixed, np.ones(g - m, dtype=bool)]),
        np.arange(g, dtype=np.int64), np.zeros(g, dtype=np.int64), object_first,
        np.arange(k) >= n_muscles, node_int, np.zeros((6, capacity)),
        np.full(capacity, -1, dtype=np.int64),
        np.zeros((2, 8 * (2 * max_depth + 2)), dtype=np.int64),
        np.array([k, 0, 0], dtype=np.int64), np.zeros(g), np.zeros((3, g)),
        np.full(g, -1, dtype=np.int64), np.zeros(g, dtype=np.int64), n_muscles, m,
        int(max_depth), int(min_primitives))


@njit(cache=True)
def _refit(u, centres, radius, perm, static, node_int, node_box, node_stamp, stamp):
    if node_stamp[u] == stamp or node_stamp[u] == STATIC:
        return
    for axis in range(3):
        node_box[axis, u] = np.inf
        node_box[3 + axis, u] = -np.inf
    for e in range(node_int[START, u], node_int[START, u] + node_int[COUNT, u]):
        g = perm[e]
        for axis in range(3):
            node_box[axis, u] = min(node_box[axis, u], centres[axis, g] - radius[g])
            node_box[3 + axis, u] = max(node_box[3 + axis, u], centres[axis, g] + radius[g])
    node_stamp[u] = STATIC if static[node_int[OBJECT, u]] else stamp


@njit(cache=True)
def _subdivide(u, centres, perm, scratch, node_int, node_box, node_stamp, state):
    """Split node ``u`` into the non-empty octants around its box's midpoint."""
    start = node_int[START, u]
    count = node_int[COUNT, u]
    mid = np.empty(3)
    for axis in range(3):
        mid[axis] = 0.5 * (node_box[axis, u] + node_box[3 + axis, u])
    tally = np.zeros(9, dtype=np.int64)
    for e in range(start, start + count):
        g = perm[e]
        octant = ((centres[0, g] > mid[0]) * 1 + (centres[1, g] > mid[1]) * 2
                  + (centres[2, g] > mid[2]) * 4)
        scratch[e] = octant
        tally[octant + 1] += 1
    for o in range(8):
        tally[o + 1] += tally[o]
    first = tally[:8].copy()
    moved = np.empty(count, dtype=np.int64)
    for e in range(start, start + count):
        moved[first[scratch[e]]] = perm[e]
        first[scratch[e]] += 1
    perm[start:start + count] = moved
    node_int[CHILD, u] = state[0]
    children = 0
    for o in range(8):
        if tally[o + 1] > tally[o]:
            c = state[0]
            node_int[START, c] = start + tally[o]
            node_int[COUNT, c] = tally[o + 1] - tally[o]
            node_int[CHILD, c] = -1
            node_int[N_CHILDREN, c] = 0
            node_int[DEPTH, c] = node_int[DEPTH, u] + 1
            node_int[OBJECT, c] = node_int[OBJECT, u]
            node_stamp[c] = -1
            state[0] += 1
            children += 1
    node_int[N_CHILDREN, u] = children


@njit(cache=True, inline="always")
def _keep_deepest(i, j, pen, nx, ny, nz, best_pen, best_dir, best_partner, touched, state):
    if best_partner[i] < 0:
        touched[state[2]] = i
        state[2] += 1
    if best_partner[i] < 0 or deeper(pen, j, best_pen[i], best_partner[i]):
        best_pen[i] = pen
        best_partner[i] = j
        best_dir[0, i] = nx
        best_dir[1, i] = ny
        best_dir[2, i] = nz


@njit(cache=True)
def _push_deepest(fixed, best_pen, best_dir, best_partner, touched, state, disp):
    """Apply every touched sphere's push for the object just tested and reset."""
    for t in range(state[2]):
        i = touched[t]
        share = push_share(fixed[i], not fixed[best_partner[i]]) * best_pen[i]
        for axis in range(3):
            disp[axis, i] += share * best_dir[axis, i]
        best_partner[i] = -1
        best_pen[i] = 0.0
    state[2] = 0


@njit(cache=True, inline="always")
def _splittable(u, node_int, max_depth, min_primitives):
    return node_int[DEPTH, u] < max_depth and node_int[COUNT, u] > min_primitives


@njit(cache=True, inline="always")
def _volume(u, node_box):
    return ((node_box[3, u] - node_box[0, u]) * (node_box[4, u] - node_box[1, u])
            * (node_box[5, u] - node_box[2, u]))


@njit(cache=True)
def _traverse(root_a, root_b, tree, collided, pairs, n_pairs):
    """Collide the trees of two objects: each sphere's deepest pair with the other object
    into ``tree.best_*`` (spheres listed in ``touched[:state[2]]``); returns (colliding pairs,
    deepest penetration mm of a pair that is not fixed on both sides). Records the pairs
    (sphere ids, lower first) in ``pairs`` while it has room."""
    (centres, radius, fixed, perm, scratch, _, static, node_int, node_box, node_stamp, stack,
     state, best_pen, best_dir, best_partner, touched, _, _, max_depth,
     min_primitives) = tree
    stamp = state[1]
    count = 0
    deepest = 0.0
    stack[0, 0] = root_a
    stack[1, 0] = root_b
    top = 1
    while top > 0:
        top -= 1
        u = stack[0, top]
        w = stack[1, top]
        _refit(u, centres, radius, perm, static, node_int, node_box, node_stamp, stamp)
        _refit(w, centres, radius, perm, static, node_int, node_box, node_stamp, stamp)
        apart = False
        for axis in range(3):
            if (node_box[axis, u] > node_box[3 + axis, w]
                    or node_box[axis, w] > node_box[3 + axis, u]):
                apart = True
        if apart:
            continue
        split_u = _splittable(u, node_int, max_depth, min_primitives)
        split_w = _splittable(w, node_int, max_depth, min_primitives)
        if not split_u and not split_w:
            for e in range(node_int[START, u], node_int[START, u] + node_int[COUNT, u]):
                i = perm[e]
                for f in range(node_int[START, w], node_int[START, w] + node_int[COUNT, w]):
                    j = perm[f]
                    pen, nx, ny, nz = sphere_push(centres[0, i], centres[1, i], centres[2, i],
                                                  radius[i], centres[0, j], centres[1, j],
                                                  centres[2, j], radius[j], i < j)
                    if pen > 0.0:
                        _keep_deepest(i, j, pen, nx, ny, nz, best_pen, best_dir, best_partner,
                                      touched, state)
                        _keep_deepest(j, i, pen, -nx, -ny, -nz, best_pen, best_dir,
                                      best_partner, touched, state)
                        collided[i] = 1
                        collided[j] = 1
                        if n_pairs[0] < pairs.shape[0]:
                            pairs[n_pairs[0], 0] = min(i, j)
                            pairs[n_pairs[0], 1] = max(i, j)
                        n_pairs[0] += 1
                        count += 1
                        if not (fixed[i] and fixed[j]):
                            deepest = max(deepest, pen)
            continue
        if split_u and (not split_w or _volume(u, node_box) >= _volume(w, node_box)):
            node, other, side = u, w, 0
        else:
            node, other, side = w, u, 1
        if node_int[CHILD, node] < 0:
            _subdivide(node, centres, perm, scratch, node_int, node_box, node_stamp, state)
        for c in range(node_int[CHILD, node], node_int[CHILD, node] + node_int[N_CHILDREN, node]):
            stack[side, top] = c
            stack[1 - side, top] = other
            top += 1
    return count, deepest


@njit(cache=True)
def bvh_pass(bones, tree, disp, collided, pairs, n_pairs):
    """Every muscle against every other muscle (``bones`` False) or every bone (True) of
    ``tree`` (:class:`OctreeBVH`).

    ``disp`` (3, G) mm and ``collided`` (G,) receive the response; returns (colliding pairs,
    deepest penetration mm); ``pairs`` (P, 2) receives the first colliding pairs, their count
    goes to ``n_pairs[0]``. Increment ``tree.state[1]`` whenever the muscle spheres have moved,
    so that their boxes are refitted.
    """
    count = 0
    deepest = 0.0
    n_muscles = tree.n_muscles
    n_objects = tree.object_first.shape[0] - 1
    for a in range(n_muscles):
        first_b = n_muscles if bones else a + 1
        last_b = n_objects if bones else n_muscles
        for b in range(first_b, last_b):
            if tree.node_int[COUNT, a] == 0 or tree.node_int[COUNT, b] == 0:
                continue
            c, d = _traverse(a, b, tree, collided, pairs, n_pairs)
            _push_deepest(tree.fixed, tree.best_pen, tree.best_dir, tree.best_partner,
                          tree.touched, tree.state, disp)
            count += c
            deepest = max(deepest, d)
    return count, deepest


def colliding_pairs(centres, bvh: OctreeBVH):
    """The colliding pairs found through the octree BVH, for muscle sphere centres (m, 3) mm.

    Returns ``(muscle_pairs (P, 2), bone_pairs (Q, 2))`` int64 sorted, in the same form as
    :func:`muscle_mss.core.contacts.spatial_hash.colliding_pairs` (bone spheres numbered from 0).
    """
    m = bvh.n_muscle_spheres
    bvh.centres[:, :m] = np.asarray(centres, dtype=np.float64).reshape(-1, 3).T
    bvh.state[1] += 1
    g = bvh.centres.shape[1]
    found = []
    for bones in (False, True):
        n_pairs = np.zeros(1, dtype=np.int64)
        bvh_pass(bones, bvh, np.zeros((3, g)), np.zeros(g, np.uint8), np.zeros((0, 2), np.int64),
                 n_pairs)
        pairs = np.zeros((int(n_pairs[0]), 2), dtype=np.int64)
        n_pairs[0] = 0
        bvh_pass(bones, bvh, np.zeros((3, g)), np.zeros(g, np.uint8), pairs, n_pairs)
        if bones:
            pairs[:, 1] -= m
        found.append(pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))])
    return found[0], found[1]
