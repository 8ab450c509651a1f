"""The springs between the particles of one muscle (the paper's §3.2, DESIGN §6 "Springs").

Four layouts, each returning the springs of one muscle as an ``(s, 2) int64`` array of particle
index pairs ``(i, j)`` with ``i < j``, sorted, every spring once and none from a particle to itself
(springs between two muscles cannot arise: every function sees one muscle's particles):

* :func:`lattice_springs` with ``neighbourhood=6`` or ``26`` — the particles as vertices of a
  cubic lattice indexed by ``(row, col)`` of their fibre's ``fibre_grid`` and their
  ``fibre_index`` along the fibre: 6 = the axis neighbours (the cube sides), 26 = the whole
  3x3x3 neighbourhood (sides, face and space diagonals). Needs a full rectangular grid with the
  same number of particles on every fibre.
* :func:`delaunay_springs` — the edges of ``scipy.spatial.Delaunay`` of the particles; given the
  muscle's surface, only those of the tetrahedra inside the muscle and no longer than
  :data:`DELAUNAY_REACH` fibre steps (the Spring Builder's Delaunay).
* :func:`knn_springs` — each particle to its ``k`` nearest particles (the paper's suggested
  layout with ``k = 15``), made symmetric.

:func:`rest_lengths` gives each spring's rest length.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay, cKDTree

from .errors import MuscleMSSError
from .volume import winding_numbers

LATTICE_NEIGHBOURHOODS = (6, 26)


def unique_springs(i, j) -> np.ndarray:
    """(s, 2) int64: the pairs ``(i[m], j[m])`` as ``(min, max)``, sorted, without repeats or
    self pairs."""
    i = np.asarray(i, dtype=np.int64).ravel()
    j = np.asarray(j, dtype=np.int64).ravel()
    low, high = np.minimum(i, j), np.maximum(i, j)
    keep = low != high
    low, high = low[keep], high[keep]
    if len(low) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    # one int64 key per pair: a 1-D unique is several times faster than unique(axis=0)
    width = int(high.max()) + 1
    key = np.unique(low * width + high)
    return np.stack([key // width, key % width], axis=1)


def rest_lengths(points, springs) -> np.ndarray:
    """(s,) float64 mm: the distance between the two particles of each spring.

    points (P, 3) float64 mm (rest pose), springs (s, 2) int.
    """
    points = np.asarray(points, dtype=np.float64)
    springs = np.asarray(springs, dtype=np.int64).reshape(-1, 2)
    return np.linalg.norm(points[springs[:, 1]] - points[springs[:, 0]], axis=1)


def lattice_offsets(neighbourhood: int) -> np.ndarray:
    """(3 or 13, 3) int: the lattice steps (drow, dcol, dindex) of one half of the neighbourhood.

    The other half are their negatives, so each spring is made once.
    """
    if neighbourhood == 6:
        return np.eye(3, dtype=np.int64)
    if neighbourhood == 26:
        steps = np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"))
        steps = steps.reshape(3, -1).T
        # lexicographically positive steps: exactly one of each pair (step, -step)
        first = np.argmax(steps != 0, axis=1)
        return steps[steps[np.arange(len(steps)), first] > 0]
    raise MuscleMSSError(f"lattice neighbourhood {neighbourhood} is not one of 6, 26")


def lattice_places(grid, fibre_id, fibre_index, where: str = "particles"):
    """Each particle's place in the cubic lattice, checking the grid is a full rectangle.

    Parameters
    ----------
    grid : (P, 2) int
        ``fibre_grid`` (row, col) of each particle's fibre.
    fibre_id, fibre_index : (P,) int
        The particle's fibre and its place along it (0 = origin).
    where : str
        Names the muscle in error messages.

    Returns
    -------
    places : (P, 3) int64
        (row, col, index), each counted from 0.
    shape : tuple (rows, cols, n)

    Raises
    ------
    MuscleMSSError
        No particles; a fibre whose particles disagree on ``fibre_grid``; fibres with different
        particle counts or an index repeated along a fibre; two fibres on one grid place; a grid
        place without a fibre (a ragged or holed grid).
    """
    grid = np.asarray(grid, dtype=np.int64)
    fibre_id = np.asarray(fibre_id, dtype=np.int64).ravel()
    fibre_index = np.asarray(fibre_index, dtype=np.int64).ravel()
    n_particles = len(fibre_id)
    if n_particles == 0:
        raise MuscleMSSError(f"{where} has no particles")
    if grid.shape != (n_particles, 2) or len(fibre_index) != n_particles:
        raise MuscleMSSError(f"{where}: fibre_grid must have 2 components (row, col) and "
                             "fibre_grid, fibre_id, fibre_index one value per particle")
    fibres, first, inverse = np.unique(fibre_id, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    fibre_cell = grid[first]
    differs = np.flatnonzero((grid != fibre_cell[inverse]).any(axis=1))
    if len(differs):
        raise MuscleMSSError(f"{where}: fibre {fibres[inverse[differs[0]]]} has particles with "
                             "different fibre_grid values; a fibre has one grid place")
    counts = np.bincount(inverse)
    n = int(counts.max())
    uneven = np.flatnonzero(counts != n)
    if len(uneven):
        full = int(np.argmax(counts))
        raise MuscleMSSError(
            f"{where}: fibre {fibres[uneven[0]]} has {counts[uneven[0]]} particles but fibre "
            f"{fibres[full]} has {n}; lattice layouts need the same number on every fibre")
    misplaced = np.flatnonzero((fibre_index < 0) | (fibre_index >= n))
    if not len(misplaced):
        along = inverse * n + fibre_index
        by_place = np.argsort(along, kind="stable")
        misplaced = by_place[np.flatnonzero(np.diff(along[by_place]) == 0)]
    if len(misplaced):
        raise MuscleMSSError(f"{where}: fibre {fibres[inverse[misplaced[0]]]} does not number "
                             f"its particles 0..{n - 1} along it (fibre_index)")
    low = fibre_cell.min(axis=0)
    rows, cols = (fibre_cell.max(axis=0) - low + 1).tolist()
    cell = (fibre_cell[:, 0] - low[0]) * cols + (fibre_cell[:, 1] - low[1])
    order = np.argsort(cell, kind="stable")
    repeated = np.flatnonzero(np.diff(cell[order]) == 0)
    if len(repeated):
        a, b = order[repeated[0]], order[repeated[0] + 1]
        r, c = fibre_cell[a]
        raise MuscleMSSError(f"{where}: fibres {fibres[a]} and {fibres[b]} share fibre_grid "
                             f"(row {r}, col {c}); lattice layouts need one fibre per grid place")
    if len(fibres) != rows * cols:
        present = cell[order]
        gap = np.flatnonzero(present != np.arange(len(present)))
        k = int(gap[0]) if len(gap) else len(present)
        raise MuscleMSSError(
            f"{where}: fibre_grid has no fibre at (row {low[0] + k // cols}, col "
            f"{low[1] + k % cols}); lattice layouts need a full rectangular grid "
            f"({rows} x {cols} = {rows * cols} fibres, the block has {len(fibres)})")
    places = np.stack([fibre_cell[inverse, 0] - low[0], fibre_cell[inverse, 1] - low[1],
                       fibre_index], axis=1)
    return places, (rows, cols, n)


def lattice_springs(grid, fibre_id, fibre_index, neighbourhood: int = 26,
                    where: str = "particles") -> np.ndarray:
    """The springs of the cubic lattice layout (paper §3.2): (s, 2) int64.

    Arguments as :func:`lattice_places`; ``neighbourhood`` 6 (cube sides) or 26 (sides, face
    and space diagonals). On an ``R x C`` grid with ``n`` particles per fibre every particle not
    on the lattice's surface has exactly ``neighbourhood`` springs.
    """
    steps = lattice_offsets(neighbourhood)
    places, shape = lattice_places(grid, fibre_id, fibre_index, where)
    volume = np.empty(shape, dtype=np.int64)
    volume[places[:, 0], places[:, 1], places[:, 2]] = np.arange(len(places))
    ends_a, ends_b = [], []
    for step in steps:
        src = tuple(slice(max(0, -d), size - max(0, d)) for d, size in zip(step, shape))
        dst = tuple(slice(max(0, d), size - max(0, -d)) for d, size in zip(step, shape))
        ends_a.append(volume[src].ravel())
        ends_b.append(volume[dst].ravel())
    return unique_springs(np.concatenate(ends_a), np.concatenate(ends_b))


# A restricted Delaunay tetrahedron's longest edge may be this many times the longest step
# between consecutive particles of one of the muscle's fibres: a lattice-26 cell's space
# diagonal is at most sqrt(3) steps, and the tetrahedra of the particle cloud's hull that span
# the muscle's length or its curve (100-480 mm on the demo thigh at N = 20, steps 17-62 mm)
# are many times longer.
DELAUNAY_REACH = 1.5
# a particle left in no restricted tetrahedron keeps this many of its shortest Delaunay edges
DELAUNAY_FALLBACK_EDGES = 4


def fibre_step(points, fibre_id, fibre_index) -> float:
    """The longest distance (mm) between consecutive particles (by ``fibre_index``) of one
    fibre (``fibre_id``), over all fibres of a muscle; 0 when no fibre has two particles."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    order = np.lexsort((np.asarray(fibre_index).ravel(), np.asarray(fibre_id).ravel()))
    ids = np.asarray(fibre_id).ravel()[order]
    same = ids[1:] == ids[:-1]
    if not same.any():
        return 0.0
    steps = np.linalg.norm(points[order][1:] - points[order][:-1], axis=1)
    return float(steps[same].max())


