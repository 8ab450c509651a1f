"""The frame cache (muscle_mss.filters.frame_cache) and the resumed run (muscle_mss.app.run_record):
every input of a frame is in its key, the same inputs hit across processes with the same
outputs, a damaged entry is solved again, concurrent writers, ``--cache off``, resume."""
import csv
import importlib
import json
import os
import shutil
import struct
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from muscle_mss.filters import frame_cache as F
from muscle_mss.filters import EXPORTS, FILTER_NAMES

RUN = ["--iterations", "20"]


def filter_instances():
    return [getattr(importlib.import_module(f"muscle_mss.filters.{EXPORTS[name]}"), name)()
            for name in FILTER_NAMES]


def all_properties():
    return [(name, prop) for name, f in zip(FILTER_NAMES, filter_instances())
            for prop in f.PROPERTIES]


def other_value(prop, value):
    """A valid value of ``prop`` other than ``value`` (a choice's index for an enum)."""
    if prop.kind == "bool":
        return not value
    if prop.kind == "enum":
        return prop.choices[(value + 1) % len(prop.choices)]
    if prop.kind == "string":
        return value + "/elsewhere"
    low = -np.inf if prop.minimum is None else prop.minimum
    high = np.inf if prop.maximum is None else prop.maximum
    step = 1 if prop.kind == "int" else 0.5 * abs(value) + 0.25
    return next(v for v in (value + step, value - step, (value + low) / 2)
                if low <= v <= high and v != value)


@pytest.mark.parametrize("filter_name,prop", all_properties(),
                         ids=[f"{n}.{p.name}" for n, p in all_properties()])
def test_changing_any_property_of_any_filter_changes_the_keys_after_it(filter_name, prop):
    """Every property of the six filters is in the key of what comes after it: a solved
    frame's key holds the solver's and those of the filters before it, the deformed surfaces'
    key the MVC Surface Deformer's too; FrameCache (where frames are kept) is in none. The
    Volume-Error Probe has no property: it measures every frame, loaded or computed."""
    filters = filter_instances()
    before = {stage: F.frame_key("scene", filters, 0.5, stage) for stage in (None, F.SURFACES)}
    owner = filters[FILTER_NAMES.index(filter_name)]
    getattr(owner, "Set" + prop.name)(other_value(prop, owner.value(prop.name)))
    for stage, keyed in ((None, F.KEYED_FILTERS), (F.SURFACES, F.SURFACE_KEYED_FILTERS)):
        after = F.frame_key("scene", filters, 0.5, stage)
        changes = filter_name in keyed and prop.name not in F.NOT_KEYED
        assert (F.key_digest(after) != F.key_digest(before[stage])) is changes
        assert F.key_digest(F.frame_key("scene", filter_instances(), 0.5, stage)) == \
            F.key_digest(before[stage])
    assert set(FILTER_NAMES) - set(F.SURFACE_KEYED_FILTERS) == {"VolumeErrorProbe"}
    assert not filters[FILTER_NAMES.index("VolumeErrorProbe")].PROPERTIES


def test_the_key_names_each_filter_by_its_class_also_in_a_subclass():
    """The application's cached solver and the ParaView proxies are subclasses of the
    filters: a frame they store has the key the plain filter asks for."""
    from muscle_mss.app.motion_run import CachedCollisionSolver
    filters = filter_instances()
    cached = [CachedCollisionSolver() if type(f).__name__ == "MSSCollisionSolver" else f
              for f in filters]
    assert F.frame_key("scene", cached, 0.5) == F.frame_key("scene", filters, 0.5)
    assert set(F.frame_key("scene", filters, 0.5)["properties"]) == set(F.KEYED_FILTERS)


def test_the_time_and_the_numerics_are_in_the_key():
    filters = filter_instances()
    key = F.frame_key("scene", filters, 0.5)
    assert F.key_digest(F.frame_key("scene", filters, np.nextafter(0.5, 1))) != F.key_digest(key)
    assert F.key_digest({**key, "numerics": {**key["numerics"], "sources": "0"}}) \
        != F.key_digest(key)


