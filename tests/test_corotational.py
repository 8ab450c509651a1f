"""Co-rotational springs (core/quasi_static/corotational.py, the solver's Springs): the rotation
fit against the SVD, the energy's invariances and gradient against a plain NumPy reference, a
lone spring against Hooke, and the quasi-static solve with them (net force, rest, cap, the
filter property)."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from muscle_mss.core import model as S
from muscle_mss.core import quasi_static as Q
from muscle_mss.core.connective_tissue import tissue_stiffness
from muscle_mss.core.quasi_static.corotational import (add_corotational_energy,
                                                       corotational_state, fit_rotation,
                                                       spring_tension)
from muscle_mss.core.settings import (DEFAULT_BULK_MODULUS, METHOD_QUASI_STATIC,
                                      SPRINGS_COROTATIONAL, SPRINGS_HOOKE, SolverSettings)
from muscle_mss.core.solver import solve
from muscle_mss.filters import MSSCollisionSolver

from test_mss import lattice
from test_quasi_static import filter_solve, reference_forces


def corotational(**values) -> SolverSettings:
    """Quasi-static settings with co-rotational springs and an isotropic tissue (the references
    here write that energy out), then ``values``."""
    return SolverSettings.build(**{"method": METHOD_QUASI_STATIC,
                                   "springs": SPRINGS_COROTATIONAL, "tissue_along": 1.0,
                                   **values})


def polar_rotation(a):
    """The rotation maximising trace(R^T a), by the SVD (a reflection never)."""
    u, _, vt = np.linalg.svd(a)
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt


def reference_pulls(x, rest_positions, springs, rest_length, stiffness):
    """Each co-rotational spring's pull (S, 3) on its second particle and energy (S,), in plain
    NumPy, the rotations by the SVD."""
    vectors = rest_positions[springs[:, 1]] - rest_positions[springs[:, 0]]
    vectors *= (rest_length / np.linalg.norm(vectors, axis=1))[:, None]
    d = x[springs[:, 1]] - x[springs[:, 0]]
    fit = np.zeros((len(x), 3, 3))
    for (a, b), k, dd, rv in zip(springs, stiffness, d, vectors):
        fit[a] += k * np.outer(dd, rv)
        fit[b] += k * np.outer(dd, rv)
    rotation = np.array([polar_rotation(f) for f in fit])
    ra = d - np.einsum("sij,sj->si", rotation[springs[:, 0]], vectors)
    rb = d - np.einsum("sij,sj->si", rotation[springs[:, 1]], vectors)
    energy = 0.25 * stiffness * (np.einsum("ij,ij->i", ra, ra) + np.einsum("ij,ij->i", rb, rb))
    return -0.5 * stiffness[:, None] * (ra + rb), energy


def reference_energy(x, rest_positions, springs, rest_length, stiffness):
    """The co-rotational energy and force (n, 3) on every particle in plain NumPy."""
    pulls, energy = reference_pulls(x, rest_positions, springs, rest_length, stiffness)
    force = np.zeros_like(x)
    np.add.at(force, springs[:, 1], pulls)
    np.add.at(force, springs[:, 0], -pulls)
    return energy.sum(), force


def kernel_energy(x, rest_positions, springs, rest_length, stiffness):
    """The kernel's energy and gradient (n, 3) for one muscle holding every particle."""
    n = len(x)
    vectors = rest_positions[springs[:, 1]] - rest_positions[springs[:, 0]]
    vectors *= (rest_length / np.linalg.norm(vectors, axis=1))[:, None]
    state = corotational_state(vectors, n)
    gradient, energy = np.zeros((3, n)), np.zeros(1)
    add_corotational_energy(np.ascontiguousarray(x.T), gradient, energy, springs, stiffness,
                            np.array([0, len(springs)]), np.array([0, n]), state)
    return energy[0], gradient.T


@pytest.fixture(scope="module")
def block():
    points, springs, rest = lattice(3, 3, 4, spacing=(2.0, 2.5, 3.0))
    return points, np.asarray(springs, dtype=np.int64), rest, np.full(len(rest), 10.0)


