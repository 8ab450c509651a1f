"""Whole motions in worker processes (muscle_mss.app.motion_jobs, ``--jobs``): the files equal
one process's, the frame cache is shared, a failure surfaces as the serial run's (the first
failing time point, its message and exit code, no traceback), Ctrl-C and errors leave no
process behind."""
import csv
import functools
import os
import re
import signal
import subprocess
import sys
import time

import pytest

import bad_input_cases as B
from muscle_mss.core.errors import MuscleMSSError

SETTINGS = {"ParticlesPerFibre": 8, "Iterations": 20}
OPTIONS = ["--resolution", "8", "--iterations", "20", "--cache", "off"]


def files(root):
    return sorted(os.path.relpath(os.path.join(d, f), root) for d, _, names in os.walk(root)
                  for f in names if not f.startswith("."))


def assert_same_outputs(a, b):
    """Every file bitwise the same but the CSVs' ``seconds`` columns (wall clock)."""
    assert files(a) == files(b)
    for relative in files(a):
        if relative.endswith(".csv"):
            rows = [list(csv.DictReader(open(os.path.join(r, relative)))) for r in (a, b)]
            assert [{k: v for k, v in r.items() if k != "seconds"} for r in rows[0]] == \
                [{k: v for k, v in r.items() if k != "seconds"} for r in rows[1]], relative
        else:
            with open(os.path.join(a, relative), "rb") as fa, \
                    open(os.path.join(b, relative), "rb") as fb:
                assert fa.read() == fb.read(), relative


def test_two_workers_write_the_files_of_one_process_and_fill_the_shared_cache(
        small_scene_dir, tmp_path):
    from muscle_mss.app import motion_run
    cache = str(tmp_path / "cache")
    steps = []
    _, serial = motion_run.run_motion(str(small_scene_dir), str(tmp_path / "one"), SETTINGS)
    pipeline, parallel = motion_run.run_motion(
        str(small_scene_dir), str(tmp_path / "two"), SETTINGS, cache=cache, jobs=2,
        on_step=lambda result, done, total: steps.append((result.index, done, total)))
    assert_same_outputs(tmp_path / "one", tmp_path / "two")
    assert len(files(tmp_path / "one" / "series")) > 21 * 3
    strip = lambda rows: [{k: v for k, v in r.items() if k != "seconds"} for r in rows]  # noqa
    assert strip(parallel) == strip(serial)
    assert sorted(i for i, _, _ in steps) == list(range(21))
    assert [d for _, d, _ in steps] == list(range(1, 22)) and {t for _, _, t in steps} == {21}
    assert (pipeline.frames.loaded, pipeline.frames.solved) == (0, 21)
    # stored: each solved frame and its deformed surfaces
    assert len([n for n in os.listdir(cache) if not n.startswith(".")]) == 2 * 21
    assert not [n for n in os.listdir(tmp_path / "two" / "series") if n.startswith(".")]
    # another process (this one) loads every frame the workers solved, to the same files
    again, _ = motion_run.run_motion(str(small_scene_dir), str(tmp_path / "three"), SETTINGS,
                                     cache=cache)
    assert (again.frames.loaded, again.frames.solved) == (21, 0)
    assert_same_outputs(tmp_path / "one", tmp_path / "three")


def test_run_jobs_2_equals_jobs_1(small_scene_dir, tmp_path, capsys):
    pytest.importorskip("pyvista")          # the run's pictures
    from muscle_mss.app.cli import main
    outputs = []
    for jobs in ("1", "2"):
        out = tmp_path / f"jobs{jobs}"
        assert main(["run", str(small_scene_dir), str(out), *OPTIONS, "--jobs", jobs]) == 0
        text = capsys.readouterr().out
        outputs.append(re.sub(r"\d+\.\d+\s*\n", "\n", text.split("-" * 20)[1]))   # s/time
    assert_same_outputs(tmp_path / "jobs1", tmp_path / "jobs2")
    assert outputs[0] == outputs[1]


def test_the_studys_motion_series_in_two_workers_is_one_processs(small_scene_dir):
    import numpy as np
    from muscle_mss.app.study import motion_series
    one, two = (motion_series(small_scene_dir, 8, jobs=jobs) for jobs in (1, 2))
    for field in ("times", "fibre_strain", "path_length", "path_strain", "arc_chord",
                  "rest_arc_chord", "bend", "buckled", "volume_error"):
        np.testing.assert_array_equal(getattr(one, field), getattr(two, field), err_msg=field)
    assert one.muscles == two.muscles and one.phases.shape == two.phases.shape
    strip = lambda rows: [{k: v for k, v in r.items() if k != "seconds"} for r in rows]  # noqa
    assert strip(one.rows) == strip(two.rows)


