"""The default collision structure: spatial hashing on a uniform grid, with candidate lists.

Spheres are hashed by their cell in a uniform grid (the key is the cell's linear index and the
sphere's size level; the spheres are counting-sorted by key and copied in that order, so a
query reads each cell's spheres contiguously; every key also carries the bit set of its
objects, so a query skips cells holding only its own muscle). Radii vary tenfold, so a cell's
spheres are split into size levels (:func:`size_levels`), and a query looks for the spheres of
each level only within ``r_i + r_level + skin`` of its centre, not as far as the largest sphere
reaches. A sphere lists the spheres of *other* objects within ``r_i + r_j + skin``; between
refreshes only those candidates are tested exactly, so the colliding pairs found are exactly
those of a brute-force test as long as the lists are complete:

* muscle-muscle (:func:`~muscle_mss.core.contacts.sphere_lists.muscle_contacts`): each sphere refreshes its own list when it has
  moved more than ``skin / 2`` from where its list was built (its reference position), and a
  pair is tested from the list refreshed last; spheres that jitter near tendon attachments pay
  for their own queries while the others keep their lists. The grid of reference positions is
  patched in place between rebuilds. (:func:`candidate_lists` still builds all lists at once,
  for :func:`colliding_pairs`.)
* bones do not move during a solve: their grid is built once, and each muscle sphere rebuilds
  its own bone list when *it* has moved more than ``skin / 2`` (:func:`own_list_contacts`).

Every parallel loop over spheres is a ``prange`` in which sphere ``i`` only writes its own
entries (its candidates, its displacement): no atomics, and sums in a fixed order, so results
do not depend on the thread count. Small bookkeeping passes run serially: waking the second
thread costs more than they do on a busy machine. The exact test and the response rule are
those of :mod:`muscle_mss.core.mss`, shared with :mod:`muscle_mss.core.contacts.octree_bvh`.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .collision_spheres import Spheres, deeper, push_share, sphere_push

# Skin of the candidate lists as a fraction of the mean muscle sphere radius: longer lists
# against more refreshes. Lists rebuilt all at once whenever any sphere moved (candidate_lists)
# need the wide skin (N = 20: 32 rebuilds at 1.5, 499 at 0.75); lists refreshed sphere by sphere
# (muscle_contacts, own_list_contacts) are fastest near 0.75 (N = 80: muscle CD 1.3-1.6 s
# against 1.8-2.2 s at 1.5).
SKIN_FRACTION = 1.5
PER_SPHERE_SKIN_FRACTION = 0.75
# Radius quantiles that split the spheres of a grid into size levels (:func:`size_levels`).
LEVEL_QUANTILES = (0.5, 0.9)
# Slots per muscle sphere for its candidates at first; doubled when one needs more.
INITIAL_ROOM = 64


def grid_table(centres, radius, cell, objects):
    """Hash ``centres`` (3, n) mm into a uniform grid over their bounding box.

    The key of a sphere is its cell's linear index ``(ix * ny + iy) * nz + iz``; spheres are
    counting-sorted by key, and their centres, radii and objects copied in that order
    (``packed`` (5, n): x, y, z, radius, object), so that a query reads each cell's spheres
    contiguously. The cell grows (from ``cell`` mm) until the grid has at most 8 cells per
    sphere. Each cell also gets the bit set of its spheres' objects (:func:`_object_bit`), so a
    query skips cells holding only its own object's spheres. Returns ``(lower (3,), dims (3,)
    int64, cell, start (cells + 1,), items (n,), bits (cells,), packed, tops (1,))``; sphere
    ``items[e]`` is the ``e``-th in key order; ``tops`` the size levels
    (:func:`size_levels`, :func:`fill_grid`). Built once per solve: Python around
    :func:`fill_grid` (compiled, it took 1.5 s of a first run's compile and its quantiles 4 s
    more).
    """
    n = centres.shape[1]
    tops = size_levels(radius)
    capacity = (8 * n + 64) * len(tops)     # cell_capacity(n) keys per level
    lower = np.zeros(3)
    dims = np.ones(3, dtype=np.int64)
    start = np.zeros(capacity + 1, dtype=np.int64)
    items = np.empty(n, dtype=np.int64)
    bits = np.zeros(capacity, dtype=np.uint64)
    packed = np.empty((5, n))
    key = np.empty(n, dtype=np.int64)
    cell = fill_grid(centres, radius, objects, tops, float(cell), lower, dims, start, items,
                     bits, packed, key)
    keys = int(dims[0] * dims[1] * dims[2]) * len(tops)
    return lower, dims, cell, start[:keys + 1], items, bits[:keys], packed, tops


def size_levels(radius) -> np.ndarray:
    """Size levels of a grid (:func:`fill_grid`): the radii at :data:`LEVEL_QUANTILES` and the
    largest radius, ascending and distinct, mm ((1,) zero for no spheres). Muscle sphere radii
    vary tenfold (tendon ends to bellies): without levels every query would reach as far as
    the largest sphere. The quantiles interpolate between the two nearest ranks as Numba's
    ``np.quantile`` does (NumPy's own differs from it in the last bit)."""
    radius = np.asarray(radius, dtype=np.float64)
    n = radius.shape[0]
    if n == 0:
        return np.zeros(1)
    ordered = np.sort(radius)
    tops = np.empty(len(LEVEL_QUANTILES) + 1)
    for level, fraction in enumerate(LEVEL_QUANTILES):
        rank = 1 + (n - 1) * ((fraction * 100.0) / 100.0)
        below = math.floor(rank)
        if n == 1:
            tops[level] = ordered[0]
        else:
            part = rank - below
            tops[level] = ordered[below - 1] * (1 - part) + ordered[min(below, n - 1)] * part
    tops[-1] = ordered[-1]
    return np.unique(tops)


@njit(cache=True, inline="always")
def cell_capacity(n):
    """Most cells a grid over ``n`` spheres gets (8 per sphere, and a few for tiny sets)."""
    return 8 * n + 64


@njit(cache=True)
def fill_grid(centres, radius, objects, tops, cell, lower, dims, start, items, bits, packed,
               key):
    """:func:`grid_table` into given arrays, with size levels: no allocation, so a solve can
    rebuild its grid every iteration (serial: a counting sort of a few 10k spheres takes less
    than waking a second thread on a busy machine).

    ``tops`` (L,) ascending: a sphere is in the first level ``l`` with ``radius <= tops[l]``
    (the last level takes the rest; ``tops[-1]`` must be the largest radius). Its key is
    ``cell * L + l``: a cell's spheres are sorted by level, so a query looks for the spheres of
    each level only as far as they can reach (:func:`scan_grid`). ``start`` and ``bits`` are per
    key (at least ``L *`` :func:`cell_capacity` ``+ 1`` / ``+ 0`` entries); ``key`` (n,)
    receives each sphere's key. Non-finite coordinates go to the border cells (they collide
    with nothing). Returns the cell size used, mm."""
    n = centres.shape[1]
    levels = tops.shape[0]
    upper = np.zeros(3)
    for axis in range(3):
        lo = np.inf
        hi = -np.inf
        for s in range(n):
            value = centres[axis, s]
            if np.isfinite(value):
                lo = min(lo, value)
                hi = max(hi, value)
        lower[axis] = lo if lo <= hi else 0.0
        upper[axis] = hi if lo <= hi else 0.0
    while True:
        # the cell counts are compared as floats, clamped before the int conversion: spheres
        # spread over 1e8 mm must grow the cell, not overflow the cell count
        cells = 1.0
        for axis in range(3):
            cells *= min((upper[axis] - lower[axis]) / cell, 1e12) + 1.0
        if cells <= cell_capacity(n):
            break
        cell *= 1.26
    for axis in range(3):
        dims[axis] = int((upper[axis] - lower[axis]) / cell) + 1
    keys = dims[0] * dims[1] * dims[2] * levels
    for s in range(n):
        level = 0
        while level < levels - 1 and radius[s] > tops[level]:
            level += 1
        key[s] = ((_cell_of(centres[0, s], lower[0], cell, dims[0]) * dims[1]
                   + _cell_of(centres[1, s], lower[1], cell, dims[1])) * dims[2]
                  + _cell_of(centres[2, s], lower[2], cell, dims[2])) * levels + level
    for k in range(keys):
        start[k + 1] = 0
        bits[k] = 0
    start[0] = 0
    for s in range(n):
        start[key[s] + 1] += 1
    for k in range(keys):
        start[k + 1] += start[k]
    # the fill pointers run in the (then shifted back) start array itself
    for s in range(n):
        items[start[key[s]]] = s
        start[key[s]] += 1
        bits[key[s]] |= _object_bit(objects[s])
    for k in range(keys, 0, -1):
        start[k] = start[k - 1]
    start[0] = 0
    for e in range(n):
        for axis in range(3):
            packed[axis, e] = centres[axis, items[e]]
        packed[3, e] = radius[items[e]]
        packed[4, e] = objects[items[e]]
    return cell


@njit(cache=True)
def move_in_grid(reference, queue, stale, key, start, items, packed, lower, dims, cell,
                  levels, drift):
    """Give the spheres ``queue[:stale]`` their new reference positions in the grid without
    rebuilding it: they stay in their cells, and ``drift[0]`` keeps the farthest any sphere now
    lies outside its cell (mm; queries reach that much farther)."""
    for q in range(stale):
        j = queue[q]
        k = key[j]
        for e in range(start[k], start[k + 1]):
            if items[e] == j:
                for axis in range(3):
                    packed[axis, e] = reference[axis, j]
                break
        c = k // levels
        index = (c // (dims[1] * dims[2]), (c // dims[2]) % dims[1], c % dims[2])
        d2 = 0.0
        for axis in range(3):
            lo = lower[axis] + index[axis] * cell
            out = max(lo - reference[axis, j], reference[axis, j] - lo - cell, 0.0)
            d2 += out * out
        drift[0] = max(drift[0], np.sqrt(d2))


@njit(cache=True, inline="always")
def _cell_of(value, lower, cell, dim):
    """Grid index of a coordinate, clamped to ``[0, dim)``; NaN goes to 0."""
    t = (value - lower) / cell
    if not t >= 0.0:
        return 0
    if t >= dim - 1:
        return dim - 1
    return int(t)


@njit(cache=True, inline="always")
def _cell_span(value, reach, lower, cell, dim):
    """Grid indices ``(first, last)`` of the cells within ``reach`` of a coordinate, clamped to
    ``[0, dim)`` as floats before the int conversion (a coordinate far outside the grid or not
    finite gives an empty span, never an index out of range)."""
    lo = np.floor((value - reach - lower) / cell)
    hi = np.floor((value + reach - lower) / cell)
    if not (lo <= hi and hi >= 0.0 and lo < dim):
        return 1, 0
    return int(max(lo, 0.0)), int(min(hi, dim - 1.0))


@njit(cache=True, inline="always")
def _object_bit(obj):
    """Objects 0..62 have a bit of their own; all others share bit 63 (and are never skipped)."""
    return np.uint64(1) << np.uint64(min(obj, 63))


@njit(cache=True, inline="always")
def owns_pair(i, j, stamp):
    """Whether the pair (i, j) of muscle spheres is tested from ``i``'s list: the list refreshed
    last (``stamp``: refresh number of each list; ties, lists refreshed together: the lower
    index). That list was built from the other sphere's current reference position."""
    return stamp[i] > stamp[j] or (stamp[i] == stamp[j] and i < j)


@njit(cache=True)
def scan_grid(i, query, q_radius, q_object, table, skin, pad, out, first, room, stamp, shared):
    """Targets of another object within ``r_i + r_j + skin`` of query sphere ``i``, written in
    increasing index order to ``out[first:first + room]``; returns how many there are (more
    than ``room`` means they did not fit). ``table`` as :func:`grid_table`'s (size levels as
    :func:`fill_grid`); ``pad`` mm: how far a target may lie outside its cell. With
    ``shared`` (queries and targets the same spheres, lists owned as :func:`owns_pair` says) only
    the targets ``i`` owns are listed, in cell order."""
    lower, dims, cell, start, items, bits, packed, tops = table
    levels = tops.shape[0]
    found = 0
    own = _object_bit(q_object[i]) if q_object[i] < 63 else np.uint64(0)
    for level in range(levels):
        reach = q_radius[i] + tops[level] + skin + pad
        x0, x1 = _cell_span(query[0, i], reach, lower[0], cell, dims[0])
        y0, y1 = _cell_span(query[1, i], reach, lower[1], cell, dims[1])
        z0, z1 = _cell_span(query[2, i], reach, lower[2], cell, dims[2])
        for ix in range(x0, x1 + 1):
            for iy in range(y0, y1 + 1):
                row = (ix * dims[1] + iy) * dims[2]
                for c in range(row + z0, row + z1 + 1):
                    k = c * levels + level
                    if bits[k] == 0 or bits[k] == own:
                        continue
                    for e in range(start[k], start[k + 1]):
                        if packed[4, e] == q_object[i]:
                            continue
                        limit = q_radius[i] + packed[3, e] + skin
                        d2 = 0.0
                        for axis in range(3):
                            d2 += (query[axis, i] - packed[axis, e]) ** 2
                        if d2 < limit * limit:
                            j = items[e]
                            if shared:
                                if not owns_pair(i, j, stamp):
                                    continue
                                if found < room:
                                    out[first + found] = j
                            elif found < room:
                                # insertion keeps the list sorted: a target object's spheres
                                # are then contiguous (spheres are numbered object by object)
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
    ``idx[begin[i]:end[i]]`` in increasing index order (the lists need not be adjacent in
    ``idx``); ``table`` from :func:`grid_table` of the targets; ``idx`` int32, as the sphere
    lists' (one type for :func:`scan_grid`). One scan of the grid when every list fits in
    :data:`INITIAL_ROOM` slots (each sphere writes its own; half the time of counting first),
    else a second scan into lists sized by the first's counts."""
    nq = query.shape[1]
    none = np.empty(0, dtype=np.int64)
    found = np.empty(nq, dtype=np.int64)
    idx = np.empty(nq * INITIAL_ROOM, dtype=np.int32)
    for i in prange(nq):
        found[i] = scan_grid(np.int64(i), query, q_radius, q_object, table, skin, 0.0, idx,
                             np.int64(i * INITIAL_ROOM), np.int64(INITIAL_ROOM), none,
                             np.bool_(False))
    begin = np.empty(nq, dtype=np.int64)
    most = 0
    for i in range(nq):
        most = max(most, found[i])
    if most <= INITIAL_ROOM:
        for i in range(nq):
            begin[i] = i * INITIAL_ROOM
        return begin, begin + found, idx
    total = 0
    for i in range(nq):
        begin[i] = total
        total += found[i]
    idx = np.empty(total, dtype=np.int32)
    for i in prange(nq):
        scan_grid(np.int64(i), query, q_radius, q_object, table, skin, 0.0, idx, begin[i],
                  found[i], none, np.bool_(False))
    return begin, begin + found, idx


@njit(cache=True, parallel=True)
def _own_list_contacts(query, q_radius, fixed, q_object, table, skin, built, begin, end, idx,
                       room, longest, pending, retry, t_centres, t_radius, t_object, t_moves,
                       disp, collided, pair_count, pair_pen):
    """Collisions of the query spheres with targets that do not move (the bones), through
    lists each sphere keeps on its own, in one pass over the spheres: a sphere that moved more
    than ``skin / 2`` since its list was built rebuilds it (exact, the targets being still),
    then is tested against it as :func:`list_contacts` does (same response, bit for bit).

    Sphere ``i`` owns the slots ``idx[i * room:(i + 1) * room]``; ``built`` (3, nq) holds the
    positions at its last build (inf: build now); ``longest`` (nq,) receives each rebuilt list's
    length. A sphere whose list does not fit its room is left untested with ``pending[i]`` set:
    the caller then grows ``room`` (and ``idx``), sets ``built`` to inf and calls again with
    ``retry``, which rebuilds every list and tests only the pending spheres. Returns the
    longest list found (above ``room``: call again)."""
    for k in prange(query.shape[1]):
        i = np.int64(k)   # one type for the index in and outside the parallel loop's body
        if retry and not pending[i]:
            continue
        longest[i] = 0
        d2 = 0.0
        for axis in range(3):
            d2 += (query[axis, i] - built[axis, i]) ** 2
        if d2 > 0.25 * skin * skin:
            found = scan_grid(i, query, q_radius, q_object, table, skin, 0.0, idx, i * room,
                              room, begin, np.bool_(False))
            for axis in range(3):
                built[axis, i] = query[axis, i]
            begin[i] = i * room
            end[i] = i * room + min(found, room)
            longest[i] = found
        pending[i] = longest[i] > room
        if pending[i]:
            pair_count[i] = 0
            pair_pen[i] = 0.0
        else:
            sphere_contact(i, query, q_radius, fixed, begin[i], end[i], idx, t_centres, t_radius,
                     t_object, t_moves, False, disp, collided, pair_count, pair_pen)
    return longest.max() if query.shape[1] else 0


@njit(cache=True)
def own_list_contacts(spheres, hashed, table, begin, end, idx, room, retry):
    """Collisions of the muscle spheres of ``spheres``
    (:class:`~muscle_mss.core.contacts.sphere_contacts.SphereState`) with the bone spheres of ``hashed``
    (:class:`~muscle_mss.core.contacts.sphere_contacts.HashState`) through the lists each sphere keeps on its own
    (:func:`_own_list_contacts`, whose arguments are the tuples' arrays: Numba's parallel loops
    lost writes to arrays taken out of a tuple), from the bones' grid ``table``. Returns the
    longest list found (above ``room``: call again with ``retry``)."""
    return _own_list_contacts(
        spheres.centres, spheres.radius, spheres.fixed, spheres.muscle, table, hashed.skin,
        hashed.mb_built, begin, end, idx, room, hashed.longest, hashed.pending, retry,
        hashed.bone_centres, hashed.bone_radius, hashed.bone_object, hashed.bone_moves,
        spheres.disp, spheres.collided, spheres.pair_count, spheres.pair_pen)


@njit(cache=True, parallel=True)
def list_contacts(centres, radius, fixed, begin, end, idx, t_centres, t_radius, t_object,
                  t_moves, same_set, disp, collided, pair_count, pair_pen):
    """Exact tests of every sphere against its candidates, and the response.

    Sphere ``i`` (centres (3, n) mm) adds to ``disp[:, i]``, per target object, its share of
    the penetration of its deepest pair with that object along the centre line
    (:mod:`muscle_mss.core.mss`), and sets ``collided[i]``. ``pair_count[i]``, ``pair_pen[i]``
    get its number of colliding pairs (each pair counted once: with ``same_set``, from its
    lower sphere) and the deepest penetration (mm) of those a response can resolve (not fixed
    on both sides: a tendon attachment sits inside its bone for good). ``t_moves[j]``: target
    ``j`` is a free
    particle.
    """
    for i in prange(centres.shape[1]):
        sphere_contact(i, centres, radius, fixed, begin[i], end[i], idx, t_centres, t_radius,
                 t_object, t_moves, same_set, disp, collided, pair_count, pair_pen)


@njit(cache=True, inline="always")
def sphere_contact(i, centres, radius, fixed, first, last, idx, t_centres, t_radius, t_object,
             t_moves, same_set, disp, collided, pair_count, pair_pen):
    """:func:`list_contacts` for sphere ``i`` and its candidates ``idx[first:last]``."""
    count = 0
    deepest = 0.0
    best_pen = 0.0
    best = -1
    bx = by = bz = 0.0
    for e in range(first, last + 1):
        j = idx[e] if e < last else -1
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
                if not fixed[i] or t_moves[j]:
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


def skin_width(spheres: Spheres, per_sphere: bool = False) -> float:
    """Skin of the candidate lists, mm: :data:`SKIN_FRACTION` of the mean muscle radius, or
    :data:`PER_SPHERE_SKIN_FRACTION` for lists that every sphere refreshes on its own."""
    fraction = PER_SPHERE_SKIN_FRACTION if per_sphere else SKIN_FRACTION
    return fraction * float(spheres.radius.mean()) if spheres.count else 0.0


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
