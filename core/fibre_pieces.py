"""Fibres exported in pieces: polylines that chain end to end are joined into fibres.

Some exporters write each fibre as several polylines, down to one two-point segment per
fibre step (16 fibres of 12 points as 176 segments). Read as they are, each segment would be a
fibre of its own: a fibre strain of 1.6 and arc/chord 2.3 from a scene that is right. A block
whose polylines share end points (within :data:`JOIN_TOLERANCE` of their median length) is
therefore joined: the polylines that meet two at a point form one fibre, in any order in the
file and either direction; each fibre runs the way most of its pieces run, and the fibres are
in the order of their first piece in the file, so that a fibre split in order gives back its
own points. Fibres that share only an end (a fan meeting at its tendon) are not pieces and are
left alone when no polyline needs joining; a point where three or more polylines meet while
others join (a branching fibre), or pieces that close into a loop, cannot be told apart and are
refused, naming the block and the count.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .errors import MuscleMSSError

JOIN_TOLERANCE = 1e-6
"""Two polyline ends closer than this fraction of the block's median polyline length are one
point. A piece's end and the next one's start are the same point written twice (equal in the
file, float32 or not); the demo scenes' fibres converge on their tendons to 0.2 mm apart, which
1e-3 of a 200 mm fibre would take for one point."""


def _ends_graph(points, offsets):
    """``(node (2F,) of each polyline's first then last point, degree (nodes,))``: the
    polylines' end points merged within the tolerance."""
    count = len(offsets) - 1
    ends = np.concatenate([points[offsets[:-1]], points[offsets[1:] - 1]])
    step = np.linalg.norm(np.diff(points, axis=0), axis=1)
    step[offsets[1:-1] - 1] = 0.0           # no step from one polyline into the next
    lengths = np.add.reduceat(step, offsets[:-1]) if len(step) else np.zeros(count)
    lengths[np.diff(offsets) < 2] = 0.0
    tolerance = JOIN_TOLERANCE * float(np.median(lengths))
    pairs = cKDTree(ends).query_pairs(tolerance, output_type="ndarray") if tolerance > 0 \
        else np.zeros((0, 2), dtype=np.int64)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                       shape=(2 * count, 2 * count))
    node = connected_components(graph, directed=False)[1]
    return node, np.bincount(node)


def joined_fibres(points, offsets, grid=None, where: str = "fibres"):
    """``(points, offsets, grid, joined)``: the polylines of one block (``points`` (v, 3) mm,
    ``offsets`` (P + 1,), ``grid`` (P, 2) or None) with those that chain end to end joined
    into fibres (see the module docstring), and the number of polylines joined (0: the input
    itself is returned). A joined fibre's ``grid`` is its pieces' cell, which they must share.
    Raises :class:`MuscleMSSError` naming ``where`` for a branching point, a loop, or pieces of
    one fibre in different grid cells."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    offsets = np.asarray(offsets, dtype=np.int64)
    count = len(offsets) - 1
    if count < 2 or (np.diff(offsets) < 2).any() or not np.isfinite(points).all() or (
            grid is not None and np.shape(grid) != (count, 2)):
        return points, offsets, grid, 0         # fibre_problems names these
    node, degree = _ends_graph(points, offsets)
    if not (degree == 2).any():
        return points, offsets, grid, 0
    branching = np.flatnonzero(degree > 2)
    if len(branching):
        at = points[np.concatenate([offsets[:-1], offsets[1:] - 1])][
            np.flatnonzero(node == branching[0])[0]]
        raise MuscleMSSError(
            f"{where}: its {count} polylines chain end to end, but {int(degree[branching[0]])} "
            f"of them meet at one point ({at[0]:.1f}, {at[1]:.1f}, {at[2]:.1f}) mm"
            + (f" ({len(branching)} such points)" if len(branching) > 1 else "")
            + ", so which piece continues which is ambiguous: a fibre cannot branch; write "
            "each fibre as one polyline from origin to insertion")
    first, last = node[:count], node[count:]
    # each node's (at most two) polyline ends, 2 p for polyline p's first point, 2 p + 1 its last
    owner = np.full((len(degree), 2), -1, dtype=np.int64)
    for p in range(count):
        for side, n in ((0, first[p]), (1, last[p])):
            owner[n, 0 if owner[n, 0] < 0 else 1] = 2 * p + side
    used = np.zeros(count, dtype=bool)
    chains = []
    for n in np.flatnonzero(degree == 1):
        if used[owner[n, 0] // 2]:
            continue                             # the other end of a chain already walked
        chain, previous = [], -1
        while True:                              # from one free end to the other
            ends = [e for e in owner[n] if e >= 0 and e // 2 != previous]
            if not ends or used[ends[0] // 2]:
                break
            p, backwards = ends[0] // 2, bool(ends[0] % 2)
            used[p] = True
            chain.append((p, backwards))
            previous = p
            n = first[p] if backwards else last[p]
        forward = sum(not b for _, b in chain)
        if 2 * forward < len(chain) or (2 * forward == len(chain) and min(chain)[1]):
            chain = [(p, not b) for p, b in reversed(chain)]
        chains.append(chain)
    if not used.all():
        raise MuscleMSSError(
            f"{where}: its {count} polylines chain end to end, but {int((~used).sum())} of them "
            "close into a loop: a fibre runs from origin to insertion; write each fibre as one "
            "polyline")
    chains.sort(key=min)
    pieces, sizes, cells = [], [], []
    for k, chain in enumerate(chains):
        parts = [points[offsets[p]:offsets[p + 1]][::-1 if b else 1] for p, b in chain]
        fibre = np.concatenate([parts[0]] + [part[1:] for part in parts[1:]])
        pieces.append(fibre)
        sizes.append(len(fibre))
        if grid is not None:
            members = np.asarray(grid)[[p for p, _ in chain]]
            if (members != members[0]).any():
                raise MuscleMSSError(
                    f"{where}: the {len(chain)} polylines joined into fibre {k} lie in "
                    f"different fibre_grid cells ({len(np.unique(members, axis=0))}); the "
                    "pieces of one fibre share its cell")
            cells.append(members[0])
    joined_offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    joined_grid = None if grid is None else np.asarray(cells).astype(np.asarray(grid).dtype)
    return np.concatenate(pieces), joined_offsets, joined_grid, count


def joined_warning(where: str, pieces: int, fibres: int) -> str:
    """The sentence of a block whose ``pieces`` polylines were joined into ``fibres``."""
    return (f"{where}: {pieces} polylines joined end to end into {fibres} fibres (each fibre "
            "was written in pieces, e.g. as two-point segments); a fibre is one polyline from "
            "origin to insertion, and the input is unchanged")
