"""Boundary particles and collision sphere radii (core/radii.py, paper §3.3)."""
import numpy as np
import pytest

from muscle_mss.core.radii import (boundary_from_grid, boundary_from_surface,
                                   clear_of_obstacles, overlapping_pairs, shrink_radii,
                                   sphere_radii)


def grid_particles(rows, cols, n):
    r, c, j = np.meshgrid(np.arange(rows), np.arange(cols), np.arange(n), indexing="ij")
    grid = np.stack([r.ravel() - 3, c.ravel() + 10], axis=1)
    return grid, (r * cols + c).ravel(), j.ravel()


def brute_overlaps(centres, radii, object_id):
    """Slow reference: every pair of spheres of different objects that overlap."""
    d = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    other = object_id[:, None] != object_id[None]
    live = (radii[:, None] > 0) & (radii[None] > 0)
    return np.argwhere(other & live & (d < radii[:, None] + radii[None]))


@pytest.mark.parametrize("rows, cols, n", [(8, 8, 20), (8, 8, 21), (8, 8, 81), (3, 5, 4),
                                            (1, 4, 6), (2, 2, 2)])
def test_boundary_with_grid_is_the_lattice_surface(rows, cols, n):
    grid, fid, fidx = grid_particles(rows, cols, n)
    boundary = boundary_from_grid(grid, fid, fidx)
    r, c = grid[:, 0] + 3, grid[:, 1] - 10
    surface = (r == 0) | (r == rows - 1) | (c == 0) | (c == cols - 1) | (fidx == 0) | \
        (fidx == n - 1)
    assert np.array_equal(boundary, surface)
    inner = max(rows - 2, 0) * max(cols - 2, 0)
    assert boundary.sum() == (rows * cols - inner) * n + 2 * inner


def test_boundary_counts_match_the_paper_with_n_plus_one_particles():
    # the paper's 1344 / 660, 2624 / 1220, 3904 / 1780, 5184 / 2340 are 64 fibres of N + 1
    for n, particles, boundary in [(20, 1344, 660), (40, 2624, 1220), (60, 3904, 1780),
                                   (80, 5184, 2340)]:
        grid, fid, fidx = grid_particles(8, 8, n + 1)
        assert len(fid) == particles
        assert boundary_from_grid(grid, fid, fidx).sum() == boundary


def test_boundary_of_a_holed_grid_includes_the_fibres_around_the_hole():
    grid, fid, fidx = grid_particles(5, 5, 4)
    keep = fid != 12                                   # the centre fibre (2, 2) missing
    boundary = boundary_from_grid(grid[keep], fid[keep], fidx[keep])
    around = np.isin(fid[keep], [7, 11, 13, 17])
    assert boundary[around].all()
    assert not boundary[np.isin(fid[keep], [6, 8, 16, 18]) & (fidx[keep] == 1)].any()


def test_boundary_from_surface_is_the_set_of_nearest_particles():
    rng = np.random.default_rng(1)
    particles = rng.normal(size=(200, 3))
    surface = rng.normal(size=(500, 3)) * 2.0
    boundary = boundary_from_surface(particles, surface)
    nearest = np.argmin(np.linalg.norm(surface[:, None] - particles[None], axis=2), axis=1)
    expected = np.zeros(len(particles), dtype=bool)
    expected[nearest] = True
    assert np.array_equal(boundary, expected)


def brute_radii(particles, boundary, surface, heuristic):
    centres = np.flatnonzero(boundary)
    radii = np.zeros(len(particles))
    for i in centres:
        radii[i] = np.linalg.norm(surface - particles[i], axis=1).min()
    if heuristic:
        d = np.linalg.norm(surface[:, None] - particles[centres][None], axis=2)
        collector = np.argmin(d, axis=1)
        for k, i in enumerate(centres):
            mine = collector == k
            if mine.any():
                radii[i] = d[mine, k].mean()
    return radii


@pytest.mark.parametrize("heuristic", [True, False])
def test_sphere_radii_equal_the_reference(heuristic):
    rng = np.random.default_rng(2)
    particles = rng.normal(size=(150, 3))
    boundary = rng.random(150) < 0.4
    surface = rng.normal(size=(300, 3)) * 1.5
    radii = sphere_radii(particles, boundary, surface, heuristic)
    assert np.allclose(radii, brute_radii(particles, boundary, surface, heuristic))
    assert (radii[~boundary] == 0).all() and (radii[boundary] > 0).all()


