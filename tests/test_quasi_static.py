"""Quasi-static solver (core/quasi_static/) against a slow obvious reference, and its use in
the MSS Collision Solver filter (Method, Tolerance, WarmStart, residual, converged)."""
import numpy as np
import pytest
from scipy.optimize import minimize
from vtkmodules.vtkCommonCore import vtkOutputWindow, vtkStringOutputWindow

from muscle_mss.core import quasi_static as Q
from muscle_mss.core import model as S
from muscle_mss.core import relaxation
from muscle_mss.core.bones.distance import BoneSolids
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.settings import (DEFAULT_BULK_MODULUS, DEFAULT_CONTACT_WEIGHTS,
                                      DEFAULT_ITERATIONS, DEFAULT_PENETRATION_TOLERANCE,
                                      DEFAULT_TOLERANCE,
                                      METHOD_QUASI_STATIC, SPRINGS_HOOKE, SolverSettings)
from muscle_mss.filters import MSSCollisionSolver
from muscle_mss.filters import array_names as A
from muscle_mss.filters import vtk_arrays as V

from test_filter_solver import posed_at
from test_mss import lattice


PAPER_MODEL = {"springs": SPRINGS_HOOKE, "connective_tissue": 0.0, "tissue_along": 1.0}
"""The paper's model (Hooke springs, no connective tissue), whose energy this module's NumPy
references write out: the quasi-static method's minimiser is tested on it, whatever the
defaults (co-rotational springs and the tissue have their own tests)."""


def quasi_static(**values) -> SolverSettings:
    """Quasi-static settings of the paper's model (:data:`PAPER_MODEL`) from flat keywords
    (:meth:`SolverSettings.build`)."""
    return SolverSettings.build(method=METHOD_QUASI_STATIC, **{**PAPER_MODEL, **values})


# ---- the slow obvious reference: energy and forces of the model in plain NumPy -----------------


def reference_forces(model, positions, bulk_modulus):
    """(n, 3) spring + volume-pressure force on every particle (g mm/s^2), one spring and one
    cage triangle at a time (input particle order)."""
    force = np.zeros_like(positions)
    for (a, b), rest, k in zip(model.springs, model.rest_length, model.stiffness):
        d = positions[b] - positions[a]
        length = np.linalg.norm(d)
        force[a] += k * (length - rest) * d / length
        force[b] -= k * (length - rest) * d / length
    prep = S.prepare(model)
    ptr, triangles, rest_volume = prep.cages.arrays
    for m in range(len(ptr) - 1):
        tri = prep.order[triangles[ptr[m]:ptr[m + 1]]]
        if not len(tri):
            continue
        a, b, c = positions[tri[:, 0]], positions[tri[:, 1]], positions[tri[:, 2]]
        volume = np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0
        pressure = -bulk_modulus * (volume / rest_volume[m] - 1.0)
        for corner, (p, q) in enumerate(((b, c), (c, a), (a, b))):
            np.add.at(force, tri[:, corner], pressure * np.cross(p, q) / 6.0)
    return force


def chain_on_a_ball():
    """A 2 x 2 x 6 lattice muscle (ends fixed, every particle a 0.8 mm sphere) bent over a
    5 mm bone sphere that its rest line passes through: few particles, one contact object."""
    points, springs, rest = lattice(2, 2, 6, spacing=(2.0, 2.0, 3.0))
    n = len(points)
    index = np.tile(np.arange(6), 4)
    posed = points.copy()
    model = S.MSSModel(["chain"], np.array([0, n]), posed, (index == 0) | (index == 5),
                       np.ones(n), np.ones(n, bool), np.full(n, 0.8), np.repeat(np.arange(4), 6),
                       index, springs, rest, np.full(len(rest), 10.0), np.full(len(rest), 0.5),
                       None, points)
    bone = (np.array([[1.0, 1.0 - 4.0, 7.5]]), np.array([5.0]), np.array([0]))
    return model, bone


def chain_contact_stiffness(model, prep) -> float:
    """The contact stiffness of :func:`chain_on_a_ball`'s particles, written out: the Hooke
    springs' contact weight times the stiffest particle's spring sum, times 19 / 5 for its 6
    particles per fibre (the reference resolution is 20)."""
    stiffest = Q.preconditioner(model, prep).stiffest
    return DEFAULT_CONTACT_WEIGHTS[SPRINGS_HOOKE] * stiffest * 19.0 / 5.0