def test_one_byte_of_any_scene_file_changes_the_key(small_scene_dir, tmp_path):
    from muscle_mss.filters.scene_io import scene_files
    reference = F.scene_digest(small_scene_dir)
    files = [os.path.relpath(p, small_scene_dir) for p in scene_files(str(small_scene_dir))]
    assert len(files) >= 4 + 3      # the three .vtm files, their blocks and the motion table
    for relative in files:
        copy = tmp_path / relative.replace(os.sep, "_")
        shutil.copytree(small_scene_dir, copy)
        path = copy / relative
        data = bytearray(path.read_bytes())
        data[len(data) // 2] ^= 0x01
        path.write_bytes(bytes(data))
        assert F.scene_digest(copy) != reference, relative
    shutil.copytree(small_scene_dir, tmp_path / "same")
    assert F.scene_digest(tmp_path / "same") == reference      # the path is not in the key


def test_an_entry_round_trips_and_a_wrong_key_or_a_flipped_byte_is_refused(tmp_path):
    warnings = []
    cache = F.FrameStore(str(tmp_path), warn=warnings.append)
    key = {"frame": 1}
    arrays = {"positions": np.arange(12.0).reshape(4, 3), "flag": np.asarray(np.True_)}
    assert cache.save(key, arrays, {"method": "quasi-static", "passes": 3})
    loaded, scalars = cache.load(key)
    assert scalars["passes"] == 3 and loaded["flag"].dtype == np.bool_
    np.testing.assert_array_equal(loaded["positions"], arrays["positions"])
    path = cache.path(key)
    data = bytearray(open(path, "rb").read())
    with pytest.raises(F.DamagedEntry, match="not the frame's"):
        F.decode_entry(bytes(data), {"frame": 2})
    data[-10] ^= 0x01
    with pytest.raises(F.DamagedEntry, match="checksum"):
        F.decode_entry(bytes(data), key)
    open(path, "wb").write(bytes(data))
    assert cache.load(key) is None and not os.path.exists(path)
    assert warnings and warnings[0].startswith("warning: frame cache entry ")


def test_the_bound_keeps_the_most_recently_used_entries(tmp_path):
    cache = F.FrameStore(str(tmp_path), bound=10 ** 9)
    payload = {"a": np.zeros(1000)}
    cache.save({"k": 0}, payload, {})
    os.utime(cache.path({"k": 0}), (0, 0))
    size = cache.info()["bytes"]
    cache.bound = int(2.5 * size)
    for k in range(1, 4):
        cache.save({"k": k}, payload, {})
        os.utime(cache.path({"k": k}), (k, k))        # k used at second k: 1 the oldest
    cache.save({"k": 9}, payload, {})
    kept = {os.path.basename(p) for _, _, p in cache.entries()}
    assert kept == {os.path.basename(cache.path({"k": k})) for k in (3, 9)}


WRITER = textwrap.dedent("""
    import sys, numpy as np
    from muscle_mss.filters.frame_cache import FrameStore
    cache = FrameStore(sys.argv[1])
    arrays = {"positions": np.linspace(0.0, 1.0, 300000)}
    for _ in range(20):
        assert cache.save({"frame": "same"}, arrays, {"method": "m"})
""")


def test_two_writers_at_once_leave_one_valid_entry(tmp_path):
    writers = [subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path)])
               for _ in range(2)]
    assert [w.wait(timeout=120) for w in writers] == [0, 0]
    assert sorted(os.listdir(tmp_path)) == [os.path.basename(
        F.FrameStore(str(tmp_path)).path({"frame": "same"}))]
    arrays, scalars = F.FrameStore(str(tmp_path)).load({"frame": "same"})
    np.testing.assert_array_equal(arrays["positions"], np.linspace(0.0, 1.0, 300000))


# ---- whole runs --------------------------------------------------------------------------------

