"""The quasi-static solve's first stage at softened contacts (``QuasiStaticSettings.soft_start``,
core/quasi_static/driver.py): it changes the path, never the problem solved; the answer is the
full stiffness's equilibrium, and the stages share the cap and the record."""
import math

import numpy as np
import pytest

from muscle_mss.core import model as S
from muscle_mss.core import quasi_static as Q
from muscle_mss.core.errors import MuscleMSSError

from test_contact_preconditioner import pressed_lattices
from test_quasi_static import quasi_static, stretched  # noqa: F401 (a fixture)


def solve(model, **values):
    return Q.solve(model, prepared=S.prepare(model), settings=quasi_static(
        projection_passes=0, **values))


def test_soft_start_ends_at_the_equilibrium_of_the_full_contact_stiffness(monkeypatch):
    """Two lattices pressed on each other (one equilibrium): the two-stage solve and the
    one-stage solve meet a tight tolerance at the same particles and the same energy, the
    muscles still pressing there; the two-stage record's energy rises once (the contacts
    stiffening between the stages), the one-stage record's never. The soft stage runs to a
    tight tolerance here so that it ends pressed (this small problem leaves its 0.5 mm after
    the first step, before the lattices meet again)."""
    monkeypatch.setattr(Q.driver, "SOFT_STAGE_TOLERANCE", 1e-6)
    model = pressed_lattices()
    two = solve(model, tolerance=1e-9, iterations=5000, soft_start=0.3)
    one = solve(model, tolerance=1e-9, iterations=5000, soft_start=1.0)
    for result in (one, two):
        assert result.converged and result.muscle_pairs[-1] > 0
    np.testing.assert_allclose(two.positions, one.positions, atol=1e-6)
    assert np.abs(one.positions - model.positions).max() > 0.1
    assert two.energy[-1] == pytest.approx(one.energy[-1], rel=1e-9)
    rises = np.flatnonzero(np.diff(two.energy) > 1e-9 * abs(two.energy[-1]))
    assert len(rises) == 1
    assert not (np.diff(one.energy) > 1e-9 * abs(one.energy[-1])).any()
    # the soft stage presses deeper: more overlap at its end than at the answer
    assert two.max_penetration[rises[0]] > 1.5 * two.max_penetration[-1]


def test_a_model_at_rest_ends_in_one_iteration_with_a_soft_start(stretched):
    """The first stage meets the tolerance at once with no contact touching: the softened and
    the full energy agree there, so no second stage runs."""
    rest = S.MSSModel(**{**stretched.__dict__, "positions": stretched.rest_positions.copy()})
    result = Q.solve(rest, settings=quasi_static(soft_start=0.3))
    assert result.converged and result.iterations == 1 and result.residual[0] < 1e-12
    np.testing.assert_allclose(result.positions, rest.positions, atol=1e-9)


def test_a_cap_spent_in_the_soft_stage_is_not_converged():
    result = solve(pressed_lattices(), tolerance=1e-9, iterations=3, soft_start=0.3)
    assert not result.converged and result.iterations == 3
    assert result.stopped_by == "iterations"


@pytest.mark.parametrize("value", [0.0, -0.3, 1.5, math.nan, True, "0.3"])
def test_a_soft_start_outside_zero_to_one_is_refused(value):
    from muscle_mss.core.solver import solve as checked_solve
    with pytest.raises(MuscleMSSError, match=f"soft_start is {value!r}.*above 0 and at most 1"):
        checked_solve(pressed_lattices(), settings=quasi_static(soft_start=value))