def minimise_reference(model, bone, weight, tissue=None):
    """The same energy minimised by scipy (L-BFGS-B): springs plus the contact penalty
    ``weight / 2 * penetration^2`` of each free sphere against the bone sphere, plus the
    connective tissue ``tissue[i] / 2 |x_i - posed_i|^2`` (``tissue`` (n,) g/s^2, input
    order) when given."""
    free = ~model.fixed
    centre, radius = bone[0][0], bone[1][0]
    tissue = np.zeros(len(free)) if tissue is None else tissue

    def energy(flat):
        x = model.positions.copy()
        x[free] = flat.reshape(-1, 3)
        d = x[model.springs[:, 1]] - x[model.springs[:, 0]]
        length = np.linalg.norm(d, axis=1)
        e = 0.5 * np.sum(model.stiffness * (length - model.rest_length) ** 2)
        grad = np.zeros_like(x)
        g = (model.stiffness * (length - model.rest_length) / length)[:, None] * d
        np.add.at(grad, model.springs[:, 1], g)
        np.add.at(grad, model.springs[:, 0], -g)
        off = x - centre
        dist = np.linalg.norm(off, axis=1)
        pen = np.maximum(model.radius + radius - dist, 0.0) * free
        e += 0.5 * weight * np.sum(pen ** 2)
        grad -= (weight * pen / dist)[:, None] * off
        pull = x - model.positions
        e += 0.5 * np.sum(tissue[:, None] * pull ** 2)
        grad += tissue[:, None] * pull
        return e, grad[free].ravel()

    best = minimize(energy, model.positions[free].ravel(), jac=True, method="L-BFGS-B",
                    options={"gtol": 1e-12, "ftol": 1e-16, "maxiter": 20000, "maxcor": 30})
    x = model.positions.copy()
    x[free] = best.x.reshape(-1, 3)
    return x


def test_matches_scipy_minimiser_of_the_same_energy_on_a_few_particles():
    model, bone = chain_on_a_ball()
    prep = S.prepare(model)
    weight = chain_contact_stiffness(model, prep)
    result = Q.solve(model, S.Bones(bone), prepared=prep, settings=quasi_static(
        tolerance=1e-9, iterations=5000, projection_passes=0))
    assert result.converged and result.residual[-1] < 1e-9
    assert result.collided.any()
    expected = minimise_reference(model, bone, weight)
    assert np.abs(result.positions - model.positions).max() > 0.5      # it did bend
    np.testing.assert_allclose(result.positions, expected, atol=1e-5)


def spring_gradient_and_hessian(model, x):
    """The Hooke springs' energy gradient (n, 3) and dense Hessian (3n, 3n) at ``x``, one
    spring at a time (g mm/s^2, g/s^2)."""
    n = len(x)
    gradient, hessian = np.zeros((n, 3)), np.zeros((3 * n, 3 * n))
    for (a, b), rest, k in zip(model.springs, model.rest_length, model.stiffness):
        d = x[b] - x[a]
        length = np.linalg.norm(d)
        unit = d / length
        gradient[b] += k * (length - rest) * unit
        gradient[a] -= k * (length - rest) * unit
        block = k * ((1.0 - rest / length) * np.eye(3) + rest / length * np.outer(unit, unit))
        for p, q, sign in ((a, a, 1.0), (b, b, 1.0), (a, b, -1.0), (b, a, -1.0)):
            hessian[3 * p:3 * p + 3, 3 * q:3 * q + 3] += sign * block
    return gradient, hessian


