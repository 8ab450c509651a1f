"""What `muscle-mss run` and the batch do to their output folder, and what they print: an
earlier run is never clobbered silently, writes are checked and atomic, pictures render
off-screen without X warnings."""
import csv
import math
import os
import subprocess
import sys

import pytest

from muscle_mss.app import output_folder, run_output
from muscle_mss.app.cli import main

pytest.importorskip("pyvista")  # the CLI's pictures; ParaView's Python has no pyvista

EARLIER_RUN = {"summary.csv": "time,muscle\n9.0,earlier\n",
               "surfaces.pvd": "<VTKFile>an earlier run</VTKFile>\n",
               os.path.join("series", "surfaces_0009.vtm"): "an earlier time point\n"}


def _earlier_run(folder, *more):
    """The files of an earlier run, listed in its manifest (as a run writes them), and
    ``more`` such files."""
    for name, text in [*EARLIER_RUN.items(), *((name, "earlier\n") for name in more)]:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text(text)
        output_folder.record(str(folder), name)


def _files(folder):
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def _run(scene, out, *options):
    return main(["run", str(scene), str(out), "--time", "0.5", "--iterations", "5", *options])


def test_run_refuses_a_folder_holding_another_run(small_scene_dir, tmp_path, capsys):
    _earlier_run(tmp_path)
    before = _files(tmp_path)
    assert _run(small_scene_dir, tmp_path) == 2
    err = capsys.readouterr().err
    assert f"output folder {tmp_path} holds the results of another run (summary.csv, " \
           "surfaces.pvd, series)" in err and "--overwrite" in err
    assert "Traceback" not in err
    assert _files(tmp_path) == before


