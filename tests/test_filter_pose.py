"""The Rigid Pose Transform filter (filters/rigid_pose_transform.py) as a plain VTK algorithm.

Contracts of DESIGN §5: time steps from the motion table, bones moved rigidly, every model array
kept and ``bone_weights`` added, inputs untouched, bad motion rows refused naming the row.
"""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from vtkmodules.vtkCommonCore import vtkOutputWindow, vtkStringOutputWindow
from vtkmodules.vtkCommonDataModel import vtkDataObject, vtkUnstructuredGrid
from vtkmodules.vtkIOInfovis import vtkDelimitedTextReader
from vtkmodules.vtkIOXML import vtkXMLMultiBlockDataReader, vtkXMLMultiBlockDataWriter

import muscle_mss.filters.rigid_pose_transform as module
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.pose import pose_at
from muscle_mss.core.scene import MOTION_COLUMNS
from muscle_mss.filters import FibreResampler, RigidPoseTransform, SpringBuilder
from muscle_mss.filters import array_names as A
from muscle_mss.filters import vtk_arrays as V
from muscle_mss.filters.base import SDDP
from muscle_mss.filters.scene_io import scene_readers

CUBE_CORNERS = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                         [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=np.float64)
CUBE_TRIANGLES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                           [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
BONES = ("femur", "tibia")
TIMES = (0.0, 0.5, 1.0)
KNEE_ANGLES = (0.0, 45.0, 90.0)   # tibia about the x axis through the knee at the origin, degrees


def box(half, centre):
    return CUBE_CORNERS * np.asarray(half) + np.asarray(centre)


def make_bones():
    """A femur above and a tibia below a knee at the origin (mm)."""
    return V.make_multiblock([
        ("femur", V.make_polydata(box((8, 8, 40), (0, 0, 45)), CUBE_TRIANGLES)),
        ("tibia", V.make_polydata(box((7, 7, 40), (0, 0, -45)), CUBE_TRIANGLES)),
    ])


def make_model():
    """One muscle along the leg in front of the bones: 3 fibres of 9 particles with springs."""
    z = np.linspace(-60.0, 60.0, 9)
    points = np.concatenate([np.stack([np.full(9, x), np.full(9, 15.0), z], axis=1)
                             for x in (-4.0, 0.0, 4.0)])
    segments = np.array([[f * 9 + k, f * 9 + k + 1] for f in range(3) for k in range(8)])
    block = V.make_polydata(points, segments=segments)
    V.set_point_array(block, A.REST_POSITION, points)
    V.set_point_array(block, A.FIBRE_ID, np.repeat(np.arange(3, dtype=np.int32), 9))
    V.set_point_array(block, A.FIBRE_INDEX, np.tile(np.arange(9, dtype=np.int32), 3))
    V.set_point_array(block, A.FIXED, np.tile((np.arange(9) % 8 == 0).astype(np.uint8), 3))
    V.set_point_array(block, A.MASS, np.ones(27))
    V.set_cell_array(block, A.REST_LENGTH, np.full(24, 15.0))
    V.set_field(block, A.MUSCLE_NAME, "rectus")
    return V.make_multiblock([("rectus", block)])


def make_surfaces():
    return V.make_multiblock([("rectus", V.make_polydata(box((6, 3, 62), (0, 15, 0)),
                                                         CUBE_TRIANGLES))])


def knee(angle_deg):
    m = np.zeros((3, 4))
    m[:, :3] = Rotation.from_euler("x", angle_deg, degrees=True).as_matrix()
    return m


def motion_rows(times=TIMES, angles=KNEE_ANGLES):
    rows = []
    for t, angle in zip(times, angles):
        rows.append((t, "femur", knee(0.0)))
        rows.append((t, "tibia", knee(angle)))
    return rows


def write_csv(path, rows, header=",".join(MOTION_COLUMNS)):
    lines = [header] + [f"{t!r},{bone}," + ",".join(repr(float(v)) for v in np.ravel(m))
                        for t, bone, m in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def csv_reader(path):
    reader = vtkDelimitedTextReader()
    reader.SetFileName(str(path))
    reader.SetHaveHeaders(True)
    reader.SetDetectNumericColumns(True)
    return reader


def table(rows):
    return V.make_table({
        "time": np.array([t for t, _, _ in rows], dtype=np.float64),
        "bone": [b for _, b, _ in rows],
        **{name: np.array([np.ravel(m)[k] for _, _, m in rows])
           for k, name in enumerate(MOTION_COLUMNS[2:])}})


def pose_filter(motion, surfaces=True, **properties):
    f = RigidPoseTransform()
    f.SetInputDataObject(0, make_model())
    f.SetInputDataObject(1, make_bones())
    if hasattr(motion, "GetOutputPort"):
        f.SetInputConnection(2, motion.GetOutputPort())
    else:
        f.SetInputDataObject(2, motion)
    if surfaces:
        f.SetInputDataObject(3, make_surfaces())
    for name, value in properties.items():
        getattr(f, "Set" + name)(value)
    return f


def block_points(multiblock, name):
    return dict((n, V.points_of(b)) for n, b in V.blocks(multiblock))[name]


@pytest.fixture
def messages():
    """VTK's messages (warnings, errors) of the test as text instead of on the terminal."""
    previous = vtkOutputWindow.GetInstance()
    window = vtkStringOutputWindow()
    vtkOutputWindow.SetInstance(window)
    yield window
    vtkOutputWindow.SetInstance(previous)


def test_time_steps_come_from_the_csv_and_the_time_moves_the_bones(tmp_path):
    reader = csv_reader(write_csv(tmp_path / "motion.csv", motion_rows()))
    f = pose_filter(reader)
    f.UpdateInformation()
    for port in range(3):
        info = f.GetOutputInformation(port)
        assert list(info.Get(SDDP.TIME_STEPS())) == list(TIMES)
        assert list(info.Get(SDDP.TIME_RANGE())) == [TIMES[0], TIMES[-1]]
    rest_tibia = block_points(make_bones(), "tibia")
    for t, angle in zip(TIMES, KNEE_ANGLES):
        f.UpdateTimeStep(t)
        bones = f.GetOutputDataObject(1)
        expected = rest_tibia @ knee(angle)[:, :3].T
        np.testing.assert_allclose(block_points(bones, "tibia"), expected, atol=1e-12)
        assert np.array_equal(block_points(bones, "femur"), block_points(make_bones(), "femur"))
        for port in range(3):
            assert f.GetOutputDataObject(port).GetInformation().Get(
                vtkDataObject.DATA_TIME_STEP()) == t
    f.UpdateTimeStep(0.25)
    np.testing.assert_allclose(block_points(f.GetOutputDataObject(1), "tibia"),
                               rest_tibia @ knee(22.5)[:, :3].T, atol=1e-12)


def test_posed_model_keeps_every_array_and_adds_the_weights():
    f = pose_filter(table(motion_rows()), FallOff=5.0)
    f.UpdateTimeStep(1.0)
    (name, posed), = V.blocks(f.GetOutputDataObject(0))
    (_, rest), = V.blocks(make_model())
    assert name == "rectus"
    for array in (A.FIBRE_ID, A.FIBRE_INDEX, A.FIXED, A.MASS):
        assert np.array_equal(V.point_array(posed, array), V.point_array(rest, array))
    assert np.array_equal(V.point_array(posed, A.REST_POSITION), V.points_of(rest))
    assert np.array_equal(V.cell_array(posed, A.REST_LENGTH), V.cell_array(rest, A.REST_LENGTH))
    assert np.array_equal(V.lines_of(posed)[1], V.lines_of(rest)[1])
    assert V.field(posed, A.MUSCLE_NAME) == "rectus"
    assert V.field(posed, A.BONE_NAMES) == list(BONES)
    weights = V.point_array(posed, A.BONE_WEIGHTS)
    assert weights.dtype == np.float64 and weights.shape == (27, 2)
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-12)
    # Both bones are boxes the muscle lies outside of: distances and weights by hand (FallOff 5).
    d = np.stack([np.linalg.norm(np.maximum(np.abs(V.points_of(rest) - centre) - half, 0), axis=1)
                  for half, centre in (((8, 8, 40), (0, 0, 45)), ((7, 7, 40), (0, 0, -45)))], 1)
    closeness = np.exp(-d / 5.0)
    expected = closeness / closeness.sum(axis=1, keepdims=True)
    z = V.points_of(rest)[:, 2]
    # The fixed ends follow one bone each: the model names none, so the nearest, femur on top.
    fixed = V.point_array(rest, A.FIXED) == 1
    expected[fixed] = np.eye(2)[np.where(z[fixed] > 0.0, 0, 1)]
    np.testing.assert_allclose(weights, expected, atol=1e-12)
    assert (V.field(posed, A.ORIGIN_BONE), V.field(posed, A.INSERTION_BONE)) == ("tibia", "femur")
    # ... rigidly: the top ones stay, the bottom ones turn with the tibia.
    posed_points = V.points_of(posed)
    top, bottom = z == 60.0, z == -60.0
    np.testing.assert_allclose(posed_points[top], V.points_of(rest)[top], atol=1e-9)
    moved = V.points_of(rest)[bottom] @ knee(90.0)[:, :3].T
    np.testing.assert_allclose(posed_points[bottom], moved, atol=1e-9)
    (_, surface), = V.blocks(f.GetOutputDataObject(2))
    assert V.points_of(surface).shape == (8, 3)
    assert V.point_array(surface, A.BONE_WEIGHTS).shape == (8, 2)


def test_identity_motion_leaves_every_point_exactly_where_it_was():
    rows = [(t, b, knee(0.0)) for t in TIMES for b in BONES]
    for blending in ("linear", "dual quaternion"):
        f = pose_filter(table(rows), Blending=blending)
        f.UpdateTimeStep(0.3)
        for port, source in ((0, make_model()), (1, make_bones()), (2, make_surfaces())):
            for (name, out), (_, rest) in zip(V.blocks(f.GetOutputDataObject(port)),
                                              V.blocks(source)):
                assert np.array_equal(V.points_of(out), V.points_of(rest)), (port, name)


def test_the_same_transform_on_every_bone_moves_the_muscle_rigidly():
    m = np.zeros((3, 4))
    m[:, :3] = Rotation.from_rotvec([0.3, -1.1, 0.8]).as_matrix()
    m[:, 3] = [12.0, -40.0, 7.5]
    rows = [(0.0, b, knee(0.0)) for b in BONES] + [(1.0, b, m) for b in BONES]
    f = pose_filter(table(rows))
    f.UpdateTimeStep(1.0)
    rest = V.points_of(V.blocks(make_model())[0][1])
    posed = V.points_of(V.blocks(f.GetOutputDataObject(0))[0][1])
    distances = [np.linalg.norm(p[:, None] - p[None], axis=2) for p in (rest, posed)]
    assert np.abs(distances[1] - distances[0]).max() < 1e-9
    np.testing.assert_allclose(posed, rest @ m[:, :3].T + m[:, 3], atol=1e-9)


def test_linear_and_dual_quaternion_blending_differ_at_the_bent_knee():
    results = {}
    for blending in ("linear", "dual quaternion"):
        f = pose_filter(table(motion_rows()), Blending=blending, FallOff=60.0)
        f.UpdateTimeStep(1.0)
        results[blending] = V.points_of(V.blocks(f.GetOutputDataObject(0))[0][1])
    knee_particles = np.abs(V.points_of(V.blocks(make_model())[0][1])[:, 2]) < 1.0
    lin, dq = (np.linalg.norm(results[b][knee_particles], axis=1)
               for b in ("linear", "dual quaternion"))
    rest = np.linalg.norm(V.points_of(V.blocks(make_model())[0][1])[knee_particles], axis=1)
    np.testing.assert_allclose(dq, rest, atol=1e-9)   # a blend of rotations about the knee
    assert (lin < rest - 1.0).all()                    # linear blending pulls them in


def test_outside_the_range_the_pose_is_clamped_with_a_warning(messages):
    f = pose_filter(table(motion_rows()))
    f.UpdateTimeStep(4.0)
    tibia = block_points(f.GetOutputDataObject(1), "tibia")
    np.testing.assert_allclose(tibia, block_points(make_bones(), "tibia") @ knee(90)[:, :3].T,
                               atol=1e-12)
    text = messages.GetOutput()
    assert "time 4 is outside the motion's time range [0, 1]" in text
    assert "ERROR" not in text.upper()
    f.UpdateTimeStep(-1.0)
    assert np.array_equal(block_points(f.GetOutputDataObject(1), "tibia"),
                          block_points(make_bones(), "tibia"))


def test_weights_are_computed_once_per_rest_input(monkeypatch):
    calls = []
    real = module.bone_weights

    def counting(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(module, "bone_weights", counting)
    f = pose_filter(table(motion_rows()))
    for t in (0.0, 0.25, 0.5, 1.0, 0.7):
        f.UpdateTimeStep(t)
    assert len(calls) == 1
    f.SetBlending("linear")
    f.UpdateTimeStep(0.1)
    assert len(calls) == 1
    f.SetFallOff(5.0)
    f.UpdateTimeStep(0.1)
    assert len(calls) == 2
    f.SetInputDataObject(1, make_bones())
    f.UpdateTimeStep(0.1)
    assert len(calls) == 3


def test_weights_survive_time_changes_behind_a_file_reader(monkeypatch, tmp_path):
    calls = []
    real = module.bone_weights
    monkeypatch.setattr(module, "bone_weights", lambda *a, **k: calls.append(1) or real(*a, **k))
    writer = vtkXMLMultiBlockDataWriter()
    writer.SetFileName(str(tmp_path / "bones.vtm"))
    writer.SetInputDataObject(make_bones())
    writer.Write()
    bones = vtkXMLMultiBlockDataReader()
    bones.SetFileName(str(tmp_path / "bones.vtm"))
    motion = csv_reader(write_csv(tmp_path / "motion.csv", motion_rows()))
    f = pose_filter(motion)
    f.SetInputConnection(1, bones.GetOutputPort())
    for t in (0.0, 0.5, 1.0, 0.25):
        f.UpdateTimeStep(t)
    assert len(calls) == 1
    np.testing.assert_allclose(block_points(f.GetOutputDataObject(1), "tibia"),
                               block_points(make_bones(), "tibia") @ knee(22.5)[:, :3].T,
                               atol=1e-9)


def test_inputs_are_not_modified():
    model, bones, surfaces = make_model(), make_bones(), make_surfaces()
    motion = table(motion_rows())

    def snapshot():
        out = []
        for mb in (model, bones, surfaces):
            for name, block in V.blocks(mb):
                out.append((name, V.points_of(block), sorted(V.point_arrays(block)),
                            block.GetFieldData().GetNumberOfArrays()))
        return out

    before = snapshot()
    f = RigidPoseTransform()
    for port, data in enumerate((model, bones, motion, surfaces)):
        f.SetInputDataObject(port, data)
    f.UpdateTimeStep(1.0)
    after = snapshot()
    for (n0, p0, a0, f0), (n1, p1, a1, f1) in zip(before, after):
        assert n0 == n1 and np.array_equal(p0, p1) and a0 == a1 and f0 == f1
    assert A.BONE_WEIGHTS not in V.point_arrays(V.blocks(model)[0][1])
    assert motion.GetNumberOfRows() == 6


def test_without_surfaces_the_third_output_is_empty():
    f = pose_filter(table(motion_rows()), surfaces=False)
    f.UpdateTimeStep(0.5)
    assert f.GetOutputDataObject(2).GetNumberOfBlocks() == 0
    assert len(V.blocks(f.GetOutputDataObject(0))) == 1


def bad_rows(kind):
    rows = motion_rows()
    if kind == "non-rigid":
        rows[3] = (rows[3][0], rows[3][1], knee(45.0) * [[1.2], [1.0], [1.0]])
    elif kind == "nan":
        m = knee(45.0)
        m[1, 3] = np.nan
        rows[3] = (rows[3][0], rows[3][1], m)
    elif kind == "unknown":
        rows[4] = (rows[4][0], "fibula", rows[4][2])
    elif kind == "no rows":
        rows = [r for r in rows if r[1] != "tibia"]
    return rows


@pytest.mark.parametrize("kind, match", [
    ("non-rigid", r"motion.csv row 4 \(bone 'tibia', time 0.5\): the transform is not rigid"),
    ("nan", r"motion.csv row 4 \(bone 'tibia'\): m13 is not a finite number"),
    ("unknown", r"motion.csv row 5: bone 'fibula' is not a bone of the scene"),
    ("no rows", r"motion.csv: bone 'tibia' has no rows"),
])
def test_bad_motion_is_refused_naming_the_row(kind, match, tmp_path, messages):
    for motion in (table(bad_rows(kind)),
                   csv_reader(write_csv(tmp_path / f"{kind}.csv", bad_rows(kind)))):
        f = pose_filter(motion)
        with pytest.raises(MuscleMSSError, match=match):
            f.Update()
        assert f.GetOutputDataObject(0).GetNumberOfBlocks() == 0
    assert "Rigid Pose Transform: motion.csv" in messages.GetOutput()


def test_bad_inputs_are_refused_naming_the_block(messages):
    f = pose_filter(table(motion_rows()))
    model = make_model()
    V.blocks(model)[0][1].GetPointData().RemoveArray(A.REST_POSITION)
    f.SetInputDataObject(0, model)
    with pytest.raises(MuscleMSSError, match="Model block 'rectus': array 'rest_position'"):
        f.Update()
    f = pose_filter(table(motion_rows()))
    flat = V.make_multiblock([("femur", V.make_polydata(box((8, 8, 40), (0, 0, 45)))),
                              ("tibia", V.blocks(make_bones())[1][1])])
    f.SetInputDataObject(1, flat)
    with pytest.raises(MuscleMSSError, match="bones.vtm block 'femur': has no triangles"):
        f.Update()
    f = pose_filter(table(motion_rows()))
    f.SetInputDataObject(3, V.make_multiblock([("rectus", vtkUnstructuredGrid())]))
    with pytest.raises(MuscleMSSError, match="Surfaces block 'rectus': is a vtkUnstructuredGrid"):
        f.Update()
    f = pose_filter(table(motion_rows()), BonesPerPoint=0)
    with pytest.raises(MuscleMSSError, match="BonesPerPoint is 0"):
        f.Update()
    f = pose_filter(V.make_table({"time": np.zeros(1), "bone": ["femur"]}))
    with pytest.raises(MuscleMSSError, match="m00, m01.* missing"):
        f.Update()


def test_text_columns_are_parsed_and_bad_text_is_refused(messages):
    rows = motion_rows()
    columns = {"time": [repr(t) for t, _, _ in rows], "bone": [b for _, b, _ in rows]}
    for k, name in enumerate(MOTION_COLUMNS[2:]):
        columns[name] = [repr(float(np.ravel(m)[k])) for _, _, m in rows]
    f = pose_filter(V.make_table(columns))
    f.UpdateInformation()
    assert list(f.GetOutputInformation(0).Get(SDDP.TIME_STEPS())) == list(TIMES)
    f.UpdateTimeStep(1.0)
    np.testing.assert_allclose(block_points(f.GetOutputDataObject(1), "tibia"),
                               block_points(make_bones(), "tibia") @ knee(90)[:, :3].T, atol=1e-12)
    columns["m12"][2] = "abc"
    f = pose_filter(V.make_table(columns))
    with pytest.raises(MuscleMSSError, match="motion.csv row 3, column m12: 'abc' is not a number"):
        f.Update()


def test_default_time_is_the_first_row_and_properties_have_their_defaults():
    f = pose_filter(table(motion_rows(angles=(30.0, 45.0, 90.0))))
    assert (f.GetBlending(), f.GetBonesPerPoint(), f.GetFallOff()) == (1, 2, 20.0)
    f.Update()
    np.testing.assert_allclose(block_points(f.GetOutputDataObject(1), "tibia"),
                               block_points(make_bones(), "tibia") @ knee(30)[:, :3].T, atol=1e-12)
    assert math.isfinite(f.GetOutputDataObject(0).GetInformation().Get(
        vtkDataObject.DATA_TIME_STEP()))


def test_small_demo_scene_through_the_real_upstream_filters(small_scene, small_scene_dir):
    muscles, fibres, bones, motion = scene_readers(str(small_scene_dir))
    resampler = FibreResampler()
    resampler.SetInputConnection(0, fibres.GetOutputPort())
    springs = SpringBuilder()
    springs.SetInputConnection(0, resampler.GetOutputPort())
    springs.SetInputConnection(1, muscles.GetOutputPort())
    f = RigidPoseTransform()
    for port, source in enumerate((springs, bones, motion, muscles)):
        f.SetInputConnection(port, source.GetOutputPort())
    f.UpdateInformation()
    np.testing.assert_allclose(f.GetOutputInformation(0).Get(SDDP.TIME_STEPS()),
                               small_scene.motion.times, rtol=0, atol=1e-12)
    t = 0.5 * (small_scene.motion.times[3] + small_scene.motion.times[4])
    f.UpdateTimeStep(t)
    matrices, _ = pose_at(small_scene.motion, t)
    for b, (name, posed) in enumerate(V.blocks(f.GetOutputDataObject(1))):
        rest = small_scene.bones[name].points
        np.testing.assert_allclose(V.points_of(posed), rest @ matrices[b, :, :3].T
                                   + matrices[b, :, 3], atol=1e-9)
    model = V.blocks(f.GetOutputDataObject(0))
    assert [n for n, _ in model] == list(small_scene.muscles)
    for name, block in model:
        weights = V.point_array(block, A.BONE_WEIGHTS)
        assert weights.shape == (block.GetNumberOfPoints(), len(small_scene.bones))
        np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-12)
        assert np.isfinite(V.points_of(block)).all()
        assert not np.array_equal(V.points_of(block), V.point_array(block, A.REST_POSITION))


def test_an_empty_cell_behind_a_plain_csv_reader_is_named_not_read_as_zero(tmp_path, messages):
    """ParaView's CSV reader (a delimited-text reader at its defaults, as a user builds the
    pipeline by hand) reads an empty cell as 0: the filter checks the reader's file itself."""
    path = write_csv(tmp_path / "motion.csv", motion_rows())
    lines = path.read_text().splitlines()
    cells = lines[3].split(",")
    cells[5] = ""                                   # m03: the femur's x translation at t = 0.5
    lines[3] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    before = path.read_text()
    f = pose_filter(csv_reader(path))
    with pytest.raises(MuscleMSSError, match=r"row 3 \(line 4\), column m03: the cell is empty"):
        f.Update()
    assert path.read_text() == before
