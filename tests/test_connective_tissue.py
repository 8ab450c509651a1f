"""The connective tissue (core/connective_tissue.py, ConnectiveTissue): its stiffness per
particle, its energy in the quasi-static solve (against scipy's minimiser of the same energy),
its force in the paper relaxation (both methods reach the same equilibrium), the share it
carries, and what 0 and rest mean."""
import numpy as np
import pytest

from muscle_mss.core import model as S
from muscle_mss.core import quasi_static as Q
from muscle_mss.core import solver
from muscle_mss.core.connective_tissue import (REFERENCE_PARTICLES, tissue_share,
                                               tissue_stiffness)
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.settings import (DEFAULT_BULK_MODULUS, DEFAULT_TISSUE_ALONG,
                                      METHOD_QUASI_STATIC, METHOD_RELAXATION, SPRINGS_HOOKE,
                                      TERMINATION_THRESHOLD, SolverSettings)

from test_mss import lattice
from test_quasi_static import (chain_contact_stiffness, chain_on_a_ball, minimise_reference,
                               reference_forces)


def settings(method=METHOD_QUASI_STATIC, **values) -> SolverSettings:
    """The settings of ``method`` with the paper's Hooke springs (whose energy the NumPy
    references here write out) and ``values``."""
    return SolverSettings.build(method=method, **{"springs": SPRINGS_HOOKE, **values})


def slab(per_fibre, bend=0.0, length=38.0):
    """A 3 x 3 x ``per_fibre`` lattice muscle ``length`` mm long, ends fixed; the free
    particles posed on a circular arc that lifts its middle by ``bend`` mm (the tissue around
    it moved), the ends where they were."""
    step = length / (per_fibre - 1)
    points, springs, rest = lattice(3, 3, per_fibre, spacing=(2.0, 2.0, step))
    n = len(points)
    row, col, index = (a.ravel() for a in np.meshgrid(np.arange(3), np.arange(3),
                                                        np.arange(per_fibre), indexing="ij"))
    boundary = (row != 1) | (col != 1) | (index == 0) | (index == per_fibre - 1)
    posed = points.copy()
    u = points[:, 2] / length
    posed[:, 0] += bend * np.sin(np.pi * u)
    model = S.MSSModel(["slab"], np.array([0, n]), posed,
                       (index == 0) | (index == per_fibre - 1), np.ones(n), boundary,
                       np.zeros(n), row * 3 + col, index, springs, rest,
                       np.full(len(rest), 10.0), np.full(len(rest), 0.5),
                       np.stack([row, col], 1), points)
    return model


def test_stiffness_per_particle_is_the_ratio_at_the_reference_resolution_and_scales():
    ratio = 0.02
    coarse, fine = slab(REFERENCE_PARTICLES), slab(2 * REFERENCE_PARTICLES - 1)
    k = tissue_stiffness(coarse, np.arange(len(coarse.fixed)), coarse.fixed, ratio)
    assert np.all(k[coarse.fixed] == 0.0)
    np.testing.assert_allclose(k[~coarse.fixed], ratio * 10.0)
    # twice the fibre steps: a quarter of the stiffness per particle
    k_fine = tissue_stiffness(fine, np.arange(len(fine.fixed)), fine.fixed, ratio)
    np.testing.assert_allclose(k_fine[~fine.fixed], ratio * 10.0 / 4.0)
    assert not tissue_stiffness(coarse, np.arange(len(coarse.fixed)), coarse.fixed, 0.0).any()
    # in the solver's order
    prep = S.prepare(fine)
    ordered = tissue_stiffness(fine, prep.order, prep.fixed, ratio)
    np.testing.assert_array_equal(ordered, k_fine[prep.order])


