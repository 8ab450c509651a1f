"""Scene folders (DESIGN §4): write/read round trip, every validation rule, `muscle-mss validate`."""
import copy
import csv

import numpy as np
import pytest

from muscle_mss.core.scene import FibreSet
from muscle_mss.app.cli import main
from muscle_mss.filters.scene_io import check_scene, load_scene, read_scene, write_scene


def assert_scenes_equal(a, b):
    assert list(a.muscles) == list(b.muscles)
    assert list(a.fibres) == list(b.fibres)
    assert list(a.bones) == list(b.bones)
    for group in ("muscles", "bones"):
        for name, s in getattr(a, group).items():
            t = getattr(b, group)[name]
            np.testing.assert_array_equal(s.points, t.points)
            np.testing.assert_array_equal(s.triangles, t.triangles)
    for name, fs in a.fibres.items():
        gs = b.fibres[name]
        np.testing.assert_array_equal(fs.points, gs.points)
        np.testing.assert_array_equal(fs.offsets, gs.offsets)
        np.testing.assert_array_equal(fs.grid, gs.grid)
    np.testing.assert_array_equal(a.motion.times, b.motion.times)
    assert list(a.motion.bones) == list(b.motion.bones)
    np.testing.assert_array_equal(a.motion.matrices, b.motion.matrices)


def test_round_trip_is_identical(small_scene, small_scene_dir):
    read_back = load_scene(small_scene_dir)
    assert_scenes_equal(small_scene, read_back)


def test_read_scene_gives_vtk_objects(small_scene, small_scene_dir):
    muscles, fibres, bones, motion = read_scene(small_scene_dir)
    assert muscles.GetNumberOfBlocks() == len(small_scene.muscles)
    assert fibres.GetNumberOfBlocks() == len(small_scene.fibres)
    assert bones.GetNumberOfBlocks() == len(small_scene.bones)
    assert motion.GetNumberOfRows() == len(small_scene.motion.times) * len(small_scene.bones)


# ---- one deliberately broken scene per rule ---------------------------------------------------

def _break_surface(scene, group, change):
    name = next(iter(getattr(scene, group)))
    surface = getattr(scene, group)[name]
    change(surface)
    return name


def _rewrite_motion(folder, change):
    path = folder / "motion.csv"
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    rows = [rows[0]] + change(rows[1:])
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows(rows)


def _open_surface(scene, folder):
    _break_surface(scene, "muscles", lambda s: setattr(s, "triangles", s.triangles[1:]))


def _inward_surface(scene, folder):
    _break_surface(scene, "muscles", lambda s: setattr(s, "triangles", s.triangles[:, ::-1]))


def _fibre_names(scene, folder):
    first = next(iter(scene.fibres))
    scene.fibres = {("renamed" if k == first else k): v for k, v in scene.fibres.items()}


def _fibre_one_point(scene, folder):
    name = next(iter(scene.fibres))
    fs = scene.fibres[name]
    lines = [fs.fibre(f) for f in range(fs.count)]
    lines[3] = lines[3][:1]
    scene.fibres[name] = FibreSet.from_polylines(lines, fs.grid)


def _nan_coordinate(scene, folder):
    def change(s):
        s.points = s.points.copy()
        s.points[5, 1] = np.nan
    _break_surface(scene, "bones", change)


def _missing_motion_row(scene, folder):
    _rewrite_motion(folder, lambda rows: [r for i, r in enumerate(rows) if i != 7])


def _non_rigid(scene, folder):
    def change(rows):
        rows[4][2] = repr(float(rows[4][2]) * 1.2)  # m00 scaled
        return rows
    _rewrite_motion(folder, change)


def _times_not_ascending(scene, folder):
    bones = len(scene.bones)
    def change(rows):
        a, b = rows[bones:2 * bones], rows[2 * bones:3 * bones]
        return rows[:bones] + b + a + rows[3 * bones:]
    _rewrite_motion(folder, change)


BROKEN = [
    (_open_surface, "muscles.vtm block", "is open"),
    (_inward_surface, "muscles.vtm block", "oriented inward"),
    (_fibre_names, "fibres.vtm", "do not match"),
    (_fibre_one_point, "fibres.vtm block", "fibre 3 has 1 point"),
    (_nan_coordinate, "bones.vtm block", "point 5 has a NaN"),
    (_missing_motion_row, "motion.csv", "no row for bone"),
    (_non_rigid, "motion.csv row 5", "is not rigid"),
    (_times_not_ascending, "motion.csv row", "times must be ascending"),
]


@pytest.mark.parametrize("breaker, where, rule", BROKEN, ids=[b[0].__name__[1:] for b in BROKEN])
def test_each_rule_has_exactly_its_error(small_scene, tmp_path, breaker, where, rule, capsys):
    scene = copy.deepcopy(small_scene)
    folder = tmp_path / "scene"
    if breaker.__name__ in ("_missing_motion_row", "_non_rigid", "_times_not_ascending"):
        write_scene(scene, folder)
        breaker(scene, folder)
    else:
        breaker(scene, folder)
        write_scene(scene, folder)
    _, problems = check_scene(folder)
    assert len(problems) == 1, problems
    assert problems[0].startswith(where) and rule in problems[0], problems[0]

    assert main(["validate", str(folder)]) == 1
    out = capsys.readouterr().out
    assert rule in out and "1 problem" in out


def test_validate_ok_prints_counts(small_scene, small_scene_dir, capsys):
    assert main(["validate", str(small_scene_dir)]) == 0
    out = capsys.readouterr().out.strip().splitlines()[0]
    fibres = sum(fs.count for fs in small_scene.fibres.values())
    assert out == (f"ok: {len(small_scene.muscles)} muscles, {len(small_scene.bones)} bones, "
                   f"{fibres} fibres, {len(small_scene.motion.times)} time points")


def test_missing_file_is_named(tmp_path, small_scene_dir, capsys):
    folder = tmp_path / "partial"
    folder.mkdir()
    (folder / "motion.csv").write_text((small_scene_dir / "motion.csv").read_text())
    assert main(["validate", str(folder)]) == 1
    assert "muscles.vtm: missing" in capsys.readouterr().out
