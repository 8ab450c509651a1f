"""The solvers' divergence guard: a solve with no rest state near its pose stops with a
:class:`PoseError` naming the muscle and the cause instead of writing results (issue 46); a pose
that shortens a muscle past what FibreShortening can follow is refused; the filter adds the
time. The scenes that used to diverge silently are cases of ``tests/bad_input_cases.py``."""
import dataclasses

import numpy as np
import pytest

from muscle_mss.core import divergence, solver
from muscle_mss.core.errors import MuscleMSSError, PoseError
from muscle_mss.core.fibre_shortening import SHORTEST, check_ends, shortened_springs
from muscle_mss.core.settings import METHOD_QUASI_STATIC, METHOD_RELAXATION, SolverSettings

from test_connective_tissue import slab
from test_fibre_shortening import posed


def pulled_away(model, by):
    """``model`` with its connective tissue's target moved ``by`` mm in x: no rest state near
    the pose (``by`` not finite: an energy that is not finite)."""
    target = np.array(model.positions, dtype=np.float64)
    target[:, 0] += by
    return dataclasses.replace(model, tissue_target=target)


def test_quasi_static_stops_naming_the_muscle_when_a_particle_runs_off():
    settings = SolverSettings(method=METHOD_QUASI_STATIC, connective_tissue=0.1)
    calm = solver.solve(pulled_away(slab(8), 1.0), settings=settings)
    assert np.isfinite(calm.positions).all()
    with pytest.raises(PoseError, match=r"^muscle 'slab' diverged in the quasi-static solve: "
                       r"after iteration \d+ a particle of it lay [0-9.e+]+ mm from its posed "
                       r"place, farther than the scene's size \(\d+\.?\d* mm\)") as caught:
        solver.solve(pulled_away(slab(8), 1e7), settings=settings)
    assert caught.value.muscle == "slab"


def test_quasi_static_refuses_an_energy_that_is_not_finite():
    settings = SolverSettings(method=METHOD_QUASI_STATIC, connective_tissue=0.1)
    with pytest.raises(PoseError, match=r"^muscle 'slab': the quasi-static energy of the posed "
                       r"model is not finite"):
        solver.solve(pulled_away(slab(8), np.inf), settings=settings)


def test_paper_relaxation_stops_naming_the_muscle_when_it_runs_off():
    settings = SolverSettings(method=METHOD_RELAXATION, connective_tissue=0.1)
    with pytest.raises(PoseError, match=r"^muscle 'slab' diverged"):
        solver.solve(pulled_away(slab(8), 1e7), settings=settings)


def test_a_solved_particle_farther_than_the_scene_is_across_or_not_finite_is_refused():
    model = slab(8)
    positions = np.array(model.positions, dtype=np.float64)
    divergence.check_solved(model, positions, METHOD_RELAXATION)
    near = positions.copy()
    across = np.linalg.norm(np.ptp(positions, axis=0))
    near[17, 1] += across + 0.5
    divergence.check_solved(model, near, METHOD_RELAXATION)
    far = positions.copy()
    far[17, 1] += across + 1.5     # the scene's size: across + 1 mm (no radii, no bones)
    with pytest.raises(PoseError, match=r"^muscle 'slab' diverged in the paper relaxation "
                       r"solve: a particle of it ended [0-9.]+ mm from its posed place"):
        divergence.check_solved(model, far, METHOD_RELAXATION)
    far[17, 1] = np.nan
    with pytest.raises(PoseError, match="ended nan mm"):
        divergence.check_solved(model, far, METHOD_RELAXATION)


def test_fibre_shortening_refuses_ends_closer_than_its_shortest_and_accepts_the_rest():
    model = slab(8)
    shortened_springs(posed(model, SHORTEST + 0.01))
    check_ends(posed(model, SHORTEST + 0.01))
    with pytest.raises(PoseError, match=r"^muscle 'slab': its origin and insertion \(its "
                       r"fibres' end centroids\) are 15.2 mm apart, 40 % of their 38 mm at "
                       r"rest; FibreShortening gives no rest shape"):
        shortened_springs(posed(model, 0.4))
    # one fibre's ends brought together, the muscle's centroids not: the fibre is named
    one = posed(model, 1.0)
    positions = np.array(one.positions)
    fibre = np.flatnonzero(one.fibre_id == 4)
    last = fibre[np.argmax(one.fibre_index[fibre])]
    positions[last, 2] = 0.0
    with pytest.raises(PoseError, match=r"^muscle 'slab': the ends of its fibre 4 are 0 mm "
                       r"apart, 0 % of their 38 mm at rest"):
        check_ends(dataclasses.replace(one, positions=positions))


def test_a_pose_error_names_the_time_when_given_one():
    err = PoseError("gracilis", ": its origin and insertion meet")
    assert str(err) == "muscle 'gracilis': its origin and insertion meet"
    assert str(err.at(0.25)) == "muscle 'gracilis' at time 0.25 s: its origin and insertion meet"
    assert err.at(None) is err and isinstance(err, MuscleMSSError)