def test_quasi_static_matches_scipy_minimiser_of_the_energy_with_tissue():
    model, bone = chain_on_a_ball()
    ratio = 0.05
    prep = S.prepare(model)
    weight = chain_contact_stiffness(model, prep)
    result = Q.solve(model, S.Bones(bone), prepared=prep, settings=settings(    # the isotropic energy
        tolerance=1e-9, iterations=5000, projection_passes=0, connective_tissue=ratio,
        tissue_along=1.0))
    assert result.converged and result.collided.any()
    n = len(model.fixed)
    expected = minimise_reference(model, bone, weight,
                                  tissue_stiffness(model, np.arange(n), model.fixed, ratio))
    untethered = minimise_reference(model, bone, weight)
    np.testing.assert_allclose(result.positions, expected, atol=1e-5)
    # the tissue changed the answer: it held the chain nearer its posed place
    posed = model.positions
    assert (np.linalg.norm(expected - posed, axis=1).mean()
            < np.linalg.norm(untethered - posed, axis=1).mean() - 0.05)


@pytest.fixture(scope="module")
def bent():
    """The slab at the reference resolution posed with its middle lifted 6 mm."""
    return slab(REFERENCE_PARTICLES, bend=6.0)


def tissue_forces(model, positions, ratio, along):
    """(n, 3) the tissue's pull on every particle, written out: ``-k (d - (1 - along) (d . f)
    f)``, ``f`` the particle's fibre direction at the posed positions."""
    from muscle_mss.core.fibre_shortening import fibre_tangents
    n = len(model.fixed)
    k = tissue_stiffness(model, np.arange(n), model.fixed, ratio)
    d = positions - model.positions
    f = fibre_tangents(model, model.positions)
    along_d = np.einsum("ij,ij->i", d, f)[:, None] * f
    return -k[:, None] * (d - (1.0 - along) * along_d)


@pytest.mark.parametrize("along", [0.1, 1.0])
def test_net_force_with_tissue_is_below_the_tolerance_equivalent(bent, along):
    ratio, tolerance = 0.05, 1e-4
    result = solver.solve(bent, settings=settings(tolerance=tolerance, iterations=5000,
                                                 connective_tissue=ratio, tissue_along=along))
    assert result.converged
    n = len(bent.fixed)
    k = tissue_stiffness(bent, np.arange(n), bent.fixed, ratio)
    pulls = tissue_forces(bent, result.positions, ratio, along)
    force = reference_forces(bent, result.positions, DEFAULT_BULK_MODULUS) + pulls
    free = ~bent.fixed
    diagonal = np.bincount(bent.springs.ravel(), np.repeat(bent.stiffness, 2))
    bound = 2 * (diagonal.max() + k.max()) * tolerance
    assert np.linalg.norm(force[free], axis=1).max() < bound
    # not trivially: the springs alone pull hard there, and the tissue carries a share
    springs_only = reference_forces(bent, result.positions, DEFAULT_BULK_MODULUS)
    assert np.linalg.norm(springs_only[free], axis=1).max() > 5 * bound
    # the share reported is the tissue's pull over the springs' tensions at the solution
    d = result.positions[bent.springs[:, 1]] - result.positions[bent.springs[:, 0]]
    tension = np.abs(bent.stiffness * (np.linalg.norm(d, axis=1) - bent.rest_length)).sum()
    pull = np.linalg.norm(pulls, axis=1).sum()
    assert result.tissue_share[0] == pytest.approx(100.0 * pull / tension, rel=1e-9)


def test_both_methods_reach_the_same_equilibrium_with_tissue(bent):
    ratio = 0.05
    static = solver.solve(bent, settings=settings(tolerance=1e-5, iterations=5000,
                                                 connective_tissue=ratio))
    relaxed = solver.solve(bent, settings=settings(
        METHOD_RELAXATION, iterations=20000, termination=TERMINATION_THRESHOLD,
        displacement_threshold=1e-7, connective_tissue=ratio))
    assert relaxed.stopped_by == TERMINATION_THRESHOLD
    assert np.linalg.norm(static.positions - relaxed.positions, axis=1).max() < 0.01
    # and the tissue moved it: without it the relaxation goes elsewhere
    free = solver.solve(bent, settings=settings(
        METHOD_RELAXATION, iterations=20000, termination=TERMINATION_THRESHOLD,
        displacement_threshold=1e-7, connective_tissue=0.0))
    assert np.linalg.norm(free.positions - relaxed.positions, axis=1).max() > 0.5


