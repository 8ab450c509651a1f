"""The relaxation loop (core/relaxation.py): terminations, history, determinism, divergence, abort."""
import numpy as np
import pytest

from muscle_mss.core import model as core_model, solver
from muscle_mss.core.contacts import spatial_hash
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.model import Bones
from muscle_mss.core.settings import METHOD_RELAXATION, STRUCTURES, SolverSettings

from test_mss import lattice


@pytest.fixture(scope="module")
def pressed():
    """Two 3x3x8 lattice muscles pushed 1 mm into each other and onto a bone sphere sheet, their
    end particles fixed, posed with a random jitter."""
    pts, springs, rest = lattice(3, 3, 8, spacing=(2.0, 2.0, 2.0))
    n = len(pts)
    second = pts + [5.0, 0.0, 0.0]
    positions = np.concatenate([pts, second])
    positions += np.random.default_rng(3).normal(scale=0.3, size=positions.shape)
    index = np.tile(np.arange(8), 18)
    fibre = np.repeat(np.arange(18), 8)
    radius = np.full(2 * n, 1.2)
    model = core_model.MSSModel(
        ["front", "back"], np.array([0, n, 2 * n]), positions, (index == 0) | (index == 7),
        np.ones(2 * n), np.ones(2 * n, bool), radius, fibre, index,
        np.concatenate([springs, springs + n]), np.concatenate([rest, rest]),
        np.full(2 * len(rest), 10.0), np.full(2 * len(rest), 0.5), np.zeros((2 * n, 2), int),
        np.concatenate([pts, second]))
    g = np.arange(-2, 10, 1.0)
    sheet = np.stack(np.meshgrid(g, g, [-1.5], indexing="ij"), -1).reshape(-1, 3)
    bones = (sheet, np.full(len(sheet), 1.0), np.zeros(len(sheet), int))
    return model, bones


def paper(**kw) -> SolverSettings:
    """The paper relaxation's settings for the paper's model (no connective tissue), whatever
    the defaults, with ``kw``."""
    return SolverSettings.build(**{"method": METHOD_RELAXATION, "connective_tissue": 0.0, **kw})


def run(pressed, **kw):
    model, bones = pressed
    return solver.solve(model, Bones(bones), paper(**kw))


def test_fixed_iterations_give_one_row_each(pressed):
    result = run(pressed, iterations=37)
    assert result.iterations == 37 and result.stopped_by == "iterations"
    assert result.mean_displacement.shape == (37, 2)
    assert np.all(np.diff(result.seconds) >= 0)
    assert np.isfinite(result.positions).all()


def test_displacement_threshold_stops_at_the_first_quiet_iteration(pressed):
    full = run(pressed, iterations=400)
    top = full.mean_displacement.max(axis=1)
    threshold = 0.5 * top.max()
    quiet = [k for k in range(1, len(top)) if top[k] < threshold and top[k] <= top[k - 1]]
    result = run(pressed, iterations=400, termination="displacement threshold",
                 displacement_threshold=threshold)
    assert result.stopped_by == "displacement threshold"
    assert result.iterations == quiet[0] + 1
    assert np.array_equal(result.positions,
                          run(pressed, iterations=quiet[0] + 1).positions)


def test_displacement_threshold_is_capped_by_iterations(pressed):
    result = run(pressed, iterations=5, termination="displacement threshold",
                 displacement_threshold=0.0)
    assert result.iterations == 5 and result.stopped_by == "iterations"


def test_time_budget_stops_once_the_budget_is_spent(pressed):
    result = run(pressed, iterations=10 ** 6, termination="time budget", time_budget=0.3)
    assert result.stopped_by == "time budget"
    assert result.seconds[-1] >= 0.3 > result.seconds[-2]


def test_same_inputs_give_bitwise_the_same_result(pressed):
    a = run(pressed, iterations=60)
    b = run(pressed, iterations=60)
    assert np.array_equal(a.positions, b.positions) and np.array_equal(a.velocity, b.velocity)
    assert np.array_equal(a.mean_displacement, b.mean_displacement)