def assert_same_outputs(a, b, solved_again=True):
    """Every file the runs wrote is bitwise the same, but the ``seconds`` columns (of
    summary.csv: the wall seconds this run spent on a time point; of a convergence table: the
    solve's clock: compared too unless ``solved_again``, frames of the second run solved anew)
    and the folder's own hidden files."""
    def files(root):
        return sorted(os.path.relpath(os.path.join(d, f), root) for d, _, names in os.walk(root)
                      for f in names if not f.startswith("."))
    assert files(a) == files(b)
    for relative in files(a):
        if relative == "summary.csv" or solved_again and relative.endswith(".csv"):
            rows = [list(csv.DictReader(open(os.path.join(r, relative)))) for r in (a, b)]
            assert [{k: v for k, v in r.items() if k != "seconds"} for r in rows[0]] == \
                [{k: v for k, v in r.items() if k != "seconds"} for r in rows[1]]
        else:
            with open(os.path.join(a, relative), "rb") as fa, \
                    open(os.path.join(b, relative), "rb") as fb:
                assert fa.read() == fb.read(), relative


@pytest.fixture(scope="module")
def first_run(small_scene_dir, tmp_path_factory):
    """A whole run of the small scene filling a fresh cache: ``(out, cache, stdout)``."""
    pytest.importorskip("pyvista")          # the run's pictures
    from muscle_mss.app.cli import main
    root = tmp_path_factory.mktemp("cached")
    out, cache = root / "out", root / "cache"
    import contextlib
    import io
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        assert main(["run", str(small_scene_dir), str(out), *RUN, "--cache", str(cache)]) == 0
    return out, cache, text.getvalue()


def test_the_same_run_in_another_process_loads_every_frame(first_run, small_scene_dir,
                                                           tmp_path):
    out, cache, text = first_run
    assert "frame cache: 0 of 21 frames loaded, 21 solved" in text
    entries = len(F.FrameStore(str(cache)).entries())
    assert entries == 2 * 21        # each time point's solved frame and deformed surfaces
    second = subprocess.run(
        [sys.executable, "-m", "muscle_mss.app.cli", "run", str(small_scene_dir),
         str(tmp_path / "out"), *RUN, "--cache", str(cache)],
        capture_output=True, text=True, timeout=600)
    assert second.returncode == 0, second.stderr
    assert "frame cache: 21 of 21 frames loaded, 0 solved" in second.stdout
    assert len(F.FrameStore(str(cache)).entries()) == entries
    assert_same_outputs(out, tmp_path / "out", solved_again=False)


def entry_key(path) -> dict:
    """The key in the header of the entry file ``path``."""
    data = open(path, "rb").read()
    start = len(F.MAGIC) + 8
    return json.loads(data[start:start + struct.unpack("<Q", data[len(F.MAGIC):start])[0]])["key"]