def constrained_reference(model, bone, start):
    """The chain's contact problem with exact constraints: the springs' energy at its least
    with every free sphere out of the bone sphere (|x_i - c| >= r_i + R), by Newton's method
    on the KKT conditions with the dense Hessian, the active set changed until every
    multiplier pushes and no other sphere overlaps. ``start`` (n, 3): where Newton starts
    and its first active set (spheres overlapping there). Returns the positions (n, 3) and
    each particle's contact force (n,) g mm/s^2 (the multiplier; 0 off the bone)."""
    centre, radius = bone[0][0], bone[1][0]
    free = np.flatnonzero(~model.fixed)
    reach = model.radius + radius
    x = start.copy()
    active = free[np.linalg.norm(x[free] - centre, axis=1) < reach[free]]
    rows = (3 * free[:, None] + np.arange(3)).ravel()
    for _ in range(len(free) + 1):                  # active-set changes
        force = np.zeros(len(x))
        for _ in range(50):                         # Newton steps
            gradient, hessian = spring_gradient_and_hessian(model, x)
            offset = x[active] - centre
            distance = np.linalg.norm(offset, axis=1)
            normal = offset / distance[:, None]
            jacobian = np.zeros((len(active), 3 * len(x)))
            for row, (i, nrm) in enumerate(zip(active, normal)):
                jacobian[row, 3 * i:3 * i + 3] = nrm
                hessian[3 * i:3 * i + 3, 3 * i:3 * i + 3] -= force[i] / distance[row] * (
                    np.eye(3) - np.outer(nrm, nrm))
            residual = np.concatenate([gradient.ravel()[rows] - jacobian[:, rows].T
                                       @ force[active], distance - reach[active]])
            if np.abs(residual).max() < 1e-10:
                break
            system = np.block([[hessian[np.ix_(rows, rows)], -jacobian[:, rows].T],
                               [jacobian[:, rows], np.zeros((len(active),) * 2)]])
            delta = np.linalg.solve(system, -residual)
            x[free] += delta[:len(rows)].reshape(-1, 3)
            force[active] += delta[len(rows):]
        else:
            raise AssertionError("Newton did not converge")
        pulling = active[force[active] < 0.0]
        gap = np.linalg.norm(x[free] - centre, axis=1) - reach[free]
        entering = free[(gap < -1e-12) & ~np.isin(free, active)]
        if not len(pulling) and not len(entering):
            return x, force
        active = np.union1d(np.setdiff1d(active, pulling), entering)
    raise AssertionError("no consistent active set")


def test_penalty_answers_tend_to_the_exact_contact_problem_solved_by_newton():
    """The penalty contact is a stand-in for the constraint 'no sphere in the bone': as its
    stiffness grows, the solver's answer (no final passes) goes to the exact constrained
    minimiser at the rate of the penalty (a tenth of the distance, about the overlap, for ten
    times the stiffness), and each sphere's penalty force to its multiplier (3 % -> 0.3 %),
    every one of them pushing.
    At each answer the net force (springs plus the penalty) on every free particle is below
    the tolerance's equivalent, and the springs press every contact sphere into the bone."""
    model, bone = chain_on_a_ball()
    prep = S.prepare(model)
    centre, radius = bone[0][0], bone[1][0]
    free = ~model.fixed
    stiffness = chain_contact_stiffness(model, prep)
    tolerance = 1e-6        # the stiffer penalty's energy cannot tell steps below 4e-7 mm
    distances = []
    for scale in (1.0, 10.0):
        weight = DEFAULT_CONTACT_WEIGHTS[SPRINGS_HOOKE] * scale
        result = Q.solve(model, S.Bones(bone), prepared=prep, settings=quasi_static(
            tolerance=tolerance, iterations=5000, projection_passes=0, contact_weight=weight))
        assert result.converged
        x = result.positions
        exact, multiplier = constrained_reference(model, bone, x)
        offset = x - centre
        distance = np.linalg.norm(offset, axis=1)
        depth = np.maximum(model.radius + radius - distance, 0.0) * free
        penalty = stiffness * scale * depth                           # g mm/s^2, pushing
        contact = depth > 0
        assert contact.sum() >= 2 and np.array_equal(contact, multiplier > 0)
        assert multiplier.min() >= 0.0                                # the bone only pushes
        np.testing.assert_allclose(penalty[contact], multiplier[contact], rtol=0.1 / scale)
        spring_force = -spring_gradient_and_hessian(model, x)[0]
        outward = offset / distance[:, None]
        net = spring_force + penalty[:, None] * outward
        bound = 2 * np.bincount(model.springs.ravel(), np.repeat(model.stiffness, 2)).max() \
            * tolerance
        assert np.linalg.norm(net[free], axis=1).max() < bound
        assert np.all(np.einsum("ij,ij->i", spring_force, outward)[contact] < 0.0)
        distances.append(np.linalg.norm(x - exact, axis=1).max())
        assert distances[-1] < 1.5 * depth.max()        # as far off as the spheres overlap
    assert np.abs(exact - model.positions).max() > 0.5                # it did bend
    assert distances[1] < 0.15 * distances[0]        # 0.054 -> 0.006 mm