def test_jobs_are_refused_with_one_time_point_and_must_be_a_count(small_scene_dir, tmp_path,
                                                                   capsys):
    from muscle_mss.app.cli import main
    assert main(["run", str(small_scene_dir), str(tmp_path / "o"), "--time", "0.5",
                 "--jobs", "2"]) == 2
    assert "error: --jobs 2 applies to a whole motion; --time solves one time point" \
        in capsys.readouterr().err
    assert main(["run", str(small_scene_dir), str(tmp_path / "o"), "--jobs", "0"]) == 2
    assert "error: --jobs 0: give the number of processes" in capsys.readouterr().err


@pytest.fixture(scope="module")
def meeting_scene(small_scene, tmp_path_factory):
    """The small scene whose rectus femoris' ends meet at time point 10 (0.5 s): a whole
    motion solves 0-9, then fails."""
    import copy
    from muscle_mss.filters.scene_io import write_scene
    scene = copy.deepcopy(small_scene)
    B.insertion_onto_origin()(scene)
    folder = tmp_path_factory.mktemp("meeting")
    write_scene(scene, folder)
    return folder


def run_in_own_group(args, **kwargs):
    """``muscle-mss ARGS`` in a new session (its own process group, as a terminal's job)."""
    return subprocess.Popen([sys.executable, "-m", "muscle_mss.app.cli", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, **kwargs)


def assert_group_ends(group, seconds=60.0):
    """Every process of the process group ``group`` ends (the workers, Python's resource
    tracker) within ``seconds`` of the run's end: none is left behind."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            os.killpg(group, 0)
        except ProcessLookupError:
            return
        time.sleep(0.2)
    left = subprocess.run(["ps", "-o", "pid,args", "-g", str(group)], capture_output=True,
                          text=True).stdout
    os.killpg(group, signal.SIGKILL)
    pytest.fail(f"processes left behind:\n{left}")


def test_a_failing_time_point_stops_the_workers_with_the_serial_message(meeting_scene,
                                                                         tmp_path):
    ends = {}
    for jobs in ("1", "2"):
        out = tmp_path / f"jobs{jobs}"
        run = run_in_own_group(["run", str(meeting_scene), str(out), *OPTIONS, "--jobs", jobs])
        _, err = run.communicate(timeout=600)
        assert_group_ends(run.pid)
        assert run.returncode == 2, err
        assert "Traceback" not in err
        ends[jobs] = err[err.rindex("error: "):].strip()       # after the progress bar
        assert re.match("error: " + B.MEET, ends[jobs]), ends[jobs]
        # the time points before the failing one are written, as one process writes them
        assert sorted(os.listdir(out / "convergence")) == [
            f"convergence_{k:04d}.csv" for k in range(10)]
    assert ends["1"] == ends["2"]
    assert files(tmp_path / "jobs1") == files(tmp_path / "jobs2")


def test_ctrl_c_stops_every_worker(small_scene_dir, tmp_path):
    out = tmp_path / "out"
    run = run_in_own_group(["run", str(small_scene_dir), str(out), "--resolution", "8",
                            "--cache", "off", "--jobs", "2"])
    first = out / "convergence" / "convergence_0000.csv"
    while not first.exists() and run.poll() is None:
        time.sleep(0.1)
    assert run.poll() is None, run.communicate()[1]
    os.killpg(run.pid, signal.SIGINT)           # what Ctrl-C in a terminal sends
    _, err = run.communicate(timeout=600)
    assert_group_ends(run.pid)
    assert run.returncode == 130, err
    assert "interrupted: " in err and "Traceback" not in err
    assert not [n for n in os.listdir(out / "series") if n.startswith(".")]


# ---- the hand-out, on a trivial work ---------------------------------------------------------

def fail_at(failing, pipeline, index):
    """A worker's work that fails at the time points ``failing``, the later ones first."""
    if index in failing:
        time.sleep(0.5 * (max(failing) - index))
        raise MuscleMSSError(f"time point {index} failed")
    return index


def end_at(index_to_end, pipeline, index):
    """A worker's work whose process ends without a word at ``index_to_end``."""
    if index == index_to_end:
        os._exit(3)
    return index


def test_the_first_failure_in_time_order_is_raised_after_the_time_points_before_it(
        small_scene_dir):
    from muscle_mss.app.motion_jobs import solve_in_workers
    taken, dropped = [], []
    with pytest.raises(MuscleMSSError, match=r"^time point 5 failed$"):
        solve_in_workers((str(small_scene_dir), SETTINGS, None), range(21),
                         functools.partial(fail_at, {5, 6}), 2,
                         on_ready=lambda index, value: taken.append(index),
                         discard=dropped.append)
    assert taken == [0, 1, 2, 3, 4]
    assert all(index > 5 for index in dropped)


def test_a_worker_that_dies_is_an_error_not_a_hang(small_scene_dir):
    from muscle_mss.app.motion_jobs import solve_in_workers
    with pytest.raises(MuscleMSSError, match=r"worker process \d \(pid \d+\) ended with exit "
                                             r"code 3 while solving time point 4"):
        solve_in_workers((str(small_scene_dir), SETTINGS, None), range(21),
                         functools.partial(end_at, 4), 2)
