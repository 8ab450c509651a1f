"""Muscle-muscle contacts through candidate lists refreshed sphere by sphere (the spatial hash's
default for the muscles, :mod:`~muscle_mss.core.contacts.spatial_hash`).

Each muscle sphere keeps a list of the spheres of other muscles within ``r_i + r_j + skin`` of
it, both taken at their *reference* positions (where each stood when its own list was last
refreshed); a pair is tested from the list of the sphere refreshed last (:func:`owns_pair`), which
always holds it when the two are that close. A sphere refreshes its list when it has moved more
than ``skin / 2`` from its reference position; the others keep theirs. So any two spheres are at
most ``skin`` closer than at their reference positions, and a pair missing from its owner's
list cannot collide: the pairs found are exactly those of a brute-force test, while only the
spheres that moved (near tendon attachments, say) pay for a grid query. The grid of reference
positions is patched in place between rebuilds (:func:`~muscle_mss.core.contacts.spatial_hash.fill_grid`,
:func:`~muscle_mss.core.contacts.spatial_hash.move_in_grid`).
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from .collision_spheres import sphere_push
from .spatial_hash import (INITIAL_ROOM, cell_capacity, fill_grid, move_in_grid, owns_pair,
                           scan_grid, size_levels, sphere_contact)

# The muscle grid is rebuilt when a sphere lies this many cells outside its cell.
DRIFT_FRACTION = 0.25
# mm added to the reach of the refreshed muscle lists, so that rounding cannot drop a pair
# whose spheres each moved exactly half the skin
ROUNDING_GUARD = 1e-9


def muscle_lists(radius, room: int = INITIAL_ROOM) -> tuple:
    """The state of :func:`muscle_contacts` for the muscle spheres of radii ``radius`` (m,) mm,
    every list stale.

    ``(reference (3, m) mm, stamp (m,), clock (1,), queue (m,), count (m,), slot (m + 1,),
    idx int32, hit int32, hits (m,), grid_cell (1,), drift (1,), lower (3,), dims (3,), start,
    items (m,), bits, packed (5, m), tops (L,), key (m,), begin (m,), end (m,), partner)``:
    sphere ``i``'s list is ``idx[slot[i]:slot[i] + count[i]]`` (room up to ``slot[i + 1]``),
    built when it stood at ``reference[:, i]`` (refresh number ``stamp[i]``, the last being
    ``clock[0]``); the ``hits[i]`` colliding pairs it owns are listed at the same place in
    ``hit``; the grid of the reference positions as :func:`fill_grid` makes it (cell
    ``grid_cell[0]`` mm, size levels ``tops``), its spheres up to ``drift[0]`` mm outside
    their cells; the colliding partners of sphere ``i`` are ``partner[begin[i]:end[i]]``.
    """
    radius = np.asarray(radius, dtype=np.float64)
    count = len(radius)
    tops = size_levels(radius)
    keys = int(cell_capacity(count)) * len(tops)
    return (np.full((3, count), np.inf), np.zeros(count, np.int64), np.zeros(1, np.int64),
            np.zeros(count, np.int64), np.zeros(count, np.int64),
            np.arange(count + 1, dtype=np.int64) * room, np.zeros(count * room, np.int32),
            np.zeros(count * room, np.int32), np.zeros(count, np.int64), np.zeros(1),
            np.full(1, np.inf), np.zeros(3), np.ones(3, np.int64),
            np.zeros(keys + 1, np.int64), np.zeros(count, np.int64), np.zeros(keys, np.uint64),
            np.zeros((5, count)), tops, np.zeros(count, np.int64), np.zeros(count, np.int64),
            np.zeros(count, np.int64), np.zeros(count, np.int64))


@njit(cache=True)
def _stale_spheres(centres, reference, limit, stamp, clock, queue):
    """Spheres farther than ``limit`` mm from their reference position, into ``queue``; they
    get the current position as reference and a new refresh number. Returns how many."""
    stale = 0
    for i in range(centres.shape[1]):
        d2 = 0.0
        for axis in range(3):
            d2 += (centres[axis, i] - reference[axis, i]) ** 2
        if d2 > limit * limit:
            queue[stale] = i
            stale += 1
    if stale:
        clock[0] += 1
    for q in range(stale):
        i = queue[q]
        for axis in range(3):
            reference[axis, i] = centres[axis, i]
        stamp[i] = clock[0]
    return stale


@njit(cache=True, parallel=True)
def _refresh_lists(reference, radius, muscle, table, skin, pad, stamp, queue, stale, count,
                   slot, idx):
    """New lists for the spheres ``queue[:stale]`` from the grid ``table`` of the reference
    positions; returns how many did not fit their room (they come first in ``queue`` then)."""
    for q in prange(stale):
        i = queue[q]
        count[i] = scan_grid(i, reference, radius, muscle, table, skin + ROUNDING_GUARD, pad, idx,
                             slot[i], slot[i + 1] - slot[i], stamp, np.bool_(True))
    over = 0
    for q in range(stale):
        i = queue[q]
        if count[i] > slot[i + 1] - slot[i]:
            queue[over] = i
            over += 1
    return over


def _relaid(count, slot, idx):
    """``(slot, idx, hit)`` with room for twice each list (and a few more), the lists that fit
    their old room copied over (the others are rebuilt next). Rare (a list outgrew its room):
    NumPy, so that no run compiles it in the middle of a solve."""
    n = count.shape[0]
    grown = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(2 * count + 4, out=grown[1:])
    pool = np.zeros(grown[n], dtype=idx.dtype)
    kept = np.where(count <= np.diff(slot), count, 0)
    within = np.arange(kept.sum()) - np.repeat(np.cumsum(kept) - kept, kept)
    pool[np.repeat(grown[:-1], kept) + within] = idx[np.repeat(slot[:-1], kept) + within]
    return grown, pool, np.zeros(grown[n], dtype=idx.dtype)


@njit(cache=True, parallel=True)
def _test_and_respond(centres, radius, fixed, muscle, moves, stamp, slot, count, idx, hit, hits,
                      begin, end, partner, disp, collided, pair_count, pair_pen):
    """The exact tests of :func:`muscle_contacts`, each pair from its owner's list (sphere
    ``i``'s colliding partners to ``hit[slot[i]:slot[i] + hits[i]]``), then
    :func:`list_contacts` on those pairs: each sphere gets its colliding partners
    ``partner[begin[i]:end[i]]`` in increasing index order and the same response. The tests
    and the responses run in parallel, the partner lists are gathered serially (a few thousand
    pairs). Returns ``partner`` (grown when too short)."""
    for i in prange(centres.shape[1]):
        found = slot[i]
        for e in range(slot[i], slot[i] + count[i]):
            j = idx[e]
            if owns_pair(i, j, stamp):
                pen, nx, ny, nz = sphere_push(centres[0, i], centres[1, i], centres[2, i],
                                              radius[i], centres[0, j], centres[1, j],
                                              centres[2, j], radius[j], True)
                if pen > 0.0:
                    hit[found] = j
                    found += 1
        hits[i] = found - slot[i]
    n = hits.shape[0]
    total = 0
    for i in range(n):
        end[i] = hits[i]
    for i in range(n):
        for e in range(slot[i], slot[i] + hits[i]):
            end[hit[e]] += 1
        total += 2 * hits[i]
    if total > partner.shape[0]:
        partner = np.empty(2 * total, dtype=np.int64)
    total = 0
    for i in range(n):
        begin[i] = total
        total += end[i]
        end[i] = begin[i]
    for i in range(n):
        for e in range(slot[i], slot[i] + hits[i]):
            j = hit[e]
            partner[end[i]] = j
            end[i] += 1
            partner[end[j]] = i
            end[j] += 1
    for i in prange(n):
        pair_count[i] = 0
        pair_pen[i] = 0.0
        if end[i] > begin[i]:
            for f in range(begin[i] + 1, end[i]):
                j = partner[f]
                g = f
                while g > begin[i] and partner[g - 1] > j:
                    partner[g] = partner[g - 1]
                    g -= 1
                partner[g] = j
            sphere_contact(i, centres, radius, fixed, begin[i], end[i], partner, centres, radius,
                     muscle, moves, True, disp, collided, pair_count, pair_pen)
    return partner


def muscle_contacts(centres, radius, muscle, fixed, moves, skin, cell, lists, disp, collided,
                    pair_count, pair_pen):
    """Muscle-muscle collisions of one iteration with lists refreshed sphere by sphere.

    A sphere's list holds the spheres of other muscles within ``r_i + r_j + skin`` of it, both
    taken at their *reference* positions (where each stood when its own list was last
    refreshed); a pair is tested from the list of the sphere refreshed last (:func:`owns_pair`),
    which always holds it when the two are that close. A sphere refreshes its list when it has
    moved more than ``skin / 2`` from its reference position; the others keep theirs. So any
    two spheres are at most ``skin`` closer than at their reference positions, and a pair
    missing from its owner's list cannot collide: the pairs found are exactly those of a brute
    force test, while only the spheres that moved (near tendon attachments, say) pay for a
    grid query. The grid of reference positions is rebuilt in place (:func:`fill_grid`)
    whenever a list is refreshed.

    ``centres`` (3, m) mm, ``radius`` (m,) mm, ``muscle`` (m,), ``fixed`` (m,) bool, ``moves``
    (m,) bool (free), ``skin`` mm, ``cell`` grid cell mm (:func:`muscle_cell`), ``lists`` from
    :func:`muscle_lists`; ``disp``, ``collided``, ``pair_count``, ``pair_pen`` as
    :func:`list_contacts` fills them (the same response, bit for bit). Returns ``(spheres
    refreshed, lists)``: keep the returned lists (lists that outgrew their room got more).
    Python around the kernels, called once an iteration: compiled, it compiled its kernels a
    second time (docs/performance.md, "The first run").
    """
    (reference, stamp, clock, queue, count, slot, idx, hit, hits, grid_cell, drift, lower, dims,
     start, items, bits, packed, tops, key, begin, end, partner) = lists
    n = centres.shape[1]
    if n == 0:
        return 0, lists
    stale = _stale_spheres(centres, reference, 0.5 * skin, stamp, clock, queue)
    if stale:
        if not drift[0] <= DRIFT_FRACTION * grid_cell[0]:
            grid_cell[0] = fill_grid(reference, radius, muscle, tops, cell, lower, dims, start,
                                      items, bits, packed, key)
            drift[0] = 0.0
        else:
            move_in_grid(reference, queue, stale, key, start, items, packed, lower, dims,
                          grid_cell[0], tops.shape[0], drift)
        table = (lower, dims, grid_cell[0], start, items, bits, packed, tops)
        over = _refresh_lists(reference, radius, muscle, table, skin, drift[0], stamp, queue,
                              stale, count, slot, idx)
        if over:
            slot, idx, hit = _relaid(count, slot, idx)
            _refresh_lists(reference, radius, muscle, table, skin, drift[0], stamp, queue,
                           over, count, slot, idx)
    partner = _test_and_respond(centres, radius, fixed, muscle, moves, stamp, slot, count, idx,
                                hit, hits, begin, end, partner, disp, collided, pair_count,
                                pair_pen)
    return stale, (reference, stamp, clock, queue, count, slot, idx, hit, hits, grid_cell,
                   drift, lower, dims, start, items, bits, packed, tops, key, begin, end,
                   partner)
