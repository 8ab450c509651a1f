"""Segmented and exported surfaces made into scene surfaces (DESIGN §4, §7 "Importers", §8).

Surfaces from 3D Slicer, ITK-SNAP or an OpenSim model's mesh files break the scene's rules in
the usual ways: each triangle with its own three points (STL), neighbours running their shared
edge the same way, the whole surface inside out, small holes, specks of segmentation beside the
muscle, 100 000 triangles where the cage follows a few thousand. :func:`clean_surface` repairs
what can be repaired without guessing (merge, drop degenerate triangles, orient consistently and
outward, fill small holes) and refuses the rest naming it (non-manifold edges, large holes, two
large pieces of one muscle); :func:`split_long_edges` and :func:`principal_length` set the
density the MVC cage can follow (the decimation itself is VTK's, in
``muscle_mss.filters.mesh_files``). Arrays only: points (n, 3) float64 mm, triangles (m, 3)
int64.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components
from scipy.spatial import cKDTree
from scipy.spatial.distance import pdist

from .errors import MuscleMSSError
from .mesh_checks import surface_problems

MERGE_TOLERANCE = 1e-6
"""Points closer than this fraction of the surface's bounding-box diagonal are one point: STL
stores every triangle with its own copies of its corners, and exporters round coordinates,
so the copies agree to about 1e-7 of the size (float32); real neighbours of a segmentation lie
1e-3 of the size apart or more."""

MAX_HOLE_SPAN_MM = 10.0
"""Holes whose boundary spans (largest distance between two of its points) at most this are
filled (mm), larger ones refused. A hole of a few millimetres is a defect of the export (a
voxel gap, a dropped triangle); the demo's muscles are 20-60 mm thick, so a flat patch over a
10 mm hole misses a cap of well under 1 % of a muscle's volume. A larger opening is usually
a muscle cut off by the image's border or a lost end: filling it would invent the missing
shape, so the user closes it in the segmentation tool instead."""

SMALL_PIECE_FRACTION = 0.01
"""A separate piece of a muscle file with less than this fraction of its largest piece's
volume is a segmentation speck and dropped (said in the summary); a larger second piece is
refused (a muscle is one closed surface)."""

MAX_MUSCLE_TRIANGLES = 4000
"""Muscles with more triangles are decimated to this many. The demo muscles the solver is
tuned and measured on have 2176 triangles (864 in the small demo), and the cage's MVC weights
cost (vertices x cage particles) in time and memory at the first time point: 4000 triangles
(2000 vertices) keep a segmentation's shape (its 0.5-1 mm voxel steps are below the cage's
resolution anyway) at about twice the demo's cost; a 100 000-triangle export would be 50
times."""

MAX_EDGE_FRACTION = 0.05
"""Edges longer than this fraction of the muscle's length (:func:`principal_length`) are split.
At the default 20 particles per fibre the cage's rings lie 1/19 = 0.053 of the length apart:
an edge longer than that spans two rings and cannot bend with the cage (the surface would cut
through the bend). The demo muscles' edges average 0.022-0.036 of their length; their longest,
at the tapered tips, reach 0.04-0.13."""

METRES_BELOW = 5.0
"""``--muscle-units auto``: a surface whose bounding box's largest side is below this is in
metres (OpenSim's unit), else millimetres. No muscle is 5 mm long or 5 m long, so the two
cannot be confused."""


@dataclass
class Cleaning:
    """What :func:`clean_surface` changed: points merged into others, triangles dropped
    (degenerate or repeated), triangles flipped (to agree with their neighbours or to face
    outward), holes filled as ``(edges, span mm)``, small pieces dropped."""

    merged_points: int = 0
    dropped_triangles: int = 0
    flipped_triangles: int = 0
    holes: list = field(default_factory=list)
    dropped_pieces: int = 0

    def summary(self) -> str:
        """One phrase for the importer's printed summary ("" when nothing changed)."""
        parts = [f"{self.merged_points} duplicate points merged" if self.merged_points else "",
                 f"{self.dropped_triangles} degenerate triangles removed"
                 if self.dropped_triangles else "",
                 f"{self.flipped_triangles} triangles flipped" if self.flipped_triangles else "",
                 f"{len(self.holes)} holes filled (largest "
                 f"{max(s for _, s in self.holes):.1f} mm)" if self.holes else "",
                 f"{self.dropped_pieces} specks dropped" if self.dropped_pieces else ""]
        return ", ".join(p for p in parts if p)


def length_scale(points, units: str, where: str) -> float:
    """The factor to millimetres of a surface in ``units`` (``"m"``, ``"mm"`` or ``"auto"``:
    metres when its bounding box's largest side is below :data:`METRES_BELOW`)."""
    if units not in ("m", "mm", "auto"):
        raise MuscleMSSError(f"{where}: units {units!r}; give m, mm or auto")
    if units == "auto":
        units = "m" if np.ptp(points, axis=0).max() < METRES_BELOW else "mm"
    return 1000.0 if units == "m" else 1.0


def principal_length(points) -> float:
    """The surface's length (mm): the extent of ``points`` (n, 3) along their first principal
    axis (a muscle's long axis, whatever its orientation in the model)."""
    centred = points - points.mean(axis=0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    return float(np.ptp(centred @ axis))


def merge_duplicate_points(points, triangles, tolerance: float):
    """``(points, triangles, merged)``: points closer than ``tolerance`` (mm) joined into the
    first of their group (groups are the connected sets of close pairs), unused points
    dropped; ``merged`` how many points were joined into others."""
    pairs = cKDTree(points).query_pairs(tolerance, output_type="ndarray")
    n = len(points)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    count, labels = connected_components(graph, directed=False)
    first = np.full(count, n)
    np.minimum.at(first, labels, np.arange(n))
    points, triangles = compact(points, first[labels][triangles])
    return points, triangles, n - count


def compact(points, triangles):
    """``(points, triangles)`` without the points no triangle uses, indices renumbered."""
    used, inverse = np.unique(triangles, return_inverse=True)
    return points[used], inverse.reshape(-1, 3).astype(np.int64)


def drop_degenerate_triangles(triangles):
    """``(triangles, dropped)``: without triangles that use a point twice (collapsed by the
    merge) and without repeats of a triangle on the same three points (the first is kept)."""
    t = np.sort(triangles, axis=1)
    keep = (t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2])
    _, first = np.unique(t[keep], axis=0, return_index=True)
    kept = np.flatnonzero(keep)[np.sort(first)]
    return triangles[kept], len(triangles) - len(kept)


def _edges(triangles, n_points: int):
    """``(directed (3m, 2), owner (3m,), key (3m,))``: each triangle's three edges as it runs
    them, the triangle of each, and one int64 key per undirected edge."""
    directed = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    owner = np.tile(np.arange(len(triangles)), 3)
    ordered = np.sort(directed, axis=1)
    return directed, owner, ordered[:, 0] * n_points + ordered[:, 1]


def _neighbours(triangles, n_points: int, where: str):
    """``(first, second, same)`` per edge shared by two triangles: the two triangles and
    whether they run it the same way (disagree on orientation); edges of more than two
    triangles are refused (non-manifold)."""
    directed, owner, key = _edges(triangles, n_points)
    order = np.argsort(key, kind="stable")
    _, start, counts = np.unique(key[order], return_index=True, return_counts=True)
    if (counts > 2).any():
        edge = order[start[np.flatnonzero(counts > 2)[0]]]
        raise MuscleMSSError(f"{where}: {int((counts > 2).sum())} edges are shared by more than "
                             f"two triangles (non-manifold), the first between points "
                             f"{directed[edge].tolist()}; a surface must be manifold: repair "
                             "it in the segmentation or mesh tool")
    a, b = order[start[counts == 2]], order[start[counts == 2] + 1]
    return owner[a], owner[b], directed[a, 0] == directed[b, 0]


def _pieces(first, second, m: int):
    """``(count, labels (m,))``: the connected pieces of m triangles joined by shared edges."""
    graph = coo_matrix((np.ones(len(first)), (first, second)), shape=(m, m))
    return connected_components(graph, directed=False)


def orient_consistently(triangles, n_points: int, where: str):
    """``(triangles, flipped (m,) bool)``: every piece's triangles turned to agree with the
    first of the piece (each shared edge run once each way). A breadth-first tree from one
    root per piece gives each triangle's parent; whether a triangle flips is the parity of
    disagreements on its path to the root, found for all triangles at once by pointer jumping
    (log2 of the tree's depth steps). A surface on which no orientation agrees everywhere (a
    Moebius band) is refused."""
    m = len(triangles)
    first, second, same = _neighbours(triangles, n_points, where)
    _, labels = _pieces(first, second, m)
    roots = np.unique(labels, return_index=True)[1]
    # a virtual triangle m joined to each piece's root: one search covers every piece
    rows = np.concatenate([first, second, np.full(len(roots), m), roots])
    cols = np.concatenate([second, first, roots, np.full(len(roots), m)])
    relation = np.concatenate([same, same, np.zeros(2 * len(roots), bool)]).astype(np.float64)
    graph = coo_matrix((relation + 1.0, (rows, cols)), shape=(m + 1, m + 1)).tocsr()
    graph.sum_duplicates()
    parent = breadth_first_order(graph, m, directed=True, return_predecessors=True)[1]
    parent[m] = m
    parity = np.zeros(m + 1, dtype=np.int8)
    parity[:m] = np.asarray(graph[np.arange(m), parent[:m]]).ravel() == 2.0
    while (parent != m).any():
        parity, parent = parity ^ parity[parent], parent[parent]
    flip = parity[:m].astype(bool)
    triangles = triangles.copy()
    triangles[flip] = triangles[flip][:, [0, 2, 1]]
    if _neighbours(triangles, n_points, where)[2].any():
        raise MuscleMSSError(f"{where}: cannot be oriented (one-sided, like a Moebius band); "
                             "a surface must be closed and two-sided")
    return triangles, flip


def fill_small_holes(points, triangles, where: str, max_span: float = MAX_HOLE_SPAN_MM):
    """``(points, triangles, holes)``: each boundary loop of a consistently oriented surface
    closed by a fan of triangles from a new point at the loop's centroid, oriented like its
    neighbours; ``holes`` lists ``(edges, span mm)`` of those filled. A loop spanning more
    than ``max_span`` (mm), or two loops through one point, is refused naming it."""
    directed, _, key = _edges(triangles, len(points))
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    border = directed[counts[inverse.ravel()] == 1]
    if len(border) == 0:
        return points, triangles, []
    outgoing = np.bincount(border[:, 0], minlength=len(points))
    if (outgoing > 1).any():
        p = int(np.flatnonzero(outgoing > 1)[0])
        raise MuscleMSSError(f"{where}: two holes meet at point {p} "
                             f"({', '.join(f'{c:.1f}' for c in points[p])}) mm (a non-manifold "
                             "point); repair it in the segmentation or mesh tool")
    graph = coo_matrix((np.ones(len(border)), (border[:, 0], border[:, 1])),
                       shape=(len(points),) * 2)
    loop_of = connected_components(graph, directed=False)[1][border[:, 0]]
    holes, new_points, new_triangles = [], [], []
    for k, loop in enumerate(np.unique(loop_of)):
        edges = border[loop_of == loop]
        corners = points[edges[:, 0]]
        span = float(pdist(corners).max()) if len(corners) <= 4000 else float(
            np.linalg.norm(np.ptp(corners, axis=0)))
        if span > max_span:
            centre = ", ".join(f"{c:.1f}" for c in corners.mean(axis=0))
            raise MuscleMSSError(f"{where}: has a hole of {len(edges)} edges spanning "
                                 f"{span:.1f} mm around ({centre}) mm, larger than the "
                                 f"{max_span:g} mm filled; close it in the segmentation tool "
                                 "(an opening this large is usually a cut-off muscle)")
        centre = len(points) + k
        new_points.append(corners.mean(axis=0))
        new_triangles.append(np.column_stack([edges[:, 1], edges[:, 0],
                                              np.full(len(edges), centre)]))
        holes.append((len(edges), span))
    return (np.vstack([points, new_points]), np.vstack([triangles, *new_triangles]), holes)


def _piece_volumes(points, triangles, labels, count: int) -> np.ndarray:
    """Signed volume (mm³) of each of ``count`` pieces (triangle ``labels``)."""
    corners = (points - points.mean(axis=0))[triangles]
    each = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])) / 6.0
    return np.bincount(labels, weights=each, minlength=count)


