"""Fibres digitised in both directions are oriented from origin to insertion on a copy, with a
warning, and give the results of the consistently oriented scene (issue 30); the coarsest
resolution each layout supports is refused below it, naming N."""
import contextlib
import io

import numpy as np
import pytest

import bad_input_cases as B
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.fibre_direction import (direction_warning, fibre_directions,
                                             fibre_end_points, reversed_fibres)

REVERSED = next(c for c in B.CASES if c.name == "fibres-reversed")


def straight_fibres(flip, count=8, points=5):
    """``count`` parallel fibres from z = 0 to z = 100 mm, those in ``flip`` reversed."""
    fibres = []
    for f in range(count):
        line = np.c_[np.full(points, float(f)), np.zeros(points), np.linspace(0, 100, points)]
        fibres.append(line[::-1] if f in flip else line)
    return np.concatenate(fibres), np.arange(count + 1) * points


def distances_to_planes(points, offsets, z):
    """(F, 2) distances of each fibre's first and last point to the plane at height z."""
    first, last = fibre_end_points(points, offsets)
    return np.c_[np.abs(first[:, 2] - z), np.abs(last[:, 2] - z)]


# ---- the rule, on arrays ------------------------------------------------------------------------

def test_the_bones_decide_each_fibre_and_reversing_twice_gives_the_input_back():
    points, offsets = straight_fibres({1, 3, 5, 7})
    directions = fibre_directions(points, offsets, distances_to_planes(points, offsets, 0.0),
                                  distances_to_planes(points, offsets, 100.0))
    assert np.flatnonzero(directions.reversed).tolist() == [1, 3, 5, 7]
    assert directions.by_bones.all() and not directions.tie
    oriented = reversed_fibres(points, offsets, directions.reversed)
    assert np.array_equal(oriented, straight_fibres(set())[0])
    assert np.array_equal(reversed_fibres(oriented, offsets, directions.reversed), points)
    message = direction_warning("fibres.vtm block 'm'", directions, "pelvis", "tibia")
    assert message.startswith("fibres.vtm block 'm': 4 of its 8 fibres ran from insertion to "
                              "origin and were reversed on a copy (4 by their ends' distances "
                              "to the origin bone 'pelvis' and the insertion bone 'tibia')")


def test_the_bones_decide_even_against_the_majority():
    points, offsets = straight_fibres({0, 1, 2, 3, 4, 5})
    directions = fibre_directions(points, offsets, distances_to_planes(points, offsets, 0.0))
    assert np.flatnonzero(directions.reversed).tolist() == [0, 1, 2, 3, 4, 5]


def test_without_bones_the_minority_follows_the_majority():
    points, offsets = straight_fibres({2, 5, 6})
    directions = fibre_directions(points, offsets)
    assert np.flatnonzero(directions.reversed).tolist() == [2, 5, 6]
    assert not directions.by_bones.any() and not directions.tie
    message = direction_warning("fibres.vtm block 'm'", directions)
    assert "3 to run with most of the muscle's fibres, because the block names no origin_bone"\
           in message


def test_a_tie_keeps_fibre_0s_direction_and_says_so():
    points, offsets = straight_fibres({0, 2, 4, 6})
    directions = fibre_directions(points, offsets)
    assert directions.tie
    assert np.flatnonzero(directions.reversed).tolist() == [1, 3, 5, 7]
    message = direction_warning("fibres.vtm block 'm'", directions, bones_known=False)
    assert "4 to run as fibre 0 does, because the bones are not known here" in message


def test_ends_equally_near_both_bones_fall_back_to_the_majority():
    points, offsets = straight_fibres({3})
    same = distances_to_planes(points, offsets, 0.0)
    directions = fibre_directions(points, offsets, same, same)    # one bone at both ends
    assert not directions.by_bones.any()
    assert np.flatnonzero(directions.reversed).tolist() == [3]
    assert "about equally near the named bones" in direction_warning(
        "fibres.vtm block 'm'", directions, "femur", "femur")


