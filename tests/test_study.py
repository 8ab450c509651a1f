"""``muscle-mss study`` (issue 29): the paper's experiments and the fibre-length study on the
small demo scene, and the measures it is built from."""
import csv
import dataclasses
import re

import numpy as np
import pytest

from muscle_mss.filters import array_names as A


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def study_out(small_scene_dir, tmp_path_factory):
    from muscle_mss.app.cli import main
    out = tmp_path_factory.mktemp("study")
    assert main(["study", str(small_scene_dir), str(out), "--overwrite"]) == 0
    return out


def test_the_study_writes_its_report_figures_and_tables(study_out, small_scene):
    from muscle_mss.filters.spring_builder import LAYOUTS
    from muscle_mss.app.study_report import FIGURES, STUDY_FILES
    for name in STUDY_FILES:
        assert (study_out / name).stat().st_size > 0, name
    text = (study_out / "report.html").read_text()
    assert text.count("data:image/png;base64,") == len(FIGURES)   # opens on its own
    assert "Each layout solves time point 15 (t = 0.75 s), where the bones are rotated " \
           "farthest from rest, by the paper relaxation" in text and "--time" not in text
    assert "http://" not in text and "https://" not in text
    named = re.findall(r"numbers in ([\w.]+\.csv)", text)      # every caption's CSV is there
    assert len(named) == len(FIGURES) and all((study_out / n).is_file() for n in named)
    layouts = {r["layout"]: r for r in _rows(study_out / "layouts.csv")}
    assert list(layouts) == list(LAYOUTS)
    per = {k: float(r["springs_per_particle"]) for k, r in layouts.items()}
    assert per["lattice-6"] < per["Delaunay"] < per["lattice-26"]    # 6, ~13, up to 26
    assert all(float(r["memory_mb"]) > 0 and float(r["median_slope"]) < 0
               for r in layouts.values())          # every layout settles, slower and slower
    assert all(float(r["time_step_s"]) in (0.05, 0.025, 0.0125) for r in layouts.values())
    pairs = _rows(study_out / "layout_distances.csv")
    assert len(pairs) == 6 and all(0 < float(p["mean_mm"]) <= float(p["max_mm"]) for p in pairs)
    fibres = _rows(study_out / "fibre_length.csv")
    assert len(fibres) == len(small_scene.motion.times) * len(small_scene.muscles)
    assert all(float(r[A.MAX_ARC_CHORD]) >= 1.0 for r in fibres)     # arc never below chord
    assert all(float(r["min_fibre_strain"]) <= float(r[A.MEAN_FIBRE_STRAIN])
               <= float(r[A.MAX_FIBRE_STRAIN]) for r in fibres)
    split = _rows(study_out / "time_split.csv")
    assert sum(float(r["share_pct"]) for r in split) == pytest.approx(100.0)
    assert float(split[0]["seconds"]) > 0.0                             # the MSS part


def test_the_studys_tables_agree_with_a_runs_summary(study_out, small_scene_dir, tmp_path):
    """Where the study's CSVs and a run's summary.csv overlap (the default layout, the whole
    motion) they hold the same numbers. The run as ``muscle-mss run`` and the batch compute and
    write it (the CLI's pictures need pyvista, which Debian's Python lacks)."""
    from muscle_mss.app import motion_run, run_output
    out = tmp_path / "run"
    with run_output.output_folder(str(out)):
        _, rows = motion_run.run_motion(small_scene_dir, str(out), series_names=("fibres",))
        run_output.write_summary(str(out), rows)
    summary = {(r[A.TIME], r[A.MUSCLE]): r for r in _rows(out / "summary.csv")}
    fibres = _rows(study_out / "fibre_length.csv")
    volume = _rows(study_out / "volume.csv")
    assert len(summary) == len(fibres) == len(volume)
    for f, v in zip(fibres, volume):
        row = summary[(f[A.TIME], f[A.MUSCLE])]
        for column in (A.MEAN_FIBRE_STRAIN, A.MAX_FIBRE_STRAIN, A.MAX_ARC_CHORD):
            assert float(f[column]) == pytest.approx(float(row[column]), abs=1e-12), column
        assert float(v[A.VOLUME_ERROR_PCT]) == pytest.approx(float(row[A.VOLUME_ERROR_PCT]),
                                                             abs=1e-12)
    untimed = lambda rows: [{k: v for k, v in r.items() if k != A.SECONDS}  # noqa: E731
                            for r in rows]
    assert untimed(_rows(study_out / "summary.csv")) == untimed(summary.values())


def test_fibres_and_paths_keep_their_rest_length_when_the_bones_do_not_move(
        small_scene, tmp_path):
    """Every bone at rest at every time point: the origin-insertion path is the rest one, the
    fibres' strain stays 0 (within rounding) and their tortuosity is the rest one."""
    from muscle_mss.filters.scene_io import write_scene
    from muscle_mss.app.study import motion_series
    motion = small_scene.motion
    still = np.zeros((3, len(motion.bones), 3, 4))
    still[:, :, :, :3] = np.eye(3)
    scene = dataclasses.replace(small_scene, motion=dataclasses.replace(
        motion, times=motion.times[:3].copy(), matrices=still))
    write_scene(scene, tmp_path / "still")
    series = motion_series(tmp_path / "still", 20)
    assert np.abs(series.path_strain).max() < 1e-12
    assert np.ptp(series.path_length, axis=0).max() < 1e-9
    assert np.abs(series.fibre_strain).max() < 1e-12      # nothing moves a resting model
    assert (series.buckled == 0).all() and series.arc_chord.max() < 1.1
    np.testing.assert_allclose(series.arc_chord, series.rest_arc_chord[None].repeat(3, 0),
                               atol=1e-12)     # the rest tortuosity, from the rest positions
    assert np.abs(series.bend - 1.0).max() < 1e-12                   # bent as at rest
    assert max(abs(r[A.MEAN_KEPT_SHAPE_STRAIN]) for r in series.rows) < 1e-12


