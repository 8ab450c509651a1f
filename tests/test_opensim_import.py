"""``muscle-mss import-opensim`` (issue 50, DESIGN §7 "Importers"): an elbow model written here
with the opensim API from the small demo arm's bones imports to the scene the model itself
says (bones at the default pose, motion from OpenSim's kinematics, reference lengths), and bad
input is named. Needs the ``opensim`` extra (pip); without it only the install hint is tested."""
import csv
import os
import sys

import numpy as np
import pytest

from muscle_mss.app.cli import main
from muscle_mss.core.errors import MuscleMSSError

ELBOW_DEFAULT = 0.35
"""The elbow coordinate's default value (rad): the default pose is not the zero pose."""
MOTION_DEGREES = (10.0, 45.0, 90.0, 130.0, 60.0)
MOTION_TIMES = (0.0, 0.25, 0.5, 0.75, 1.0)
MUSCLE = "biceps_long_head"
RADIUS_OFFSET = ((0.3, (0.0, 0.0, 1.0)), (0.01, -0.02, 0.005))
"""The offset frame the radius mesh hangs on: (angle rad, axis), translation m in the forearm."""


@pytest.fixture(scope="module")
def osim():
    """The opensim package, its log file (``opensim.log`` in the working folder) off."""
    from muscle_mss.app.opensim_import import opensim_module
    pytest.importorskip("opensim", reason="the opensim extra is not installed in this Python "
                                          "(pip install 'muscle-mss[opensim]')")
    return opensim_module()


@pytest.fixture(scope="module")
def arm():
    from muscle_mss.core.demo.arm import demo_arm_scene
    return demo_arm_scene("small")


def write_vtp(points, triangles, path):
    from vtkmodules.vtkIOXML import vtkXMLPolyDataWriter
    from muscle_mss.filters.vtk_arrays import make_polydata
    writer = vtkXMLPolyDataWriter()
    writer.SetFileName(str(path))
    writer.SetInputData(make_polydata(points, triangles=triangles))
    assert writer.Write()


def write_stl(points, triangles, path):
    from vtkmodules.vtkIOGeometry import vtkSTLWriter
    from muscle_mss.filters.vtk_arrays import make_polydata
    writer = vtkSTLWriter()
    writer.SetFileName(str(path))
    writer.SetInputData(make_polydata(points, triangles=triangles))
    assert writer.Write()


def to_local(osim, frame, state, points_mm):
    """Ground points (mm) in ``frame``'s coordinates (m) at ``state``."""
    from muscle_mss.app.opensim_import import matrix34
    placed = matrix34(frame.getTransformInGround(state))
    return (points_mm / 1000.0 - placed[:, 3]) @ placed[:, :3]


