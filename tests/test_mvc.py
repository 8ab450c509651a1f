"""Mean value coordinates (core/mvc.py): the promises of Ju, Schaefer & Warren (2005)."""
import numpy as np
import pytest
from scipy.spatial import ConvexHull

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.mesh_checks import surface_problems
from muscle_mss.core.mvc import (ILL_CONDITIONED, WELL_CONDITIONED, bounded_coordinates,
                                mean_value_coordinates, mvc_deform, nearest_point_weights)
from muscle_mss.core.volume import signed_volume

OFFSET = np.array([310.0, -205.0, 820.0])   # mm: muscles sit far from the origin


def _rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _outward_hull(points):
    hull = ConvexHull(points)
    tri = hull.simplices.copy()
    normal = np.cross(points[tri[:, 1]] - points[tri[:, 0]], points[tri[:, 2]] - points[tri[:, 0]])
    inward = (normal * hull.equations[:, :3]).sum(axis=1) < 0
    tri[inward] = tri[inward][:, ::-1]
    return tri


def cube_cage():
    """Unit-ish cube (edge 20 mm), rotated and moved away from the origin."""
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    points = (corners - 0.5) * 20.0 @ _rotation(1).T + OFFSET
    return points, _outward_hull(points)


def sphere_cage(n=120):
    """Radius 15 mm, vertices on a Fibonacci spiral (an irregular triangulation)."""
    i = np.arange(n) + 0.5
    polar = np.arccos(1 - 2 * i / n)
    azimuth = np.pi * (1 + 5 ** 0.5) * i
    unit = np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar),
                     np.cos(polar)], axis=1)
    points = unit * 15.0 + OFFSET
    return points, _outward_hull(points)


def l_cage():
    """Concave L-shaped prism: L = [0,2]x[0,1] u [0,1]x[0,2] (x 10 mm), height 10 mm."""
    outline = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], float) * 10.0
    n = len(outline)
    points = np.concatenate([np.column_stack([outline, np.zeros(n)]),
                             np.column_stack([outline, np.full(n, 10.0)])])
    fan = [(0, i, i + 1) for i in range(1, n - 1)]   # vertex 0 sees the whole L
    triangles = [(c, b, a) for a, b, c in fan] + [(a + n, b + n, c + n) for a, b, c in fan]
    for i in range(n):
        j = (i + 1) % n
        triangles += [(i, j, j + n), (i, j + n, i + n)]
    points = (points - [10, 10, 5]) @ _rotation(2).T + OFFSET
    return points, np.array(triangles)


def l_inside(points):
    local = (points - OFFSET) @ _rotation(2) + [10, 10, 5]
    x, y, z = local.T
    in_l = ((x > 0) & (y > 0) & (z > 0) & (z < 10)
            & (((x < 20) & (y < 10)) | ((x < 10) & (y < 20))))
    return in_l


CAGES = {"cube": cube_cage, "sphere": sphere_cage, "L": l_cage}