def test_a_damaged_entry_is_reported_and_solved_again(first_run, small_scene_dir, tmp_path,
                                                      capsys):
    from muscle_mss.app.cli import main
    out, cache, _ = first_run
    copy = tmp_path / "cache"
    shutil.copytree(cache, copy)
    victim = next(path for _, _, path in F.FrameStore(str(copy)).entries()
                  if "stage" not in entry_key(path))             # a solved frame's
    size = os.path.getsize(victim)
    with open(victim, "r+b") as f:
        f.truncate(size // 2)
    assert main(["run", str(small_scene_dir), str(tmp_path / "out"), *RUN,
                 "--cache", str(copy)]) == 0
    captured = capsys.readouterr()
    assert f"warning: frame cache entry {victim} is damaged (truncated" in captured.err
    assert "frame cache: 20 of 21 frames loaded, 1 solved" in captured.out
    data = open(victim, "rb").read()            # written again, whole
    key = entry_key(victim)
    F.decode_entry(data, key)
    assert os.path.basename(victim) == F.key_digest(key) + F.SUFFIX
    assert_same_outputs(out, tmp_path / "out")


def test_cache_off_writes_nothing(small_scene_dir, tmp_path, monkeypatch, capsys):
    pytest.importorskip("pyvista")
    from muscle_mss.app.cli import main
    monkeypatch.delenv(F.ENVIRONMENT, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    frames = tmp_path / "xdg" / "muscle-mss" / "frames"
    assert main(["run", str(small_scene_dir), str(tmp_path / "off"), *RUN, "--time", "0.5",
                 "--cache", "off"]) == 0
    assert "frame cache" not in capsys.readouterr().out and not frames.exists()
    # without --cache the user's cache folder is used: the check above can fail
    assert main(["run", str(small_scene_dir), str(tmp_path / "on"), *RUN, "--time", "0.5"]) == 0
    assert len(F.FrameStore(str(frames)).entries()) == 2       # the frame and its surfaces
    assert main(["cache", "info"]) == 0
    assert f"frame cache {frames}: 2 entries" in capsys.readouterr().out
    assert main(["cache", "clear"]) == 0 and not F.FrameStore(str(frames)).entries()


def test_an_interrupted_run_resumes_to_the_uninterrupted_outputs(first_run, small_scene_dir,
                                                                 tmp_path, monkeypatch, capsys):
    from muscle_mss.app import cli
    out, _, _ = first_run
    resumed, cache = tmp_path / "out", str(tmp_path / "cache")
    update = cli.ProgressBar.update

    def interrupt_after_five(self, done, note=""):
        update(self, done, note)
        if done == 5:
            raise KeyboardInterrupt

    monkeypatch.setattr(cli.ProgressBar, "update", interrupt_after_five)
    assert cli.main(["run", str(small_scene_dir), str(resumed), *RUN, "--cache", cache]) == 130
    monkeypatch.setattr(cli.ProgressBar, "update", update)
    assert not (resumed / "summary.csv").exists()
    capsys.readouterr()
    # other options are refused, naming what differs
    assert cli.main(["run", str(small_scene_dir), str(resumed), "--iterations", "25",
                     "--cache", cache]) == 2
    assert "--iterations 20 there, 25 now" in capsys.readouterr().err
    assert cli.main(["run", str(small_scene_dir), str(resumed), *RUN, "--cache", cache]) == 0
    text = capsys.readouterr().out
    assert f"resuming the run in {resumed} (the same scene and options): 5 of 21 time " \
           "points were written" in text
    assert "frame cache: 5 of 21 frames loaded, 16 solved" in text
    assert_same_outputs(out, resumed)
    assert cli.main(["run", str(small_scene_dir), str(resumed), *RUN, "--cache", cache]) == 0
    assert f"{resumed}: complete already" in capsys.readouterr().out


# ---- the solver's FrameCache property -----------------------------------------------------------

def _plain_pipeline(scene_folder, frame_cache):
    from muscle_mss.app.motion_run import build_pipeline
    return build_pipeline(scene_folder, {"Iterations": 20, "FrameCache": frame_cache})


def test_the_solvers_frame_cache_property_loads_what_it_stored_in_a_new_pipeline(
        small_scene_dir, tmp_path):
    from muscle_mss.app.motion_run import update_at
    from muscle_mss.filters import vtk_arrays as V
    cache = str(tmp_path / "cache")
    outputs = []
    for _ in range(2):
        p = _plain_pipeline(small_scene_dir, cache)
        outputs.append([V.points_of(b) for _, b in V.blocks(update_at(p.solver, 0, p.times[3]))])
    assert p.solver.frame_counts == {"loaded": 1, "solved": 0}
    assert len(F.FrameStore(cache).entries()) == 1
    for first, second in zip(*outputs):
        np.testing.assert_array_equal(first, second)


def shown_surfaces(surfaces) -> dict:
    """``{(muscle, what): array}``: each deformed surface's points, point data and field data."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from muscle_mss.filters import vtk_arrays as V
    shown = {}
    for name, block in V.blocks(surfaces):
        shown[name, "points"] = V.points_of(block)
        for kind, data in (("point", block.GetPointData()), ("field", block.GetFieldData())):
            for k in range(data.GetNumberOfArrays()):
                array = data.GetAbstractArray(k)
                shown[name, f"{kind} {array.GetName()}"] = (
                    array.GetValue(0) if array.IsA("vtkStringArray") else vtk_to_numpy(array))
    return shown


def assert_same_surfaces(first: dict, second: dict):
    assert list(first) == list(second)
    for key in first:
        np.testing.assert_array_equal(first[key], second[key], err_msg=str(key))


def deformer_properties():
    return [prop for name, prop in all_properties() if name == "MVCSurfaceDeformer"]


@pytest.mark.parametrize("prop", deformer_properties(),
                         ids=[p.name for p in deformer_properties()])
def test_the_deformed_surfaces_are_loaded_and_a_deformer_property_computes_them_again(
        prop, small_scene_dir, tmp_path):
    """A new pipeline with the same properties loads the solved frame and its deformed
    surfaces, bitwise what computing them gives; with one of the MVC Surface Deformer's
    properties changed it loads the solved frame and computes the surfaces again, as a
    pipeline without a cache does."""
    from muscle_mss.app.motion_run import update_at
    cache, t = str(tmp_path / "cache"), 3
    first = _plain_pipeline(small_scene_dir, cache)
    computed = shown_surfaces(update_at(first.probe, 0, first.times[t]))
    again = _plain_pipeline(small_scene_dir, cache)
    assert_same_surfaces(shown_surfaces(update_at(again.probe, 0, again.times[t])), computed)
    assert again.solver.frame_counts == {"loaded": 1, "solved": 0}
    assert again.deformer.frame_counts == {"loaded": 1, "computed": 0}
    changed = other_value(prop, first.deformer.value(prop.name))
    shown = []
    for frame_cache in (cache, "off"):
        p = _plain_pipeline(small_scene_dir, frame_cache)
        getattr(p.deformer, "Set" + prop.name)(changed)
        shown.append(shown_surfaces(update_at(p.probe, 0, p.times[t])))
        assert p.deformer.frame_counts == {"loaded": 0, "computed": 1}
        assert p.solver.frame_counts == ({"loaded": 1, "solved": 0} if frame_cache != "off"
                                         else {"loaded": 0, "solved": 1})
    assert_same_surfaces(*shown)
    assert len(F.FrameStore(cache).entries()) == 3     # the frame, its surfaces twice


def test_frame_cache_off_or_empty_in_a_plain_pipeline_writes_nothing(small_scene_dir, tmp_path,
                                                                     monkeypatch):
    """``off`` reads and writes nothing; empty is the application's choice, none in a plain
    VTK pipeline (``muscle-mss run`` gives its solver its ``--cache``), even with
    $MUSCLE_MSS_FRAME_CACHE naming a folder."""
    from muscle_mss.app.motion_run import update_at
    folder = tmp_path / "user"
    monkeypatch.setenv(F.ENVIRONMENT, str(folder))
    for value in ("off", ""):
        p = _plain_pipeline(small_scene_dir, value)
        update_at(p.probe, 0, p.times[1])
        assert p.solver.frame_counts == {"loaded": 0, "solved": 1}
    assert not folder.exists()
    p = _plain_pipeline(small_scene_dir, str(folder))     # the check above can fail
    update_at(p.probe, 0, p.times[1])
    assert len(F.FrameStore(str(folder)).entries()) == 2


def test_a_solver_fed_by_another_filter_than_the_scenes_does_not_use_the_cache(
        small_scene_dir, tmp_path):
    """A filter between the scene's readers and the solver makes the frame depend on more
    than the key: the cache is not used, and the messages say why."""
    from vtkmodules.vtkFiltersCore import vtkPassThrough
    from muscle_mss.app.motion_run import update_at
    from muscle_mss.filters.scene_io import vtk_messages
    p = _plain_pipeline(small_scene_dir, str(tmp_path / "cache"))
    between = vtkPassThrough()
    between.SetInputConnection(p.pose.GetOutputPort(1))
    p.solver.SetInputConnection(1, between.GetOutputPort())
    with vtk_messages() as messages:
        update_at(p.solver, 0, p.times[1])
    assert "the frame cache is not used: vtkPassThrough feeds it" in messages.GetOutput()
    assert p.solver.frame_counts == {"loaded": 0, "solved": 1}
    assert not (tmp_path / "cache").exists()
