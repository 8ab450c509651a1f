"""Shared fixtures: the small demo scene in memory and on disk (the tests' default data)."""
import pytest


@pytest.fixture(scope="session")
def small_scene():
    """The small demo scene (core ``Scene``); do not modify it, copy what you change."""
    from muscle_mss.core.demo_scene import demo_scene
    return demo_scene("small")


@pytest.fixture(scope="session")
def small_scene_dir(tmp_path_factory, small_scene):
    """The small demo scene written as a scene folder."""
    from muscle_mss.filters.scene_io import write_scene
    folder = tmp_path_factory.mktemp("small_scene")
    write_scene(small_scene, folder)
    return folder
