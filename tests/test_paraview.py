"""Real ParaView 5.11 (Debian's pvpython, pvbatch, paraview under xvfb-run), headless.

Each test starts ParaView's own executables with this checkout on PYTHONPATH through
``plugin/shim``, so these are the same interpreters, readers and plugin loader users run.
"""
import pytest

from paraview_support import run_script

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