def test_rotation_fit_is_the_polar_rotation_even_for_reflections_and_thin_matrices():
    rng = np.random.default_rng(3)
    for trial in range(300):
        a = rng.normal(size=(3, 3)) * 10.0 ** rng.uniform(-3, 4)
        if trial % 3 == 1:          # nearly rank one or two
            a = a @ np.diag([1.0, 10.0 ** -rng.uniform(1, 6), 10.0 ** -rng.uniform(3, 9)])
        frame = a.reshape(1, 9).copy()
        fit_rotation(frame, 0)
        r = frame.reshape(3, 3)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-10)
        assert np.linalg.det(r) > 0.0
        best = polar_rotation(a)
        assert np.trace(r.T @ a) >= np.trace(best.T @ a) - 1e-12 * np.abs(a).max()
    # the zero matrix: any rotation fits; the identity is kept
    frame = np.zeros((1, 9))
    fit_rotation(frame, 0)
    np.testing.assert_array_equal(frame.reshape(3, 3), np.eye(3))


def test_energy_is_zero_at_rest_and_under_rigid_motion(block):
    points, springs, rest, k = block
    for turn in (np.eye(3), Rotation.from_rotvec([0.4, -2.5, 1.0]).as_matrix()):
        energy, gradient = kernel_energy(points @ turn.T + [3.0, -1.0, 7.0], points, springs,
                                         rest, k)
        assert energy < 1e-18 and np.abs(gradient).max() < 1e-10


def test_energy_and_gradient_match_the_reference_and_finite_differences(block):
    points, springs, rest, k = block
    rng = np.random.default_rng(4)
    turn = Rotation.from_rotvec([1.0, 0.3, -0.7]).as_matrix()
    x = points @ turn.T + rng.normal(scale=0.4, size=points.shape)
    x[:, 2] *= 0.8                                   # compressed along the fibres
    energy, gradient = kernel_energy(x, points, springs, rest, k)
    expected, force = reference_energy(x, points, springs, rest, k)
    assert energy > 1.0
    np.testing.assert_allclose(energy, expected, rtol=1e-12)
    np.testing.assert_allclose(gradient, -force, atol=1e-9 * np.abs(force).max())
    h = 1e-6
    for p, axis in ((0, 0), (17, 2), (30, 1)):
        up, down = x.copy(), x.copy()
        up[p, axis] += h
        down[p, axis] -= h
        difference = (kernel_energy(up, points, springs, rest, k)[0]
                      - kernel_energy(down, points, springs, rest, k)[0]) / (2 * h)
        np.testing.assert_allclose(difference, gradient[p, axis], rtol=1e-6, atol=1e-8)


def test_a_lone_spring_costs_what_a_hooke_spring_does_at_any_length_and_turn():
    rest_positions = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    springs, rest, k = np.array([[0, 1]]), np.array([2.0]), np.array([10.0])
    rng = np.random.default_rng(6)
    for _ in range(20):
        x = rng.normal(scale=2.0, size=(2, 3))
        length = np.linalg.norm(x[1] - x[0])
        energy, _ = kernel_energy(x, rest_positions, springs, rest, k)
        np.testing.assert_allclose(energy, 0.5 * k[0] * (length - rest[0]) ** 2, rtol=1e-10)
        np.testing.assert_allclose(spring_tension(_model_of(x, rest_positions, springs, rest,
                                                            k), x),
                                   k * abs(length - rest[0]), rtol=1e-10)


def _model_of(x, rest_positions, springs, rest, k):
    n = len(x)
    return S.MSSModel(["m"], np.array([0, n]), x, np.zeros(n, bool), np.ones(n),
                      np.zeros(n, bool), np.zeros(n), np.zeros(n, int), np.arange(n), springs,
                      rest, k, np.zeros(len(k)), rest_positions=rest_positions)


@pytest.fixture(scope="module")
def compressed():
    """A 4 x 4 x 10 lattice muscle (with a cage) whose insertion end is pushed 6 mm toward its
    origin and 3 mm across, the rest posed with a jitter: its springs compressed."""
    points, springs, rest = lattice(4, 4, 10, spacing=(2.0, 2.0, 2.5))
    n = len(points)
    row, col, index = (a.ravel() for a in np.meshgrid(np.arange(4), np.arange(4),
                                                        np.arange(10), indexing="ij"))
    boundary = (row == 0) | (row == 3) | (col == 0) | (col == 3) | (index == 0) | (index == 9)
    posed = points + np.random.default_rng(5).normal(scale=0.2, size=points.shape)
    posed[:, 2] *= 1.0 - 6.0 / 22.5 * index / 9.0
    posed[index == 9] = points[index == 9] + [3.0, 0.0, -6.0]
    posed[index == 0] = points[index == 0]
    return S.MSSModel(["m"], np.array([0, n]), posed, (index == 0) | (index == 9), np.ones(n),
                      boundary, np.where(boundary, 0.9, 0.0), row * 4 + col, index, springs,
                      rest, np.full(len(rest), 10.0), np.full(len(rest), 0.5),
                      np.stack([row, col], 1), points)


