"""The default collision structure: spatial hashing on a uniform grid, with candidate lists.

Spheres are hashed by their cell in a uniform grid (the key is the cell's linear index; the
spheres are counting-sorted by key and copied in that order, so a query reads each cell's spheres
contiguously; every cell also carries the bit set of its objects, so a query skips cells holding
only its own muscle). Sphere ``i`` visits the cells within ``r_i + r_max + skin`` of its centre
and lists the spheres of *other* objects within ``r_i + r_j + skin``. Between rebuilds only those
candidates are tested exactly, so the colliding pairs found are exactly those of a brute-force
test as long as the lists are complete:

* muscle-muscle lists are rebuilt when any muscle sphere has moved more than ``skin / 2`` since
  they were built (two spheres farther apart than ``r_i + r_j + skin`` cannot then have come
  closer than ``r_i + r_j``);
* bones do not move during a solve: their grid is built once, and each muscle sphere rebuilds
  its own bone list when *it* has moved more than ``skin / 2`` (spheres pressed against a bone
  jitter there every iteration; the others keep their lists).

Every loop over spheres is a ``prange`` in which sphere ``i`` only writes its own entries (its
candidates, its displacement): no atomics, and sums in a fixed order, so results do not depend
on the thread count. The exact test and the response rule are those of
:mod:`muscle_mss.core.mss`, shared with :mod:`muscle_mss.core.octree_bvh`.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from .mss import Spheres, deeper, push_share, sphere_push

# Skin of the candidate lists as a fraction of the mean muscle sphere radius: larger lists
# against fewer rebuilds.
SKIN_FRACTION = 1.5
# Slots per muscle sphere for its bone candidates at first; doubled when one needs more.
INITIAL_ROOM = 64


@njit(cache=True)
def grid_table(centres, radius, cell, objects):
    """Hash ``centres`` (3, n) mm into a uniform grid over their bounding box.

    The key of a sphere is its cell's linear index ``(ix * ny + iy) * nz + iz``; spheres are
    counting-sorted by key, and their centres, radii and objects copied in that order
    (``packed`` (5, n): x, y, z, radius, object), so that a query reads each cell's spheres
    contiguously. The cell grows (from ``cell`` mm) until the grid has at most 8 cells per
    sphere. Each cell also gets the bit set of its spheres' objects (:func:`_object_bit`), so a
    query skips cells holding only its own object's spheres. Returns ``(lower (3,), dims (3,)
    int64, cell, start (cells + 1,), items (n,), bits (cells,), packed)``; sphere ``items[e]``
    is the ``e``-th in key order.
    """
    n = centres.shape[1]
    lower = np.zeros(3)
    upper = np.zeros(3)
    for axis in range(3):
        if n:
            lower[axis] = centres[axis].min()
            upper[axis] = centres[axis].max()
    dims = np.ones(3, dtype=np.int64)
    while True:
        for axis in range(3):
            dims[axis] = int((upper[axis] - lower[axis]) / cell) + 1
        if dims[0] * dims[1] * dims[2] <= 8 * n + 64:
            break
        cell *= 1.26
    key = np.empty(n, dtype=np.int64)
    for s in range(n):
        ix = min(int((centres[0, s] - lower[0]) / cell), dims[0] - 1)
        iy = min(int((centres[1, s] - lower[1]) / cell), dims[1] - 1)
        iz = min(int((centres[2, s] - lower[2]) / cell), dims[2] - 1)
        key[s] = (ix * dims[1] + iy) * dims[2] + iz
    start = np.zeros(dims[0] * dims[1] * dims[2] + 1, dtype=np.int64)
    for s in range(n):
        start[key[s] + 1] += 1
    for c in range(start.shape[0] - 1):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    items = np.empty(n, dtype=np.int64)
    bits = np.zeros(start.shape[0] - 1, dtype=np.uint64)
    for s in range(n):
        items[fill[key[s]]] = s
        fill[key[s]] += 1
        bits[key[s]] |= _object_bit(objects[s])
    packed = np.empty((5, n))
    for e in range(n):
        for axis in range(3):
            packed[axis, e] = centres[axis, items[e]]
        packed[3, e] = radius[items[e]]
        packed[4, e] = objects[items[e]]
    return lower, dims, cell, start, items, bits, packed


@njit(cache=True, inline="always")
def _object_bit(obj):
    """Objects 0..62 have a bit of their own; all others share bit 63 (and are never skipped)."""
    return np.uint64(1) << np.uint64(min(obj, 63))


@njit(cache=True)
def _scan(i, query, q_radius, q_object, t_top, lower, dims, cell, start, items, bits, packed,
          skin, out, first, room):
    """Targets of another object within ``r_i + r_j + skin`` of query sphere ``i``, written in
    increasing index order to ``out[first:first + room]``; returns how many there are (more
    than ``room`` means they did not fit). ``t_top``: the largest target radius."""
    reach = q_radius[i] + t_top + skin
    x0 = max(int(np.floor((query[0, i] - reach - lower[0]) / cell)), 0)
    x1 = min(int(np.floor((query[0, i] + reach - lower[0]) / cell)), dims[0] - 1)
    y0 = max(int(np.floor((query[1, i] - reach - lower[1]) / cell)), 0)
    y1 = min(int(np.floor((query[1, i] + reach - lower[1]) / cell)), dims[1] - 1)
    z0 = max(int(np.floor((query[2, i] - reach - lower[2]) / cell)), 0)
    z1 = min(int(np.floor((query[2, i] + reach - lower[2]) / cell)), dims[2] - 1)
    found = 0
    own = _object_bit(q_object[i]) if q_object[i] < 63 else np.uint64(0)
    for ix in range(x0, x1 + 1):
        for iy in range(y0, y1 + 1):
            row = (ix * dims[1] + iy) * dims[2]
            for c in range(row + z0, row + z1 + 1):
                if bits[c] == 0 or bits[c] == own:
                    continue
                for e in range(start[c], start[c + 1]):
                    if packed[4, e] == q_object[i]:
                        continue
                    limit = q_radius[i] + packed[3, e] + skin
                    d2 = 0.0
                    for axis in range(3):
                        d2 += (query[axis, i] - packed[axis, e]) ** 2
                    if d2 < limit * limit:
                        j = items[e]
                        if found < room:
                            # insertion keeps the list sorted: a target object's spheres are then
                            # contiguous (spheres are numbered object by object)
                            f = first + found
                            while f > first and out[f - 1] > j:
                                out[f] = out[f - 1]
                                f -= 1
                            out[f] = j
                        found += 1
    return found


@njit(cache=True, parallel=True)
def candidate_lists(query, q_radius, q_object, table, skin):
    """For every query sphere, the target spheres of another object within
    ``r_i + r_j + skin`` mm: ``(begin (nq,), end (nq,), idx)``, sphere ``i``'s list being
    ``idx[begin[i]:end[i]]`` in increasing index order; ``table`` from :func:`grid_table` of
    the targets."""
    lower, dims, cell, start, items, bits, packed = table
    nq = query.shape[1]
    t_top = packed[3].max() if packed.shape[1] else 0.0
    counts = np.zeros(nq + 1, dtype=np.int64)
    none = np.empty(0, dtype=np.int64)
    for i in prange(nq):
        counts[i + 1] = _scan(i, query, q_radius, q_object, t_top, lower, dims, cell, start,
                              items, bits, packed, skin, none, 0, 0)
    for i in range(nq):
        counts[i + 1] += counts[i]
    idx = np.empty(counts[nq], dtype=np.int64)
    for i in prange(nq):
        _scan(i, query, q_radius, q_object, t_top, lower, dims, cell, start, items, bits, packed,
              skin, idx, counts[i], counts[i + 1] - counts[i])
    return counts[:-1].copy(), counts[1:].copy(), idx


@njit(cache=True, parallel=True)
def refresh_own_lists(query, q_radius, q_object, table, skin, built, begin, end, idx, room,
                      longest):
    """Rebuild the lists of the query spheres that moved more than ``skin / 2`` since their own
    list was built (exact when the targets do not move: the bones). Each sphere owns the
    slots ``idx[i * room:(i + 1) * room]``; ``built`` (3, nq) holds the positions at the last
    build. ``longest`` (nq,) work array. Returns the largest list length found (above
    ``room``: rebuild with more room)."""
    lower, dims, cell, start, items, bits, packed = table
    t_top = packed[3].max() if packed.shape[1] else 0.0
    for i in prange(query.shape[1]):
        longest[i] = 0
        d2 = 0.0
        for axis in range(3):
            d2 += (query[axis, i] - built[axis, i]) ** 2
        if d2 > 0.25 * skin * skin:
            found = _scan(i, query, q_radius, q_object, t_top, lower, dims, cell, start, items,
                          bits, packed, skin, idx, i * room, room)
            for axis in range(3):
                built[axis, i] = query[axis, i]
            begin[i] = i * room
            end[i] = i * room + min(found, room)
            longest[i] = found
    return longest.max() if query.shape[1] else 0


@njit(cache=True, parallel=True)
def list_contacts(centres, radius, fixed, begin, end, idx, t_centres, t_radius, t_object,
                  t_moves, same_set, disp, collided, pair_count, pair_pen):
    """Exact tests of every sphere against its candidates, and the response.

    Sphere ``i`` (centres (3, n) mm) adds to ``disp[:, i]``, per target object, its share of
    the penetration of its deepest pair with that object along the centre line
    (:mod:`muscle_mss.core.mss`), and sets ``collided[i]``. ``pair_count[i]``, ``pair_pen[i]``
    get its number of colliding pairs (each pair counted once: with ``same_set``, from its
    lower sphere) and their deepest penetration (mm). ``t_moves[j]``: target ``j`` is a free
    particle.
    """
    for i in prange(centres.shape[1]):
        count = 0
        deepest = 0.0
        best_pen = 0.0
        best = -1
        bx = by = bz = 0.0
        for e in range(begin[i], end[i] + 1):
            j = idx[e] if e < end[i] else -1
            if best >= 0 and (j < 0 or t_object[j] != t_object[best]):
                share = push_share(fixed[i], t_moves[best]) * best_pen
                disp[0, i] += share * bx
                disp[1, i] += share * by
                disp[2, i] += share * bz
                best = -1
                best_pen = 0.0
            if j < 0:
                break
            pen, nx, ny, nz = sphere_push(centres[0, i], centres[1, i], centres[2, i], radius[i],
                                          t_centres[0, j], t_centres[1, j], t_centres[2, j],
                                          t_radius[j], i < j or not same_set)
            if pen > 0.0:
                collided[i] = 1
                if deeper(pen, j, best_pen, best if best >= 0 else j + 1):
                    best_pen = pen
                    best = j
                    bx, by, bz = nx, ny, nz
                if j > i or not same_set:
                    count += 1
                    deepest = max(deepest, pen)
        pair_count[i] = count
        pair_pen[i] = deepest


@njit(cache=True)
def list_pairs(centres, radius, begin, end, idx, t_centres, t_radius, same_set):
    """(P, 2) int64: the colliding (query, target) pairs in the candidate lists, each once."""
    hits = np.empty((idx.shape[0], 2), dtype=np.int64)
    n = 0
    for i in range(centres.shape[1]):
        for e in range(begin[i], end[i]):
            j = idx[e]
            if same_set and j < i:
                continue
            pen, nx, ny, nz = sphere_push(centres[0, i], centres[1, i], centres[2, i], radius[i],
                                          t_centres[0, j], t_centres[1, j], t_centres[2, j],
                                          t_radius[j], i < j or not same_set)
            if pen > 0.0:
                hits[n, 0] = i
                hits[n, 1] = j
                n += 1
    return hits[:n].copy()


def skin_width(spheres: Spheres) -> float:
    """Skin of the candidate lists, mm (:data:`SKIN_FRACTION` of the mean muscle radius)."""
    return SKIN_FRACTION * float(spheres.radius.mean()) if spheres.count else 0.0


def bone_cell(spheres: Spheres, skin: float) -> float:
    """Cell size of the bone table, mm: the bone spheres' diameter."""
    mean_b = float(spheres.bone_radius.mean()) if len(spheres.bone_radius) else 0.0
    return max(2.0 * mean_b + skin, 1e-6)