def test_consistent_fibres_are_kept_without_a_word():
    points, offsets = straight_fibres(set())
    for directions in (fibre_directions(points, offsets),
                       fibre_directions(points, offsets,
                                        distances_to_planes(points, offsets, 0.0), None)):
        assert directions.count == 0
        assert direction_warning("fibres.vtm block 'm'", directions, "pelvis") is None


# ---- the filters: the reversed scene gives the unmodified scene's results ----------------------

@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    clean = B.make_scene(B.Case("clean", "", ""), tmp_path_factory.mktemp("clean"))
    reversed_ = B.make_scene(REVERSED, tmp_path_factory.mktemp("reversed"))
    return clean, reversed_


def _solve(folder, settings):
    """The solved particles' and the deformed surfaces' points per muscle at the bad-input
    time point, and the VTK warnings of the run."""
    from muscle_mss.app import motion_run
    from muscle_mss.filters import vtk_arrays as V
    from muscle_mss.filters.scene_io import vtk_messages
    with vtk_messages() as window:
        pipeline = motion_run.build_pipeline(str(folder), settings)
        result = motion_run.solve_time_point(pipeline, B.TIME_INDEX)
    points = {(kind, name): V.points_of(block)
              for kind, data in (("particles", result.particles), ("surfaces", result.surfaces))
              for name, block in V.blocks(data, kind)}
    return points, window.GetOutput()


@pytest.mark.parametrize("method", ["paper relaxation", "quasi-static"])
def test_reversed_fibres_give_the_results_of_the_oriented_scene(folders, method):
    clean, reversed_ = folders
    expected, quiet = _solve(clean, {"Method": method})
    got, warnings = _solve(reversed_, {"Method": method})
    assert "fibres ran from insertion to origin" not in quiet
    assert B.matches(REVERSED.expect, warnings), warnings
    assert expected.keys() == got.keys()
    for key in expected:
        np.testing.assert_allclose(got[key], expected[key], rtol=0, atol=1e-9, err_msg=str(key))


def test_the_resampler_without_bones_orients_by_the_majority(folders):
    """Half the fibres reversed and no Bones input: a tie, so fibre 0 (as digitised) sets the
    direction, which here is the right one; the warning asks for the bones."""
    from muscle_mss.filters import FibreResampler
    from muscle_mss.filters import vtk_arrays as V
    from muscle_mss.filters.scene_io import read_scene, vtk_messages
    outputs = []
    for folder in folders:
        resampler = FibreResampler()
        resampler.SetInputDataObject(0, read_scene(str(folder))[1])
        with vtk_messages() as window:
            resampler.Update()
        outputs.append({name: V.points_of(block)
                        for name, block in V.blocks(resampler.GetOutputDataObject(0), "p")})
    assert "8 to run as fibre 0 does, because the bones are not known here (connect bones.vtm "\
           "to the Bones input) and half the fibres run each way" in window.GetOutput()
    for name in outputs[0]:
        assert np.array_equal(outputs[0][name], outputs[1][name]), name


def test_validate_prints_what_a_run_would_reverse(folders):
    from muscle_mss.app.cli import main
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["validate", str(folders[1])]) == 0
    assert B.matches(REVERSED.expect.replace("Fibre Resampler: ", "warning: "), out.getvalue())


# ---- the coarsest resolution of each layout -------------------------------------------------------

@pytest.mark.parametrize("layout", ["lattice-6", "lattice-26", "Delaunay", "k-NN"])
def test_each_layout_takes_its_coarsest_resolution_and_refuses_one_less(folders, layout):
    from muscle_mss.app import motion_run
    from muscle_mss.filters.spring_builder import MIN_PARTICLES_PER_FIBRE
    least = MIN_PARTICLES_PER_FIBRE[layout]
    pipeline = motion_run.build_pipeline(str(folders[0]), {"ParticlesPerFibre": least,
                                                           "Layout": layout})
    pipeline.springs.Update()
    pipeline = motion_run.build_pipeline(str(folders[0]), {"ParticlesPerFibre": least - 1,
                                                           "Layout": layout})
    with pytest.raises(MuscleMSSError, match=f"{least - 1} particles per fibre .* too few for "
                                             f"the {layout} layout, which needs at least {least}"):
        pipeline.springs.Update()

