"""The muscle cage and fibre polylines (core/cage.py)."""
import numpy as np
import pytest
from scipy.spatial import ConvexHull

from muscle_mss.core.cage import (CONVEX_HULL, LATTICE, fibre_polylines, muscle_cage,
                                  polyline_lengths)
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.mesh_checks import surface_problems
from muscle_mss.core.volume import signed_volume


def bent_lattice(rows=4, cols=5, n=7, mirror=False, seed=0):
    """Particles of an R x C grid of fibres, n each, along a quarter circle (a bent muscle),
    listed in random order. Returns (positions, fibre_id, fibre_index, fibre_grid, lattice)
    with lattice[r, c, k] = particle index."""
    r, c, k = np.meshgrid(np.arange(rows), np.arange(cols), np.arange(n), indexing="ij")
    angle = k / (n - 1) * np.pi / 2
    radius = 60.0 + 4.0 * c
    positions = np.stack([radius * np.cos(angle), 5.0 * r + 0.3 * c, radius * np.sin(angle)],
                         axis=-1).reshape(-1, 3)
    if mirror:
        positions[:, 1] *= -1
    perm = np.random.default_rng(seed).permutation(len(positions))
    where = np.empty_like(perm)
    where[perm] = np.arange(len(perm))
    lattice = where.reshape(rows, cols, n)
    fibre_id = (r * cols + c).reshape(-1)[perm] + 100   # ids need not start at 0
    grid = np.stack([r + 3, 2 * c], axis=-1).reshape(-1, 2)[perm]   # nor be 0..R-1
    return positions[perm], fibre_id, k.reshape(-1)[perm], grid, lattice


def _surface_mask(lattice):
    mask = np.zeros(lattice.shape, bool)
    mask[[0, -1]] = mask[:, [0, -1]] = mask[:, :, [0, -1]] = True
    return np.isin(np.arange(lattice.size), lattice[mask])


@pytest.mark.parametrize("mirror", [False, True])
@pytest.mark.parametrize("shape", [(4, 5, 7), (2, 2, 2), (8, 8, 20)])
def test_lattice_cage_is_closed_manifold_outward(shape, mirror):
    positions, fibre_id, fibre_index, grid, lattice = bent_lattice(*shape, mirror=mirror)
    rows, cols, n = shape
    boundary = _surface_mask(lattice)
    cage = muscle_cage(positions, boundary, fibre_id, fibre_index, grid)
    assert cage.kind == LATTICE
    assert surface_problems(positions[cage.vertices], cage.triangles) == []
    ring = 2 * (rows - 1) + 2 * (cols - 1)
    assert len(cage.triangles) == 2 * (ring * (n - 1) + 2 * (rows - 1) * (cols - 1))
    edges = np.unique(np.sort(np.concatenate([cage.triangles[:, [0, 1]],
                                              cage.triangles[:, [1, 2]],
                                              cage.triangles[:, [2, 0]]]), axis=1), axis=0)
    assert len(cage.vertices) - len(edges) + len(cage.triangles) == 2   # a sphere
    np.testing.assert_array_equal(np.sort(cage.vertices), np.flatnonzero(boundary))


def test_lattice_cage_follows_the_grid_and_the_bend():
    positions, fibre_id, fibre_index, grid, lattice = bent_lattice()
    cage = muscle_cage(positions, _surface_mask(lattice), fibre_id, fibre_index, grid)
    place = np.argwhere(np.ones(lattice.shape, bool))[np.argsort(lattice.reshape(-1))]
    corners = place[cage.vertices][cage.triangles]          # (t, 3, 3) lattice coordinates
    # Each triangle is half a lattice quad: its corners differ by at most one step per axis.
    assert np.abs(corners[:, :, None] - corners[:, None]).max() == 1
    hull = ConvexHull(positions)
    assert signed_volume(positions[cage.vertices], cage.triangles) < 0.9 * hull.volume


def test_without_grid_the_cage_is_the_hull_of_the_boundary_particles():
    positions, fibre_id, fibre_index, _, lattice = bent_lattice()
    boundary = _surface_mask(lattice)
    cage = muscle_cage(positions, boundary, fibre_id, fibre_index, None)
    assert cage.kind == CONVEX_HULL
    assert boundary[cage.vertices].all()
    assert surface_problems(positions[cage.vertices], cage.triangles) == []
    volume = signed_volume(positions[cage.vertices], cage.triangles)
    assert volume == pytest.approx(ConvexHull(positions[boundary]).volume, rel=1e-12)


def test_a_grid_with_a_missing_fibre_falls_back_to_the_hull():
    positions, fibre_id, fibre_index, grid, lattice = bent_lattice()
    keep = fibre_id != fibre_id[lattice[1, 1, 0]]
    cage = muscle_cage(positions[keep], np.ones(keep.sum(), bool), fibre_id[keep],
                       fibre_index[keep], grid[keep])
    assert cage.kind == CONVEX_HULL


def test_bad_particles_are_refused_with_the_muscle_named():
    positions, fibre_id, fibre_index, grid, lattice = bent_lattice()
    boundary = _surface_mask(lattice)
    where = "RestModel block 'gracilis'"
    with pytest.raises(MuscleMSSError, match="block 'gracilis': has no boundary particles"):
        muscle_cage(positions, np.zeros(len(positions)), fibre_id, fibre_index, grid, where)
    twice = fibre_index.copy()
    twice[lattice[2, 3, 4]] = 3
    with pytest.raises(MuscleMSSError, match=r"'gracilis': fibre 113 has fibre_index values"):
        muscle_cage(positions, boundary, fibre_id, twice, grid, where)
    mixed = grid.copy()
    mixed[lattice[0, 1, 2]] = [3, 0]
    with pytest.raises(MuscleMSSError, match="fibre 101 have different fibre_grid cells"):
        muscle_cage(positions, boundary, fibre_id, fibre_index, mixed, where)
    flat = positions.copy()
    flat[:, 1] = 0.0
    with pytest.raises(MuscleMSSError, match="'gracilis': the convex hull .* is degenerate"):
        muscle_cage(flat, boundary, fibre_id, fibre_index, None, where)
    with pytest.raises(MuscleMSSError, match="'gracilis': the lattice cage of its 110 boundary "
                       "particles encloses no volume"):
        muscle_cage(flat, boundary, fibre_id, fibre_index, grid, where)


def test_fibre_polylines_and_lengths_against_loops():
    positions, fibre_id, fibre_index, _, _ = bent_lattice(3, 3, 6, seed=4)
    rng = np.random.default_rng(1)
    positions = positions + rng.normal(size=positions.shape)
    order, offsets, ids = fibre_polylines(fibre_id, fibre_index)
    np.testing.assert_array_equal(ids, np.unique(fibre_id))
    for f, fid in enumerate(ids):
        members = np.flatnonzero(fibre_id == fid)
        expected = members[np.argsort(fibre_index[members])]
        np.testing.assert_array_equal(order[offsets[f]:offsets[f + 1]], expected)
    lengths = polyline_lengths(positions, order, offsets)
    for f, fid in enumerate(ids):
        walk = positions[order[offsets[f]:offsets[f + 1]]]
        expected = sum(np.linalg.norm(walk[i + 1] - walk[i]) for i in range(len(walk) - 1))
        assert lengths[f] == pytest.approx(expected, rel=1e-12)