def test_a_zigzag_fibre_is_flagged_and_a_straight_one_is_not():
    from muscle_mss.core.cage import polyline_chords, polyline_lengths
    from muscle_mss.filters import vtk_arrays as V
    from muscle_mss.app.study import BEND_LIMIT, fibre_statistics
    t = np.linspace(0.0, 100.0, 11)
    straight = np.column_stack([t, np.zeros(11), np.zeros(11)])
    zigzag = np.column_stack([t, 8.0 * (np.arange(11) % 2), np.zeros(11) + 30.0])
    points = np.concatenate([straight, zigzag])
    offsets = np.array([0, 11, 22])
    order = np.arange(22)
    lengths = polyline_lengths(points, order, offsets)
    arc_chord = lengths / polyline_chords(points, order, offsets)
    assert arc_chord[0] == pytest.approx(1.0) and arc_chord[1] > BEND_LIMIT
    block = V.make_polydata(points, line_offsets=offsets, line_connectivity=order)
    V.set_cell_array(block, A.FIBRE_STRAIN, lengths / 100.0 - 1.0)
    V.set_cell_array(block, A.FIBRE_ARC_CHORD, arc_chord)
    V.set_cell_array(block, A.FIBRE_BEND, arc_chord)                   # both straight at rest
    mean, least, largest, worst, bent, buckled = fibre_statistics(block)
    assert buckled == 1 and worst == bent == pytest.approx(arc_chord[1])
    assert least == pytest.approx(0.0) and largest > 0.1
    # the same zigzag at rest: as bent as it was, not buckled
    V.set_cell_array(block, A.FIBRE_BEND, np.ones(2))
    assert fibre_statistics(block)[5] == 0 and fibre_statistics(block)[3] > BEND_LIMIT


def test_the_later_phase_slope_is_the_decay_rate():
    from muscle_mss.app.study import later_slope
    k = np.arange(1, 501)
    displacement = np.column_stack([10.0 ** (-0.002 * k), 10.0 ** (-0.0005 * k), 0.0 * k])
    slopes = later_slope(displacement)
    np.testing.assert_allclose(slopes[:2], [-0.002, -0.0005], rtol=1e-9)
    assert np.isnan(slopes[2])          # a muscle that stopped moving has no rate


def test_study_options_are_checked(small_scene_dir, tmp_path, capsys):
    from muscle_mss.app.cli import main
    from muscle_mss.plugin.batch import main as batch
    assert main(["study", str(small_scene_dir), str(tmp_path / "a"), "--time", "9"]) == 2
    assert "outside the motion's time range" in capsys.readouterr().err
    assert batch([str(small_scene_dir), str(tmp_path / "b"), "--time", "0.5"]) == 1
    assert "--time applies only to --study" in capsys.readouterr().err
    assert batch(["--study", str(small_scene_dir), str(tmp_path / "c"), "--method",
                  "quasi-static"]) == 1
    assert "--method do not apply to --study" in capsys.readouterr().err


def test_the_report_names_the_pose_asked_with_time(small_scene_dir, tmp_path, monkeypatch):
    """``--time 0.5``: the report said t = 0.5 s was "where the bones are rotated farthest from
    rest"; the small demo's most flexed pose is t = 0.75 s."""
    from muscle_mss.app import study, study_report
    from muscle_mss.app.cli import main
    asked = {}

    def run_study(scene_folder, resolution, index=None, progress=None, asked_time=None,
                  cache=None, jobs=1):
        asked.update(index=index, asked_time=asked_time)
        times = np.linspace(0.0, 1.0, 21)
        return study.Study(str(scene_folder), index, float(times[index]), resolution, [],
                           dataclasses.replace(_no_motion(), times=times), "", 0.0, asked_time,
                           15)
    monkeypatch.setattr(study, "run_study", run_study)
    monkeypatch.setattr(study_report, "write_report",
                        lambda result, out: asked.update(text=study_report.pose_text(result)))
    for time, text in (("0.5", "time point 10 (t = 0.5 s), the nearest to the t = 0.5 s asked "
                                "with --time (the most flexed pose, where the bones are rotated "
                                "farthest from rest, is t = 0.75 s)"),
                       ("0.76", "time point 15 (t = 0.75 s), the nearest to the t = 0.76 s "
                                "asked with --time, where the bones are rotated farthest from "
                                "rest")):
        assert main(["study", str(small_scene_dir), str(tmp_path / time), "--time", time]) == 0
        assert asked["asked_time"] == float(time) and asked["text"] == text
    assert main(["study", str(small_scene_dir), str(tmp_path / "flexed")]) == 0
    assert asked["asked_time"] is None and asked["text"] == (
        "time point 15 (t = 0.75 s), where the bones are rotated farthest from rest")


def _no_motion():
    from muscle_mss.app.study import MotionSeries
    fields = {f.name: None for f in dataclasses.fields(MotionSeries)}
    return MotionSeries(**fields)