def test_radius_is_the_mean_distance_to_the_collected_vertices():
    particles = np.array([[0.0, 0, 0], [10.0, 0, 0], [5.0, 0, 0]])
    surface = np.array([[0.0, 1, 0], [0.0, 0, 3], [10.0, 2, 0], [-1.0, 0, 0]])
    boundary = np.array([True, True, False])
    assert np.allclose(sphere_radii(particles, boundary, surface), [5 / 3, 2.0, 0.0])
    # off: the distance to the nearest surface vertex
    assert np.allclose(sphere_radii(particles, boundary, surface, False), [1.0, 2.0, 0.0])


def touching_blocks(seed=0):
    """Two lattices of spheres side by side, their surfaces interleaving: overlaps everywhere."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 10, size=(300, 3))
    b = rng.uniform(0, 10, size=(300, 3)) + [9.0, 0, 0]
    centres = np.concatenate([a, b])
    radii = rng.uniform(0.2, 2.0, size=600)
    radii[rng.random(600) < 0.2] = 0.0
    radii[5] = 30.0                                       # one huge sphere, as the paper mentions
    return centres, radii, np.repeat([3, 7], 300)


def test_shrink_leaves_no_overlap_between_objects_and_never_grows():
    centres, radii, objects = touching_blocks()
    assert len(brute_overlaps(centres, radii, objects)) > 0
    shrunk = shrink_radii(centres, radii, objects)
    assert len(brute_overlaps(centres, shrunk, objects)) == 0
    assert (shrunk <= radii).all() and (shrunk >= 0).all()
    assert (shrunk[radii == 0] == 0).all()
    # spheres without a partner of another object keep their radius
    a, b, _ = overlapping_pairs(centres, radii, objects)
    untouched = np.setdiff1d(np.arange(len(radii)), np.concatenate([a, b]))
    assert np.array_equal(shrunk[untouched], radii[untouched])
    assert shrunk[5] < 30.0


def test_shrink_does_not_touch_overlaps_inside_one_object():
    centres = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    radii = np.array([1.0, 1.0, 1.0])
    assert np.array_equal(shrink_radii(centres, radii, [0, 0, 0]), radii)


@pytest.mark.parametrize("ra, rb, d, expected", [
    (10.0, 1.0, 8.0, (7.0, 1.0)),        # the large sphere gives way first
    (3.0, 3.0, 4.0, (2.0, 2.0)),         # equal spheres meet half way
    (3.0, 1.0, 1.0, (0.5, 0.5)),         # deep overlap: both shrink to half the distance
    (2.0, 1.0, 3.5, (2.0, 1.0)),         # apart: unchanged
])
def test_shrink_of_one_pair(ra, rb, d, expected):
    centres = np.array([[0.0, 0, 0], [d, 0, 0]])
    shrunk = shrink_radii(centres, [ra, rb], [0, 1])
    assert np.allclose(shrunk, expected, rtol=1e-8)
    assert shrunk.sum() <= d or not (ra + rb > d)


def test_coinciding_particles_of_two_objects_lose_their_spheres():
    centres = np.array([[1.0, 2, 3], [1.0, 2, 3], [5.0, 2, 3]])
    shrunk = shrink_radii(centres, [1.0, 1.0, 1.0], [0, 1, 1])
    assert np.array_equal(shrunk, [0.0, 0.0, 1.0])


def test_clear_of_obstacles_equals_the_all_pairs_reference():
    rng = np.random.default_rng(11)
    centres = rng.uniform(0, 30, size=(200, 3))
    radii = np.where(rng.random(200) < 0.2, 0.0, rng.uniform(0.5, 6.0, 200))
    obstacles = rng.uniform(0, 30, size=(300, 3))
    obstacle_radii = rng.uniform(0.5, 2.5, 300)
    got = clear_of_obstacles(centres, radii, obstacles, obstacle_radii)
    room = (np.linalg.norm(centres[:, None] - obstacles[None], axis=2) - obstacle_radii).min(1)
    expected = np.where(radii > 0, np.minimum(radii, np.maximum(room, 0.0)), 0.0)
    np.testing.assert_allclose(got, expected, rtol=1e-8, atol=0)
    assert (got < radii).sum() > 20 and (got == 0).sum() > (radii == 0).sum()
    gap = np.linalg.norm(centres[:, None] - obstacles[None], axis=2) - obstacle_radii
    assert ((got[:, None] <= gap) | (got[:, None] == 0)).all()
    assert np.array_equal(clear_of_obstacles(centres, radii, np.zeros((0, 3)), np.zeros(0)),
                          radii)
