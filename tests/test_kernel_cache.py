"""The Numba cache folder follows the core's sources and the Python, Numba and NumPy versions
(core.kernel_cache)."""
import os

import numba

from muscle_mss.core import kernel_cache


def test_any_change_to_a_source_gives_a_new_cache_folder(tmp_path):
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "b.py").write_text("y = 2\n")
    (tmp_path / "notes.txt").write_text("not a source")
    first = kernel_cache.kernel_cache_dir(str(tmp_path / "cache"), str(tmp_path))
    assert first.startswith(str(tmp_path / "cache"))
    (tmp_path / "notes.txt").write_text("changed, still not a source")
    assert kernel_cache.kernel_cache_dir(str(tmp_path / "cache"), str(tmp_path)) == first
    (tmp_path / "b.py").write_text("y = 3\n")  # a called module changed
    assert kernel_cache.kernel_cache_dir(str(tmp_path / "cache"), str(tmp_path)) != first


def test_numba_uses_it_under_numba_cache_dir():
    assert numba.config.CACHE_DIR == kernel_cache.kernel_cache_dir()
    base = os.environ.get("NUMBA_CACHE_DIR")
    if base:
        assert numba.config.CACHE_DIR.startswith(base)


def test_the_folder_names_the_python_numba_and_numpy_versions(tmp_path):
    import sys

    import numpy
    name = os.path.basename(kernel_cache.kernel_cache_dir(str(tmp_path), str(tmp_path)))
    assert name.startswith("numba-") and name.endswith(kernel_cache.runtime_tag())
    tag = kernel_cache.runtime_tag()
    assert f"numba{numba.__version__}" in tag and f"numpy{numpy.__version__}" in tag
    assert f"{sys.version_info.major}{sys.version_info.minor}" in tag


REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PYTHONS = {"venv": os.path.join(REPO, ".venv", "bin", "python"), "debian": "/usr/bin/python3"}
SMALL_KERNEL = ("import numpy as np\n"
                "from muscle_mss.core import kernel_cache\n"
                "from muscle_mss.core.volume import signed_volume\n"
                "p = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])\n"
                "t = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])\n"
                "assert abs(signed_volume(p, t) - 1 / 6) < 1e-12\n"
                "print(kernel_cache.kernel_cache_dir())\n")


def _run_kernel(which, base):
    """Run a small cached kernel in the Python ``which`` with cache base ``base``; return its
    cache folder."""
    import subprocess
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONHOME", "VIRTUAL_ENV")}
    env.update(NUMBA_CACHE_DIR=str(base), PYTHONPATH=os.path.join(REPO, "plugin", "shim"))
    proc = subprocess.run([PYTHONS[which], "-c", SMALL_KERNEL], env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.strip().splitlines()[-1]


def _files(folder):
    """Every file under ``folder`` with its modification time and contents."""
    found = {}
    for root, _, names in os.walk(folder):
        for name in names:
            path = os.path.join(root, name)
            with open(path, "rb") as f:
                found[os.path.relpath(path, folder)] = (os.stat(path).st_mtime_ns, f.read())
    return found


def test_two_pythons_keep_their_own_kernels(tmp_path):
    """The venv and Debian's Python (another numba) each compile into a folder of their own;
    neither rewrites the other's, and each reuses its own on the next run."""
    import subprocess
    import pytest
    for which, python in PYTHONS.items():
        if not os.path.exists(python) or subprocess.run(
                [python, "-c", "import numba, scipy"], capture_output=True).returncode:
            pytest.skip(f"no {which} Python with numba at {python}")
    venv = _run_kernel("venv", tmp_path)
    venv_files = _files(venv)
    assert any(name.endswith(".nbi") for name in venv_files)
    assert any(name.endswith(".nbc") for name in venv_files)
    debian = _run_kernel("debian", tmp_path)
    assert debian != venv and os.path.dirname(debian) == os.path.dirname(venv) == str(tmp_path)
    debian_files = _files(debian)
    assert any(name.endswith(".nbc") for name in debian_files)
    assert _files(venv) == venv_files  # Debian's numba left the venv's kernels alone
    assert _run_kernel("debian", tmp_path) == debian
    assert _files(debian) == debian_files  # its own kernels reused, nothing recompiled
    assert _run_kernel("venv", tmp_path) == venv
    assert _files(venv) == venv_files


def test_numba_keeps_the_folder_when_it_rereads_the_environment(monkeypatch):
    """Numba re-reads its configuration whenever the environment changed (pictures set a VTK
    variable in the CLI); the cache folder must survive that."""
    monkeypatch.setenv("MUSCLE_MSS_TEST_ENVIRONMENT_CHANGED", "1")
    numba.core.config.reload_config()
    assert numba.config.CACHE_DIR == kernel_cache.kernel_cache_dir()


def test_a_child_process_inherits_the_base_not_a_nested_folder(monkeypatch):
    resolved = kernel_cache.kernel_cache_dir()
    monkeypatch.setenv("NUMBA_CACHE_DIR", resolved)
    assert kernel_cache.base_cache_dir() == os.path.dirname(resolved)
    assert kernel_cache.kernel_cache_dir() == resolved


def test_parallel_kernels_run_on_tbb_where_the_tbb_package_is_installed():
    """The pip package tbb (a dependency of the venv) puts its library in ``<venv>/lib``, off
    the loader's path; importing muscle_mss.core loads it, so that Numba takes its TBB layer
    (faster than OpenMP's sleeping threads, README "Speed"). Debian's Numba has none."""
    import importlib.metadata
    import numpy as np
    import pytest
    try:
        importlib.metadata.version("tbb")
    except importlib.metadata.PackageNotFoundError:
        pytest.skip("no tbb package for this Python (Debian's: OpenMP)")
    from muscle_mss.core.mvc import mvc_deform
    np.testing.assert_array_equal(mvc_deform(np.full((4, 3), 0.5), np.ones((3, 3))),
                                  np.full((4, 3), 1.5))
    assert numba.threading_layer() == "tbb"
