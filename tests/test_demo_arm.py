"""The demo elbow scene (issue 12, DESIGN §4): a valid scene of four bones and seven elbow muscles
attached to the right bones, closed outward surfaces, fibres inside their muscles, muscles
touching each other and the humerus but not intersecting each other or the bones at rest, a rigid
flexion 10 -> 130 -> 10 degrees about the elbow axis, determinism.

Runs in the venv and in Debian's ParaView Python (vtkmodules only).
"""
import numpy as np
import pytest

from muscle_mss.core.demo import arm
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.motion import rigid_problem
from muscle_mss.core.validation import scene_problems
from surface_probes import (assert_closed_and_outward, assert_identical_scenes, gap, inside,
                            signed_distance)

ATTACHMENTS = {  # the anatomy the scene is built to: (origin bone, insertion bone)
    "biceps_long_head": ("scapula", "radius"),
    "biceps_short_head": ("scapula", "radius"),
    "brachialis": ("humerus", "ulna"),
    "brachioradialis": ("humerus", "radius"),
    "triceps_long_head": ("scapula", "ulna"),
    "triceps_lateral_head": ("humerus", "ulna"),
    "triceps_medial_head": ("humerus", "ulna"),
}
LYING_ON_HUMERUS = ("brachialis", "triceps_medial_head", "triceps_lateral_head")
TOUCH_TOLERANCE = 1.0        # mm: neighbours touch or overlap
HUMERUS_TOLERANCE = 3.0      # mm: deep muscles lie against the humerus
ATTACHMENT_TOLERANCE = 2.5   # mm: fibre ends on their bone (plus the bone mesh's chord error)
OVERLAP_TOLERANCE = 1.0      # mm: muscles press at most this far into a bone away from tendons
TENDON_REACH = 25.0          # mm around an attachment where a tendon may enter its bone


@pytest.fixture(scope="module")
def full():
    return arm.demo_arm_scene("full")


@pytest.fixture(scope="module")
def small():
    return arm.demo_arm_scene("small")


# ---- structure -----------------------------------------------------------------------------

def test_full_scene_has_the_anatomical_parts(full):
    assert list(full.bones) == ["scapula", "humerus", "ulna", "radius"]
    assert list(full.muscles) == list(ATTACHMENTS) == list(arm.MUSCLE_NAMES)
    for name, fibres in full.fibres.items():
        assert fibres.count == 64, name
        assert np.array_equal(np.diff(fibres.offsets), np.full(64, 30)), name
        assert {tuple(g) for g in fibres.grid} == {(r, c) for r in range(8) for c in range(8)}
    assert full.motion.bones == ["scapula", "humerus", "ulna", "radius"]
    assert len(full.motion.times) == 13


@pytest.mark.parametrize("size", ["full", "small"])
def test_scene_passes_validation(size, full, small):
    assert scene_problems(full if size == "full" else small) == []


def test_small_scene_is_a_coarser_scene_of_the_same_anatomy(full, small):
    assert list(small.bones) == list(full.bones) and list(small.muscles) == list(full.muscles)
    for name, fibres in small.fibres.items():
        assert fibres.count == 16
        assert {tuple(x) for x in fibres.grid} == {(r, c) for r in range(4) for c in range(4)}
        assert len(small.muscles[name].triangles) < len(full.muscles[name].triangles)
    for bone in full.bones:
        assert len(small.bones[bone].triangles) < len(full.bones[bone].triangles)
    assert np.array_equal(small.motion.matrices, full.motion.matrices)


def test_unknown_size_is_refused():
    with pytest.raises(MuscleMSSError, match="size 'huge'"):
        arm.demo_arm_scene("huge")


def test_arm_scene_is_deterministic(small):
    assert_identical_scenes(small, arm.demo_arm_scene("small"))


# ---- surfaces ------------------------------------------------------------------------------

@pytest.mark.parametrize("size", ["full", "small"])
def test_every_surface_is_closed_manifold_and_outward(size, full, small):
    scene = full if size == "full" else small
    assert_closed_and_outward(scene)


def test_bones_have_adult_proportions(full):
    """Humerus ~320 mm with a wide distal end, ulna longer than radius, radius lateral to ulna,
    the humeral head in the glenoid and the bones apart at their joints."""
    humerus = full.bones["humerus"].points
    assert 310.0 < np.ptp(humerus[:, 2]) < 370.0
    head = np.linalg.norm(humerus - arm.SHOULDER_CENTRE, axis=1)
    assert abs(np.median(head[head < arm.HUMERAL_HEAD_RADIUS + 2.0]) - arm.HUMERAL_HEAD_RADIUS) < 1.0
    shaft = humerus[np.abs(humerus[:, 2] + 150.0) < 2.0]
    epicondyles = humerus[np.abs(humerus[:, 2] + 300.0) < 2.0]
    assert np.ptp(shaft[:, 0]) < 26.0 and np.ptp(epicondyles[:, 0]) > 2.5 * np.ptp(shaft[:, 0])
    ulna, radius = full.bones["ulna"].points, full.bones["radius"].points
    assert 250.0 < np.ptp(ulna[:, 2]) < 300.0 and 220.0 < np.ptp(radius[:, 2]) < np.ptp(ulna[:, 2])
    assert radius[:, 0].mean() > ulna[:, 0].mean() + 15.0
    socket = np.linalg.norm(full.bones["scapula"].points - arm.SHOULDER_CENTRE, axis=1)
    assert socket.min() > arm.HUMERAL_HEAD_RADIUS
    for a, b in (("humerus", "ulna"), ("humerus", "radius"), ("ulna", "radius"),
                 ("scapula", "humerus")):
        assert gap(full.bones[a], full.bones[b]) > 1.0, (a, b)