def test_equilibrium_net_force_with_corotational_springs_is_below_the_tolerance(compressed):
    model, ratio, tolerance = compressed, 0.1, 1e-4
    result = solve(model, settings=corotational(tolerance=tolerance, iterations=3000,
                                                connective_tissue=ratio))
    assert result.converged and result.stopped_by == "tolerance"
    n = len(model.fixed)
    x = result.positions
    _, springs = reference_energy(x, model.rest_positions, model.springs, model.rest_length,
                                  model.stiffness)
    volume = reference_forces(S.MSSModel(**{**model.__dict__,
                                            "stiffness": np.zeros_like(model.stiffness)}),
                              x, DEFAULT_BULK_MODULUS)
    k = tissue_stiffness(model, np.arange(n), model.fixed, ratio)
    force = springs + volume - k[:, None] * (x - model.positions)
    free = ~model.fixed
    diagonal = np.bincount(model.springs.ravel(), np.repeat(model.stiffness, 2))
    bound = 2 * (diagonal.max() + k.max()) * tolerance
    assert np.linalg.norm(force[free], axis=1).max() < bound
    assert np.linalg.norm(springs[free], axis=1).max() > 100 * bound      # not trivially
    # a different answer from Hooke's springs, which are soft across when compressed
    hooke = solve(model, settings=corotational(springs=SPRINGS_HOOKE, tolerance=tolerance,
                                               iterations=3000, connective_tissue=ratio))
    assert hooke.converged
    assert np.linalg.norm(hooke.positions - x, axis=1).max() > 100 * tolerance
    # the share: the tissue's pull over the co-rotational springs' pulls
    pulls, _ = reference_pulls(x, model.rest_positions, model.springs, model.rest_length,
                               model.stiffness)
    tension = np.linalg.norm(pulls, axis=1).sum()
    np.testing.assert_allclose(result.tissue_share[0], 100.0 * np.linalg.norm(
        k[:, None] * (x - model.positions), axis=1).sum() / tension, rtol=1e-9)


def test_model_at_rest_stays_at_rest_and_cap_times_ten_agrees(compressed):
    rest = S.MSSModel(**{**compressed.__dict__, "positions": compressed.rest_positions.copy()})
    result = Q.solve(rest, settings=corotational(connective_tissue=0.1))
    assert result.converged and result.iterations == 1 and result.residual[0] < 1e-12
    np.testing.assert_allclose(result.positions, rest.positions, atol=1e-9)
    a = Q.solve(compressed, settings=corotational(connective_tissue=0.1, iterations=300))
    b = Q.solve(compressed, settings=corotational(connective_tissue=0.1, iterations=3000))
    assert a.converged and b.converged
    np.testing.assert_array_equal(a.positions, b.positions)


def test_filter_property_springs_selects_the_energy(small_scene):
    from test_filter_solver import posed_at
    model, bones = posed_at(small_scene, small_scene.motion.times[len(small_scene.motion.times)
                                                                   // 3])
    solver = MSSCollisionSolver()
    assert solver.choice("Springs") == SPRINGS_COROTATIONAL     # the default
    assert solver.settings().quasi_static.springs == SPRINGS_COROTATIONAL
    filter_solve(solver, model, bones)
    first = solver.GetOutputDataObject(0)
    from test_quasi_static import points
    hooke = MSSCollisionSolver()
    hooke.SetSprings(SPRINGS_HOOKE)
    assert hooke.settings().quasi_static.springs == SPRINGS_HOOKE
    filter_solve(hooke, model, bones)
    apart = np.linalg.norm(points(first) - points(hooke.GetOutputDataObject(0)), axis=1)
    assert apart.max() > 0.01
