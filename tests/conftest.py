"""Shared fixtures: the small demo scene in memory and on disk (the tests' default data).

The bones' distance fields and the muscles' mean value coordinates are not read from or written
to the user's disk stores (:mod:`muscle_mss.core.bones.field_store`,
``muscle_mss.filters.mvc_surface_deformer.WEIGHTS_STORE``, the placement verdicts of
``muscle_mss.filters.check_cache``) during the tests, nor by the ParaView
processes they start: every run computes them, so the counts the tests assert are exact. Nor is
the frame cache (``muscle_mss.filters.frame_cache``): a test that wants it names its folder."""
import os

import pytest

os.environ["MUSCLE_MSS_BONE_FIELDS"] = "off"
os.environ["MUSCLE_MSS_MVC_WEIGHTS"] = "off"
os.environ["MUSCLE_MSS_PLACEMENT_CHECKS"] = "off"
os.environ["MUSCLE_MSS_FRAME_CACHE"] = "off"
os.environ["MUSCLE_MSS_JOBS"] = "1"      # whole motions in one process; tests/test_jobs.py: --jobs


@pytest.fixture(scope="session")
def small_scene():
    """The small demo scene (core ``Scene``); do not modify it, copy what you change."""
    from muscle_mss.core.demo.scene import demo_scene
    return demo_scene("small")


@pytest.fixture(scope="session")
def small_scene_dir(tmp_path_factory, small_scene):
    """The small demo scene written as a scene folder."""
    from muscle_mss.filters.scene_io import write_scene
    folder = tmp_path_factory.mktemp("small_scene")
    write_scene(small_scene, folder)
    return folder


@pytest.fixture(scope="session", autouse=True)
def compiled_kernels():
    """This Python's kernels compiled before the first test, outside any test's timeout:
    ./test.sh's ./setup.sh has compiled them into the user's kernel cache, which the tests and
    the processes they start load them from; a pytest run without it compiles them here, in a
    process of its own (the warm-up's filter chain leaves nothing behind in this one)."""
    import subprocess
    import sys

    from muscle_mss.core import kernel_cache
    if not kernel_cache.is_warm():
        subprocess.run([sys.executable, "-m", "muscle_mss.app.warm_up", "--quiet"],
                       check=True)