def test_contact_stiffness_keeps_the_force_per_length_of_fibre_at_every_resolution():
    """Twice the fibre steps (39 particles per fibre against the reference 20): each particle's
    contact stiffness halves, so a patch pressed as deep pushes as hard per mm of fibre."""
    from test_connective_tissue import slab
    settings = quasi_static()
    weights = []
    for per_fibre in (20, 39):
        model = slab(per_fibre)
        prep = S.prepare(model)
        pre = Q.preconditioner(model, prep)
        w = Q.driver.contact_stiffness(model, prep, pre, settings)
        assert w.shape == (len(model.fixed),) and np.all(w == w[0])
        weights.append((w[0], pre.stiffest))
    (coarse, stiffest), (fine, fine_stiffest) = weights
    assert stiffest == fine_stiffest
    assert coarse == settings.quasi_static.weight * stiffest
    assert fine == pytest.approx(coarse / 2.0, rel=1e-12)


@pytest.fixture(scope="module")
def stretched():
    """A 4 x 4 x 10 lattice muscle with a fibre grid (so it has a cage and a volume), its
    insertion end pulled 4 mm along and 3 mm across, the rest posed with a jitter."""
    points, springs, rest = lattice(4, 4, 10, spacing=(2.0, 2.0, 2.5))
    n = len(points)
    row, col, index = np.meshgrid(np.arange(4), np.arange(4), np.arange(10), indexing="ij")
    row, col, index = row.ravel(), col.ravel(), index.ravel()
    boundary = (row == 0) | (row == 3) | (col == 0) | (col == 3) | (index == 0) | (index == 9)
    posed = points + np.random.default_rng(5).normal(scale=0.2, size=points.shape)
    posed[index == 9] = points[index == 9] + [3.0, 0.0, 4.0]
    posed[index == 0] = points[index == 0]
    model = S.MSSModel(["m"], np.array([0, n]), posed, (index == 0) | (index == 9), np.ones(n),
                       boundary, np.where(boundary, 0.9, 0.0), row * 4 + col, index, springs,
                       rest, np.full(len(rest), 10.0), np.full(len(rest), 0.5),
                       np.stack([row, col], 1), points)
    return model


def test_equilibrium_net_force_on_free_particles_is_below_the_tolerance_equivalent(stretched):
    model = stretched
    prep = S.prepare(model)
    assert prep.cages.ptr[-1] > 0                       # the volume term is in play
    tolerance = 1e-4
    result = Q.solve(model, prepared=prep, settings=quasi_static(
        tolerance=tolerance, iterations=3000))
    assert result.converged and result.stopped_by == "tolerance"
    force = reference_forces(model, result.positions, DEFAULT_BULK_MODULUS)
    free = ~model.fixed
    # the plain step (A + K)^-1 f moves no particle more than the tolerance, so |f| <= |A + K|
    # tolerance: |A| is at most twice the largest sum of a particle's stiffnesses (K acts along
    # the volume gradient only)
    diagonal = np.bincount(model.springs.ravel(), np.repeat(model.stiffness, 2))
    bound = 2 * diagonal.max() * tolerance
    assert np.linalg.norm(force[free], axis=1).max() < bound
    # and it is not trivially so: the posed state is far from balanced
    posed_force = reference_forces(model, model.positions, DEFAULT_BULK_MODULUS)
    assert np.linalg.norm(posed_force[free], axis=1).max() > 1000 * bound
    assert np.array_equal(result.positions[model.fixed], model.positions[model.fixed])


def test_a_tolerance_finer_than_the_energy_can_see_stops_as_stalled_not_at_the_cap(stretched):
    """At 1e-14 mm no step can measurably lower the energy before the plain step is within the
    tolerance: the solve stops after STALLED_STEPS such plain steps, unconverged, and where it
    stopped is the answer of a tolerance it can meet."""
    tight = Q.solve(stretched, settings=quasi_static(tolerance=1e-14, iterations=5000))
    assert not tight.converged and tight.stopped_by == Q.driver.TERMINATION_STALLED
    assert tight.iterations < 1000
    met = Q.solve(stretched, settings=quasi_static(tolerance=1e-6, iterations=5000))
    assert met.converged
    np.testing.assert_allclose(tight.positions, met.positions, atol=1e-5)


def test_model_at_rest_stays_at_rest(stretched):
    model = stretched
    rest = S.MSSModel(**{**model.__dict__, "positions": model.rest_positions.copy()})
    result = Q.solve(rest)
    assert result.converged and result.iterations == 1 and result.residual[0] < 1e-12
    np.testing.assert_allclose(result.positions, rest.positions, atol=1e-9)


