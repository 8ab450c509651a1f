"""Spring layouts (core/springs.py, paper §3.2)."""
import itertools

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.demo.geometry import tube_triangles
from muscle_mss.core.springs import (DELAUNAY_FALLBACK_EDGES, DELAUNAY_REACH, delaunay_springs,
                                     fibre_step, knn_springs, lattice_offsets, lattice_springs,
                                     rest_lengths, unique_springs)
from muscle_mss.core.volume import signed_volume


def lattice(rows=8, cols=8, n=20, spacing=(3.0, 2.5, 1.7), shuffle_seed=None):
    """Particles on a rows x cols x n lattice, fibre by fibre like the resampler's output.

    Returns (points (P, 3), grid (P, 2), fibre_id, fibre_index), optionally in shuffled order.
    """
    r, c, j = np.meshgrid(np.arange(rows), np.arange(cols), np.arange(n), indexing="ij")
    r, c, j = r.ravel(), c.ravel(), j.ravel()
    points = np.stack([r * spacing[0], c * spacing[1], j * spacing[2]], axis=1).astype(float)
    grid = np.stack([r + 4, c - 2], axis=1)       # grids need not start at 0
    fibre_id = r * cols + c
    if shuffle_seed is not None:
        order = np.random.default_rng(shuffle_seed).permutation(len(points))
        return points[order], grid[order], fibre_id[order], j[order]
    return points, grid, fibre_id, j


def brute_lattice_springs(grid, fibre_index, neighbourhood):
    """Slow reference: every pair of lattice places at Chebyshev distance 1 (26) or Manhattan
    distance 1 (6)."""
    place = np.column_stack([grid, fibre_index])
    pairs = []
    for a, b in itertools.combinations(range(len(place)), 2):
        d = np.abs(place[a] - place[b])
        if (neighbourhood == 26 and d.max() == 1) or (neighbourhood == 6 and d.sum() == 1):
            pairs.append((a, b))
    return np.array(pairs)


def degrees(springs, count):
    return np.bincount(springs.ravel(), minlength=count)


def assert_clean(springs, count):
    assert springs.dtype == np.int64 and springs.shape[1] == 2
    assert (springs[:, 0] < springs[:, 1]).all(), "self spring or unordered pair"
    assert len(np.unique(springs, axis=0)) == len(springs), "duplicate spring"
    assert springs.min() >= 0 and springs.max() < count


@pytest.mark.parametrize("neighbourhood, expected", [(6, 3456), (26, 13396)])
def test_lattice_spring_count_on_8x8x20(neighbourhood, expected):
    points, grid, fid, fidx = lattice()
    springs = lattice_springs(grid, fid, fidx, neighbourhood)
    assert_clean(springs, len(points))
    assert len(springs) == expected


@pytest.mark.parametrize("n", [2, 5, 20, 40])
@pytest.mark.parametrize("neighbourhood", [6, 26])
def test_lattice_counts_and_interior_degree_on_8x8xN(neighbourhood, n):
    points, grid, fid, fidx = lattice(n=n)
    springs = lattice_springs(grid, fid, fidx, neighbourhood)
    # sum over one half of the neighbourhood of the pairs the step fits in the 8 x 8 x n box
    expected = sum((8 - abs(dr)) * (8 - abs(dc)) * (n - abs(dj))
                   for dr, dc, dj in lattice_offsets(neighbourhood))
    assert len(springs) == expected
    deg = degrees(springs, len(points))
    r, c = grid[:, 0] - 4, grid[:, 1] + 2
    interior = (r > 0) & (r < 7) & (c > 0) & (c < 7) & (fidx > 0) & (fidx < n - 1)
    assert interior.sum() == 36 * max(n - 2, 0)
    assert (deg[interior] == neighbourhood).all()
    assert (deg[~interior] < neighbourhood).all()


@pytest.mark.parametrize("neighbourhood", [6, 26])
def test_lattice_equals_brute_force_in_any_particle_order(neighbourhood):
    points, grid, fid, fidx = lattice(4, 3, 5, shuffle_seed=2)
    springs = lattice_springs(grid, fid, fidx, neighbourhood)
    assert np.array_equal(springs, brute_lattice_springs(grid, fidx, neighbourhood))
    # lattice springs join lattice neighbours only: rest lengths are sides and diagonals
    lengths = rest_lengths(points, springs)
    assert lengths.max() <= np.linalg.norm([3.0, 2.5, 1.7]) + 1e-12


