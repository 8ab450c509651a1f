"""Real ParaView 5.11 (Debian's pvpython, pvbatch, paraview under xvfb-run), headless.

Each test starts ParaView's own executables with this checkout on PYTHONPATH through
``plugin/shim``, so these are the same interpreters, readers and plugin loader users run.
"""
import json

import numpy as np
import pytest

from muscle_mss.core.settings import DEFAULT_TOLERANCE
from paraview_support import SCRIPTS, run_script

pytestmark = pytest.mark.paraview


def test_pvpython_reads_demo_scene_with_its_own_readers(small_scene, small_scene_dir):
    result = run_script("pvpython", "read_scene.py", small_scene_dir)
    assert result["numba"].startswith("0.56") and result["numpy"].startswith("1.24")
    assert result["core_file"].endswith("core/__init__.py")
    assert result["muscle_blocks"] == list(small_scene.muscles)
    assert result["muscle_points"] == sum(len(s.points) for s in small_scene.muscles.values())
    assert result["motion_rows"] == len(small_scene.motion.times) * len(small_scene.bones)
    assert result["motion_columns"][:3] == ["time", "bone", "m00"]
    assert result["problems"] == []
    assert result["time_points"] == len(small_scene.motion.times)


ITERATIONS = "60"  # enough to exercise the solver; the numbers only need to agree


@pytest.fixture(scope="module")
def venv_chain(small_scene_dir):
    from muscle_mss.app import motion_run
    return motion_run.build_pipeline(small_scene_dir, {"Iterations": int(ITERATIONS)})



def test_pipeline_built_by_hand_without_the_spring_builders_bones_gives_the_builders_numbers(
        small_scene, small_scene_dir):
    """Issue 14: the six filters added one by one through the proxies, as a GUI user does
    (nothing asks for the Spring Builder's optional Bones), give bitwise the one-click builder's
    solved particles, surfaces and volume errors at the most flexed pose: the Rigid Pose
    Transform clears the radii of the bones either way."""
    from muscle_mss.core.motion import farthest_pose_index
    t = float(small_scene.motion.times[farthest_pose_index(small_scene.motion)])
    result = run_script("pvpython", "hand_built_pipeline.py", small_scene_dir, t, ITERATIONS)
    assert result["blocks"] == len(small_scene.muscles)
    assert result["largest_move"] > 1.0                 # a real solve, not the posed state
    assert result["solved"] == 0.0 and result["surfaces"] == 0.0
    assert result["volume_error"] == 0.0
    # the hand-built Spring Builder's radii are not cleared of the bones (it warns); the
    # pose's are, exactly as the builder's Spring Builder (with Bones) cleared them
    assert result["hand_model_radii_sum"] > result["builder_model_radii_sum"]
    assert result["hand_posed_radii_sum"] == result["builder_model_radii_sum"]