def build_model(osim, arm, folder):
    """An elbow model in ``folder``: scapula and humerus welded to ground (the humerus mesh
    stored at half size, scale factors 2), a forearm on a pin joint at the demo's elbow (ulna
    on the body, radius on an offset frame), a hand with no mesh on a locked wrist, the biceps
    long head as a Millard muscle; the meshes written in their frames' coordinates so that at
    the default pose they lie where the demo's bones do. Returns the model's path."""
    from muscle_mss.core.demo.arm import ELBOW_CENTRE
    model = osim.Model()
    model.setName("elbow")
    inertia = osim.Inertia(0.01, 0.01, 0.01)
    bodies = {name: osim.Body(name, 1.0, osim.Vec3(0), inertia)
              for name in ("scapula", "humerus", "forearm", "hand")}
    for body in bodies.values():
        model.addBody(body)
    model.addJoint(osim.WeldJoint("shoulder_girdle", model.getGround(), bodies["scapula"]))
    model.addJoint(osim.WeldJoint("shoulder", bodies["scapula"], bodies["humerus"]))
    elbow = osim.PinJoint("elbow", bodies["humerus"], osim.Vec3(*(ELBOW_CENTRE / 1000.0)),
                          osim.Vec3(0.0, np.pi / 2, 0.0), bodies["forearm"], osim.Vec3(0),
                          osim.Vec3(0.0, np.pi / 2, 0.0))
    elbow.upd_coordinates(0).setName("elbow_flexion")
    elbow.upd_coordinates(0).setDefaultValue(ELBOW_DEFAULT)
    model.addJoint(elbow)
    wrist = osim.PinJoint("wrist", bodies["forearm"], osim.Vec3(0, 0, -0.25), osim.Vec3(0),
                          bodies["hand"], osim.Vec3(0), osim.Vec3(0))
    wrist.upd_coordinates(0).setName("wrist_flexion")
    wrist.upd_coordinates(0).setDefaultValue(0.1)
    wrist.upd_coordinates(0).setDefaultLocked(True)
    model.addJoint(wrist)
    (angle, axis), shift = RADIUS_OFFSET
    offset = osim.PhysicalOffsetFrame("radius_frame", bodies["forearm"], osim.Transform(
        osim.Rotation(angle, osim.Vec3(*axis)), osim.Vec3(*shift)))
    bodies["forearm"].addComponent(offset)
    muscle = osim.Millard2012EquilibriumMuscle(MUSCLE, 400.0, 0.15, 0.2, 0.0)
    muscle.addNewPathPoint("origin", bodies["scapula"], osim.Vec3(0.01, 0.02, 0.0))
    muscle.addNewPathPoint("insertion", bodies["forearm"], osim.Vec3(0.0, 0.03, -0.04))
    model.addForce(muscle)
    model.finalizeConnections()
    state = model.initSystem()
    geometry = folder / "Geometry"
    geometry.mkdir()
    meshes = (("scapula", bodies["scapula"], 1.0), ("humerus", bodies["humerus"], 2.0),
              ("ulna", bodies["forearm"], 1.0), ("radius", offset, 1.0))
    for bone, frame, scale in meshes:      # every file first: attaching changes the system
        local = to_local(osim, frame, state, arm.bones[bone].points) / scale
        write_vtp(local, arm.bones[bone].triangles, geometry / f"{bone}.vtp")
    for bone, frame, scale in meshes:
        mesh = osim.Mesh(f"{bone}.vtp")
        mesh.set_scale_factors(osim.Vec3(scale))
        frame.attachGeometry(mesh)
    model.finalizeConnections()
    path = folder / "elbow.osim"
    model.printToXML(str(path))
    return path


def write_mot(osim, path, columns: dict, degrees=True):
    """A motion file of ``columns`` (label -> values at :data:`MOTION_TIMES`)."""
    table = osim.TimeSeriesTable()
    table.setColumnLabels(osim.StdVectorString(list(columns)))
    for k, time in enumerate(MOTION_TIMES):
        table.appendRow(time, osim.RowVector([float(v[k]) for v in columns.values()]))
    table.addTableMetaDataString("inDegrees", "yes" if degrees else "no")
    osim.STOFileAdapter.write(table, str(path))
    return path


@pytest.fixture(scope="module")
def elbow(osim, arm, tmp_path_factory):
    """The model, its motion in degrees, a muscle folder (the biceps long head in metres as
    STL, the brachialis, which the model lacks, in mm as PLY), and the import's output."""
    from vtkmodules.vtkIOPLY import vtkPLYWriter
    from muscle_mss.filters.vtk_arrays import make_polydata
    folder = tmp_path_factory.mktemp("opensim")
    model = build_model(osim, arm, folder)
    motion = write_mot(osim, folder / "flexion.mot",
                       {"/jointset/elbow/elbow_flexion/value": MOTION_DEGREES})
    muscles = folder / "muscles"
    muscles.mkdir()
    biceps = arm.muscles[MUSCLE]
    write_stl(biceps.points / 1000.0, biceps.triangles, muscles / f"{MUSCLE}.stl")
    ply = vtkPLYWriter()
    ply.SetFileName(str(muscles / "brachialis.ply"))
    ply.SetInputData(make_polydata(arm.muscles["brachialis"].points,
                                   triangles=arm.muscles["brachialis"].triangles))
    assert ply.Write()
    out = folder / "scene"
    assert main(["import-opensim", str(model), str(motion), str(out), "--muscles",
                 str(muscles)]) == 0
    return {"model": model, "motion": motion, "muscles": muscles, "out": out,
            "folder": folder}


