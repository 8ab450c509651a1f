"""The Fibre Generator filter, `muscle-mss fibres SCENE` and the scene's `attachments.csv`
(DESIGN §4, §6 "Fibre generation"), on the small demo elbow: fibres made from its muscle
surfaces and bones validate, run from bone to bone inside their muscles along the shipped
fibres' directions; the attachments table names the bones for the generator, `validate` and the
Fibre Resampler; bad input is named."""
import csv
import os
import shutil

import numpy as np
import pytest

from muscle_mss.app.cli import main
from muscle_mss.core.attachments import fibre_ends
from muscle_mss.core.bones.weights import bone_distances
from muscle_mss.core.demo.arm import demo_arm_scene
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.scene import Surface
from muscle_mss.core.volume import winding_numbers
from muscle_mss.filters import array_names as A
from muscle_mss.filters import vtk_arrays as V
from muscle_mss.filters.scene_io import check_scene, load_scene, surfaces_to_vtk, write_scene

COUNT, POINTS = 16, 12


@pytest.fixture(scope="module")
def arm():
    return demo_arm_scene("small")


@pytest.fixture(scope="module")
def generated(tmp_path_factory, arm):
    """The small elbow scene with its fibres replaced by generated ones: ``(folder, output)``."""
    folder = tmp_path_factory.mktemp("generated") / "scene"
    write_scene(arm, folder)
    before = (folder / "fibres.vtm").read_bytes()
    assert main(["fibres", str(folder)]) == 2                      # refused: fibres.vtm exists
    assert (folder / "fibres.vtm").read_bytes() == before
    assert main(["fibres", str(folder), "--overwrite", "--count", str(COUNT),
                 "--points", str(POINTS)]) == 0
    return folder


def mean_direction(fibres) -> np.ndarray:
    origins, insertions = fibre_ends(fibres)
    d = (insertions - origins).mean(axis=0)
    return d / np.linalg.norm(d)


def test_generated_fibres_validate_and_run_bone_to_bone_inside_their_muscles(generated, arm):
    scene, problems = check_scene(str(generated))
    assert problems == []
    for name, fibres in scene.fibres.items():
        shipped, surface = arm.fibres[name], arm.muscles[name]
        assert fibres.count == COUNT and len(fibres.points) == COUNT * POINTS
        assert sorted(map(tuple, fibres.grid)) == [(r, c) for r in range(4) for c in range(4)]
        assert (fibres.origin_bone, fibres.insertion_bone) == \
            (shipped.origin_bone, shipped.insertion_bone)
        inside = winding_numbers(fibres.points, surface.points, surface.triangles) > 0.5
        assert inside.all(), name
        angle = np.degrees(np.arccos(mean_direction(fibres) @ mean_direction(shipped)))
        assert angle < 3.0, name
        for ends, bone in zip(fibre_ends(fibres), (fibres.origin_bone, fibres.insertion_bone)):
            b = arm.bones[bone]
            assert bone_distances(ends, [(b.points, b.triangles)]).mean() < 8.0, (name, bone)
    # the block files of the replaced fibres.vtm were replaced, none left over
    assert sorted(os.listdir(generated / "fibres")) == \
        sorted(f"fibres_{k}.vtp" for k in range(len(arm.fibres)))


def test_a_scene_without_fibres_asks_for_them_infers_their_bones_or_reads_them(
        tmp_path, arm, generated, capsys):
    folder = tmp_path / "scene"
    write_scene(arm, folder)
    os.remove(folder / "fibres.vtm")
    shutil.rmtree(folder / "fibres")
    assert "muscle-mss fibres" in check_scene(str(folder))[1][0]
    assert main(["fibres", str(folder), "--count", "4", "--points", "5"]) == 0
    assert capsys.readouterr().out.count("(inferred)") == len(arm.fibres)
    for name, fibres in load_scene(str(folder)).fibres.items():    # the shipped bones
        assert (fibres.origin_bone, fibres.insertion_bone) == \
            (arm.fibres[name].origin_bone, arm.fibres[name].insertion_bone)
    with open(folder / "attachments.csv", "w", newline="") as f:
        rows = csv.writer(f)
        rows.writerow(["muscle", "origin_bone", "insertion_bone"])
        for name, fibres in arm.fibres.items():
            rows.writerow([name, fibres.origin_bone, fibres.insertion_bone])
    assert main(["fibres", str(folder), "--overwrite", "--count", str(COUNT), "--points",
                 str(POINTS)]) == 0
    assert capsys.readouterr().out.count("(attachments.csv)") == len(arm.fibres)
    ours, theirs = load_scene(str(folder)), load_scene(str(generated))
    for name in arm.fibres:        # the same bones from either source: the same fibres
        np.testing.assert_array_equal(ours.fibres[name].points, theirs.fibres[name].points)


def unnamed_scene_with_attachments(folder, arm, origin_of=None):
    """The small elbow with no bone names in fibres.vtm and an attachments.csv naming them
    (``origin_of``: {muscle: origin bone} to name instead)."""
    scene = demo_arm_scene("small")
    for fibres in scene.fibres.values():
        fibres.origin_bone = fibres.insertion_bone = None
    write_scene(scene, folder)
    with open(folder / "attachments.csv", "w", newline="") as f:
        rows = csv.writer(f)
        rows.writerow(["muscle", "origin_bone", "insertion_bone"])
        for name, fibres in arm.fibres.items():
            rows.writerow([name, (origin_of or {}).get(name, fibres.origin_bone),
                           fibres.insertion_bone])


