"""The relaxation loop (core/solver.py): terminations, history, determinism, divergence, abort."""
import numpy as np
import pytest

from muscle_mss.core import solver
from muscle_mss.core.errors import MuscleMSSError

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
    model = solver.MSSModel(
        ["front", "back"], np.array([0, n, 2 * n]), positions, (index == 0) | (index == 7),
        np.ones(2 * n), np.ones(2 * n, bool), radius, fibre, index,
        np.concatenate([springs, springs + n]), np.concatenate([rest, rest]),
        np.full(2 * len(rest), 10.0), np.full(2 * len(rest), 0.5), np.zeros((2 * n, 2), int),
        np.concatenate([pts, second]))
    g = np.arange(-2, 10, 1.0)
    sheet = np.stack(np.meshgrid(g, g, [-1.5], indexing="ij"), -1).reshape(-1, 3)
    bones = (sheet, np.full(len(sheet), 1.0), np.zeros(len(sheet), int))
    return model, bones


def run(pressed, **kw):
    model, bones = pressed
    return solver.solve(model, *bones, settings=solver.SolverSettings(**kw))


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
    with pytest.raises(MuscleMSSError, match="muscle '(front|back)' diverged.*TimeStep"):
        run(pressed, iterations=300, time_step=2.0)


def test_abort_between_chunks(pressed):
    calls = []

    def progress(fraction):
        calls.append(fraction)
        return True

    model, bones = pressed
    with pytest.raises(MuscleMSSError, match="stopped by the user"):
        solver.solve(model, *bones, settings=solver.SolverSettings(iterations=10 ** 5),
                     progress=progress)
    assert len(calls) == 1 and 0 < calls[0] < 1


def test_bad_settings_are_refused(pressed):
    with pytest.raises(MuscleMSSError, match="termination"):
        run(pressed, termination="forever")
    with pytest.raises(MuscleMSSError, match="time step"):
        run(pressed, time_step=0.0)