def expected_motion(osim, model_path):
    """Each body's transform from the default pose at each motion row, computed here with
    OpenSim: (T, 4 bodies, 3, 4), translation mm."""
    from muscle_mss.app.opensim_import import matrix34
    model = osim.Model(str(model_path))
    state = model.initSystem()
    names = ("scapula", "humerus", "forearm")
    rest = [matrix34(model.getBodySet().get(n).getTransformInGround(state)) for n in names]
    coordinate = model.getCoordinateSet().get("elbow_flexion")
    out, lengths = [], []
    for angle in MOTION_DEGREES:
        coordinate.setValue(state, np.radians(angle))
        model.realizePosition(state)
        row = []
        for name, r in zip(names, rest):
            now = matrix34(model.getBodySet().get(name).getTransformInGround(state))
            rotation = now[:, :3] @ np.linalg.inv(r[:, :3])
            row.append(np.column_stack([rotation, 1000.0 * (now[:, 3] - rotation @ r[:, 3])]))
        out.append(row)
        lengths.append(1000.0 * model.getMuscles().get(MUSCLE).getLength(state))
    return names, np.array(out), np.array(lengths)


def read_rows(path):
    with open(path, newline="") as f:
        return list(csv.reader(f))


def read_surfaces(path):
    from muscle_mss.filters.scene_io import multiblock_reader, surfaces_from_vtk
    return surfaces_from_vtk(multiblock_reader(str(path)).GetOutputDataObject(0), path.name)


def test_motion_is_the_models_own_kinematics(osim, elbow):
    names, matrices, _ = expected_motion(osim, elbow["model"])
    rows = read_rows(elbow["out"] / "motion.csv")
    assert rows[0] == ["time", "bone"] + [f"m{i}{j}" for i in range(3) for j in range(4)]
    assert [r[1] for r in rows[1:]] == list(names) * len(MOTION_TIMES)   # hand: no mesh
    assert [float(r[0]) for r in rows[1:]] == [t for t in MOTION_TIMES for _ in names]
    values = np.array([[float(v) for v in r[2:]] for r in rows[1:]]).reshape(matrices.shape)
    np.testing.assert_allclose(values, matrices, atol=1e-6)
    assert abs(values[:, 2, 1, 1] - np.cos(np.radians(MOTION_DEGREES) - ELBOW_DEFAULT)).max() \
        < 1e-9   # the forearm turns about x by the angle less the default
    np.testing.assert_allclose(values[:, :2], np.tile(np.eye(3, 4), (5, 2, 1, 1)), atol=1e-12)


def test_bones_lie_where_the_meshes_are_at_the_default_pose(elbow, arm):
    """Every bone point is a mesh point at the default pose (1e-6 mm), and every mesh point has
    one within the merge tolerance (the demo's marching-tetrahedra meshes have a few points
    closer than that, which the cleaning merges); the volumes agree."""
    from scipy.spatial import cKDTree
    from muscle_mss.core.mesh_cleaning import MERGE_TOLERANCE
    from muscle_mss.core.volume import signed_volume
    bones = read_surfaces(elbow["out"] / "bones.vtm")
    assert list(bones) == ["scapula", "humerus", "forearm"]
    parts = {"scapula": ["scapula"], "humerus": ["humerus"], "forearm": ["ulna", "radius"]}
    for name, bone in bones.items():
        points = np.vstack([arm.bones[b].points for b in parts[name]])
        assert cKDTree(points).query(bone.points)[0].max() < 1e-6
        merge = MERGE_TOLERANCE * np.linalg.norm(np.ptp(points, axis=0))
        assert cKDTree(bone.points).query(points)[0].max() < merge
        assert len(points) - 10 <= len(bone.points) <= len(points)
        volume = sum(signed_volume(arm.bones[b].points, arm.bones[b].triangles)
                     for b in parts[name])
        assert signed_volume(bone.points, bone.triangles) == pytest.approx(volume, rel=1e-6)