def test_hash_and_bvh_solve_to_bitwise_the_same_state(pressed):
    a = run(pressed, iterations=60, structure="spatial hash")
    b = run(pressed, iterations=60, structure="octree BVH", bvh_min_primitives=4)
    assert a.muscle_pairs.sum() > 0 and a.bone_pairs.sum() > 0
    assert np.array_equal(a.muscle_pairs, b.muscle_pairs)
    assert np.array_equal(a.bone_pairs, b.bone_pairs)
    assert np.array_equal(a.positions, b.positions)


def test_solve_separates_the_muscles_and_lifts_them_off_the_bone(pressed):
    model, _ = pressed
    result = run(pressed, iterations=300)
    front, back = result.positions[:72], result.positions[72:]
    free = ~model.fixed
    gap = np.linalg.norm(front[:, None] - back[None], axis=2)
    pairs = (free[:72, None] | free[None, 72:]) & (gap < 2.4)
    # spheres squeezed between the other muscle and the bone keep a little of both overlaps
    assert (2.4 - gap[pairs]).max(initial=0.0) <= 0.02 * 1.2
    assert result.mean_displacement[-20:].mean() < result.mean_displacement[:20].mean()
    assert np.array_equal(result.positions[model.fixed], model.positions[model.fixed])


def test_switching_collisions_off(pressed):
    result = run(pressed, iterations=3, muscle_muscle=False, muscle_bone=False)
    assert result.colliding_pairs.sum() == 0 and not result.collided.any()


def test_divergence_names_the_muscle(pressed):
    # inside the margin of the stability bound, so it is not refused up front, and too long
    # for the springs: the run itself must stop
    dt = core_model.stable_time_step(pressed[0])[0]
    with pytest.raises(MuscleMSSError, match="muscle '(front|back)' diverged.*TimeStep"):
        run(pressed, iterations=300, time_step=0.95 * core_model.STABILITY_MARGIN * dt)


@pytest.mark.parametrize("structure", STRUCTURES)
@pytest.mark.parametrize("length, moved", [(1e9, r"\d.*e\+0\d"), (np.inf, "(inf|nan)")])
def test_a_sphere_thrown_out_of_the_scene_stops_before_collision_detection(
        pressed, structure, length, moved):
    """Particles that jump ~1e8 mm (or to inf) in one step are caught before the spatial hash
    or the BVH index a grid with them (the hash crashed the process with a segfault). A spring
    whose rest length is 1e9 mm throws its particles that far in the first step."""
    model, bones = pressed
    free = ~model.fixed[model.springs].any(axis=1) & (model.springs < 72).all(axis=1)
    rest = model.rest_length.copy()
    rest[np.flatnonzero(free)[0]] = length
    thrown = core_model.MSSModel(**{**model.__dict__, "rest_length": rest})
    with pytest.raises(MuscleMSSError, match=r"muscle 'front' diverged at iteration 1: its mean "
                       rf"particle displacement was {moved} mm"):
        solver.solve(thrown, Bones(bones), paper(iterations=5,
                                                                    structure=structure))


def test_the_grid_spans_take_any_coordinate():
    span = spatial_hash._cell_span
    assert span(5.0, 1.0, 0.0, 1.0, 10) == (4, 6)
    assert span(-5.0, 1.0, 0.0, 1.0, 10) == (1, 0) and span(50.0, 1.0, 0.0, 1.0, 10) == (1, 0)
    for value in (1e300, -1e300, np.inf, -np.inf, np.nan):
        first, last = span(value, 1.0, 0.0, 1.0, 10)
        assert first > last or 0 <= first <= last < 10