def test_iteration_cap_times_ten_gives_the_same_particles_with_tissue(bent):
    """Converged means converged: once the tolerance is met the cap does not matter, and a ten
    times tighter tolerance moves no particle more than a few tolerances."""
    a = solver.solve(bent, settings=settings(tolerance=1e-3, iterations=400,
                                            connective_tissue=0.05))
    b = solver.solve(bent, settings=settings(tolerance=1e-3, iterations=4000,
                                            connective_tissue=0.05))
    assert a.converged and b.converged
    assert np.array_equal(a.positions, b.positions)
    tight = solver.solve(bent, settings=settings(tolerance=1e-4, iterations=4000,
                                                connective_tissue=0.05))
    assert tight.converged
    assert np.linalg.norm(a.positions - tight.positions, axis=1).max() < 5e-3


@pytest.mark.parametrize("springs", ["co-rotational", SPRINGS_HOOKE])
@pytest.mark.parametrize("method", [METHOD_QUASI_STATIC, METHOD_RELAXATION])
def test_no_tissue_adds_nothing_whatever_its_along_fraction(bent, method, springs):
    """ConnectiveTissue 0 is the model without tissue: no stiffness on any particle, no share,
    and the along-fibre fraction, which only shapes a tissue that exists, changes no bit of
    the answer (both methods, both spring energies)."""
    assert not tissue_stiffness(bent, np.arange(len(bent.fixed)), bent.fixed, 0.0).any()
    results = [solver.solve(bent, settings=SolverSettings.build(
        method=method, springs=springs, iterations=300, connective_tissue=0.0,
        tissue_along=along)) for along in (1.0, 0.1, 0.0)]
    for result in results:
        assert not result.tissue_share.any()
        np.testing.assert_array_equal(result.positions, results[0].positions)
    assert np.linalg.norm(results[0].positions - bent.positions, axis=1).max() > 0.1


@pytest.mark.parametrize("method", [METHOD_QUASI_STATIC, METHOD_RELAXATION])
def test_model_at_rest_stays_at_rest_with_tissue(method):
    model = slab(REFERENCE_PARTICLES)         # posed = rest: springs and tissue at rest
    result = solver.solve(model, settings=settings(method, iterations=50,
                                                  connective_tissue=0.05))
    np.testing.assert_allclose(result.positions, model.positions, atol=1e-9)
    assert not result.tissue_share.any()


def middle_fibre(per_fibre, ratio):
    """The slab's middle fibre (per_fibre, 3) mm after the quasi-static solve of its 6 mm
    bend with tissue ``ratio``."""
    model = slab(per_fibre, bend=6.0)
    result = solver.solve(model, settings=settings(tolerance=1e-5, iterations=5000,
                                                  connective_tissue=ratio))
    assert result.converged
    middle = model.fibre_id == 4
    return result.positions[middle][np.argsort(model.fibre_index[middle])]


def test_same_muscle_at_two_resolutions_gives_the_same_shape():
    """The tissue scaled by the square of the fibre step keeps the shape: the slab's middle
    fibre at N = 20 and N = 39 (fibre steps halved) lies within 0.1 mm where the springs and
    the tissue share the load (0.05 mm measured; held as hard per particle at both
    resolutions, i.e. without the scaling, 1.5 mm)."""
    ratio = 0.002
    coarse = middle_fibre(REFERENCE_PARTICLES, ratio)
    fine = middle_fibre(2 * REFERENCE_PARTICLES - 1, ratio)
    # the springs and the tissue share the load: four times the tissue holds the middle
    # markedly nearer the posed 6 mm bend
    lift = np.abs(coarse[:, 0] - 2.0).max()
    held = np.abs(middle_fibre(REFERENCE_PARTICLES, 4 * ratio)[:, 0] - 2.0).max()
    assert held > lift + 0.5
    # the coarse particles are every other fine one
    assert np.linalg.norm(coarse - fine[::2], axis=1).max() < 0.1
    unscaled = middle_fibre(2 * REFERENCE_PARTICLES - 1, 4 * ratio)
    assert np.linalg.norm(coarse - unscaled[::2], axis=1).max() > 1.0