def test_plugin_builder_gives_the_venv_chain_numbers_and_time_moves_the_pose(
        small_scene, small_scene_dir, venv_chain, tmp_path):
    import numpy as np
    from muscle_mss.filters import vtk_arrays as V
    from muscle_mss.app.motion_run import update_at

    times = small_scene.motion.times
    t0, t1 = float(times[0]), float(times[len(times) * 3 // 4])
    npz = tmp_path / "pv.npz"
    result = run_script("pvpython", "pipeline_numbers.py", small_scene_dir, npz, t0, t1)
    assert result["filters"] == ["FibreResampler", "MSSCollisionSolver", "MVCSurfaceDeformer",
                                 "RigidPoseTransform", "SpringBuilder", "VolumeErrorProbe"]
    np.testing.assert_allclose(result["timesteps"], times, rtol=0, atol=1e-12)
    np.testing.assert_allclose(result["keeper"], times, rtol=0, atol=1e-12)
    pv = np.load(npz)
    for k, t in enumerate((t0, t1)):
        surfaces = update_at(venv_chain.probe, 0, t)
        for name, block in V.blocks(surfaces):
            # the quasi-static solve meets its tolerance (mm) in both Pythons, whose kernels
            # round differently (1e-9 mm apart seen), not the same bits
            np.testing.assert_allclose(pv[f"surfaces/{k}/{name}"], V.points_of(block),
                                       rtol=0, atol=DEFAULT_TOLERANCE, err_msg=f"{name} at t={t}")
    for key, algorithm in (("particles", venv_chain.resampler), ("model", venv_chain.springs)):
        algorithm.Update()
        for name, block in V.blocks(algorithm.GetOutputDataObject(0)):
            np.testing.assert_array_equal(pv[f"{key}/{name}/points"], V.points_of(block))
            arrays = V.point_arrays(block)
            assert {k.split("/")[-1] for k in pv.files if k.startswith(f"{key}/{name}/point/")} \
                == set(arrays)
            for array, values in arrays.items():
                np.testing.assert_array_equal(pv[f"{key}/{name}/point/{array}"], values,
                                              err_msg=f"{key} {name} {array}")
    for name, block in V.blocks(venv_chain.springs.GetOutputDataObject(0)):
        np.testing.assert_array_equal(pv[f"model/{name}/cell/rest_length"],
                                      V.cell_array(block, "rest_length"))
    moved = [np.abs(pv[f"bones/1/{b}"] - pv[f"bones/0/{b}"]).max() for b in small_scene.bones]
    assert max(moved) > 10.0  # mm: the femur and tibia swing between the two times


def test_state_file_reloads_to_the_same_numbers(small_scene, small_scene_dir, tmp_path):
    import shutil
    work = tmp_path / "review"
    shutil.copytree(small_scene_dir, work / "data")
    saved = run_script("xvfb-run", "-a", "pvpython", "save_state.py", "data", "review.pvsm",
                       float(small_scene.motion.times[15]), cwd=work)
    moved = tmp_path / "elsewhere"
    shutil.move(str(work), str(moved))  # every path stored in the state is now dead
    loaded = run_script("xvfb-run", "-a", "pvpython", "load_state.py",
                        moved / "review.pvsm", moved / "data")
    assert loaded["muscle"] == saved["muscle"] == list(small_scene.muscles) + ["mean"]
    assert loaded["volume"] == saved["volume"]
    assert loaded["iterations"] == int(ITERATIONS)
    assert loaded["time"] == pytest.approx(float(small_scene.motion.times[15]))


def test_saved_state_hides_fibres_charts_every_muscle_and_follows_the_colour_range(
        small_scene, small_scene_dir, venv_chain, tmp_path):
    """The saved state hides the fibres, charts every muscle's convergence and its mean fibre
    strain over the whole motion (a line per muscle, labelled by name, the venv chain's
    numbers), and colours by a range that follows the time shown."""
    import shutil
    import numpy as np
    from muscle_mss.filters import array_names as A
    from muscle_mss.filters import vtk_arrays as V
    from muscle_mss.app.motion_run import update_at
    from muscle_mss.plugin.pipeline import fibre_strain_series
    from paraview_support import run
    work = tmp_path / "review"
    shutil.copytree(small_scene_dir, work / "data")
    saved = run(["xvfb-run", "-a", "pvpython", SCRIPTS / "save_state.py", "data", "review.pvsm",
                 float(small_scene.motion.times[15])], cwd=work)
    assert "Invalid producer" not in saved.stderr and "ERR" not in saved.stderr, saved.stderr
    shown = run_script("xvfb-run", "-a", "pvpython", "state_displays.py",
                       work / "review.pvsm", work / "data")
    assert shown["fibres_visible"] is False
    assert sorted(shown["chart_series"]) == sorted(f"mean_displacement_{m}"
                                                   for m in small_scene.muscles)
    muscles = list(small_scene.muscles)
    assert shown["strain_series"] == fibre_strain_series(muscles)
    labels = dict(zip(shown["strain_labels"][0::2], shown["strain_labels"][1::2]))
    assert [labels[s] for s in fibre_strain_series(muscles)] == muscles
    values = np.array(shown["strain_values"])            # (muscles, time points)
    times = small_scene.motion.times
    assert values.shape == (len(muscles), len(times))
    for k in (0, 15):
        fibres = dict(V.blocks(update_at(venv_chain.deformer, 1, float(times[k]))))
        expected = [V.cell_array(fibres[m], A.FIBRE_STRAIN).mean() for m in muscles]
        np.testing.assert_allclose(values[:, k], expected, rtol=0, atol=1e-9)
    assert np.ptp(values, axis=1).max() > 0.01          # the strains change over the motion
    (_, first), (_, second) = shown["ranges"]
    assert abs(second[1] - first[1]) > 0.2 * first[1]  # the two times differ enough to tell
    for colours, data in shown["ranges"]:
        assert colours == pytest.approx(data, rel=1e-6, abs=1e-9)
    assert_charts_readable(shown)


def test_gui_opens_the_state_and_shows_the_muscles(small_scene, small_scene_dir, tmp_path):
    import numpy as np
    from PIL import Image
    from paraview_support import run

    work = tmp_path / "gui"
    import shutil
    shutil.copytree(small_scene_dir, work / "data")
    run_script("xvfb-run", "-a", "pvpython", "save_state.py", "data", "review.pvsm",
               float(small_scene.motion.times[15]), cwd=work)
    shot = tmp_path / "gui.png"
    run(["xvfb-run", "-a", "-s", "-screen 0 1280x1024x24", "paraview", "--dr",
         f"--script={SCRIPTS / 'gui_screenshot.py'}", "--exit"],
        MUSCLE_MSS_STATE=work / "review.pvsm", MUSCLE_MSS_DATA=work / "data",
        MUSCLE_MSS_SCREENSHOT=shot)
    pixels = np.asarray(Image.open(shot).convert("RGB"), dtype=float)
    background = np.median(pixels.reshape(-1, 3), axis=0)
    differs = np.abs(pixels - background).sum(axis=2) > 30
    assert pixels.std() > 10.0 and differs.mean() > 0.02, "the view looks blank"


def test_mpi_batch_equals_the_serial_batch(small_scene_dir, tmp_path):
    import csv
    from paraview_support import run

    # every time point from the posed state, so ranks give bitwise the serial result
    serial, parallel = tmp_path / "serial", tmp_path / "mpi"
    options = ["--iterations", ITERATIONS, "--method", "paper"]
    run(["pvpython", "-m", "muscle_mss.plugin.batch", small_scene_dir, serial, *options])
    run(["mpiexec", "--allow-run-as-root", "--oversubscribe", "-n", "2", "pvbatch", "--sym",
         "-m", "muscle_mss.plugin.batch", small_scene_dir, parallel, *options])

    def table(folder):
        with open(folder / "summary.csv", newline="") as f:
            return [{k: v for k, v in row.items() if k != "seconds"} for row in csv.DictReader(f)]
    assert table(serial) == table(parallel)
    assert len(table(serial)) > 0
    for name in ("surfaces.pvd", "fibres.pvd", "particles.pvd"):
        assert (serial / name).read_text() == (parallel / name).read_text()


def test_pvpython_batch_writes_the_study_the_cli_writes(small_scene, small_scene_dir, tmp_path):
    """``pvpython -m muscle_mss.plugin.batch --study`` (issue 29) writes the report and the
    tables ``muscle-mss study`` writes in the venv, with the same numbers; under MPI it is
    refused with a message."""
    import csv
    import subprocess
    from paraview_support import REPO, paraview_env, run
    from muscle_mss.app.cli import main
    from muscle_mss.app.study_report import STUDY_FILES
    t = float(small_scene.motion.times[10])
    run(["pvpython", "-m", "muscle_mss.plugin.batch", "--study", small_scene_dir,
         tmp_path / "pv", "--time", str(t)])
    assert main(["study", str(small_scene_dir), str(tmp_path / "venv"), "--time", str(t)]) == 0
    assert all((tmp_path / "pv" / name).stat().st_size > 0 for name in STUDY_FILES)

    def table(folder, name, columns):
        with open(folder / name, newline="") as f:
            return [[row[c] for c in columns] for row in csv.DictReader(f)]
    for name, columns in (("volume.csv", ["volume_error_pct"]),
                          ("fibre_length.csv", ["mean_fibre_strain", "path_length_mm"]),
                          ("layouts.csv", ["springs_per_particle", "mean_volume_error_pct"])):
        pv, venv = (np.array(table(f, name, columns), dtype=float)
                    for f in (tmp_path / "pv", tmp_path / "venv"))
        # the two Pythons' kernels round differently (Numba 0.56 / 0.68) and the motion's
        # quasi-static solves meet their tolerance, not the same bits: 4e-6 % apart seen
        np.testing.assert_allclose(pv, venv, rtol=1e-6, atol=1e-4, err_msg=name)
    refused = subprocess.run(
        ["mpiexec", "--allow-run-as-root", "--oversubscribe", "-n", "2", "pvbatch", "--sym",
         "-m", "muscle_mss.plugin.batch", "--study", str(small_scene_dir), str(tmp_path / "mpi")],
        cwd=REPO, env=paraview_env(), capture_output=True, text=True, timeout=600)
    assert refused.returncode != 0 and "start it with pvpython" in refused.stderr


def _paraview_kernels_unmarked(folder):
    """A copy in ``folder`` of ParaView's Python's kernel cache, every kernel compiled but not
    recorded as such (this checkout's warm marker removed; the user's cache folder may hold
    other checkouts' too): a run in it goes through the cold path (the notice, the warm-up) in
    seconds. Returns the removed marker's path in a list."""
    import glob
    import os
    import shutil
    from paraview_support import REPO, run
    from muscle_mss.core import kernel_cache

    run(["pvpython", "-m", "muscle_mss.app.warm_up"])  # ParaView's Python's own cache
    digest = kernel_cache.sources_digest(os.path.join(REPO, "core"))
    (own,) = glob.glob(os.path.join(kernel_cache.base_cache_dir(),
                                    f"numba-{digest}-*numba0.56*"))
    shutil.copytree(own, folder / os.path.basename(own))
    marker = folder / os.path.basename(own) / os.path.basename(
        kernel_cache.warm_marker(str(REPO / "core")))
    marker.unlink()
    return [marker]


def test_mpi_ranks_share_one_compile(small_scene_dir, tmp_path):
    """With ParaView's Python's kernels not yet recorded as compiled, rank 0 compiles (says so,
    once) while the other rank waits and then finds them compiled."""
    from paraview_support import run

    markers = _paraview_kernels_unmarked(tmp_path / "kernels")
    proc = run(["mpiexec", "--allow-run-as-root", "--oversubscribe", "-n", "2", "pvbatch",
                "--sym", "-m", "muscle_mss.plugin.batch", small_scene_dir, tmp_path / "out",
                "--iterations", "3"], NUMBA_CACHE_DIR=tmp_path / "kernels")
    assert proc.stderr.count("compiling the numeric kernels once for this Python") == 1
    assert all(marker.exists() for marker in markers) and markers


def test_the_plugin_says_it_compiles_among_the_output_messages(small_scene_dir, tmp_path):
    """ParaView's entry point is the plugin: the first filter update in a ParaView Python whose
    kernels are not recorded as compiled says so once among the output messages, then compiles
    them all; the next session finds them compiled and says nothing."""
    from paraview_support import run

    markers = _paraview_kernels_unmarked(tmp_path / "kernels")
    runs = [run(["pvpython", SCRIPTS / "bad_input.py", small_scene_dir, '{"Iterations": 3}',
                 "0.5"], NUMBA_CACHE_DIR=tmp_path / "kernels") for _ in range(2)]
    notice = "compiling the numeric kernels once for this Python"
    assert runs[0].stderr.count("Muscle MSS: " + notice) == 1
    assert all(marker.exists() for marker in markers) and markers
    assert notice not in runs[1].stderr


def test_shipped_demo_state_opens_the_demo_walk(tmp_path):
    from muscle_mss.core.demo.scene import MUSCLE_NAMES, demo_scene
    from muscle_mss.core.motion import farthest_pose_index
    from muscle_mss.filters.scene_io import write_scene
    from muscle_mss.plugin.pipeline import fibre_strain_series

    scene = demo_scene("full")
    write_scene(scene, tmp_path / "demo_out" / "scene")  # where ./demo.sh puts it
    state = SCRIPTS.parents[1] / "state_files" / "demo_walk.pvsm"
    loaded = run_script("xvfb-run", "-a", "pvpython", "load_state.py", state, tmp_path)
    assert loaded["muscle"] == list(MUSCLE_NAMES) + ["mean"]
    assert all(v > 0 for v in loaded["volume"])
    assert loaded["time"] == pytest.approx(scene.motion.times[farthest_pose_index(scene.motion)])
    shown = run_script("xvfb-run", "-a", "pvpython", "state_displays.py", state, tmp_path)
    assert shown["fibres_visible"] is False
    assert sorted(shown["chart_series"]) == sorted(f"mean_displacement_{m}" for m in MUSCLE_NAMES)
    assert shown["strain_series"] == fibre_strain_series(MUSCLE_NAMES)
    labels = dict(zip(shown["strain_labels"][0::2], shown["strain_labels"][1::2]))
    assert [labels[s] for s in fibre_strain_series(MUSCLE_NAMES)] == list(MUSCLE_NAMES)
    assert len(shown["strain_values"]) == len(MUSCLE_NAMES)
    assert all(len(v) == len(scene.motion.times) for v in shown["strain_values"])
    assert_charts_readable(shown)


def assert_charts_readable(shown):
    """No chart has a log axis over a value <= 0 (ParaView would cover it with "One or more
    plot series crosses or contains an axis origin"), and every legend is beside its plot."""
    for chart, axes in shown["axes"].items():
        for axis in ("left", "bottom"):
            log, least = axes[axis]
            assert not log or least > 0, (chart, axis, least)
        assert axes["legend"] == "Right", chart


def test_the_solver_in_paraview_loads_every_frame_a_cli_run_solved(small_scene_dir, tmp_path):
    """A CLI run of the small scene fills a frame cache; the plugin's pipeline with the same
    properties in pvpython takes every frame from it (the solver's counts), FrameCache naming
    the folder or left empty with $MUSCLE_MSS_FRAME_CACHE naming it (an empty FrameCache in
    ParaView is the user's frame cache, the CLI's default); ``off`` solves and writes
    nothing."""
    import subprocess
    import sys
    from muscle_mss.filters.frame_cache import FrameStore
    cache = tmp_path / "cache"
    cli = subprocess.run([sys.executable, "-m", "muscle_mss.app.cli", "run", str(small_scene_dir),
                          str(tmp_path / "out"), "--iterations", "20", "--write", "surfaces",
                          "--cache", str(cache)], capture_output=True, text=True, timeout=900)
    assert cli.returncode == 0, cli.stderr[-3000:]
    assert "frame cache: 0 of 21 frames loaded, 21 solved" in cli.stdout
    named = run_script("pvpython", "frame_cache_pipeline.py", small_scene_dir, 20, cache, 0)
    assert named["counts"] == {"loaded": 21, "solved": 0}
    default = run_script("pvpython", "frame_cache_pipeline.py", small_scene_dir, 20, "-", 2,
                         MUSCLE_MSS_FRAME_CACHE=cache)
    assert default["frame_cache"] == "" and default["counts"] == {"loaded": 2, "solved": 0}
    np.testing.assert_allclose(default["volume"], named["volume"][:2], rtol=0, atol=1e-9)
    # the CLI's 21 solved frames and their deformed surfaces, which ParaView's deformer loaded
    assert len(FrameStore(str(cache)).entries()) == 2 * 21
    other = tmp_path / "other"
    off = run_script("pvpython", "frame_cache_pipeline.py", small_scene_dir, 20, "off", 1,
                     MUSCLE_MSS_FRAME_CACHE=other)
    assert off["counts"] == {"loaded": 0, "solved": 1} and not other.exists()
    # the plugin runs the kernels on workqueue: omp beside ParaView's OpenMP ran 5-6x slower
    assert named["threading_layer"] == "workqueue"
    np.testing.assert_allclose(off["volume"], named["volume"][:1], rtol=0, atol=1e-5)


def _digest(path) -> str:
    import hashlib
    with open(path, "rb") as f:
        return hashlib.sha1(f.read()).hexdigest()


@pytest.mark.parametrize("how, expect", [
    ("LoadState", "Fibre Resampler: fibres.vtm: the reader produced nothing for input 'Fibres': "
                  "the file {folder}/demo_out/scene/fibres.vtm does not exist; if the pipeline "
                  "comes from a state file, load it with its data folder: "
                  "LoadState(STATE, data_directory=FOLDER)"),
    ("LoadState-empty", "Fibre Resampler: the reader produced nothing for input 'Fibres': the "
                        "reader has no file name (LoadState leaves it empty for a file it does "
                        "not find under its data_directory)")])
def test_a_state_loaded_without_its_scene_names_the_missing_file(tmp_path, how, expect):
    """The shipped state loaded in a folder without demo_out/scene (or with a data folder that
    lacks it): after ParaView's reader errors the Fibre Resampler names the file its reader could
    not read, not "fibres.vtm has no blocks", and nothing downstream complains."""
    from paraview_support import run
    state = SCRIPTS.parents[1] / "state_files" / "demo_walk.pvsm"
    before = _digest(state)
    proc = run(["xvfb-run", "-a", "pvpython", SCRIPTS / "state_without_data.py", state, how],
               cwd=tmp_path)
    assert expect.format(folder=tmp_path) in proc.stderr, proc.stderr[-3000:]
    assert "has no blocks; it needs one block per muscle" not in proc.stderr
    for downstream in ("Spring Builder:", "Rigid Pose Transform:", "MSS Collision Solver:",
                       "MVC Surface Deformer:", "Volume-Error Probe:"):
        assert downstream not in proc.stderr, proc.stderr[-3000:]
    assert '"probe_blocks": 0' in proc.stdout
    assert _digest(state) == before


def test_load_state_without_its_scene_exits_non_zero_naming_the_missing_file(tmp_path):
    """ParaView's LoadState carries on past missing files (the script exited 0 with every output
    empty); muscle_mss.plugin.pipeline.load_state raises, so pvpython exits 1."""
    from paraview_support import run
    state = SCRIPTS.parents[1] / "state_files" / "demo_walk.pvsm"
    before = _digest(state)
    proc = run(["xvfb-run", "-a", "pvpython", SCRIPTS / "state_without_data.py", state,
                "load_state"], cwd=tmp_path, check=False)
    assert proc.returncode == 1, proc.stderr[-3000:]
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith(
        f"muscle_mss.core.errors.MuscleMSSError: {state}: reader 'bones.vtm' reads "
        f"demo_out/scene/bones.vtm: {tmp_path}/demo_out/scene/bones.vtm does not exist; load "
        "the state with its data folder, load_state(STATE, data_directory=FOLDER)"), last
    assert "RESULT" not in proc.stdout
    assert _digest(state) == before


@pytest.mark.parametrize("settings, message", [
    ('{"ParticlesPerFibre": 1}',
     "Fibre Resampler: property ParticlesPerFibre is 1; it must be at least 2"),
    ('{"Mass": 1e-8, "Method": "paper relaxation"}',
     "MSS Collision Solver: the model cannot be solved with TimeStep 0.05 s")])
def test_pvpython_shows_the_failing_filters_message_and_no_follow_on_complaints(
        small_scene_dir, settings, message):
    """In ParaView the upstream filter's error is the only message (the downstream filters
    empty their outputs silently), and springs too stiff for the time step give an error, not
    a crash of the whole session (the spatial hash segfaulted)."""
    from paraview_support import run
    proc = run(["pvpython", SCRIPTS / "bad_input.py", small_scene_dir, settings, "0.5"])
    result = json.loads(next(line for line in proc.stdout.splitlines()
                             if line.startswith("RESULT "))[len("RESULT "):])
    assert result["probe_blocks"] == 0
    assert message in proc.stderr
    for follow_on in ("has no muscle blocks", "has no blocks", "has no block '"):
        assert follow_on not in proc.stderr, proc.stderr[-3000:]


def test_shipped_state_has_every_port_and_property_of_the_filters_as_they_are():
    """A state saved before a filter gained an input or a property reloads without it (the
    Fibre Resampler's Bones, which orients fibres, and the solver's ConnectiveTissue were
    missing): regenerate it (state_files/README.md) whenever this fails."""
    import xml.etree.ElementTree as ET
    from muscle_mss import filters as F
    state = ET.parse(SCRIPTS.parents[1] / "state_files" / "demo_walk.pvsm").getroot()
    for cls in (F.FibreResampler, F.SpringBuilder, F.RigidPoseTransform, F.MSSCollisionSolver,
                F.MVCSurfaceDeformer, F.VolumeErrorProbe):
        proxy = state.find(f".//Proxy[@group='filters'][@type='{cls.__name__}']")
        assert proxy is not None, cls.__name__
        saved = {p.get("name"): p for p in proxy.findall("Property")}
        for port in cls.INPUTS:
            assert port.name in saved, (cls.__name__, port.name)
            # the demo scene has no attachments.csv: its reader is made only for one that has
            connected = (cls.__name__, port.name) != ("FibreResampler", "Attachments")
            assert (saved[port.name].find("Proxy") is not None) is connected, \
                (cls.__name__, port.name)
        for prop in cls.PROPERTIES:
            assert prop.name in saved, (cls.__name__, prop.name)


def test_the_fibre_generator_in_pvpython_gives_the_venvs_fibres(tmp_path):
    """The Fibre Generator from the plugin, on ParaView's readers of the small elbow's muscles,
    bones and an attachments.csv, feeds the Fibre Resampler and gives the fibres `muscle-mss
    fibres` writes in the venv (numpy 1.24 / scipy 1.10 against the venv's: within 1e-6 mm); the
    one-click pipeline reads the scene's attachments.csv into its Fibre Resampler."""
    from muscle_mss.app.scene_fibres import generate_fibres_file
    from muscle_mss.core.demo.arm import demo_arm_scene
    from muscle_mss.filters.scene_io import load_scene, write_scene
    arm = demo_arm_scene("small")
    write_scene(arm, tmp_path)
    with open(tmp_path / "attachments.csv", "w") as f:
        f.write("muscle,origin_bone,insertion_bone\n" + "".join(
            f"{m},{fs.origin_bone},{fs.insertion_bone}\n" for m, fs in arm.fibres.items()))
    generate_fibres_file(str(tmp_path), 9, 7, overwrite=True, report=lambda line: None)
    venv = load_scene(str(tmp_path)).fibres
    result = run_script("pvpython", "fibre_generator.py", tmp_path, 9, 7)
    assert list(result["blocks"]) == list(arm.muscles)
    for name, block in result["blocks"].items():
        np.testing.assert_allclose(block["points"], venv[name].points, atol=1e-6, rtol=0)
        assert block["grid"] == venv[name].grid.tolist()
        assert block["bones"] == [arm.fibres[name].origin_bone, arm.fibres[name].insertion_bone]
    assert result["particles"] == len(arm.muscles) * 9 * 20
    assert result["pipeline_reads_attachments"]
    assert result["handed_on"] == {name: block["bones"] for name, block in result["blocks"].items()}