def test_iteration_cap_times_ten_gives_the_same_particles_once_converged(stretched):
    settings = quasi_static(tolerance=1e-3, iterations=400)
    a = Q.solve(stretched, settings=settings)
    settings.iterations = 4000
    b = Q.solve(stretched, settings=settings)
    assert a.converged and b.converged
    assert np.array_equal(a.positions, b.positions)
    # a tenth of the tolerance: the residual (the L-BFGS step) estimates the distance left
    # roughly (7e-3 mm measured here at 1e-3), far below the 0.5 mm the posed state is away
    c = Q.solve(stretched, settings=quasi_static(tolerance=1e-4, iterations=4000))
    assert c.converged and c.iterations > a.iterations
    assert np.linalg.norm(a.positions - c.positions, axis=1).max() < 20 * 1e-3


def test_warm_start_and_cold_start_agree(stretched):
    settings = quasi_static(tolerance=1e-4, iterations=3000)
    cold = Q.solve(stretched, settings=settings)
    # start from the solution of a nearby pose carried by the pose change
    nearby = S.MSSModel(**{**stretched.__dict__, "positions": stretched.positions.copy()})
    end = stretched.fibre_index == 9
    nearby.positions[end] += [0.5, 0.0, 0.0]
    near = Q.solve(nearby, settings=settings)
    start = stretched.positions + (near.positions - nearby.positions)
    warm = Q.solve(stretched, settings=settings, start=start)
    assert warm.converged and warm.residual[0] < 0.2 * cold.residual[0]
    assert warm.iterations < cold.iterations
    # each within ~7 tolerances of the minimum (the residual estimates the distance roughly)
    assert np.linalg.norm(warm.positions - cold.positions, axis=1).max() < 20 * 1e-4


def test_bad_settings_and_start_are_refused(stretched):
    from muscle_mss.core.solver import solve
    with pytest.raises(MuscleMSSError, match="property Tolerance is -1.0; it must be at least 0"):
        solve(stretched, settings=quasi_static(tolerance=-1.0))
    with pytest.raises(MuscleMSSError, match="contact weight is 0.0"):
        solve(stretched, settings=quasi_static(contact_weight=0.0))
    with pytest.raises(MuscleMSSError, match="start positions"):
        Q.solve(stretched, start=np.zeros((3, 3)))
    before = stretched.positions.copy()
    Q.solve(stretched, settings=quasi_static(iterations=3))
    assert np.array_equal(before, stretched.positions)


# ---- the filter --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def walk(small_scene):
    """The small demo's posed model and bones at two neighbouring walking poses."""
    times = small_scene.motion.times
    k = len(times) // 3
    return posed_at(small_scene, times[k]), posed_at(small_scene, times[k + 1])


def filter_solve(solver, model, bones):
    solver.SetInputDataObject(0, model)
    solver.SetInputDataObject(1, bones)
    solver.Update()
    return solver.GetOutputDataObject(0), solver.GetOutputDataObject(1)


def points(multiblock):
    return np.concatenate([V.points_of(b) for _, b in V.blocks(multiblock)])


def test_filter_quasi_static_method_has_residual_and_converged_fields(walk):
    solver = MSSCollisionSolver()
    assert solver.choice("Method") == "quasi-static" and not solver.GetWarmStart()
    assert solver.GetTolerance() == DEFAULT_TOLERANCE
    out, table = filter_solve(solver, *walk[0])
    columns = V.table_columns(table)
    assert "residual" in columns and len(columns["residual"]) == len(columns["iteration"])
    assert V.field(table, A.METHOD) == "quasi-static"
    converged = V.field(table, A.CONVERGED)
    remaining = V.field(table, A.REMAINING_PENETRATION)
    residual = columns["residual"]
    # the defaults converge here: stopped by the tolerance, no overlap left above 0.01 mm
    assert converged and residual[-1] < DEFAULT_TOLERANCE and remaining <= 0.01
    assert len(residual) < DEFAULT_ITERATIONS
    paper = MSSCollisionSolver()
    paper.SetMethod("paper relaxation")
    paper.SetIterations(5)
    _, table = filter_solve(paper, *walk[0])
    assert "residual" not in V.table_columns(table)
    assert V.field(table, A.METHOD) == "paper relaxation" and V.field(table, A.CONVERGED) == 0


