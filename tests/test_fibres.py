"""Resampling fibres into particles (core/fibres.py, paper §3.1)."""
import numpy as np
import pytest

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.fibres import fibre_lengths, resample_fibres


def bent_fibres(n_fibres=6, seed=3):
    """Fibres as polylines with unevenly spaced vertices and bends: (points, offsets)."""
    rng = np.random.default_rng(seed)
    polylines = []
    for f in range(n_fibres):
        count = 3 + f % 4
        steps = rng.normal(size=(count - 1, 3)) + [0.0, 0.0, 4.0]
        steps *= rng.uniform(0.2, 3.0, size=(count - 1, 1))
        polylines.append(np.concatenate([[[f * 5.0, 0.0, 0.0]], f * 5.0 * np.array([1, 0, 0])
                                         + np.cumsum(steps, axis=0)]))
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in polylines])])
    return np.concatenate(polylines), offsets


def arc_length_of(point, polyline):
    """Slow reference: arc length along ``polyline`` of a point lying on it."""
    walked = 0.0
    best = (np.inf, 0.0)
    for a, b in zip(polyline[:-1], polyline[1:]):
        seg = b - a
        length = np.linalg.norm(seg)
        t = 0.0 if length == 0 else np.clip(np.dot(point - a, seg) / length ** 2, 0.0, 1.0)
        gap = np.linalg.norm(a + t * seg - point)
        if gap < best[0]:
            best = (gap, walked + t * length)
        walked += length
    assert best[0] < 1e-9, "particle is not on its fibre"
    return best[1]


def particle_arc_lengths(points, offsets, particles, n):
    return np.array([[arc_length_of(particles[f * n + j], points[offsets[f]:offsets[f + 1]])
                      for j in range(n)] for f in range(len(offsets) - 1)])


@pytest.mark.parametrize("n", [2, 3, 7, 20])
def test_random_particles_lie_on_the_fibre_inside_their_own_interval(n):
    points, offsets = bent_fibres()
    particles, fibre_id, fibre_index, fixed = resample_fibres(points, offsets, n, True, 11)
    lengths = fibre_lengths(points, offsets)
    arc = particle_arc_lengths(points, offsets, particles, n)
    h = lengths[:, None] / (n - 1)
    k = np.arange(n)[None, :]
    tol = 1e-9
    # particle k in interval k = [k h, (k + 1) h]; the insertion particle at the far end
    assert (arc[:, :-1] >= k[:, :-1] * h - tol).all()
    assert (arc[:, :-1] <= (k[:, :-1] + 1) * h + tol).all()
    assert np.allclose(arc[:, -1], lengths)
    assert (np.diff(arc, axis=1) >= -tol).all()
    if n > 2:  # randomised: not all at the interval starts
        assert not np.allclose(arc[:, 1:-1], k[:, 1:-1] * h)


def test_end_particles_are_the_fibre_end_points_exactly_and_fixed():
    points, offsets = bent_fibres()
    n = 9
    particles, fibre_id, fibre_index, fixed = resample_fibres(points, offsets, n, True, 0)
    grid = particles.reshape(-1, n, 3)
    assert np.array_equal(grid[:, 0], points[offsets[:-1]])
    assert np.array_equal(grid[:, -1], points[offsets[1:] - 1])
    assert np.array_equal(fixed.reshape(-1, n)[:, [0, -1]], np.ones((len(grid), 2)))
    assert fixed.reshape(-1, n)[:, 1:-1].sum() == 0
    assert fixed.dtype == np.uint8 and fibre_id.dtype == np.int32 and fibre_index.dtype == np.int32
    assert np.array_equal(fibre_id, np.repeat(np.arange(len(grid)), n))
    assert np.array_equal(fibre_index, np.tile(np.arange(n), len(grid)))


def test_randomise_off_gives_equal_arc_length_spacing():
    points, offsets = bent_fibres()
    n = 12
    particles, *_ = resample_fibres(points, offsets, n, False, 5)
    arc = particle_arc_lengths(points, offsets, particles, n)
    expected = fibre_lengths(points, offsets)[:, None] * np.arange(n) / (n - 1)
    assert np.allclose(arc, expected, atol=1e-9)
    # and independent of the seed
    again, *_ = resample_fibres(points, offsets, n, False, 99)
    assert np.array_equal(particles, again)


def test_straight_fibre_randomise_off_matches_linspace():
    points = np.array([[0.0, 0, 0], [1.0, 0, 0], [10.0, 0, 0]])
    particles, *_ = resample_fibres(points, [0, 3], 6, False)
    assert np.allclose(particles[:, 0], np.linspace(0, 10, 6))
    assert np.allclose(particles[:, 1:], 0)


def test_placement_is_reproducible_with_the_seed_and_differs_with_another():
    points, offsets = bent_fibres()
    a, *_ = resample_fibres(points, offsets, 20, True, 7)
    b, *_ = resample_fibres(points, offsets, 20, True, 7)
    c, *_ = resample_fibres(points, offsets, 20, True, 8)
    d, *_ = resample_fibres(points, offsets, 20, True, [7, 1])
    assert np.array_equal(a, b)
    assert not np.allclose(a, c)
    assert not np.allclose(a, d)


def test_repeated_vertices_inside_a_fibre_are_harmless():
    points = np.array([[0.0, 0, 0], [0.0, 0, 0], [0, 0, 5.0], [0, 0, 5.0], [0, 0, 10.0]])
    particles, *_ = resample_fibres(points, [0, 5], 11, False)
    assert np.allclose(particles[:, 2], np.arange(11.0))
    assert np.isfinite(particles).all()


def test_inputs_are_not_modified():
    points, offsets = bent_fibres()
    p0, o0 = points.copy(), offsets.copy()
    resample_fibres(points, offsets, 10, True, 1)
    assert np.array_equal(points, p0) and np.array_equal(offsets, o0)


@pytest.mark.parametrize("points, offsets, n, message", [
    (np.zeros((2, 3)) + [[0, 0, 0], [1, 0, 0]], [0, 2], 1, "at least 2"),
    (np.zeros((0, 3)), [0], 5, "has no fibres"),
    (np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]), [0, 2, 3], 5, "fibre 1 has 1 point;"),
    (np.array([[0.0, 0, 0], [0, 0, 0]]), [0, 2], 5, "fibre 0 has zero length"),
    (np.array([[0.0, 0, 0], [1, 0, 0], [0, 0, 0], [np.nan, 0, 0]]), [0, 2, 4], 5,
     "fibre 1 has a NaN"),
])
def test_bad_fibres_are_refused_naming_the_block_and_fibre(points, offsets, n, message):
    with pytest.raises(MuscleMSSError, match=message) as err:
        resample_fibres(points, offsets, n, True, 0, where="fibres.vtm block 'gracilis'")
    assert "fibres.vtm block 'gracilis'" in str(err.value)