def test_muscles_are_cleaned_in_name_order_and_reference_lengths_match(osim, elbow, arm):
    from muscle_mss.core.mesh_checks import surface_problems
    from muscle_mss.core.volume import signed_volume
    muscles = read_surfaces(elbow["out"] / "muscles.vtm")
    assert list(muscles) == ["biceps_long_head", "brachialis"]
    for name, surface in muscles.items():
        assert surface_problems(surface.points, surface.triangles) == []
        rest = arm.muscles[name]
        assert signed_volume(surface.points, surface.triangles) == pytest.approx(
            signed_volume(rest.points, rest.triangles), rel=1e-4)   # metres and mm found
    _, _, lengths = expected_motion(osim, elbow["model"])
    rows = read_rows(elbow["out"] / "reference_lengths.csv")
    assert rows[0] == ["time", "muscle", "length_mm"]
    assert [r[1] for r in rows[1:]] == [MUSCLE] * len(MOTION_TIMES)
    np.testing.assert_allclose([float(r[2]) for r in rows[1:]], lengths, atol=1e-9)
    from muscle_mss.app.reference_lengths import read_reference_lengths
    times, read = read_reference_lengths(str(elbow["out"]))[MUSCLE]
    np.testing.assert_array_equal(times, MOTION_TIMES)
    np.testing.assert_allclose(read, lengths, atol=1e-9)


def test_the_imported_scene_gets_fibres_and_validates(elbow, tmp_path, capsys):
    """The README's second command on the import: `muscle-mss fibres` infers each muscle's
    bones from the imported ones (the forearm carries ulna and radius) and the scene passes
    `validate`."""
    import shutil
    from muscle_mss.filters.scene_io import check_scene
    scene = tmp_path / "scene"
    shutil.copytree(elbow["out"], scene)
    assert main(["fibres", str(scene), "--count", "9", "--points", "8"]) == 0
    printed = capsys.readouterr().out
    assert "biceps_long_head: scapula -> forearm (inferred)" in printed
    assert "brachialis: humerus -> forearm (inferred)" in printed
    loaded, problems = check_scene(str(scene))
    assert problems == [] and sorted(loaded.fibres) == ["biceps_long_head", "brachialis"]


def test_an_import_is_replaced_only_with_overwrite(elbow, capsys):
    args = ["import-opensim", str(elbow["model"]), str(elbow["motion"]), str(elbow["out"])]
    assert main(args) == 2
    assert "--overwrite" in capsys.readouterr().err
    before = read_rows(elbow["out"] / "motion.csv")
    assert main(args + ["--overwrite", "--muscles", str(elbow["muscles"])]) == 0
    printed = capsys.readouterr().out
    assert "skipped, no mesh: hand" in printed and "replacing the earlier import" in printed
    assert "no reference length for brachialis: the model has no muscle" in printed
    assert read_rows(elbow["out"] / "motion.csv") == before


def test_radians_in_a_classic_inverse_kinematics_file_give_the_same_motion(elbow):
    """The header OpenSim's IK tool writes (``Coordinates``, ``nRows``, ``inDegrees=no``), the
    coordinate by name, angles in radians: the same motion.csv as the degrees by path."""
    lines = ["Coordinates", "version=1", f"nRows={len(MOTION_TIMES)}", "nColumns=2",
             "inDegrees=no", "endheader", "time\telbow_flexion"]
    lines += [f"{t!r}\t{float(np.radians(a))!r}" for t, a in zip(MOTION_TIMES, MOTION_DEGREES)]
    motion = elbow["folder"] / "radians.mot"
    motion.write_text("\n".join(lines) + "\n")
    out = elbow["folder"] / "radians"
    assert main(["import-opensim", str(elbow["model"]), str(motion), str(out)]) == 0
    ours = np.array([[float(v) for v in r[2:]] for r in read_rows(out / "motion.csv")[1:]])
    theirs = np.array([[float(v) for v in r[2:]]
                       for r in read_rows(elbow["out"] / "motion.csv")[1:]])
    np.testing.assert_allclose(ours, theirs, atol=1e-9)
    assert not (out / "muscles.vtm").exists() and not (out / "reference_lengths.csv").exists()


def failing(elbow, capsys, model=None, motion=None, muscles=None, out="bad"):
    """The import of these inputs (default: the good ones) fails; its message."""
    args = ["import-opensim", str(model or elbow["model"]), str(motion or elbow["motion"]),
            str(elbow["folder"] / out)]
    if muscles:
        args += ["--muscles", str(muscles)]
    assert main(args) == 2
    assert not os.path.exists(elbow["folder"] / out / "motion.csv")
    return capsys.readouterr().err


