"""The Fibre Generator's core (muscle_mss.core.fibre_generation): fibres along a harmonic field
inside a muscle surface, checked on shapes whose fibres are known: a cylinder between its end
caps, a curved tube, a spindle between two tendon patches."""
import numpy as np
import pytest

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.fibre_generation import concentric_disc, generate_fibres
from muscle_mss.core.volume import signed_volume, winding_numbers


def tube(centre, tangent, radius, length, around=48, along=60, cap_rings=6):
    """A closed, outward triangle surface around the centreline ``centre(s)`` (s in [0, 1],
    unit ``tangent(s)``) of ``radius(s)`` mm, each end closed by a disc of ``cap_rings``
    concentric rings; returns ``(points, triangles, origin_cap, insertion_cap)``, the caps'
    vertices as masks."""
    s = np.linspace(0.0, 1.0, along)
    c, t = np.array([centre(v) for v in s]), np.array([tangent(v) for v in s])
    helper = np.array([0.0, 0.0, 1.0]) if abs(t[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    n1 = np.cross(t, helper)
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    n2 = np.cross(t, n1)
    phi = 2 * np.pi * np.arange(around) / around
    r = np.array([radius(v) for v in s])

    def ring(i, scale=1.0):
        return c[i] + scale * r[i] * (np.cos(phi)[:, None] * n1[i] + np.sin(phi)[:, None] * n2[i])

    # rows of ``around`` points: the origin cap's inner rings, the side, the insertion cap's
    rows = [ring(0, k / cap_rings) for k in range(1, cap_rings)]
    rows += [ring(i) for i in range(along)]
    rows += [ring(along - 1, k / cap_rings) for k in range(cap_rings - 1, 0, -1)]
    points = np.concatenate(rows + [c[[0, -1]]])
    triangles = []
    for i in range(len(rows) - 1):
        for j in range(around):
            a, b = i * around + j, i * around + (j + 1) % around
            triangles += [(a, b, b + around), (a, b + around, a + around)]
    first, last = len(rows) * around, len(rows) * around + 1
    base = (len(rows) - 1) * around
    for j in range(around):
        triangles.append((first, (j + 1) % around, j))
        triangles.append((last, base + j, base + (j + 1) % around))
    triangles = np.array(triangles)
    if signed_volume(points, triangles) < 0:
        triangles = triangles[:, ::-1].copy()
    origin = np.zeros(len(points), dtype=bool)
    insertion = np.zeros(len(points), dtype=bool)
    origin[:cap_rings * around], origin[first] = True, True
    insertion[base - (cap_rings - 1) * around:base + around], insertion[last] = True, True
    return points, triangles, origin, insertion


def straight(length):
    return (lambda s: np.array([0.0, 0.0, length * s])), (lambda s: np.array([0.0, 0.0, 1.0]))


def angles_to(fibres, axis_of) -> np.ndarray:
    """Degrees between each fibre segment and ``axis_of(points)`` at its middle."""
    out = []
    for f in range(fibres.count):
        p = fibres.fibre(f)
        d = np.diff(p, axis=0)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        axis = axis_of(0.5 * (p[1:] + p[:-1]))
        out.append(np.degrees(np.arccos(np.clip(np.abs((d * axis).sum(axis=1)), 0, 1))))
    return np.array(out)


def test_the_concentric_map_spaces_a_square_grid_evenly_on_the_disc():
    disc = concentric_disc(8, 8)
    assert np.hypot(*disc.T).max() == pytest.approx(7 / 8)
    gaps = np.sort(np.linalg.norm(disc[:, None] - disc[None], axis=2), axis=1)[:, 1]
    assert (gaps.max() - gaps.min()) / gaps.mean() < 0.12
    assert np.allclose(disc.mean(axis=0), 0.0, atol=1e-12)


@pytest.fixture(scope="module")
def cylinder():
    points, triangles, origin, insertion = tube(*straight(80.0), lambda s: 10.0, 80.0)
    return points, triangles, generate_fibres(points, triangles, origin, insertion,
                                              where="cylinder")


def test_a_cylinders_fibres_run_along_its_axis_spread_evenly_across_it(cylinder):
    points, triangles, fibres = cylinder
    assert fibres.count == 64 and fibres.grid.shape == (64, 2)
    assert sorted(map(tuple, fibres.grid)) == [(r, c) for r in range(8) for c in range(8)]
    assert angles_to(fibres, lambda p: np.array([0.0, 0.0, 1.0])).max() <= 1.0
    ends = np.array([[fibres.fibre(f)[0], fibres.fibre(f)[-1]] for f in range(fibres.count)])
    assert np.all(ends[:, 0, 2] < 1.5) and np.all(ends[:, 1, 2] > 78.5)     # on the caps
    middle = np.array([fibres.fibre(f)[15, :2] for f in range(fibres.count)])
    gaps = np.sort(np.linalg.norm(middle[:, None] - middle[None], axis=2), axis=1)[:, 1]
    assert (gaps.max() - gaps.min()) / gaps.mean() <= 0.2
    assert np.hypot(*middle.T).max() > 7.0                     # across the whole section
    assert np.all(winding_numbers(fibres.points, points, triangles) > 0.5)


def test_fibres_are_deterministic_and_do_not_cross(cylinder):
    points, triangles, fibres = cylinder
    again = generate_fibres(points, triangles, *tube(*straight(80.0), lambda s: 10.0,
                                                     80.0)[2:], where="cylinder")
    np.testing.assert_array_equal(again.points, fibres.points)
    at = fibres.points.reshape(fibres.count, -1, 3)
    for k in range(1, at.shape[1] - 1):
        d = np.linalg.norm(at[:, None, k] - at[None, :, k], axis=2)
        assert d[~np.eye(len(d), dtype=bool)].min() > 0.5


def test_a_curved_tubes_fibres_follow_its_centreline():
    bend, radius = 60.0, 8.0
    sweep = np.pi / 2
    points, triangles, origin, insertion = tube(
        lambda s: bend * np.array([np.cos(sweep * s), np.sin(sweep * s), 0.0]),
        lambda s: np.array([-np.sin(sweep * s), np.cos(sweep * s), 0.0]),
        lambda s: radius, bend * sweep)
    fibres = generate_fibres(points, triangles, origin, insertion, where="curved tube")
    centreline = sweep / (2 * np.sin(sweep / 2))             # arc / chord of a circular arc
    for f in range(fibres.count):
        p = fibres.fibre(f)
        arc = np.linalg.norm(np.diff(p, axis=0), axis=1).sum()
        assert arc / np.linalg.norm(p[-1] - p[0]) == pytest.approx(centreline, rel=0.02)
    assert np.all(winding_numbers(fibres.points, points, triangles) > 0.5)


def test_a_spindles_fibres_start_and_end_on_its_tendon_patches_and_stay_inside():
    length, belly = 120.0, 15.0
    points, triangles, _, _ = tube(*straight(length),
                                   lambda s: 1.5 + belly * np.sin(np.pi * s) ** 1.5, length)
    origin, insertion = points[:, 2] < 4.0, points[:, 2] > length - 4.0
    fibres = generate_fibres(points, triangles, origin, insertion, where="spindle")
    patch = {"origin": points[origin], "insertion": points[insertion]}
    for f in range(fibres.count):
        p = fibres.fibre(f)
        for end, name in ((p[0], "origin"), (p[-1], "insertion")):
            assert np.linalg.norm(patch[name] - end, axis=1).min() < 3.0, (f, name)
    assert np.all(winding_numbers(fibres.points, points, triangles) > 0.5)


def test_an_area_the_surface_does_not_have_is_refused_naming_the_muscle():
    points, triangles, origin, _ = tube(*straight(80.0), lambda s: 10.0, 80.0)
    with pytest.raises(MuscleMSSError, match="gracilis: .*insertion area"):
        generate_fibres(points, triangles, origin, np.zeros(len(points), dtype=bool),
                        where="gracilis")