def test_the_fibre_resampler_reads_the_bones_from_attachments_csv(tmp_path, arm):
    from muscle_mss.app.motion_run import build_pipeline
    folder = tmp_path / "scene"
    unnamed_scene_with_attachments(folder, arm)
    scene = load_scene(str(folder))
    assert scene.fibres["brachialis"].origin_bone == "humerus"
    assert scene.fibres["biceps_long_head"].insertion_bone == "radius"
    pipeline = build_pipeline(str(folder))
    pipeline.resampler.Update()
    particles = dict(V.blocks(pipeline.resampler.GetOutputDataObject(0)))
    for name, fibres in arm.fibres.items():
        assert V.field(particles[name], A.ORIGIN_BONE) == fibres.origin_bone
        assert V.field(particles[name], A.INSERTION_BONE) == fibres.insertion_bone
    # a bone the fibres' ends do not lie on is refused, as when fibres.vtm names it
    unnamed_scene_with_attachments(tmp_path / "wrong", arm, {"brachialis": "scapula"})
    with pytest.raises(MuscleMSSError, match="'brachialis': origin_bone is 'scapula', but the "
                                             "fibres' origin ends lie 9"):
        load_scene(str(tmp_path / "wrong"))


def test_attachments_that_contradict_the_fibres_are_named(tmp_path, arm, generated):
    shutil.copytree(generated, tmp_path / "scene")
    with open(tmp_path / "scene" / "attachments.csv", "w") as f:
        f.write("muscle,origin_bone,insertion_bone\nbrachialis,scapula,ulna\n")
    problems = check_scene(str(tmp_path / "scene"))[1]
    assert any("fibres.vtm block 'brachialis': origin_bone is 'humerus' but" in p and
               "attachments.csv names 'scapula'" in p for p in problems)
    with open(tmp_path / "scene" / "attachments.csv", "w") as f:
        f.write("muscle,origin_bone,insertion_bone\nbrachialis,humerus,femur\n")
    problems = check_scene(str(tmp_path / "scene"))[1]
    assert "attachments.csv row 2, column insertion_bone: 'femur' is not a bone" in problems[0]


def test_the_filter_refuses_a_muscle_far_from_its_bone_naming_it(arm):
    from muscle_mss.filters.fibre_generator import FibreGenerator
    muscles = dict(arm.muscles)
    moved = muscles["brachialis"]
    muscles["brachialis"] = Surface(moved.points + np.array([0.0, 120.0, 0.0]), moved.triangles)
    generator = FibreGenerator()
    generator.SetInputData(0, surfaces_to_vtk(muscles))
    generator.SetInputData(1, surfaces_to_vtk(arm.bones))
    generator.SetInputData(2, V.make_table({"muscle": ["brachialis"],
                                            "origin_bone": ["humerus"],
                                            "insertion_bone": ["ulna"]}))
    with pytest.raises(MuscleMSSError) as err:
        generator.Update()
    assert "muscles.vtm block 'brachialis'" in str(err.value)
    assert "origin bone 'humerus'" in str(err.value) and "attachments.csv" in str(err.value)


def summary_by_muscle(out) -> dict:
    with open(out / "summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    by_muscle = {}
    for row in rows:
        by_muscle.setdefault(row["muscle"], []).append(row)
    return by_muscle


@pytest.mark.parametrize("region", ["arm", "thigh"])
def test_the_demo_motions_with_generated_fibres_keep_volume_and_follow(tmp_path, region):
    """The small demo elbow and thigh with their fibres replaced by generated ones (the same
    4 x 4 grid of 12 points) solve their whole motions with a mean volume error within 0.5
    percentage points of the shipped fibres', and the fibres of every muscle that shortens by
    over 3 % follow its length (`follows`, the slope of fibre strain on end-to-end strain, at
    least 0.8: the arm's flexors, the thigh's rectus femoris)."""
    pytest.importorskip("pyvista")    # the run's pictures; ParaView's Python has no pyvista
    from muscle_mss.app.demo_folder import demo_region_scene
    from muscle_mss.app.study import follow_slope
    shipped, generated = tmp_path / "shipped", tmp_path / "generated"
    write_scene(demo_region_scene(region, "small"), shipped)
    shutil.copytree(shipped, generated)
    assert main(["fibres", str(generated), "--overwrite", "--count", "16", "--points",
                 "12"]) == 0
    volume_errors = {}
    for scene in (shipped, generated):
        out = tmp_path / f"out-{scene.name}"
        assert main(["run", str(scene), str(out), "--cache", "off", "--write", "surfaces"]) == 0
        rows = summary_by_muscle(out)
        volume_errors[scene.name] = np.mean([float(r["volume_error_pct"])
                                             for rs in rows.values() for r in rs])
    assert abs(volume_errors["generated"] - volume_errors["shipped"]) <= 0.5, volume_errors
    shortening = {m: rs for m, rs in rows.items()
                  if min(float(r["mean_end_to_end_strain"]) for r in rs) < -0.03}
    assert shortening, "the motion shortens some muscle"
    for muscle, rs in shortening.items():
        assert follow_slope(rs) >= 0.8, muscle