def test_a_grid_over_spheres_1e8_mm_apart_grows_its_cell_instead_of_overflowing():
    centres = np.array([[0.0, 1e8, 0.0, 5.0], [0.0, 1e8, 1e8, 5.0], [0.0, 1e8, 3.0, np.nan]])
    lower, dims, cell, start, items, bits, packed, tops = spatial_hash.grid_table(
        centres, np.ones(4), 1.0, np.arange(4))
    assert np.prod(dims.astype(float)) <= 8 * 4 + 64 and cell > 1e6
    assert sorted(items) == [0, 1, 2, 3] and start[-1] == 4


def test_a_time_step_far_beyond_the_stable_one_is_refused_up_front(pressed):
    model, _ = pressed
    with pytest.raises(MuscleMSSError, match=r"cannot be solved with TimeStep 2 s: particle \d+ "
                       r"of muscle 'front' \(mass 1 g, springs of total damping 13 g/s\) is stable only "
                       r"below 0.0769 s.*\(26 times too long\); lower the "
                       r"MSS Collision Solver's TimeStep below .*Spring Builder's Mass"):
        run(pressed, time_step=2.0)
    light = core_model.MSSModel(**{**model.__dict__, "mass": np.full(len(model.mass), 1e-8)})
    with pytest.raises(MuscleMSSError, match="mass 1e-08 g"):
        solver.solve(light, settings=paper())
    stiff = core_model.MSSModel(**{**model.__dict__, "stiffness": np.full(len(model.stiffness), 1e9)})
    with pytest.raises(MuscleMSSError, match="springs of total stiffness 2.6e\\+10 g/s\\^2.*lower its "
                       "Stiffness"):
        solver.solve(stiff, settings=paper())
    # a centre particle of the lattice: 26 springs of damping 0.5 g/s, 2 / (26 (1 + 1))
    assert core_model.stable_time_step(model) == (pytest.approx(2 / 26), 0, 34, "damping")


def test_an_iteration_history_too_large_for_memory_is_refused(pressed):
    with pytest.raises(MuscleMSSError, match=r"Iterations 1000000000 would need a 44.7 GiB "
                       r"history .*lower Iterations"):
        run(pressed, iterations=10 ** 9, termination="time budget")


def test_the_progress_callback_aborts_the_solve(pressed):
    calls = []

    def progress(fraction):
        calls.append(fraction)
        return True

    model, bones = pressed
    with pytest.raises(MuscleMSSError, match="stopped by the user"):
        solver.solve(model, Bones(bones), paper(iterations=10 ** 5),
                     progress=progress)
    assert len(calls) == 1 and 0 < calls[0] < 1


def test_bad_settings_are_refused(pressed):
    with pytest.raises(MuscleMSSError, match="property Termination is 'forever'; it must be "
                                             "one of iterations, displacement threshold"):
        run(pressed, termination="forever")
    with pytest.raises(MuscleMSSError, match=r"property TimeStep is 0.0; it must be at least"):
        run(pressed, time_step=0.0)
    with pytest.raises(MuscleMSSError, match="property CollisionStructure is 'grid'"):
        run(pressed, structure="grid")
    with pytest.raises(MuscleMSSError, match="property Method is 'newton'; it must be one of"):
        run(pressed, method="newton")
    with pytest.raises(MuscleMSSError, match="takes no start positions"):
        model, bones = pressed
        solver.solve(model, Bones(bones), paper(), start=model.positions)


def test_settings_route_flat_names_to_their_part_and_refuse_unknown_ones():
    settings = SolverSettings.build(iterations=7, structure="octree BVH", time_step=0.01,
                                    tolerance=1e-4)
    assert settings.iterations == 7 and settings.contacts.structure == "octree BVH"
    assert settings.relaxation.time_step == 0.01 and settings.quasi_static.tolerance == 1e-4
    assert settings.relaxation.drag == SolverSettings().relaxation.drag
    with pytest.raises(TypeError, match="no field tolerence"):
        SolverSettings.build(tolerence=1e-4)
    with pytest.raises(AttributeError):
        settings.tolerance = 1e-4       # the quasi-static part's, not a field of the whole