def test_lattice_needs_a_full_rectangular_grid():
    points, grid, fid, fidx = lattice(3, 3, 4)
    keep = fid != 4                                          # the middle fibre missing
    with pytest.raises(MuscleMSSError, match=r"'m'.*no fibre at \(row 5, col -1\)"):
        lattice_springs(grid[keep], fid[keep], fidx[keep], 26, where="'m'")
    ragged = grid.copy()
    ragged[fid == 8] = [4 + 3, -2]                           # last fibre moved off the rectangle
    with pytest.raises(MuscleMSSError, match="no fibre at|full rectangular"):
        lattice_springs(ragged, fid, fidx, 6)
    shared = grid.copy()
    shared[fid == 8] = grid[fid == 0][0]
    with pytest.raises(MuscleMSSError, match="fibres 0 and 8 share fibre_grid"):
        lattice_springs(shared, fid, fidx, 6)


def test_lattice_needs_equal_fibres_and_consistent_grid():
    points, grid, fid, fidx = lattice(2, 2, 4)
    short = ~((fid == 3) & (fidx == 3))
    with pytest.raises(MuscleMSSError, match="fibre 3 has 3 particles but fibre 0 has 4"):
        lattice_springs(grid[short], fid[short], fidx[short], 26)
    twice = fidx.copy()
    twice[(fid == 2) & (fidx == 1)] = 2
    with pytest.raises(MuscleMSSError, match="fibre 2 does not number"):
        lattice_springs(grid, fid, twice, 26)
    split = grid.copy()
    split[(fid == 1) & (fidx == 0)] = [9, 9]
    with pytest.raises(MuscleMSSError, match="fibre 1 has particles with different fibre_grid"):
        lattice_springs(split, fid, fidx, 26)
    with pytest.raises(MuscleMSSError, match="no particles"):
        lattice_springs(np.zeros((0, 2)), [], [], 26)


def random_muscle(count=300, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(count, 3)) * [10.0, 6.0, 40.0]


def test_delaunay_edges_equal_scipys_tetrahedra_edges():
    points = random_muscle()
    springs = delaunay_springs(points)
    assert_clean(springs, len(points))
    simplices = Delaunay(points).simplices
    edges = np.concatenate([simplices[:, [a, b]] for a, b in itertools.combinations(range(4), 2)])
    assert np.array_equal(springs, unique_springs(edges[:, 0], edges[:, 1]))


def test_delaunay_keeps_coinciding_particles_connected():
    points = random_muscle(60, seed=4)
    points = np.concatenate([points, points[:3]])            # three particles doubled
    springs = delaunay_springs(points)
    assert_clean(springs, len(points))
    assert (degrees(springs, len(points)) > 0).all()


def test_delaunay_of_flat_particles_is_refused_with_a_clear_error():
    flat = np.column_stack([random_muscle(50)[:, :2], np.zeros(50)])
    with pytest.raises(MuscleMSSError, match="block 'flat'.*3D space"):
        delaunay_springs(flat, where="block 'flat'")


def c_shaped_muscle(radius=40.0, thickness=6.0, sweep=1.5 * np.pi, steps=25):
    """A tube bent into a C (``sweep`` of a circle of ``radius`` mm): its particles, 3 x 3
    fibres of ``steps`` particles along the arc, each particle's place along its fibre, and
    the tube's closed, outward surface (points, triangles)."""
    theta = np.linspace(-sweep / 2, sweep / 2, steps)
    offsets = [(dr, dz) for dr in (-4.0, 0.0, 4.0) for dz in (-4.0, 0.0, 4.0)]
    points = np.array([[(radius + dr) * np.cos(t), (radius + dr) * np.sin(t), dz]
                       for dr, dz in offsets for t in theta])
    along = np.tile(np.arange(steps), len(offsets))
    fibre = np.repeat(np.arange(len(offsets)), steps)
    rings = np.linspace(-sweep / 2 - 0.1, sweep / 2 + 0.1, steps + 4)
    phi = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    ring_points = [[(radius + thickness * np.cos(f)) * np.cos(t),
                    (radius + thickness * np.cos(f)) * np.sin(t), thickness * np.sin(f)]
                   for t in rings for f in phi]
    end = sweep / 2 + 0.2
    surface = np.array([[radius * np.cos(-end), radius * np.sin(-end), 0.0], *ring_points,
                        [radius * np.cos(end), radius * np.sin(end), 0.0]])
    triangles = tube_triangles(len(rings), len(phi))
    if signed_volume(surface, triangles) < 0:
        triangles = np.ascontiguousarray(triangles[:, ::-1])
    return points, along, fibre, (surface, triangles)