def muscle_cell(spheres: Spheres, skin: float) -> float:
    """Cell size of the muscle table, mm: a typical muscle-muscle reach."""
    mean_m = float(spheres.radius.mean()) if spheres.count else 0.0
    return max(2.0 * mean_m + skin, 1e-6)


def colliding_pairs(centres, spheres: Spheres):
    """The colliding pairs found through the spatial hash, for muscle sphere centres (m, 3) mm.

    Returns ``(muscle_pairs (P, 2), bone_pairs (Q, 2))`` int64, sorted: muscle sphere pairs
    ``i < j`` of different muscles, and (muscle sphere, bone sphere) pairs.
    """
    query = np.ascontiguousarray(np.asarray(centres, dtype=np.float64).reshape(-1, 3).T)
    table = grid_table(query, spheres.radius, muscle_cell(spheres, 0.0), spheres.muscle)
    begin, end, idx = candidate_lists(query, spheres.radius, spheres.muscle, table, 0.0)
    muscle_pairs = list_pairs(query, spheres.radius, begin, end, idx, query, spheres.radius, True)
    table = grid_table(spheres.bone_centres, spheres.bone_radius, bone_cell(spheres, 0.0),
                       spheres.bone + spheres.n_muscles)
    begin, end, idx = candidate_lists(query, spheres.radius, spheres.muscle, table, 0.0)
    bone_pairs = list_pairs(query, spheres.radius, begin, end, idx, spheres.bone_centres,
                            spheres.bone_radius, False)
    return _sorted(muscle_pairs), _sorted(bone_pairs)


def _sorted(pairs):
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
