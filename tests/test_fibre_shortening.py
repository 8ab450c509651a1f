"""Fibres that shorten with their muscle (core/fibre_shortening.py, FibreShortening, issue 31):
the rule's rest lengths on a lattice slab, the slab solved with its ends brought 30 % closer
(it shortens and thickens instead of folding), and the MSS Collision Solver's property."""
import numpy as np
import pytest
from scipy.spatial import ConvexHull

from muscle_mss.core import solver
from muscle_mss.core.cage import fibre_polylines, polyline_lengths
from muscle_mss.core.fibre_shortening import (TARGET_BLEND, kept_shape_lengths,
                                              shortened_rest_lengths, shortened_springs,
                                              shortened_target, shortening_factors,
                                              volume_kept_stretch)
from muscle_mss.core.settings import METHOD_QUASI_STATIC, SPRING_ENERGIES, SolverSettings

from test_connective_tissue import slab

PER_FIBRE = 20
LENGTH = 38.0


def posed(model, ratio, bend=0.0):
    """The slab with its far end moved to ``ratio`` of its length, the free particles scaled
    with it and their middle lifted ``bend`` mm."""
    rest = model.rest_positions
    positions = rest * [1.0, 1.0, ratio]
    positions[:, 0] += bend * np.sin(np.pi * rest[:, 2] / LENGTH) * ~model.fixed
    return type(model)(**{**model.__dict__, "positions": positions})


def fibre_lengths(model, positions):
    """(F,) length and (F,) end-to-end distance of each fibre (mm)."""
    lengths, chords = [], []
    for f in np.unique(model.fibre_id):
        members = np.flatnonzero(model.fibre_id == f)
        walk = positions[members[np.argsort(model.fibre_index[members])]]
        lengths.append(np.linalg.norm(np.diff(walk, axis=0), axis=1).sum())
        chords.append(np.linalg.norm(walk[-1] - walk[0]))
    return np.array(lengths), np.array(chords)