def test_unconverged_solve_prints_a_warning(walk):
    messages = vtkStringOutputWindow()
    previous = vtkOutputWindow.GetInstance()
    vtkOutputWindow.SetInstance(messages)
    try:
        solver = MSSCollisionSolver()
        solver.SetMethod("quasi-static")
        solver.SetIterations(2)
        _, table = filter_solve(solver, *walk[0])
    finally:
        vtkOutputWindow.SetInstance(previous)
    assert V.field(table, A.CONVERGED) == 0
    assert "did not converge in 2 iterations" in messages.GetOutput()


def test_warm_start_starts_from_the_last_solution_and_agrees_with_a_cold_start(walk):
    (model_a, bones_a), (model_b, bones_b) = walk
    solves = []
    for warm_start in (True, False):
        solver = MSSCollisionSolver()
        solver.SetMethod("quasi-static")
        solver.SetTolerance(1e-3)
        solver.SetIterations(2000)
        solver.SetWarmStart(warm_start)
        filter_solve(solver, model_a, bones_a)
        solves.append(filter_solve(solver, model_b, bones_b))
    (out_warm, table_warm), (out_cold, table_cold) = solves
    # the warm solve started elsewhere (from the last solution), and both converged. Contacts
    # make the equilibrium not unique: here the two land in neighbouring minima (energies
    # 618.9 and 623.6, median 0.26 mm apart, and so they stay at a tolerance of 1e-5 mm);
    # test_warm_start_and_cold_start_agree checks the agreement where the minimum is unique
    first_step = [V.table_columns(t)["residual"][0] for t in (table_warm, table_cold)]
    assert first_step[0] != first_step[1]
    assert V.field(table_warm, A.CONVERGED) == 1 and V.field(table_cold, A.CONVERGED) == 1
    distance = np.linalg.norm(points(out_warm) - points(out_cold), axis=1)
    assert np.median(distance) < 0.5


def test_warm_start_also_where_the_fibres_shorten(small_scene):
    """FibreShortening gives each pose its own rest lengths; WarmStart still starts from the
    last solution there (it was silently a cold start), and both starts converge."""
    times = small_scene.motion.times
    poses = [posed_at(small_scene, t) for t in times[-4:-2]]    # fibres shortened at both
    first_step = []
    for warm_start in (True, False):
        solver = MSSCollisionSolver()
        solver.SetWarmStart(warm_start)
        for model, bones in poses:
            out, table = filter_solve(solver, model, bones)
        assert solver.setup_counts["prepared"] == 1
        assert V.field(table, A.CONVERGED) == 1
        first_step.append(V.table_columns(table)["residual"][0])
    assert first_step[0] != first_step[1]


def test_a_time_point_gets_the_same_answer_whatever_was_solved_before(small_scene, walk):
    """The default (no warm start): the same pose solved alone, right after its neighbour and
    after a jump across the motion gives bitwise the same particles (so do MPI ranks and a
    reopened state file, which only change what was solved before)."""
    (model_a, bones_a), (model_b, bones_b) = walk
    far = posed_at(small_scene, small_scene.motion.times[-1])
    answers = []
    for before in (None, (model_a, bones_a), far):
        solver = MSSCollisionSolver()
        solver.SetMethod("quasi-static")
        solver.SetConnectiveTissue(0.1)
        solver.SetIterations(40)
        if before is not None:
            filter_solve(solver, *before)
        answers.append(points(filter_solve(solver, model_b, bones_b)[0]))
    assert np.array_equal(answers[0], answers[1]) and np.array_equal(answers[0], answers[2])


def test_filter_refuses_a_negative_tolerance(walk):
    solver = MSSCollisionSolver()
    solver.SetMethod("quasi-static")
    solver.SetTolerance(-1.0)
    with pytest.raises(MuscleMSSError, match="Tolerance"):
        filter_solve(solver, *walk[0])


# ---- bones as solids ---------------------------------------------------------------------------

def chain_in_a_box(face):
    """The chain of chain_on_a_ball and a box bone reaching from below its strands to its +x
    face at ``face`` mm, spanning the chain's width and its middle (z 4.5 to 10.5 mm), as a
    solid with a 0.5 mm clearance: ``(model, box mesh, BoneSolids, inside at the start)``."""
    from muscle_mss.core.bones.field_sampling import bone_field_set
    from reference_distance import reference_signed_distance
    from test_bone_distance import box_mesh
    model, _ = chain_on_a_ball()
    box = box_mesh([-10.0, -10.0, 4.5], [face, 12.0, 10.5])
    solids = BoneSolids(bone_field_set([box]), np.eye(3, 4)[None], np.array([0.5]))
    return model, box, solids, reference_signed_distance(*box, model.positions) < 0