def test_restricted_delaunay_keeps_a_curved_muscle_from_being_joined_across_its_bend():
    points, along, fibre, surface = c_shaped_muscle()
    whole = delaunay_springs(points)
    # the plain tetrahedralisation fills the C's convex hull: springs across the bend
    assert np.abs(np.diff(along[whole], axis=1)).max() > 10
    step = fibre_step(points, fibre, along)
    assert step == pytest.approx(2 * 44.0 * np.sin(1.5 * np.pi / 48))    # the outer fibres
    springs = delaunay_springs(points, surface=surface, longest_edge=DELAUNAY_REACH * step)
    assert_clean(springs, len(points))
    assert len(np.setdiff1d(springs[:, 0] * len(points) + springs[:, 1],
                            whole[:, 0] * len(points) + whole[:, 1])) == 0   # a subset
    assert np.abs(np.diff(along[springs], axis=1)).max() <= 2
    assert rest_lengths(points, springs).max() <= DELAUNAY_REACH * step
    assert degrees(springs, len(points)).min() >= DELAUNAY_FALLBACK_EDGES
    graph = coo_matrix((np.ones(len(springs)), (springs[:, 0], springs[:, 1])),
                       shape=(len(points), len(points)))
    assert connected_components(graph, directed=False)[0] == 1
    # a particle outside the surface, in no kept tetrahedron, keeps its shortest Delaunay edges
    outside = np.vstack([points, [[40.0, 0.0, 20.0]]])
    lone = delaunay_springs(outside, surface=surface, longest_edge=DELAUNAY_REACH * step)
    assert degrees(lone, len(outside))[-1] == DELAUNAY_FALLBACK_EDGES


def brute_knn(points, k):
    distance = np.linalg.norm(points[:, None] - points[None], axis=2)
    np.fill_diagonal(distance, np.inf)
    nearest = np.argsort(distance, axis=1, kind="stable")[:, :k]
    return unique_springs(np.repeat(np.arange(len(points)), k), nearest.ravel())


@pytest.mark.parametrize("k", [1, 6, 15])
def test_knn_is_symmetric_unique_and_every_degree_at_least_k(k):
    points = random_muscle(250, seed=k)
    springs = knn_springs(points, k)
    assert_clean(springs, len(points))
    assert (degrees(springs, len(points)) >= k).all()
    assert np.array_equal(springs, brute_knn(points, k))


def test_knn_with_fewer_particles_than_k_connects_all():
    points = random_muscle(5)
    springs = knn_springs(points, 15)
    assert len(springs) == 10
    assert len(knn_springs(points[:1], 3)) == 0


def test_knn_with_coinciding_particles_still_gives_k_others():
    points = random_muscle(40, seed=1)
    points = np.concatenate([points, points])
    springs = knn_springs(points, 4)
    assert_clean(springs, len(points))
    assert (degrees(springs, len(points)) >= 4).all()


def test_rest_lengths_are_distances():
    points = random_muscle(30)
    springs = knn_springs(points, 3)
    expected = [np.linalg.norm(points[a] - points[b]) for a, b in springs]
    assert np.allclose(rest_lengths(points, springs), expected)


def test_unique_springs_drops_self_pairs_and_repeats():
    assert np.array_equal(unique_springs([3, 1, 2, 2, 0], [1, 3, 2, 0, 2]), [[0, 2], [1, 3]])