def outward_pieces(points, triangles, where: str, single_piece: bool):
    """``(triangles, flipped (m,) bool, kept (m,) bool)``: each closed piece turned to enclose
    a positive volume; with ``single_piece`` (a muscle) only the largest kept, pieces below
    :data:`SMALL_PIECE_FRACTION` of it dropped and a larger second piece refused."""
    first, second, _ = _neighbours(triangles, len(points), where)
    count, labels = _pieces(first, second, len(triangles))
    volumes = _piece_volumes(points, triangles, labels, count)
    inward = volumes[labels] < 0
    triangles = triangles.copy()
    triangles[inward] = triangles[inward][:, [0, 2, 1]]
    if not single_piece or count == 1:
        return triangles, inward, np.ones(len(triangles), bool)
    sizes = np.abs(volumes)
    largest = int(np.argmax(sizes))
    big = np.flatnonzero(sizes >= SMALL_PIECE_FRACTION * sizes[largest])
    if len(big) > 1:
        raise MuscleMSSError(f"{where}: has {len(big)} separate pieces of "
                             f"{', '.join(f'{v:.0f}' for v in np.sort(sizes[big])[::-1])} mm³; "
                             "a muscle is one closed surface: one file per muscle")
    return triangles, inward, labels == largest


def clean_surface(points, triangles, where: str, max_hole_span: float = MAX_HOLE_SPAN_MM,
                  single_piece: bool = False):
    """``(points, triangles, Cleaning)``: a closed, manifold, outward surface from an exported
    one (``points`` (n, 3) mm, ``triangles`` (m, 3)): duplicate points merged
    (:data:`MERGE_TOLERANCE`), degenerate and repeated triangles dropped, orientation made
    consistent, holes up to ``max_hole_span`` mm filled, every piece outward (``single_piece``:
    one piece kept, :func:`outward_pieces`). What cannot be repaired is refused naming
    ``where``."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if len(triangles) == 0:
        raise MuscleMSSError(f"{where}: has no triangles; a surface must be a triangle mesh")
    report = Cleaning()
    diagonal = float(np.linalg.norm(np.ptp(points[np.unique(triangles)], axis=0)))
    points, triangles, report.merged_points = merge_duplicate_points(
        points, triangles, MERGE_TOLERANCE * diagonal)
    triangles, report.dropped_triangles = drop_degenerate_triangles(triangles)
    points, triangles = compact(points, triangles)
    m = len(triangles)
    triangles, flipped = orient_consistently(triangles, len(points), where)
    points, triangles, report.holes = fill_small_holes(points, triangles, where, max_hole_span)
    triangles, outward, kept = outward_pieces(points, triangles, where, single_piece)
    report.dropped_pieces = _pieces(*_neighbours(triangles[~kept], len(points), where)[:2],
                                    int((~kept).sum()))[0]
    report.flipped_triangles = int(((flipped ^ outward[:m]) & kept[:m]).sum())
    points, triangles = compact(points, triangles[kept])
    problems = surface_problems(points, triangles)
    if problems:
        raise MuscleMSSError(f"{where}: {problems[0]} after cleaning; repair it in the "
                             "segmentation or mesh tool")
    return points, triangles, report


def split_long_edges(points, triangles, max_edge: float):
    """``(points, triangles)`` with no edge longer than ``max_edge`` (mm): longest-edge
    bisection, each pass splitting at its midpoint every edge that is the longest (ties by
    key) of each triangle it belongs to, so that no triangle is split twice in a pass and the
    longest edge of all is always split. The shape and the enclosed volume do not change."""
    points = np.asarray(points, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    while True:
        corners = np.stack([triangles, np.roll(triangles, -1, axis=1)], axis=2)   # (m, 3, 2)
        lengths = np.linalg.norm(points[corners[..., 0]] - points[corners[..., 1]], axis=2)
        ordered = np.sort(corners, axis=2)
        keys = ordered[..., 0] * len(points) + ordered[..., 1]
        longest = lengths == lengths.max(axis=1, keepdims=True)
        pick = np.argmax(np.where(longest, keys, -1), axis=1)
        rows = np.arange(len(triangles))
        wanted = lengths[rows, pick] > max_edge
        if not wanted.any():
            return points, triangles
        all_keys, all_counts = np.unique(keys, return_counts=True)
        chosen, chosen_counts = np.unique(keys[rows, pick][wanted], return_counts=True)
        chosen = chosen[chosen_counts == all_counts[np.searchsorted(all_keys, chosen)]]
        split = wanted & np.isin(keys[rows, pick], chosen)
        ends = ordered[rows, pick][split]
        _, first = np.unique(keys[rows, pick][split], return_index=True)
        middle = len(points) + np.searchsorted(chosen, keys[rows, pick][split])
        points = np.vstack([points, points[ends[first]].mean(axis=1)])
        turned = np.take_along_axis(triangles[split], (pick[split, None] + np.arange(3)) % 3,
                                    axis=1)
        halves = np.vstack([np.column_stack([turned[:, 0], middle, turned[:, 2]]),
                            np.column_stack([middle, turned[:, 1], turned[:, 2]])])
        triangles = np.vstack([triangles[~split], halves])