def test_solid_bone_pushes_a_lattice_out_on_the_near_side_with_its_clearance():
    """The chain of chain_on_a_ball, its middle posed 1 and 3 mm deep inside a box bone from the
    box's +x face (the box spans the chain's width and more): every free sphere ends its radius
    plus the clearance outside, on the +x side, where the bone's sphere shell would let the
    deeper strand be pulled through."""
    from reference_distance import reference_signed_distance
    model, box, solids, inside = chain_in_a_box(3.0)
    clearance = solids.clearance[0]
    assert inside.sum() == 8 and not (inside & model.fixed).any()
    result = Q.solve(model, S.Bones(solids=solids),
                     quasi_static(tolerance=1e-4, iterations=3000))
    assert result.converged
    free = ~model.fixed
    depth = reference_signed_distance(*box, result.positions[free])
    assert depth.min() >= 0.8 + clearance - 1e-3
    assert (result.positions[inside, 0] > 3.0 + 0.8 + clearance - 1e-3).all()
    # the penalty alone leaves an overlap of force / w, which the final push removed
    assert result.max_penetration[-1] > 1e-3


def test_solid_penalty_skips_particles_far_from_the_bones_and_solves_the_same(monkeypatch):
    """The bones' penalty looks only at the particles listed near a bone (within radius,
    clearance and skin when a particle's entry was made, remade when it moved half the skin):
    the solve is bitwise the one that looks at every particle every time."""
    model, _, solids, _ = chain_in_a_box(3.0)
    settings = quasi_static(tolerance=1e-4, iterations=3000)
    listed_sizes = []
    refresh = Q.ContactEnergy._refresh_near_solids

    def recording(self):
        refresh(self)
        listed_sizes.append((len(self.near[0]), len(self.solid_points)))

    monkeypatch.setattr(Q.ContactEnergy, "_refresh_near_solids", recording)
    listed = Q.solve(model, S.Bones(solids=solids), settings)
    assert listed.converged
    assert min(size for size, _ in listed_sizes) < listed_sizes[0][1]   # some were skipped

    def everything_near(*arguments):
        arguments[-1][:] = True

    monkeypatch.setattr(Q.energy, "near_solids", everything_near)
    full = Q.solve(model, S.Bones(solids=solids), settings)
    np.testing.assert_array_equal(listed.positions, full.positions)
    np.testing.assert_array_equal(listed.residual, full.residual)


def test_paper_relaxation_pushes_a_lattice_out_of_a_solid_bone_on_the_near_side():
    """The paper's response moves each sphere out by its own nearest face, so here the box's +x
    face is the nearest for every particle inside it (the chain's x = 0 strand, 1 mm deep, 1.5
    mm from the z faces): after the relaxation every free sphere is its radius plus the
    clearance outside the box (within the final passes' PenetrationTolerance), the strand
    that was inside on the +x side."""
    from muscle_mss.core.bones.distance import signed_distances
    from reference_distance import reference_signed_distance
    model, box, solids, inside = chain_in_a_box(1.0)
    clearance = solids.clearance[0]
    assert inside.sum() == 4 and not (inside & model.fixed).any()
    result = relaxation.solve(model, S.Bones(solids=solids),
                              SolverSettings.build(iterations=300))
    slack = DEFAULT_PENETRATION_TOLERANCE
    assert result.bone_pairs[0] > 0 and result.remaining_penetration <= slack
    free = result.positions[~model.fixed]
    assert signed_distances(solids.fields, free)[0].min() >= 0.8 + clearance - slack
    # the exact distance: less by the field's interpolation error near the box's edges
    assert reference_signed_distance(*box, free).min() >= 0.8 + clearance - 0.05
    assert (result.positions[inside, 0] > 1.0 + 0.8 + clearance - slack).all()


def test_solid_bones_are_checked():
    from muscle_mss.core.bones.field_sampling import bone_field_set
    from test_bone_distance import box_mesh
    model, _ = chain_on_a_ball()
    fields = bone_field_set([box_mesh([0, 0, 0], [1, 1, 1])])
    with pytest.raises(MuscleMSSError, match="one finite 3x4 transform per bone"):
        Q.solve(model, S.Bones(solids=BoneSolids(fields, np.eye(3, 4), np.zeros(1))))
    with pytest.raises(MuscleMSSError, match="clearance"):
        Q.solve(model, S.Bones(solids=BoneSolids(fields, np.eye(3, 4)[None], -np.ones(1))))


