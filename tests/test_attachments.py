"""Attachment bones (issue 12, DESIGN §6 "Attachments"): the scene format's optional
origin_bone / insertion_bone field data, their inference from the nearest bone, the error for an
unknown bone, and fixed particles that follow their attachment bone exactly."""
import copy

import numpy as np
import pytest

from muscle_mss.core.demo import arm as demo_arm, scene as demo_scene
from muscle_mss.core.attachments import INSERTION, ORIGIN, fixed_particle_bones, scene_attachments
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.pose import pose_at
from muscle_mss.filters import (FibreResampler, RigidPoseTransform, SpringBuilder)
from muscle_mss.filters import array_names as A
from muscle_mss.filters import vtk_arrays as V
from muscle_mss.app.cli import main
from muscle_mss.filters.scene_io import check_scene, load_scene, scene_readers, write_scene


@pytest.fixture(scope="module")
def arm():
    return demo_arm.demo_arm_scene("small")


@pytest.fixture(scope="module")
def thigh():
    return demo_scene.demo_scene("full")


def _without_names(scene):
    bare = copy.deepcopy(scene)
    for fibres in bare.fibres.values():
        fibres.origin_bone = fibres.insertion_bone = None
    return bare


@pytest.mark.parametrize("region", ["arm", "thigh"])
def test_inference_finds_the_demo_scenes_true_attachments(region, arm, thigh):
    scene = arm if region == "arm" else thigh
    module = demo_arm if region == "arm" else demo_scene
    inferred = scene_attachments(_without_names(scene))
    given = scene_attachments(scene)
    for muscle in scene.muscles:
        truth = module.muscle_attachments(muscle)
        assert (scene.fibres[muscle].origin_bone, scene.fibres[muscle].insertion_bone) == \
            (truth[0], truth[2])
        for ends in (inferred, given):
            assert (ends[muscle][ORIGIN].bone, ends[muscle][INSERTION].bone) == (truth[0], truth[2])
        assert inferred[muscle][ORIGIN].inferred and not given[muscle][ORIGIN].inferred
        assert inferred[muscle][INSERTION].mean_distance < 3.0


def test_names_travel_through_the_files_and_validate_reports_them(arm, tmp_path, capsys):
    write_scene(arm, tmp_path / "named")
    write_scene(_without_names(arm), tmp_path / "bare")
    named, bare = load_scene(tmp_path / "named"), load_scene(tmp_path / "bare")
    assert named.fibres["triceps_long_head"].origin_bone == "scapula"
    assert named.fibres["triceps_long_head"].insertion_bone == "ulna"
    assert bare.fibres["triceps_long_head"].origin_bone is None
    assert main(["validate", str(tmp_path / "named")]) == 0
    out = capsys.readouterr().out
    assert "  brachioradialis: humerus (given" in out and "-> radius (given" in out
    assert main(["validate", str(tmp_path / "bare")]) == 0
    out = capsys.readouterr().out
    assert "  brachioradialis: humerus (inferred: nearest bone" in out
    assert "-> radius (inferred: nearest bone" in out


def test_an_unknown_bone_is_refused_naming_the_block_and_the_bone(arm, tmp_path, capsys):
    broken = copy.deepcopy(arm)
    broken.fibres["brachialis"].insertion_bone = "clavicle"
    write_scene(broken, tmp_path)
    scene, problems = check_scene(tmp_path)
    assert scene is None
    assert problems == ["fibres.vtm block 'brachialis': insertion_bone 'clavicle' is not a bone "
                        "of bones.vtm (its blocks: scapula, humerus, ulna, radius); name one of "
                        "them or leave insertion_bone out to infer it"]
    assert main(["validate", str(tmp_path)]) == 1
    assert "insertion_bone 'clavicle'" in capsys.readouterr().out


def _posed_model(folder, time):
    muscles, fibres, bones, motion = scene_readers(str(folder))
    resampler = FibreResampler()
    resampler.SetInputConnection(0, fibres.GetOutputPort())
    springs = SpringBuilder()
    springs.SetInputConnection(0, resampler.GetOutputPort())
    springs.SetInputConnection(1, muscles.GetOutputPort())
    pose = RigidPoseTransform()
    for port, source in enumerate((springs, bones, motion)):
        pose.SetInputConnection(port, source.GetOutputPort())
    pose.UpdateTimeStep(time)
    return V.blocks(pose.GetOutputDataObject(0))


@pytest.mark.parametrize("named", [True, False])
def test_fixed_particles_sit_where_their_bone_puts_them_at_full_flexion(named, arm, tmp_path):
    write_scene(arm if named else _without_names(arm), tmp_path)
    time = float(arm.motion.times[6])                         # 130 degrees
    matrices, _ = pose_at(arm.motion, time)
    bones = list(arm.bones)
    for name, block in _posed_model(tmp_path, time):
        origin, _, insertion, _ = demo_arm.muscle_attachments(name)
        assert (V.field(block, A.ORIGIN_BONE), V.field(block, A.INSERTION_BONE)) == (origin, insertion)
        rest = V.point_array(block, A.REST_POSITION)
        posed = V.points_of(block)
        ends = fixed_particle_bones(V.point_array(block, A.FIBRE_ID),
                                    V.point_array(block, A.FIBRE_INDEX),
                                    V.point_array(block, A.FIXED), bones.index(origin),
                                    bones.index(insertion))
        assert (ends >= 0).sum() == 2 * arm.fibres[name].count
        for b in np.unique(ends[ends >= 0]):
            m = matrices[b]
            np.testing.assert_allclose(posed[ends == b], rest[ends == b] @ m[:, :3].T + m[:, 3],
                                       rtol=0, atol=1e-9)
        weights = V.point_array(block, A.BONE_WEIGHTS)
        assert np.array_equal(weights[ends >= 0], np.eye(len(bones))[ends[ends >= 0]])


def test_the_pose_filter_refuses_an_unknown_bone(arm, tmp_path):
    broken = copy.deepcopy(arm)
    broken.fibres["biceps_short_head"].origin_bone = "sternum"
    write_scene(broken, tmp_path)                            # the files, not check_scene
    with pytest.raises(MuscleMSSError, match="Model block 'biceps_short_head': origin_bone "
                                             "'sternum' is not a bone of bones.vtm"):
        _posed_model(tmp_path, 0.0)


def test_particles_of_a_fibre_end_get_the_end_bone():
    fibre_id = np.array([0, 0, 0, 1, 1, 1, 1])
    fibre_index = np.array([0, 1, 2, 0, 1, 2, 3])
    fixed = np.array([1, 0, 1, 1, 1, 0, 1])                  # a fixed particle inside fibre 1
    assert fixed_particle_bones(fibre_id, fibre_index, fixed, 4, 7).tolist() == \
        [4, -1, 7, 4, -1, -1, 7]