# ---- fibres ----------------------------------------------------------------------------------

@pytest.mark.parametrize("size", ["full", "small"])
def test_fibres_lie_inside_their_own_muscle(size, full, small):
    scene = full if size == "full" else small
    for name, fibres in scene.fibres.items():
        assert inside(scene.muscles[name], fibres.points).mean() >= 0.99, name


def test_fibres_run_from_origin_to_insertion_on_the_right_bones(full):
    for name, fibres in full.fibres.items():
        origin_bone, origin, insertion_bone, insertion = arm.muscle_attachments(name)
        assert (origin_bone, insertion_bone) == ATTACHMENTS[name]
        starts = fibres.points[fibres.offsets[:-1]]
        ends = fibres.points[fibres.offsets[1:] - 1]
        assert np.abs(signed_distance(full.bones[origin_bone], starts)).max() < ATTACHMENT_TOLERANCE
        assert np.abs(signed_distance(full.bones[insertion_bone], ends)).max() < ATTACHMENT_TOLERANCE
        assert np.linalg.norm(starts - origin, axis=1).max() < 3.0
        assert np.linalg.norm(ends - insertion, axis=1).max() < 3.0


# ---- packing -------------------------------------------------------------------------------

def test_each_muscle_touches_a_neighbour_and_deep_ones_the_humerus(full):
    names = list(full.muscles)
    for a in names:
        assert min(gap(full.muscles[a], full.muscles[b]) for b in names if b != a) < TOUCH_TOLERANCE
    for name in LYING_ON_HUMERUS:
        assert gap(full.muscles[name], full.bones["humerus"]) < HUMERUS_TOLERANCE, name


def test_muscles_do_not_intersect_each_other(full):
    """Neighbours share faces: hardly any of a muscle's surface lies more than 2 mm inside another
    muscle (the two biceps heads and the three triceps heads share a tendon)."""
    for a, surface in full.muscles.items():
        for b, other in full.muscles.items():
            near = surface.points[((surface.points > other.points.min(axis=0))
                                   & (surface.points < other.points.max(axis=0))).all(axis=1)]
            if a != b and len(near):
                assert (signed_distance(other, near) < -2.0).sum() < 0.03 * len(surface.points), (a, b)


def test_muscles_do_not_intersect_the_bones_away_from_their_tendons(full):
    for name, surface in full.muscles.items():
        _, origin, _, insertion = arm.muscle_attachments(name)
        away = ((np.linalg.norm(surface.points - origin, axis=1) > TENDON_REACH)
                & (np.linalg.norm(surface.points - insertion, axis=1) > TENDON_REACH))
        for bone, bone_surface in full.bones.items():
            assert signed_distance(bone_surface, surface.points[away]).min() > -OVERLAP_TOLERANCE, \
                (name, bone)


# ---- motion --------------------------------------------------------------------------------

def test_elbow_flexes_from_10_to_130_and_back_about_its_axis(full):
    m = full.motion.matrices
    identity = np.hstack([np.eye(3), np.zeros((3, 1))])
    for t in range(len(full.motion.times)):
        for b in range(len(full.motion.bones)):
            assert rigid_problem(m[t, b]) is None
    assert np.allclose(m[:, 0], identity) and np.allclose(m[:, 1], identity)
    assert np.array_equal(m[:, 2], m[:, 3])                      # the forearm moves as one
    axis_points = np.array([arm.ELBOW_CENTRE, arm.ELBOW_CENTRE + 20.0 * arm.ELBOW_AXIS])
    for t in range(len(full.motion.times)):
        assert np.allclose(axis_points @ m[t, 2, :, :3].T + m[t, 2, :, 3], axis_points)
    degrees = arm.flexion_angles(full.motion.times)
    assert np.allclose(degrees[[0, 6, 12]], [10.0, 130.0, 10.0])
    assert (np.diff(degrees[:7]) > 0).all() and (np.diff(degrees[6:]) < 0).all()
    turned = np.degrees(np.arctan2(m[:, 2, 2, 1], m[:, 2, 1, 1]))
    assert np.allclose(turned, degrees - arm.REST_FLEXION)
    wrist = np.array([20.0, 40.0, -550.0])
    flexed = m[6, 2, :, :3] @ wrist + m[6, 2, :, 3]
    assert flexed[1] > 150.0 and flexed[2] > arm.ELBOW_CENTRE[2]   # the hand comes forward and up


# ---- command line --------------------------------------------------------------------------

def test_demo_scene_command_writes_the_arm(tmp_path, capsys):
    from muscle_mss.app.cli import main
    from muscle_mss.filters.scene_io import load_scene
    pytest.importorskip("pyvista")
    assert main(["demo-scene", str(tmp_path), "--region", "arm", "--size", "small"]) == 0
    assert "(arm, small): 7 muscles, 4 bones, 112 fibres, 13 time points" in capsys.readouterr().out
    scene = load_scene(tmp_path)
    assert list(scene.bones) == list(arm.BONE_NAMES) and list(scene.muscles) == list(arm.MUSCLE_NAMES)
    assert (tmp_path / "preview.png").stat().st_size > 10000
