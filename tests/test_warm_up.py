"""Compiling the kernels once per Python, and saying so (app.warm_up, core.kernel_cache)."""
import os
import shutil
import subprocess
import sys

import pytest

from muscle_mss.core import kernel_cache
from muscle_mss.app import warm_up

NOTICE = "compiling the numeric kernels once for this Python"


def test_marker_follows_the_sources_stamps(tmp_path, monkeypatch):
    core = tmp_path / "core"
    core.mkdir()
    (core / "a.py").write_text("x = 1\n")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    assert not kernel_cache.is_warm(str(core))
    kernel_cache.mark_warm(12.3, str(core))
    assert kernel_cache.is_warm(str(core))
    assert os.path.dirname(kernel_cache.warm_marker(str(core))) == \
        kernel_cache.kernel_cache_dir(folder=str(core))
    os.utime(core / "a.py", (1, 1))  # Numba recompiles a kernel whose file time changed
    assert not kernel_cache.is_warm(str(core))


EVERY, DEFAULTS = kernel_cache.EVERY_KERNEL, kernel_cache.DEFAULT_KERNELS


def test_estimate_is_the_median_cold_compile_recorded(tmp_path):
    assert kernel_cache.compile_estimate(str(tmp_path)) == kernel_cache.COMPILE_SECONDS[EVERY]
    assert kernel_cache.compile_estimate(str(tmp_path), DEFAULTS) == \
        kernel_cache.COMPILE_SECONDS[DEFAULTS]
    for k, seconds in enumerate((95.0, 3.0, 1287.0, 120.0)):
        folder = tmp_path / f"numba-{k}-{kernel_cache.runtime_tag()}"
        folder.mkdir()
        (folder / f"{kernel_cache.WARM_PREFIX[EVERY]}x.json").write_text(
            f'{{"seconds": {seconds}}}')
        (folder / f"{kernel_cache.WARM_PREFIX[DEFAULTS]}x.json").write_text(
            f'{{"seconds": {seconds / 2}}}')
    other = tmp_path / "numba-0-cp27-numba0.1-numpy0.1"
    other.mkdir()
    (other / f"{kernel_cache.WARM_PREFIX[EVERY]}x.json").write_text('{"seconds": 999}')
    # 3 s found its kernels cached, another Python's 999 s does not count, one slow outlier;
    # the default settings' compiles are estimated from their own records
    assert kernel_cache.compile_estimate(str(tmp_path)) == 120.0
    assert kernel_cache.compile_estimate(str(tmp_path), DEFAULTS) == 60.0


def test_every_kernel_warm_covers_the_default_settings_kernels_not_the_reverse(tmp_path,
                                                                              monkeypatch):
    core = tmp_path / "core"
    core.mkdir()
    (core / "a.py").write_text("x = 1\n")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    kernel_cache.mark_warm(50.0, str(core), DEFAULTS)
    assert kernel_cache.is_warm(str(core), DEFAULTS) and not kernel_cache.is_warm(str(core))
    os.remove(kernel_cache.warm_marker(str(core), DEFAULTS))
    kernel_cache.mark_warm(120.0, str(core))
    assert kernel_cache.is_warm(str(core), DEFAULTS) and kernel_cache.is_warm(str(core))


def test_a_run_that_sets_only_resolution_and_iterations_needs_the_defaults_kernels_only():
    assert warm_up.scope_for({}) == DEFAULTS
    assert warm_up.scope_for({"ParticlesPerFibre": 40, "Iterations": 5}) == DEFAULTS
    for other in ({"Method": "quasi-static"}, {"Layout": "k-NN"}, {"ConnectiveTissue": 0.1},
                  {"FibreShortening": True}, {"Iterations": 5, "TissueAlongFibres": 0.5}):
        assert warm_up.scope_for(other) == EVERY, other


def _unsettled(monkeypatch):
    """As in a new process: no scope settled yet."""
    for scope in (EVERY, DEFAULTS):
        monkeypatch.setitem(warm_up._settled, scope, False)