def test_tissue_share_is_the_tissue_force_over_the_spring_force(bent):
    n = len(bent.fixed)
    moved = bent.positions.copy()
    moved[~bent.fixed] += [0.3, 0.0, 0.0]
    k = tissue_stiffness(bent, np.arange(n), bent.fixed, 0.1)
    d = moved[bent.springs[:, 1]] - moved[bent.springs[:, 0]]
    tension = np.abs(bent.stiffness * (np.linalg.norm(d, axis=1) - bent.rest_length)).sum()
    expected = 100.0 * (k * 0.3).sum() / tension
    assert tissue_share(bent, moved, 0.1, 1.0)[0] == pytest.approx(expected, rel=1e-12)
    assert tissue_share(bent, moved, 0.0, 1.0)[0] == 0.0


@pytest.mark.parametrize("method", [METHOD_QUASI_STATIC, METHOD_RELAXATION])
def test_negative_or_infinite_tissue_is_refused(bent, method):
    for value in (-0.1, np.inf):
        with pytest.raises(MuscleMSSError, match="^property ConnectiveTissue is "):
            solver.solve(bent, settings=settings(method, connective_tissue=value))


def test_filter_property_reaches_the_solve_and_reports_the_share(small_scene):
    """``ConnectiveTissue`` on the MSS Collision Solver (0.1 by default, 0: no share): a ratio
    moves the answer toward the posed particles and reports each muscle's share;
    ``TissueAlongFibres`` (0.1 by default, 1: isotropic) reaches the solve."""
    from muscle_mss.filters import MSSCollisionSolver
    from muscle_mss.filters import array_names as A
    from muscle_mss.filters import vtk_arrays as V
    from muscle_mss.core.settings import DEFAULT_CONNECTIVE_TISSUE
    from test_filter_solver import posed_at
    from test_quasi_static import filter_solve, points

    times = small_scene.motion.times
    model, bones = posed_at(small_scene, times[len(times) // 3])
    posed = points(model)
    solved, shares = [], []
    solver = MSSCollisionSolver()
    assert solver.GetConnectiveTissue() == DEFAULT_CONNECTIVE_TISSUE == 0.1
    assert solver.GetTissueAlongFibres() == DEFAULT_TISSUE_ALONG == 0.1
    for values in ({"ConnectiveTissue": 0.0}, {"ConnectiveTissue": 0.03, "TissueAlongFibres": 1.0},
                   {"ConnectiveTissue": 0.03, "TissueAlongFibres": 0.1}):
        solver = MSSCollisionSolver()
        solver.SetIterations(60)
        for name, value in values.items():
            getattr(solver, "Set" + name)(value)
        out, _ = filter_solve(solver, model, bones)
        solved.append(points(out))
        shares.append([V.field(block, A.TISSUE_SHARE_PCT) for _, block in V.blocks(out)])
    assert not any(shares[0]) and all(0.0 < s < 100.0 for s in shares[1])
    moved = [np.linalg.norm(x - posed, axis=1).mean() for x in solved]
    assert moved[1] < moved[0]
    # a tissue weaker along the fibres solves elsewhere
    assert np.linalg.norm(solved[2] - solved[1], axis=1).max() > 0.01


def test_weaker_along_the_fibres_energy_and_gradient():
    """The anisotropic tissue's energy is k (|d|^2 - (1 - along) (d . f)^2) / 2 with f the
    posed fibre direction, its gradient that energy's (finite differences), and along = 1 is
    the isotropic energy bitwise."""
    from muscle_mss.core.connective_tissue import add_tissue_energy, tissue_targets
    model = slab(REFERENCE_PARTICLES, bend=6.0)
    n = len(model.fixed)
    order = np.arange(n)
    k = tissue_stiffness(model, order, model.fixed, 0.1)
    target = np.ascontiguousarray(model.positions.T)
    x = target + np.random.default_rng(3).normal(scale=0.5, size=target.shape)
    offsets = np.array([0, n])

    def energy(targets, at):
        gradient, e = np.zeros((3, n)), np.zeros(1)
        add_tissue_energy(np.ascontiguousarray(at), targets, k, offsets, gradient, e)
        return e[0], gradient

    along = 0.1
    weak = tissue_targets(model, order, along)
    assert weak.shape == (6, n) and tissue_targets(model, order, 1.0) is not weak
    np.testing.assert_array_equal(weak[:3], target)        # no shortened target: the posed
    f = weak[3:] / np.sqrt(1.0 - along)
    np.testing.assert_allclose(np.linalg.norm(f, axis=0), 1.0)
    assert np.abs(f[2]).mean() > 0.9             # the slab's fibres run along z
    d = x - target
    dot = np.einsum("ij,ij->j", d, f)
    e, gradient = energy(weak, x)
    assert e == pytest.approx(0.5 * (k * ((d * d).sum(0) - (1.0 - along) * dot ** 2)).sum(),
                              rel=1e-12)
    p, step = int(np.flatnonzero(k)[5]), 1e-6
    for axis in range(3):
        up, down = x.copy(), x.copy()
        up[axis, p] += step
        down[axis, p] -= step
        numeric = (energy(weak, up)[0] - energy(weak, down)[0]) / (2 * step)
        assert gradient[axis, p] == pytest.approx(numeric, rel=1e-6, abs=1e-9)
    iso, iso_gradient = energy(tissue_targets(model, order, 1.0), x)
    assert iso == 0.5 * (k * (d * d).sum(0)).sum() or iso == pytest.approx(
        0.5 * (k * (d * d).sum(0)).sum(), rel=1e-14)
    np.testing.assert_array_equal(iso_gradient, k * d)


def pulled_slab():
    """The slab with its last ring of tendon particles moved 8 mm further along the fibres and
    every free particle posed where it was (the tissue around it did not move): the muscle must
    lengthen against its tissue."""
    model = slab(REFERENCE_PARTICLES)
    posed = model.positions.copy()
    posed[model.fibre_index == REFERENCE_PARTICLES - 1, 2] += 8.0
    model.positions = posed
    return model


@pytest.mark.parametrize("method", [METHOD_QUASI_STATIC, METHOD_RELAXATION])
def test_a_tissue_weak_along_the_fibres_lets_a_muscle_lengthen(method):
    """Pulled along its fibres, a muscle held by a tissue a tenth as stiff along them as across
    lengthens more evenly and its tissue carries less than a third of the isotropic tissue's
    share; both methods reach the same equilibrium."""
    model = pulled_slab()
    quasi = {along: solver.solve(model, settings=settings(
        tolerance=1e-6, iterations=5000, connective_tissue=0.1, tissue_along=along))
        for along in (1.0, 0.1)}
    assert all(r.converged for r in quasi.values())
    share = {along: r.tissue_share[0] for along, r in quasi.items()}
    assert share[0.1] < share[1.0] / 3.0
    free = ~model.fixed
    moved = {along: r.positions[free, 2] - model.positions[free, 2]
             for along, r in quasi.items()}
    assert moved[0.1].mean() > moved[1.0].mean() + 0.5    # the middle follows the pulled end
    if method == METHOD_RELAXATION:
        relaxed = solver.solve(model, settings=settings(
            METHOD_RELAXATION, iterations=40000, termination=TERMINATION_THRESHOLD,
            displacement_threshold=1e-8, connective_tissue=0.1, tissue_along=0.1))
        assert relaxed.stopped_by == TERMINATION_THRESHOLD
        assert np.linalg.norm(relaxed.positions - quasi[0.1].positions, axis=1).max() < 0.01


@pytest.mark.parametrize("method", [METHOD_QUASI_STATIC, METHOD_RELAXATION])
def test_a_tissue_along_fraction_outside_0_to_1_is_refused(bent, method):
    for value in (-0.1, 1.5, np.nan):
        with pytest.raises(MuscleMSSError, match="^property TissueAlongFibres is "):
            solver.solve(bent, settings=settings(method, connective_tissue=0.1,
                                                 tissue_along=value))


def test_the_command_line_sets_the_along_fraction_only_when_given():
    import argparse
    from muscle_mss.app.run_options import add_run_options, settings_from
    parser = argparse.ArgumentParser()
    add_run_options(parser)
    assert "TissueAlongFibres" not in settings_from(parser.parse_args([]))
    assert settings_from(parser.parse_args(["--tissue-along", "0.1"]))["TissueAlongFibres"] == 0.1