def delaunay_springs(points, where: str = "particles", surface=None,
                     longest_edge: float = np.inf) -> np.ndarray:
    """The springs on the edges of the Delaunay tetrahedralisation of the particles: (s, 2) int64.

    points (P, 3) float64 mm. A particle that Qhull leaves out of the tetrahedralisation
    (one coinciding with another, e.g. fibre ends meeting at a tendon) is joined to the four
    corners of the tetrahedron it lies in, so that no particle is left without springs.

    Restricted to the muscle when ``surface`` = (points (V, 3), triangles (T, 3)) of its closed,
    outward rest surface is given: only the tetrahedra whose centroid lies inside it (winding
    number > 1/2) and whose longest edge is at most ``longest_edge`` mm give springs. The plain
    tetrahedralisation fills the particles' convex hull: on a long or curved muscle its hull
    tetrahedra join particles across the muscle's bend and along its whole length (springs of
    up to the muscle's length), which resist any bending and crumple the muscle at a flexed
    pose. A particle left in no kept tetrahedron keeps its :data:`DELAUNAY_FALLBACK_EDGES`
    shortest Delaunay edges.

    Raises
    ------
    MuscleMSSError
        When the particles do not span 3D space (fewer than 5, or all in one plane).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    try:
        tri = Delaunay(points)
    except (RuntimeError, ValueError) as err:
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise MuscleMSSError(
            f"{where}: the Delaunay layout needs particles spanning 3D space (at least 5, not "
            f"all in one plane); Qhull refused the {len(points)} particles ({reason}); "
            "use k-NN or a lattice layout") from None
    left_out = np.asarray(tri.coplanar, dtype=np.int64).reshape(-1, 3)
    extra_a = np.repeat(left_out[:, 0], 4)
    extra_b = tri.simplices[left_out[:, 1]].ravel()
    indptr, indices = tri.vertex_neighbor_vertices
    owner = np.repeat(np.arange(len(points)), np.diff(indptr))
    if surface is None:
        return unique_springs(np.concatenate([owner, extra_a]), np.concatenate([indices, extra_b]))
    simplices = tri.simplices
    pairs = [(a, b) for a in range(4) for b in range(a + 1, 4)]
    edges = np.stack([np.linalg.norm(points[simplices[:, a]] - points[simplices[:, b]], axis=1)
                      for a, b in pairs], axis=1)
    inside = winding_numbers(points[simplices].mean(axis=1), *surface) > 0.5
    kept = simplices[inside & (edges.max(axis=1) <= longest_edge)]
    ends_a = [kept[:, a] for a, _ in pairs] + [extra_a]
    ends_b = [kept[:, b] for _, b in pairs] + [extra_b]
    covered = np.zeros(len(points), dtype=bool)
    covered[kept.ravel()] = True
    covered[left_out[:, 0]] = True
    lone = ~covered[owner]
    owner, neighbour = owner[lone], indices[lone]
    order = np.lexsort((np.linalg.norm(points[neighbour] - points[owner], axis=1), owner))
    owner, neighbour = owner[order], neighbour[order]
    rank = np.arange(len(owner)) - np.searchsorted(owner, owner)     # 0 = shortest edge
    ends_a.append(owner[rank < DELAUNAY_FALLBACK_EDGES])
    ends_b.append(neighbour[rank < DELAUNAY_FALLBACK_EDGES])
    return unique_springs(np.concatenate(ends_a), np.concatenate(ends_b))


def knn_springs(points, k: int, workers: int = 1) -> np.ndarray:
    """The springs from each particle to its ``k`` nearest particles, symmetric: (s, 2) int64.

    points (P, 3) float64 mm. A spring found from both ends is made once, so every particle has
    at least ``min(k, P - 1)`` springs (a muscle with ``k`` or fewer other particles is fully
    connected). ``workers`` is passed to ``cKDTree.query``.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    k = min(int(k), len(points) - 1)
    if k < 1:
        return np.zeros((0, 2), dtype=np.int64)
    # k + 1: the particle itself is normally its own nearest; among coinciding particles it may
    # not be returned, and then all k + 1 are others
    _, nearest = cKDTree(points).query(points, k=list(range(1, k + 2)), workers=workers)
    owner = np.repeat(np.arange(len(points)), k + 1)
    return unique_springs(owner, nearest.ravel())