def two_muscles():
    """:func:`chain_on_a_ball`'s chain and a 3 x 2 x 9 lattice beside it (ends fixed, varied
    spring stiffness): two muscles of different sizes and bandwidths."""
    first, _ = chain_on_a_ball()
    points, springs, rest = lattice(3, 2, 9, spacing=(2.0, 2.0, 3.0))
    k = len(points)
    index = np.tile(np.arange(9), 6)
    n0 = len(first.positions)
    return S.MSSModel(
        ["chain", "wide"], np.array([0, n0, n0 + k]),
        np.concatenate([first.positions, points + [20.0, 0.0, 0.0]]),
        np.concatenate([first.fixed, (index == 0) | (index == 8)]), np.ones(n0 + k),
        np.ones(n0 + k, bool), np.full(n0 + k, 0.8),
        np.concatenate([first.fibre_id, np.repeat(np.arange(6), 9) + 4]),
        np.concatenate([first.fibre_index, index]),
        np.concatenate([first.springs, springs + n0]), np.concatenate([first.rest_length, rest]),
        np.concatenate([first.stiffness, np.linspace(5.0, 15.0, len(rest))]),
        np.full(len(rest) + len(first.rest_length), 0.5), None,
        np.concatenate([first.positions, points + [20.0, 0.0, 0.0]]))


def test_preconditioner_solves_the_spring_matrix_with_tissue_and_volume_stiffness():
    """The compiled banded solve of every muscle's factor at once is ``A^-1`` of the dense spring
    Laplacian plus the tissue on the free particles (two muscles of different sizes and
    bandwidths), and the initial inverse Hessian adds each muscle's rank-one volume stiffness
    (Sherman-Morrison)."""
    from muscle_mss.core.quasi_static.preconditioner import (InitialInverseHessian,
                                                             model_springs, preconditioner)
    model = two_muscles()
    prep = S.prepare(model)
    pre = preconditioner(model, prep, 0.1)
    assert len(pre.widths) == 2 and pre.bandwidth > 1
    ends, _, stiffness, _ = model_springs(model, prep)
    dense = np.diag(pre.tissue)
    for (a, b), c in zip(ends, stiffness):
        dense[[a, b], [a, b]] += c
        dense[a, b] -= c
        dense[b, a] -= c
    free = pre.free
    rhs = np.random.default_rng(3).normal(size=(len(free), 3))
    expected = np.linalg.solve(dense[np.ix_(free, free)], rhs)
    np.testing.assert_allclose(pre.solve(rhs), expected, rtol=1e-10, atol=1e-12)
    volume_gradient = np.random.default_rng(4).normal(size=(len(free), 3))
    muscle = prep.muscle[free]
    stiff = np.array([2.0, 0.5])
    h0 = InitialInverseHessian(pre, muscle, stiff, volume_gradient)
    full = dense[np.ix_(free, free)]
    big = np.kron(full, np.eye(3))
    for m in range(2):
        g = np.where((muscle == m)[:, None], volume_gradient, 0.0).ravel()
        big += stiff[m] * np.outer(g, g)
    expected = np.linalg.solve(big, rhs.ravel()).reshape(-1, 3)
    np.testing.assert_allclose(h0(rhs.copy()), expected, rtol=1e-9, atol=1e-12)


def test_distance_to_go_is_the_geometric_tail_of_the_residual():
    halving = 0.5 ** np.arange(12)
    # r rho / (1 - rho) with rho = 1/2: the tail 1/2^12 + 1/2^13 + ... = the last step
    assert Q.distance_to_go(halving) == pytest.approx(halving[-1])
    assert Q.distance_to_go(0.9 ** np.arange(30)) == pytest.approx(0.9 ** 29 * 9.0)
    assert Q.distance_to_go(np.ones(5)) == np.inf
    assert Q.distance_to_go(np.array([1.0])) == np.inf
    assert Q.distance_to_go(np.array([1.0, 0.0])) == 0.0
    # a slow decay ending in a quick dip of ten steps (the walking pose of the full demo thigh
    # stopped so 1.1 mm from the minimum when the rate came from the last ten iterations):
    # the rate of the last RATE_WINDOW iterations keeps the slow decay in the estimate
    dip = np.concatenate([0.999 ** np.arange(100), 0.999 ** 99 * 0.5 ** np.arange(1, 11)])
    assert Q.RATE_WINDOW >= 30
    assert Q.distance_to_go(dip) > 3.0 * dip[-1]