def test_a_missing_mesh_file_is_named(osim, elbow, capsys, tmp_path):
    text = (elbow["model"]).read_text().replace("ulna.vtp", "ulna_lost.vtp")
    (elbow["folder"] / "lost.osim").write_text(text)
    err = failing(elbow, capsys, model=elbow["folder"] / "lost.osim")
    assert "ulna_lost.vtp" in err and "'forearm'" in err and "Geometry" in err


def test_motion_columns_must_be_the_models_coordinates(osim, elbow, capsys):
    unknown = write_mot(osim, elbow["folder"] / "knee.mot",
                        {"elbow_flexion": MOTION_DEGREES, "knee_angle": MOTION_DEGREES})
    assert "column 'knee_angle'" in failing(elbow, capsys, motion=unknown)
    lacking = write_mot(osim, elbow["folder"] / "wrist.mot", {"wrist_flexion": MOTION_DEGREES})
    err = failing(elbow, capsys, motion=lacking)
    assert "'elbow_flexion'" in err and "free" in err


def test_a_muscle_with_a_large_hole_is_refused_naming_it(elbow, arm, capsys):
    from muscle_mss.core.mesh_cleaning import MAX_HOLE_SPAN_MM
    folder = elbow["folder"] / "holed"
    folder.mkdir()
    biceps = arm.muscles[MUSCLE]
    top = biceps.points[biceps.triangles].mean(axis=1)[:, 2]
    keep = top < np.quantile(top, 0.9)          # the muscle's upper end cut off
    write_stl(biceps.points, biceps.triangles[keep], folder / "cut.stl")
    err = failing(elbow, capsys, muscles=folder)
    assert "cut.stl" in err and "hole of" in err and f"the {MAX_HOLE_SPAN_MM:g} mm" in err


def test_without_opensim_the_command_says_how_to_install_it(monkeypatch, tmp_path, capsys):
    from muscle_mss.app.opensim_import import opensim_module
    monkeypatch.setitem(sys.modules, "opensim", None)
    with pytest.raises(MuscleMSSError, match="pip install 'muscle-mss\\[opensim\\]'"):
        opensim_module()
    assert main(["import-opensim", str(tmp_path / "m.osim"), str(tmp_path / "m.mot"),
                 str(tmp_path / "out")]) == 2
    assert "needs the opensim package" in capsys.readouterr().err


def test_the_study_plots_the_models_length_beside_the_fibre_strain(tmp_path, monkeypatch):
    """A scene with ``reference_lengths.csv``: the fibre-length figure's panel of that muscle
    has the model's length change from the first time point (%), named in the legend; a scene
    without one gets the figure it had."""
    import dataclasses
    from muscle_mss.app import study, study_report
    from muscle_mss.app.reference_lengths import (read_reference_lengths,
                                                  write_reference_lengths)
    times = np.linspace(0.0, 1.0, 5)
    write_reference_lengths(str(tmp_path / "reference_lengths.csv"), times,
                            {"b": 300.0 * (1.0 - 0.1 * times)})
    reference = read_reference_lengths(str(tmp_path))
    assert read_reference_lengths(str(tmp_path / "none")) == {}
    fields = {f.name: None for f in dataclasses.fields(study.MotionSeries)}
    series = study.MotionSeries(**{**fields, "times": times, "muscles": ["a", "b"],
                                   "fibre_strain": np.zeros((5, 2, 3)),
                                   "path_strain": np.zeros((5, 2))})
    drawn = {}

    def save(figure, out, name, legend_axes=None):
        drawn.update(panels=figure.axes, legend=legend_axes)
        study_report._pyplot().close(figure)

    monkeypatch.setattr(study_report, "_save", save)
    for lengths in (reference, None):
        study_report.fibre_length_figure(study.Study(
            str(tmp_path), 0, 0.0, 20, [], series, "", 0.0, reference_lengths=lengths),
            str(tmp_path))
        labelled = [[line for line in ax.get_lines()
                     if line.get_label() == study_report.REFERENCE_LABEL]
                    for ax in drawn["panels"]]
        if lengths is None:
            assert labelled == [[], []] and drawn["legend"] is drawn["panels"][0]
            continue
        assert labelled[0] == [] and len(labelled[1]) == 1
        np.testing.assert_allclose(labelled[1][0].get_ydata(), -10.0 * times)
        assert drawn["legend"] is drawn["panels"][1]