def test_a_folder_of_other_files_is_used_as_it_is(small_scene_dir, tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    assert _run(small_scene_dir, tmp_path) == 0
    assert (tmp_path / "notes.txt").read_text() == "mine"


def _pvd_entries(path):
    import re
    return re.findall(r'timestep="([^"]+)" group="" part="0" file="([^"]+)"', path.read_text())


def test_one_time_point_with_overwrite_leaves_a_consistent_folder(small_scene_dir, tmp_path):
    _earlier_run(tmp_path)
    assert _run(small_scene_dir, tmp_path, "--overwrite") == 0
    with open(tmp_path / "summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    times = {r["time"] for r in rows}
    assert len(times) == 1 and "earlier" not in {r["muscle"] for r in rows}
    for series in run_output.SERIES:
        entries = _pvd_entries(tmp_path / f"{series}.pvd")
        assert [float(t) for t, _ in entries] == [float(t) for t in times]
        assert (tmp_path / entries[0][1]).is_file()
        assert sorted(p.name for p in (tmp_path / "series").glob(f"{series}_*.vtm")) \
            == [os.path.basename(entries[0][1])]  # the earlier run's time point is gone


def test_an_unwritable_folder_is_refused_before_solving(small_scene_dir, tmp_path, capsys):
    (tmp_path / "a_file").write_text("x")
    for out, cause in ((tmp_path / "a_file", "is a file"),
                       (tmp_path / "a_file" / "out", "cannot be written: Not a directory")):
        assert _run(small_scene_dir, out) == 2
        captured = capsys.readouterr()
        assert f"output folder {out} {cause}" in captured.err
        assert "Traceback" not in captured.err and "volume" not in captured.out


def test_a_writer_failure_is_an_error_and_leaves_no_vtm(small_scene_dir, tmp_path, capsys,
                                                        monkeypatch):
    import shutil

    class LosesItsFiles(run_output.vtkXMLMultiBlockDataWriter):
        """A writer whose .vtp files vanish (a full disk, a quota) while it reports success."""

        def Write(self):
            result = super().Write()
            shutil.rmtree(os.path.splitext(self.GetFileName())[0])
            return result

    monkeypatch.setattr(run_output, "vtkXMLMultiBlockDataWriter", LosesItsFiles)
    assert _run(small_scene_dir, tmp_path) == 2
    err = capsys.readouterr().err
    assert "writing " in err and "surfaces_" in err and "_0.vtp" in err and "not written" in err
    assert not list(tmp_path.rglob("*.vtm")) and not list(tmp_path.rglob("*.pvd"))
    assert not (tmp_path / "summary.csv").exists()


def test_batch_refuses_another_run_unless_overwrite(small_scene_dir, tmp_path, capsys):
    from muscle_mss.plugin.batch import main as batch
    _earlier_run(tmp_path)
    before = _files(tmp_path)
    assert batch([str(small_scene_dir), str(tmp_path), "--iterations", "3"]) == 1
    assert "holds the results of another run" in capsys.readouterr().err
    assert _files(tmp_path) == before


def test_pictures_render_off_screen_without_x_warnings(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.run([sys.executable, "-m", "muscle_mss.app.cli", "demo-scene",
                           str(tmp_path / "scene"), "--size", "small"],
                          env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "scene" / "preview.png").stat().st_size > 10000
    assert "X server" not in proc.stderr and "WARN" not in proc.stderr, proc.stderr


def test_batch_with_overwrite_replaces_the_earlier_run(small_scene, small_scene_dir, tmp_path):
    from muscle_mss.plugin.batch import main as batch
    _earlier_run(tmp_path, os.path.join("series", "surfaces_0099.vtm"))  # a time point more
    assert batch([str(small_scene_dir), str(tmp_path), "--iterations", "3", "--overwrite"]) == 0
    with open(tmp_path / "summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(small_scene.motion.times) * len(small_scene.muscles)
    assert "earlier" not in {r["muscle"] for r in rows}
    entries = _pvd_entries(tmp_path / "surfaces.pvd")
    assert len(entries) == len(small_scene.motion.times)
    assert sorted(p.name for p in (tmp_path / "series").glob("surfaces_*.vtm")) \
        == sorted(os.path.basename(file) for _, file in entries)
    assert not list(tmp_path.glob(".summary.rank*"))


def test_summary_table_shows_the_depth_in_bone_as_written_and_before_the_push():
    from muscle_mss.app.run_report import summary_table
    row = {"muscle": "vastus", "volume_error_pct": "1.5", "max_fibre_strain": "0.1",
           "sphere_overlap_mm": "0.01", "new_in_bone_depth_mm": "4.7",
           "new_in_bone_depth_after_push_mm": "0.0", "in_other_muscle_depth_mm": "2.5",
           "cage_drift_mm": "1.25",
           "cage_drift_vertices": "0", "tissue_share_pct": "12.5", "iterations": "500",
           "seconds": "0.7", "time": "0.5"}
    table = summary_table([row])
    header, _, line = table.splitlines()[:3]
    columns = dict(zip(["muscle", "mean", "max", "strain", "follows", "kept", "arc/chord",
                        "bend", "overlap", "in bone", "in muscle", "pushed", "drift", "tissue",
                        "iters",
                        "seconds"],
                       line.split()))
    assert "new in bone mm" in header and "in muscle mm" in header and "pushed mm" in header
    assert header.index("new in bone mm") < header.index("in muscle mm") \
        < header.index("pushed mm") < header.index("tissue %")
    assert columns["in bone"] == "0.000" and columns["pushed"] == "4.700"
    assert columns["in muscle"] == "2.500"
    assert columns["tissue"] == "12.5" and columns["iters"] == "500"
    assert columns["drift"] == "1.25" and "warning" not in table
    flung = dict(row, cage_drift_mm="13.9", cage_drift_vertices="1")
    warning = summary_table([row, flung]).splitlines()[-1]
    assert warning.startswith("warning: vastus: surface vertices left their cage by more than "
                              "10 mm at 1 of 2 time points") and "13.9 mm, at t = 0.5 s" in warning
    no_bones = dict(row, new_in_bone_depth_mm="", new_in_bone_depth_after_push_mm="")
    assert summary_table([no_bones]).splitlines()[2].split()[9:12] == ["-", "2.500", "-"]
    assert columns["follows"] == columns["kept"] == columns["arc/chord"] == columns["bend"] \
        == "-"                                                          # not in these rows


def test_the_table_says_how_the_fibres_follow_their_muscles_length():
    from muscle_mss.app.run_report import summary_table
    from muscle_mss.app.study import follow_slope
    base = {"muscle": "biceps", "volume_error_pct": "1.0", "max_fibre_strain": "0.0",
            "sphere_overlap_mm": "0", "new_in_bone_depth_mm": "", "cage_drift_vertices": "0",
            "new_in_bone_depth_after_push_mm": "", "cage_drift_mm": "0.5", "time": "0",
            "tissue_share_pct": "0", "iterations": "500", "seconds": "0.5"}
    # shortens 20 % while its fibres keep their length and fold: slope 0
    folding = [dict(base, mean_end_to_end_strain=str(-0.1 * k), mean_fibre_strain="0.01",
                    max_arc_chord=str(1.1 + 0.2 * k), max_fibre_bend=str(1.0 + 0.2 * k),
                    mean_kept_shape_strain=str(-0.08 * k)) for k in range(3)]
    following = [dict(r, mean_fibre_strain=str(0.9 * float(r["mean_end_to_end_strain"])))
                 for r in folding]
    assert follow_slope(folding) == pytest.approx(0.0)
    assert follow_slope(following) == pytest.approx(0.9)
    assert math.isnan(follow_slope(folding[:1]))        # one time point: no slope
    line = summary_table(folding).splitlines()[2].split()
    assert line[4:8] == ["0.00", "0.80", "1.50", "1.40"]
    assert follow_slope(folding, "mean_kept_shape_strain") == pytest.approx(0.8)
