"""Shared fixtures: the small demo scene in memory and on disk (the tests' default data).

The bones' distance fields are not read from or written to the user's disk store
(:mod:`muscle_mss.core.field_store`) during the tests, nor by the ParaView processes they start:
every run samples them, so the sampling counts the tests assert are exact."""
import os

import pytest

os.environ["MUSCLE_MSS_BONE_FIELDS"] = "off"


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