def _inside_convex(points, cage_points, triangles):
    a, b, c = (cage_points[triangles[:, k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    return (np.einsum("tk,ptk->pt", normal, points[:, None, :] - a[None]) < 0).all(axis=1)


def _probe_points(cage_points, n, seed):
    """Points in the cage's bounding box grown by 40 %: inside and outside."""
    rng = np.random.default_rng(seed)
    low, high = cage_points.min(axis=0), cage_points.max(axis=0)
    centre, half = (low + high) / 2, (high - low) / 2
    return centre + rng.uniform(-1.4, 1.4, (n, 3)) * half


def reference_jsw(cage_points, triangles, x):
    """The paper's trigonometric pseudocode for one generic point (no degenerate case)."""
    u = cage_points - x
    d = np.linalg.norm(u, axis=1)
    u = u / d[:, None]
    w = np.zeros(len(cage_points))
    for tri in triangles:
        uu, dd = u[tri], d[tri]
        theta = np.array([2 * np.arcsin(np.linalg.norm(uu[(i + 1) % 3] - uu[(i - 1) % 3]) / 2)
                          for i in range(3)])
        h = theta.sum() / 2
        c = np.array([2 * np.sin(h) * np.sin(h - theta[i])
                      / (np.sin(theta[(i + 1) % 3]) * np.sin(theta[(i - 1) % 3])) - 1
                      for i in range(3)])
        s = np.sign(np.linalg.det(uu)) * np.sqrt(1 - c ** 2)
        for i in range(3):
            w[tri[i]] += ((theta[i] - c[(i + 1) % 3] * theta[(i - 1) % 3]
                           - c[(i - 1) % 3] * theta[(i + 1) % 3])
                          / (dd[i] * np.sin(theta[(i + 1) % 3]) * s[(i - 1) % 3]))
    return w / w.sum()


def reference_sphere_integral(cage_points, triangles, x, directions=40000):
    """The definition: integrate over the unit sphere around x, along each direction, every
    crossing of the cage with its barycentric hat functions over the distance, signed +1 where
    the ray leaves the solid and -1 where it enters; normalise."""
    i = np.arange(directions) + 0.5
    polar = np.arccos(1 - 2 * i / directions)
    azimuth = np.pi * (1 + 5 ** 0.5) * i
    rays = np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar),
                     np.cos(polar)], axis=1)
    a, b, c = (cage_points[triangles[:, k]] - x for k in range(3))
    e1, e2 = b - a, c - a
    normal = np.cross(e1, e2)
    weights = np.zeros(len(cage_points))
    for chunk in np.array_split(rays, 20):
        # Ray r hits triangle t at distance s with barycentric (1 - beta - gamma, beta, gamma):
        # s r = a + beta e1 + gamma e2, by Cramer's rule.
        det = np.einsum("rk,tk->rt", chunk, normal)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.einsum("tk,tk->t", a, normal)[None] / det
            beta = -np.einsum("rk,tk->rt", chunk, np.cross(a, e2)) / det
            gamma = np.einsum("rk,tk->rt", chunk, np.cross(a, e1)) / det
        hit = (s > 0) & (beta >= 0) & (gamma >= 0) & (beta + gamma <= 1)
        leaving = np.sign(np.einsum("rk,tk->rt", chunk, normal))
        scale = np.where(hit, leaving / np.where(hit, s, 1.0), 0.0)
        for k, bary in enumerate((1 - beta - gamma, beta, gamma)):
            np.add.at(weights, triangles[:, k], (scale * bary).sum(axis=0))
    return weights / weights.sum()


@pytest.mark.parametrize("name", sorted(CAGES))
def test_cages_of_the_tests_are_valid(name):
    points, triangles = CAGES[name]()
    assert surface_problems(points, triangles) == []


