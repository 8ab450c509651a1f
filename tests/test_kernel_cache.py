"""The Numba cache folder follows the core's sources (core.kernel_cache)."""
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