def test_rest_lengths_contract_along_the_fibres_and_widen_across_only_where_fibres_shorten():
    model = slab(PER_FIBRE)
    step = model.rest_positions[model.springs[:, 1]] - model.rest_positions[model.springs[:, 0]]
    along = (step[:, 0] == 0) & (step[:, 1] == 0)
    across = step[:, 2] == 0
    short = shortened_rest_lengths(posed(model, 0.7))
    np.testing.assert_allclose(short[along], 0.7 * model.rest_length[along], rtol=1e-12)
    np.testing.assert_allclose(short[across], model.rest_length[across] / np.sqrt(0.7),
                               rtol=1e-12)
    diagonal = ~along & ~across
    cos2 = step[diagonal, 2] ** 2 / model.rest_length[diagonal] ** 2
    np.testing.assert_allclose(short[diagonal], model.rest_length[diagonal]
                               * np.sqrt(cos2 * 0.49 + (1 - cos2) / 0.7), rtol=1e-12)
    np.testing.assert_allclose(shortening_factors(posed(model, 0.7)), 0.7, rtol=1e-12)
    # the rest shape's vectors: along the fibres times 0.7, across divided by sqrt(0.7), as long
    # as the rest lengths
    vectors = shortened_springs(posed(model, 0.7)).rest_vectors
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), short, rtol=1e-12)
    np.testing.assert_allclose(vectors[:, 2], 0.7 * step[:, 2], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(vectors[:, :2], step[:, :2] / np.sqrt(0.7), rtol=1e-12,
                               atol=1e-12)
    # lengthened or unchanged: the rest lengths as they were, bitwise
    for ratio in (1.2, 1.0):
        assert shortened_rest_lengths(posed(model, ratio)) is model.rest_length
        unchanged = posed(model, ratio)
        assert shortened_springs(unchanged) is unchanged


def solved(model, rule: bool, springs: str):
    settings = SolverSettings.build(method=METHOD_QUASI_STATIC, tolerance=1e-4,
                                    iterations=4000, connective_tissue=0.0, springs=springs,
                                    fibre_shortening=rule)
    result = solver.solve(model, settings=settings)
    assert result.converged
    return result.positions


@pytest.mark.parametrize("springs", SPRING_ENERGIES)
def test_a_slab_whose_ends_come_30_percent_closer_shortens_and_thickens_instead_of_folding(
        springs):
    model = posed(slab(PER_FIBRE), 0.7, bend=1.0)      # a slight bend lets it fold
    rest_lengths, _ = fibre_lengths(model, model.rest_positions)
    rest_volume = ConvexHull(model.rest_positions).volume
    positions = solved(model, True, springs)
    lengths, chords = fibre_lengths(model, positions)
    np.testing.assert_allclose(lengths / rest_lengths - 1.0, -0.3, atol=0.03)
    assert (lengths / chords).max() <= 1.02
    assert ConvexHull(positions).volume == pytest.approx(rest_volume, rel=0.03)
    middle = model.fibre_index == PER_FIBRE // 2
    width = np.ptp(positions[middle, 1])
    assert width > 1.1 * np.ptp(model.rest_positions[middle, 1])        # thicker
    # without the rule the same pose keeps its fibres long and folds them
    lengths, chords = fibre_lengths(model, solved(model, False, springs))
    assert (lengths / chords).max() > 1.05
    assert (lengths / rest_lengths - 1.0).mean() > -0.2


def folded(model, ratio):
    """The slab with its far end moved to ``ratio`` of its length and its fibres keeping their
    rest length by arching sideways (x), as the Rigid Pose Transform poses a muscle whose
    attachments come closer (its particles carried by the bones, not shortened)."""
    rest = model.rest_positions
    u = rest[:, 2] / LENGTH
    z = np.linspace(0.0, ratio * LENGTH, 4001)
    height = LENGTH
    for _ in range(60):                     # the arch's height that keeps the arc LENGTH long
        arc = np.hypot(np.diff(z), np.diff(height * np.sin(np.pi * z / z[-1]))).sum()
        height *= LENGTH / arc
    positions = rest * [1.0, 1.0, ratio]
    positions[:, 0] += height * np.sin(np.pi * u) * ~model.fixed
    return type(model)(**{**model.__dict__, "positions": positions})


def test_the_tissue_target_of_a_shortened_muscle_is_its_rest_shape_shortened_volume_kept():
    """The connective tissue's target of a muscle whose ends come 30 % closer: the rest slab
    contracted 0.7 times along its length and widened 1 / sqrt(0.7) times across, straight
    between its ends, whatever arch the pose gave it; none where nothing shortens."""
    model = folded(slab(PER_FIBRE), 0.7)
    target = shortened_target(model)
    rest = model.rest_positions
    lengths, chords = fibre_lengths(model, target)
    rest_lengths, _ = fibre_lengths(model, rest)
    np.testing.assert_allclose(lengths, 0.7 * rest_lengths, rtol=1e-9)
    np.testing.assert_allclose(lengths / chords, 1.0, rtol=1e-9)
    for axis in (0, 1):
        np.testing.assert_allclose(np.ptp(target[:, axis]), np.ptp(rest[:, axis]) / np.sqrt(0.7),
                                   rtol=1e-9)
    assert ConvexHull(target).volume == pytest.approx(ConvexHull(rest).volume, rel=1e-9)
    assert shortened_springs(model).tissue_target is not None
    for ratio in (1.2, 1.0):
        assert shortened_target(posed(slab(PER_FIBRE), ratio)) is None
    # just short of the rest length: nearly the posed pose (the blend starts smoothly)
    barely = folded(slab(PER_FIBRE), 1.0 - 0.01 * TARGET_BLEND)
    assert np.abs(shortened_target(barely) - barely.positions).max() < 0.01


@pytest.mark.parametrize("springs", SPRING_ENERGIES)
def test_with_the_tissue_an_arched_slab_30_percent_shorter_shortens_its_fibres(springs):
    """The connective tissue (the default 0.1, weak along the fibres) holds the slab toward
    its shortened rest shape, not toward the arch the pose gave it (arc / chord 1.43): the fibres
    shorten 30 +- 3 % and stay straight; held toward the arch, they shortened 6-18 % and stayed
    bent (arc / chord 1.20-1.35)."""
    import dataclasses
    model = shortened_springs(folded(slab(PER_FIBRE), 0.7))
    rest_lengths, _ = fibre_lengths(model, model.rest_positions)
    settings = SolverSettings.build(method=METHOD_QUASI_STATIC, tolerance=1e-4,
                                    iterations=4000, connective_tissue=0.1, springs=springs,
                                    fibre_shortening=False)    # shortened above, by hand
    lengths, chords = fibre_lengths(model, solver.solve(model, settings=settings).positions)
    np.testing.assert_allclose(lengths / rest_lengths - 1.0, -0.3, atol=0.03)
    assert (lengths / chords).max() <= 1.02
    arch = dataclasses.replace(model, tissue_target=None)
    lengths, chords = fibre_lengths(model, solver.solve(arch, settings=settings).positions)
    assert (lengths / rest_lengths - 1.0).mean() > -0.2 and (lengths / chords).max() > 1.1


def test_the_elbow_demos_shortening_muscles_shorten_at_130_degrees_with_the_property(tmp_path):
    """Through the six filters (FibreShortening on the MSS Collision Solver): the biceps,
    brachialis and brachioradialis, whose ends come 20-30 % closer at 130 degrees, shorten
    their fibres instead of keeping their length; the lengthening triceps are unchanged."""
    from muscle_mss.filters import array_names as A
    from muscle_mss.app.motion_run import build_pipeline, solve_time_point
    from arm_scenes import written_arm_at_full_flexion
    scene, index = written_arm_at_full_flexion("small", tmp_path)
    rows = {}
    for on in (False, True):
        result = solve_time_point(build_pipeline(tmp_path, {"FibreShortening": on}), index)
        rows[on] = {r["muscle"]: r for r in result.rows}
    for name in ("biceps_short_head", "brachialis", "brachioradialis"):
        off, on = rows[False][name], rows[True][name]
        assert on[A.MEAN_END_TO_END_STRAIN] < -0.15
        # off (the other defaults: co-rotational springs, the tissue weak along the fibres):
        # measured 15-40 % of the end-to-end change, the rest folded (arc/chord 1.2-1.44)
        assert off[A.MEAN_FIBRE_STRAIN] > 0.5 * on[A.MEAN_END_TO_END_STRAIN]
        # on: measured 87-98 % of it on the small scene (its 4 x 4 fibres)
        assert on[A.MEAN_FIBRE_STRAIN] < 0.8 * on[A.MEAN_END_TO_END_STRAIN]
        assert on[A.MAX_ARC_CHORD] < off[A.MAX_ARC_CHORD]
    for name in ("triceps_long_head", "triceps_lateral_head", "triceps_medial_head"):
        assert rows[True][name][A.MEAN_END_TO_END_STRAIN] > 0.1
        assert rows[True][name][A.MEAN_FIBRE_STRAIN] == pytest.approx(
            rows[False][name][A.MEAN_FIBRE_STRAIN], abs=0.01)


def test_the_command_line_sets_the_property_only_when_asked():
    import argparse
    from muscle_mss.app.run_options import add_run_options, settings_from
    parser = argparse.ArgumentParser()
    add_run_options(parser)
    assert "FibreShortening" not in settings_from(parser.parse_args([]))
    assert settings_from(parser.parse_args(["--fibre-shortening"]))["FibreShortening"] is True
    assert settings_from(parser.parse_args(["--no-fibre-shortening"]))["FibreShortening"] is False


def test_the_kept_shape_reference_scales_straight_fibres_by_s_and_curved_ones_less():
    """A slab's straight fibres along its origin-insertion line change by s; the fibres of a
    spindle (converging on its two ends, bowed around its belly) change less than s either
    way, since the belly thickens as it shortens and thins as it lengthens (volume kept)."""
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    stretch = volume_kept_stretch(axis, 0.7)
    assert np.linalg.det(stretch) == pytest.approx(1.0, rel=1e-12)
    np.testing.assert_allclose(stretch @ axis, 0.7 * axis, rtol=1e-12)
    model = slab(PER_FIBRE)
    order, offsets, _ = fibre_polylines(model.fibre_id, model.fibre_index)
    rest = model.rest_positions
    lengths = polyline_lengths(rest, order, offsets)
    for s in (0.7, 1.0, 1.2):
        np.testing.assert_allclose(kept_shape_lengths(rest, order, offsets, s), s * lengths,
                                   rtol=1e-12)
    # a spindle: 12 fibres from (0, 0, 0) to (0, 0, 40), bowed 6 mm out in 12 directions
    t = np.linspace(0.0, 1.0, PER_FIBRE)
    angles = np.linspace(0.0, 2.0 * np.pi, 12, endpoint=False)
    spindle = np.concatenate([np.column_stack([6.0 * np.sin(np.pi * t) * np.cos(a),
                                               6.0 * np.sin(np.pi * t) * np.sin(a), 40.0 * t])
                              for a in angles])
    order, offsets, _ = fibre_polylines(np.repeat(np.arange(12), PER_FIBRE),
                                        np.tile(np.arange(PER_FIBRE), 12))
    rest_lengths = polyline_lengths(spindle, order, offsets)
    assert (rest_lengths / 40.0 > 1.05).all()                        # curved at rest
    for s in (0.7, 1.2):
        ratio = kept_shape_lengths(spindle, order, offsets, s) / rest_lengths
        assert (np.minimum(s, 1.0) < ratio).all() and (ratio < np.maximum(s, 1.0)).all()
    assert np.isnan(kept_shape_lengths(spindle, order, offsets, 0.0)).all()   # ends on one point
