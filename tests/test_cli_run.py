"""`muscle-mss demo` / `muscle-mss run` end to end on the small demo scene (DESIGN §7)."""
import csv

import numpy as np
import pytest

from muscle_mss.app.cli import main
from muscle_mss.app.run_output import SUMMARY_COLUMNS

pytest.importorskip("pyvista")  # the CLI's pictures; ParaView's Python has no pyvista


def picture_is_not_blank(path):
    from PIL import Image
    pixels = np.asarray(Image.open(path).convert("RGB"), dtype=float)
    return pixels.std() > 10.0


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    # a tolerance no time point meets in 60 iterations: every row stops at the cap
    assert main(["demo", str(out), "--size", "small", "--iterations", "60",
                 "--tolerance", "1e-5"]) == 0
    return out


def test_demo_writes_every_promised_file(demo_run, small_scene):
    out = demo_run
    for name in ("muscles.vtm", "fibres.vtm", "bones.vtm", "motion.csv", "preview.png"):
        assert (out / "scene" / name).is_file(), name
    times = small_scene.motion.times
    for series in ("surfaces", "fibres", "particles"):
        text = (out / f"{series}.pvd").read_text()
        assert text.count("<DataSet ") == len(times)
        assert len(list((out / "series").glob(f"{series}_*.vtm"))) == len(times)
    assert len(list((out / "convergence").glob("convergence_*.csv"))) == len(times)
    for picture in ("convergence.png", "poses.png", "scene/preview.png"):
        assert picture_is_not_blank(out / picture), picture


def test_demo_summary_has_a_row_per_time_and_muscle(demo_run, small_scene):
    with open(demo_run / "summary.csv", newline="") as f:
        reader = csv.DictReader(f)
        assert tuple(reader.fieldnames) == SUMMARY_COLUMNS
        rows = list(reader)
    muscles = list(small_scene.muscles)
    assert len(rows) == len(small_scene.motion.times) * len(muscles)
    assert [r["muscle"] for r in rows[:len(muscles)]] == muscles
    for r in rows:
        values = {k: float(r[k]) for k in SUMMARY_COLUMNS if k != "muscle"}
        assert all(np.isfinite(v) for v in values.values()), r
        assert values["iterations"] == 60 and values["converged"] == 0
        assert values["rest_volume"] > 0 and values["volume"] > 0
        assert values["volume_error_pct"] == pytest.approx(
            100 * abs(values["volume"] - values["rest_volume"]) / values["rest_volume"])


def test_run_one_time_point(small_scene_dir, tmp_path, capsys):
    assert main(["run", str(small_scene_dir), str(tmp_path), "--time", "0.5",
                 "--iterations", "30", "--layout", "k-NN"]) == 0
    with open(tmp_path / "summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert {float(r["time"]) for r in rows} == {0.5}
    assert "mean over muscles" in capsys.readouterr().out


def test_run_quasi_static_method_records_its_residual(small_scene_dir, tmp_path):
    assert main(["run", str(small_scene_dir), str(tmp_path), "--time", "0.5",
                 "--iterations", "12", "--method", "quasi-static", "--tolerance", "0.01"]) == 0
    with open(tmp_path / "summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert all(1 <= int(r["iterations"]) <= 12 for r in rows)
    assert {int(r["converged"]) for r in rows} <= {0, 1}
    with open(tmp_path / "convergence" / "convergence_0010.csv", newline="") as f:
        table = list(csv.DictReader(f))
    assert len(table) == int(rows[0]["iterations"]) and float(table[0]["residual"]) > 0


def test_run_refuses_a_broken_scene_with_a_clear_error(tmp_path, capsys):
    assert main(["run", str(tmp_path), str(tmp_path / "out")]) == 2
    assert "muscles.vtm: missing" in capsys.readouterr().err


def cut_off_pixels(path, panels=3, title_rows=45, frame=3):
    """Foreground pixels on the outer ``frame`` pixels of each panel of a poses picture (the
    top rows are left out where the panel's title is written, at its left)."""
    from PIL import Image
    pixels = np.asarray(Image.open(path).convert("RGB"), dtype=float)
    background = np.array([0x30, 0x34, 0x3C], dtype=float)
    width = pixels.shape[1] // panels
    counts = []
    for column in range(panels):
        panel = pixels[:, column * width:(column + 1) * width]
        shown = np.abs(panel - background).sum(axis=2) > 40
        edge = np.zeros_like(shown)
        edge[-frame:, :] = edge[:, :frame] = edge[:, -frame:] = True
        edge[:frame, width // 2:] = True
        edge[:title_rows, :width // 2] = False
        counts.append(int((shown & edge).sum()))
    return counts


@pytest.mark.parametrize("region", ["thigh", "arm"])
def test_poses_picture_frames_a_pose_that_swings_out_of_the_rest_box(region, tmp_path):
    from muscle_mss.core.motion import farthest_pose_index
    from muscle_mss.app import motion_run
    from muscle_mss.app.demo_folder import demo_region_scene
    from muscle_mss.app.pictures import poses_picture
    from muscle_mss.filters.scene_io import write_scene

    scene = demo_region_scene(region, "small")
    index = farthest_pose_index(scene.motion)
    # the whole limb carried 300 mm sideways to the view at the most flexed pose, as a scene in
    # which the pose swings a limb far from where it rests (the rotations, and so the pose
    # pictured, are unchanged)
    scene.motion.matrices[index, :, :, 3] += 300.0 * np.array([0.78, -0.62, 0.0])
    write_scene(scene, tmp_path / "scene")
    assert farthest_pose_index(scene.motion) == index
    pipeline = motion_run.build_pipeline(str(tmp_path / "scene"), {"Iterations": 5})
    path = poses_picture(pipeline, index, tmp_path / "poses.png")
    assert picture_is_not_blank(path)
    assert cut_off_pixels(path) == [0, 0, 0]