def test_ensure_compiled_says_so_once_and_records_the_cache_warm(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    _unsettled(monkeypatch)
    ran = []
    monkeypatch.setattr(warm_up, "compile_ahead", lambda scope: ran.append(scope) or 42.0)
    said = []
    assert warm_up.ensure_compiled(said.append)
    assert len(said) == 2 and said[0].startswith(NOTICE) and "42 s" in said[1]
    assert kernel_cache.is_warm() and ran == [EVERY]
    assert not warm_up.ensure_compiled(said.append)  # once per process
    assert not warm_up.ensure_compiled(said.append, DEFAULTS)  # every kernel covers them
    _unsettled(monkeypatch)
    assert not warm_up.ensure_compiled(said.append)  # a new process finds it warm
    assert len(said) == 2 and len(ran) == 1


def test_the_default_settings_kernels_compile_alone_then_the_others(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    _unsettled(monkeypatch)
    ran = []

    def compiling(scope):        # as a warm-up that compiles: a kernel file more
        ran.append(scope)
        folder = kernel_cache.kernel_cache_dir()
        os.makedirs(folder, exist_ok=True)
        open(os.path.join(folder, f"kernel{len(ran)}.nbc"), "w").close()
        return 42.0

    monkeypatch.setattr(warm_up, "compile_ahead", compiling)
    said = []
    assert warm_up.ensure_compiled(said.append, DEFAULTS)
    assert ran == [DEFAULTS] and said[0].startswith(NOTICE)
    assert "the default settings' kernels" in said[0]
    assert kernel_cache.is_warm(scope=DEFAULTS) and not kernel_cache.is_warm()
    _unsettled(monkeypatch)
    assert not warm_up.ensure_compiled(said.append, DEFAULTS)  # a new process: warm
    assert warm_up.ensure_compiled(said.append)  # every kernel asked for: the others too
    assert ran == [DEFAULTS, EVERY] and kernel_cache.is_warm()
    # the record of every kernel (the next cold start's estimate) counts both compiles
    assert kernel_cache.recorded_seconds(scope=DEFAULTS) == 42.0
    assert kernel_cache.recorded_seconds() == 84.0


@pytest.fixture
def warm_cache_copy(tmp_path_factory):
    """A copy of this Python's kernel cache with every kernel compiled but no warm markers: a
    run in it goes through the cold path (the notice, the warm-up) in seconds."""
    warm_up.ensure_compiled(lambda text: None)  # compiles here if this Python is cold
    base = tmp_path_factory.mktemp("kernels")
    source = kernel_cache.kernel_cache_dir()
    shutil.copytree(source, base / os.path.basename(source))
    for scope in (EVERY, DEFAULTS):
        copied = base / os.path.basename(source) / os.path.basename(
            kernel_cache.warm_marker(scope=scope))
        if copied.exists():
            copied.unlink()
    return base


def _cli(*args, cache):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    return subprocess.run([sys.executable, "-m", "muscle_mss.app.cli", *map(str, args)],
                          env=env, capture_output=True, text=True, timeout=600)


def test_cli_says_once_that_it_compiles_then_never_again(warm_cache_copy, small_scene_dir,
                                                         tmp_path):
    first = _cli("run", small_scene_dir, tmp_path / "one", "--time", "0.5", "--iterations", "5",
                 cache=warm_cache_copy)
    assert first.returncode == 0, first.stderr
    assert first.stderr.count(NOTICE) == 1
    assert "compiled the numeric kernels in" in first.stderr

    def marker(scope):
        return os.path.join(str(warm_cache_copy), os.path.relpath(
            kernel_cache.warm_marker(scope=scope), kernel_cache.base_cache_dir()))

    # a run with the default settings (the resolution and iterations aside) asked for their
    # kernels only
    assert os.path.exists(marker(DEFAULTS)) and not os.path.exists(marker(EVERY))
    second = _cli("run", small_scene_dir, tmp_path / "two", "--time", "0.5", "--iterations", "5",
                  cache=warm_cache_copy)
    assert second.returncode == 0, second.stderr
    assert NOTICE not in second.stderr
    other = _cli("run", small_scene_dir, tmp_path / "three", "--time", "0.5", "--iterations", "5",
                 "--method", "quasi-static", cache=warm_cache_copy)
    assert other.returncode == 0, other.stderr
    assert other.stderr.count(NOTICE) == 1 and os.path.exists(marker(EVERY))


def test_importing_a_filter_starts_nothing(tmp_path):
    """Taking a filter class from ``muscle_mss.filters`` imports it and nothing else: in a cold
    kernel cache it neither says it compiles nor compiles nor imports the application; the
    kernels it calls compile at their first call (the entry points, the CLI, the batch and the
    ParaView proxies, compile them first and say so)."""
    script = ("import sys\n"
              "from muscle_mss.filters import MSSCollisionSolver\n"
              "assert MSSCollisionSolver.__name__ == 'MSSCollisionSolver'\n"
              "print(sorted(m for m in sys.modules if m.startswith('muscle_mss.app')))\n")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    run = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]"
    assert NOTICE not in run.stderr
    markers = [name for _, _, files in os.walk(tmp_path) for name in files
               if name.endswith(".json")]
    assert markers == []


def test_the_defaults_come_first_then_every_method_structure_and_bone_contact():
    """The kernels of a run with the default settings (whichever method core.settings makes the
    default) compile before any other; then every method with every collision structure and
    bone contact, each of which calls kernels of its own."""
    from itertools import product

    from muscle_mss.core.settings import METHODS, STRUCTURES
    from muscle_mss.core.settings import BONE_CONTACTS
    assert warm_up.VARIANTS[:len(warm_up.DEFAULT_VARIANTS)] == warm_up.DEFAULT_VARIANTS
    assert all(set(v) == {"Iterations"} for v in warm_up.DEFAULT_VARIANTS)
    combinations = {(v.get("Method"), v.get("CollisionStructure"), v.get("BoneContact"))
                    for v in warm_up.OTHER_VARIANTS}
    assert combinations >= set(product(METHODS, STRUCTURES, BONE_CONTACTS))


def test_quiet_says_nothing_when_the_kernels_are_compiled(monkeypatch, capsys):
    """``./setup.sh`` runs the warm-up with ``--quiet``: silent when there is nothing to do."""
    asked = []
    monkeypatch.setattr(warm_up, "ensure_compiled",
                        lambda report, scope: asked.append(scope) and False)
    assert warm_up.main(["--quiet"]) == 0
    assert capsys.readouterr().err == ""
    assert warm_up.main([]) == 0
    assert "already compiled" in capsys.readouterr().err
    assert warm_up.main(["--quiet", "--defaults"]) == 0
    assert asked == [EVERY, EVERY, DEFAULTS]


def test_the_two_processes_shares_cover_every_variant_once():
    """``compile_ahead`` splits the warm-up between this process and a second one: together
    they solve every variant, the first the defaults first; the second compiles the surfaces'
    kernels (the chain without a solve) meanwhile."""
    first, second = warm_up.shares(EVERY)
    assert first[:len(warm_up.DEFAULT_VARIANTS)] == warm_up.DEFAULT_VARIANTS
    assert sorted(map(repr, first + second)) == sorted(map(repr, warm_up.VARIANTS))
    assert second and all(v not in first for v in second)
    assert warm_up.shares(DEFAULTS) == (warm_up.DEFAULT_VARIANTS, ())


def test_the_second_share_runs_the_surfaces_without_a_solve(monkeypatch):
    """The second process's own command (compiled kernels: seconds) exits 0; the surfaces
    alone run the MVC Surface Deformer and the probe without the solver."""
    from muscle_mss.filters.collision_solver import MSSCollisionSolver
    done = subprocess.run([sys.executable, "-m", "muscle_mss.app.warm_up",
                           "--second-share"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    solved, surfaces = [], []
    monkeypatch.setattr(MSSCollisionSolver, "_solve", lambda *a: solved.append(1))
    deform = warm_up.motion_run.MVCSurfaceDeformer.RequestData

    def counted(self, *args):
        surfaces.append(1)
        return deform(self, *args)

    monkeypatch.setattr(warm_up.motion_run.MVCSurfaceDeformer, "RequestData", counted)
    warm_up.warm_up((), surfaces_alone=True)
    assert surfaces and not solved


class _Helper:
    """A stand-in for the second process of ``compiling_beside``: records how it was started
    and what happened to it."""

    def __init__(self, returncode):
        self.returncode, self.terminated, self.args = returncode, False, None

    def popen(self, args, **kwargs):
        self.args = args
        return self

    def terminate(self):
        self.terminated = True

    def wait(self):
        return self.returncode


def _cold_defaults(monkeypatch, tmp_path, returncode=0):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    _unsettled(monkeypatch)
    monkeypatch.setattr(warm_up, "_can_start_itself", lambda: True)
    helper = _Helper(returncode)
    monkeypatch.setattr(warm_up.subprocess, "Popen", helper.popen)
    in_place = []
    monkeypatch.setattr(warm_up, "ensure_compiled",
                        lambda report, scope: in_place.append(scope) or True)
    return helper, in_place


def test_the_default_settings_kernels_compile_in_a_second_process_while_the_body_runs(
        tmp_path, monkeypatch):
    """A run with the default settings prepares on one core (Numba's parallel loops on one
    thread) while a second process compiles its kernels on the other; the body is left with
    them compiled and the thread count restored."""
    import numba
    helper, in_place = _cold_defaults(monkeypatch, tmp_path)
    threads = numba.get_num_threads()
    seen = []
    with warm_up.compiling_beside(print, DEFAULTS) as compiling:
        seen.append((compiling, helper.args, numba.get_num_threads()))
    assert seen == [(True, [sys.executable, "-m", "muscle_mss.app.warm_up", "--defaults",
                            "--quiet"], 1)]
    assert numba.get_num_threads() == threads and in_place == [] and not helper.terminated
    assert warm_up._settled[DEFAULTS]


def test_a_failed_second_process_leaves_the_compile_to_this_one(tmp_path, monkeypatch):
    helper, in_place = _cold_defaults(monkeypatch, tmp_path, returncode=1)
    with warm_up.compiling_beside(print, DEFAULTS):
        assert helper.args is not None
    assert in_place == [DEFAULTS]


def test_a_body_that_fails_stops_the_second_process(tmp_path, monkeypatch):
    helper, in_place = _cold_defaults(monkeypatch, tmp_path)
    with pytest.raises(ValueError):
        with warm_up.compiling_beside(print, DEFAULTS):
            raise ValueError("a scene refused")
    assert helper.terminated and in_place == []


@pytest.mark.parametrize("case", ["every kernel", "compiled", "one core"])
def test_no_second_process_for_every_kernel_compiled_kernels_or_one_core(case, tmp_path,
                                                                        monkeypatch):
    """Every kernel's warm-up takes both cores itself; compiled kernels need none; where this
    Python cannot start itself (ParaView) or has one core, it compiles before the body."""
    helper, in_place = _cold_defaults(monkeypatch, tmp_path)
    scope = EVERY if case == "every kernel" else DEFAULTS
    if case == "compiled":
        kernel_cache.mark_warm(40.0, scope=DEFAULTS)
    if case == "one core":
        monkeypatch.setattr(warm_up, "_can_start_itself", lambda: False)
    order = []
    monkeypatch.setattr(warm_up, "ensure_compiled",
                        lambda report, scope: order.append(("compiled", scope)))
    with warm_up.compiling_beside(print, scope) as compiling:
        order.append(("body", compiling))
    assert helper.args is None and order == [("compiled", scope), ("body", False)]


def test_the_background_compile_waits_for_the_demos_kernels_at_most_its_limit(tmp_path,
                                                                              monkeypatch):
    """``--after-defaults`` (./demo.sh's background compile) starts once the demo's own
    kernels are compiled, or after its limit when nobody compiles them."""
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert not warm_up.wait_for_defaults(limit=0.2, poll=0.05)
    kernel_cache.mark_warm(40.0, scope=DEFAULTS)
    assert warm_up.wait_for_defaults(limit=0.0)