@pytest.mark.parametrize("name", sorted(CAGES))
def test_reproduce_linear_functions_inside_and_outside(name):
    cage, triangles = CAGES[name]()
    x = _probe_points(cage, 400, seed=3)
    inside = l_inside(x) if name == "L" else _inside_convex(x, cage, triangles)
    assert 20 < inside.sum() < len(x) - 20
    w = mean_value_coordinates(cage, triangles, x)
    assert w.shape == (len(x), len(cage))
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(w @ cage, x, rtol=0, atol=1e-9)
    slope, intercept = np.array([0.3, -1.7, 2.2]), 5.0
    np.testing.assert_allclose(w @ (cage @ slope + intercept), x @ slope + intercept,
                               rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", ["cube", "sphere"])
def test_non_negative_inside_a_convex_cage(name):
    cage, triangles = CAGES[name]()
    x = _probe_points(cage, 600, seed=4)
    x = x[_inside_convex(x, cage, triangles)]
    assert len(x) > 50
    w = mean_value_coordinates(cage, triangles, x)
    assert w.min() >= 0.0
    # Outside, some weights must be negative (a check that the test can fail).
    outside = cage.mean(axis=0)[None] + [[60.0, 0.0, 0.0]]
    assert mean_value_coordinates(cage, triangles, outside).min() < 0.0


@pytest.mark.parametrize("name", sorted(CAGES))
def test_exact_on_a_vertex_an_edge_and_a_face(name):
    cage, triangles = CAGES[name]()
    a, b, c = triangles[len(triangles) // 2]
    on_edge = 0.3 * cage[a] + 0.7 * cage[b]
    on_face = 0.2 * cage[a] + 0.5 * cage[b] + 0.3 * cage[c]
    w = mean_value_coordinates(cage, triangles, np.stack([cage[c], on_edge, on_face]))
    expected = np.zeros((3, len(cage)))
    expected[0, c] = 1.0
    expected[1, [a, b]] = 0.3, 0.7
    expected[2, [a, b, c]] = 0.2, 0.5, 0.3
    np.testing.assert_allclose(w, expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", sorted(CAGES))
def test_agrees_with_the_papers_formula(name):
    cage, triangles = CAGES[name]()
    x = _probe_points(cage, 12, seed=6)
    w = mean_value_coordinates(cage, triangles, x)
    expected = np.array([reference_jsw(cage, triangles, p) for p in x])
    np.testing.assert_allclose(w, expected, rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", ["cube", "L"])
def test_agrees_with_the_integral_over_the_sphere(name):
    cage, triangles = CAGES[name]()
    centre = cage.mean(axis=0)
    x = np.stack([centre + [0.5, -1.0, 1.5], centre + [26.0, 3.0, -4.0]])
    w = mean_value_coordinates(cage, triangles, x)
    for row, point in zip(w, x):
        np.testing.assert_allclose(row, reference_sphere_integral(cage, triangles, point),
                                   rtol=0, atol=2e-3)


def test_degenerate_places_never_give_nan():
    cage, triangles = cube_cage()
    a, b, c = cage[triangles[0]]
    rng = np.random.default_rng(7)
    t = rng.uniform(-2.0, 3.0, (200, 1))
    u = rng.uniform(-2.0, 3.0, (200, 1))
    x = np.concatenate([
        cage,                                           # on the vertices
        a + t * (b - a),                                # on edge lines, inside and outside
        a + t * (b - a) + u * (c - a),                  # in a face's plane, on and off it
        a + t * (b - a) + 1e-10 * rng.normal(size=(200, 3)),   # next to edge lines
        cage[:1] + 1e-11 * rng.normal(size=(50, 3)),    # next to a vertex
    ])
    w = mean_value_coordinates(cage, triangles, x)
    assert np.isfinite(w).all()
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(w @ cage, x, rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", sorted(CAGES))
def test_affine_motion_of_the_cage_is_reproduced(name):
    cage, triangles = CAGES[name]()
    surface, surface_triangles = sphere_cage(200)
    surface = (surface - OFFSET) * 0.9 + cage.mean(axis=0)   # a closed surface in and around
    matrix = np.array([[1.3, 0.2, -0.1], [0.1, 0.8, 0.3], [-0.2, 0.1, 1.1]])
    shift = np.array([4.0, -7.0, 12.0])
    w = mean_value_coordinates(cage, triangles, surface)
    moved = mvc_deform(w, cage @ matrix.T + shift)
    np.testing.assert_allclose(moved, surface @ matrix.T + shift, rtol=0, atol=1e-9)
    ratio = signed_volume(moved, surface_triangles) / signed_volume(surface, surface_triangles)
    assert ratio == pytest.approx(np.linalg.det(matrix), rel=1e-9)


def test_bad_input_is_refused():
    cage, triangles = cube_cage()
    with pytest.raises(MuscleMSSError, match="muscle 'm': cage is open"):
        mean_value_coordinates(cage, triangles[1:], cage.mean(axis=0)[None],
                               where="muscle 'm': cage")
    with pytest.raises(MuscleMSSError, match="point 1 to express has a NaN"):
        mean_value_coordinates(cage, triangles, np.array([[0.0, 0, 0], [np.nan, 0, 0]]))
    with pytest.raises(MuscleMSSError, match="at least 4 points"):
        mean_value_coordinates(cage[:3], triangles[:1], cage[:1])


@pytest.mark.parametrize("name", sorted(CAGES))
def test_next_to_a_vertex_an_edge_and_a_face_inside_and_outside(name):
    """Points on and next to the cage (1e-9 to 0.1 mm off a face, an edge and a vertex, on
    both sides) get weights that sum to one, reproduce them, stay bounded (they approach the
    barycentric weights on the cage), and are left as they are by bounded_coordinates."""
    cage, triangles = CAGES[name]()
    a, b, c = (cage[triangles[:, k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    places = [0.2 * a + 0.5 * b + 0.3 * c, 0.4 * a + 0.6 * b, a]
    x = np.concatenate([place + side * h * normal for place in places
                        for h in (0.0, 1e-9, 1e-6, 1e-3, 0.1) for side in (1.0, -1.0)])
    w = mean_value_coordinates(cage, triangles, x)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(w @ cage, x, rtol=0, atol=1e-9)
    assert np.abs(w).sum(axis=1).max() < 1.1
    np.testing.assert_array_equal(bounded_coordinates(cage, triangles, x), w)


def folded_cube():
    """The cube cage with corner 0 pushed through the opposite corner: closed, outward in
    volume, but folded over itself (as a lattice cage whose ring fibres cross)."""
    cage, triangles = cube_cage()
    centre = cage.mean(axis=0)
    cage[0] = centre + 1.6 * (centre - cage[0])
    return cage, triangles


def test_a_folded_cage_gets_bounded_weights():
    cage, triangles = folded_cube()
    assert surface_problems(cage, triangles) == []
    x = cage.mean(axis=0) + np.random.default_rng(8).uniform(-25.0, 25.0, (4000, 3))
    w = mean_value_coordinates(cage, triangles, x)
    spread = np.abs(w).sum(axis=1)
    # the control: next to the fold the total weight cancels and the weights explode
    assert spread.max() > 1000.0
    well, ill = spread <= WELL_CONDITIONED, spread >= ILL_CONDITIONED
    assert well.sum() > 100 and ill.sum() > 100 and (~well & ~ill).sum() > 10
    bounded = bounded_coordinates(cage, triangles, x)
    np.testing.assert_allclose(bounded.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    assert np.abs(bounded).sum(axis=1).max() <= WELL_CONDITIONED + 1e-9
    np.testing.assert_array_equal(bounded[well], w[well])
    np.testing.assert_array_equal(bounded[ill], nearest_point_weights(cage, triangles, x[ill]))
    np.testing.assert_allclose(bounded[well] @ cage, x[well], rtol=0, atol=1e-9)


def test_nearest_point_weights_off_a_face_an_edge_and_a_corner():
    cage, triangles = cube_cage()
    centre = cage.mean(axis=0)
    # corner 0 is (0, 0, 0) of the unit cube, corner 4 (1, 0, 0), corner 1 (0, 0, 1)
    on_face = 0.3 * cage[0] + 0.45 * cage[4] + 0.25 * cage[1]     # a point of the face y = 0
    outward = cage[0] - cage[2]                                   # -y, 20 mm
    edge = 0.5 * (cage[0] + cage[4])
    x = np.stack([on_face + 0.4 * outward, on_face - 0.1 * outward,
                  edge + 0.5 * (edge - centre), cage[0] + 0.3 * (cage[0] - centre)])
    w = nearest_point_weights(cage, triangles, x)
    assert w.min() >= 0.0 and (np.count_nonzero(w, axis=1) <= 3).all()
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(w[:2] @ cage, [on_face, on_face], rtol=0, atol=1e-9)
    np.testing.assert_allclose(w[2, [0, 4]], [0.5, 0.5], rtol=0, atol=1e-12)
    np.testing.assert_allclose(w[3, 0], 1.0, rtol=0, atol=1e-12)
