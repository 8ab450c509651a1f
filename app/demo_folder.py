"""The demo scenes (the thigh's walk, the elbow's flexion) and the scene folder ``muscle-mss
demo`` writes, kept apart from a scene the user put or edited there: the demo records the
SHA-256 of each file it wrote, and a later demo replaces that folder silently only while it
holds just those files as written."""
from __future__ import annotations

import hashlib
import os
import sys

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.scene import Scene


DEMO_SCENE_RECORD = ".muscle-mss-demo-scene"
"""In the scene folder ``muscle-mss demo`` writes: the SHA-256 and relative path of each file
it wrote there, a line each, so that a later demo replaces that folder silently only while it
holds just those files as written (not a scene the user edited or put there)."""


def _sha256(path: str) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _demo_record(folder: str) -> dict:
    """The files ``folder``'s :data:`DEMO_SCENE_RECORD` lists: relative path -> SHA-256."""
    try:
        with open(os.path.join(folder, DEMO_SCENE_RECORD)) as f:
            return dict(reversed(line.rstrip("\n").split("  ", 1)) for line in f
                        if "  " in line)
    except OSError:
        return {}


def demo_scene_changes(folder: str) -> list:
    """What the scene folder ``folder`` holds that the demo did not write as it is there, a
    sentence each: a file its record (:data:`DEMO_SCENE_RECORD`) does not list, one changed
    since, a link; [] for a folder holding only the demo's files as written (or none)."""
    record, changes = _demo_record(folder), []
    for root, dirs, files in os.walk(folder):
        links = sorted(d for d in dirs if os.path.islink(os.path.join(root, d)))
        for name in sorted(files) + links:
            path = os.path.join(root, name)
            relative = os.path.relpath(path, folder).replace(os.sep, "/")
            if relative == DEMO_SCENE_RECORD:
                continue
            if os.path.islink(path):
                changes.append(f"{relative}: a link the demo did not write")
            elif relative not in record:
                changes.append(f"{relative}: not written by the demo" + (
                    "" if record else f" (no record {DEMO_SCENE_RECORD} of the demo's files)"))
            elif _sha256(path) != record[relative]:
                changes.append(f"{relative}: changed since the demo wrote it")
        dirs.sort()
    return changes


def check_demo_scene(folder: str, overwrite: bool) -> None:
    """Refuse to write the demo scene into ``folder`` when something there is not a file the demo
    wrote as it wrote it (:func:`demo_scene_changes`: the user's scene, or the demo's edited)
    unless ``overwrite`` (then a note says so: the demo's files are written over, others
    stay), and when ``folder`` is not a folder (never removed)."""
    if os.path.islink(folder) or (os.path.lexists(folder) and not os.path.isdir(folder)):
        kind = "a link" if os.path.islink(folder) else "a file"
        raise MuscleMSSError(f"{folder} is {kind}, where the demo writes its scene folder; "
                             "move it away or choose another output folder")
    changes = demo_scene_changes(folder)
    more = f", and {len(changes) - 1} more" if len(changes) > 1 else ""
    if changes and overwrite:
        print(f"note: writing the demo scene over {folder} (--overwrite), which held a scene "
              f"the demo did not write ({changes[0]}{more})", file=sys.stderr)
    elif changes:
        raise MuscleMSSError(f"{folder} holds a scene the demo did not write ({changes[0]}"
                             f"{more}); the demo would write its scene over it: pass --overwrite "
                             "to replace it, or choose another output folder")


def record_demo_scene(folder: str, files) -> None:
    """Write ``folder``'s :data:`DEMO_SCENE_RECORD` of ``files`` (paths in it), atomically."""
    lines = "".join(f"{_sha256(path)}  {os.path.relpath(path, folder).replace(os.sep, '/')}\n"
                    for path in files)
    temporary = os.path.join(folder, f"{DEMO_SCENE_RECORD}.{os.getpid()}.tmp")
    try:
        with open(temporary, "w") as f:
            f.write(lines)
        os.replace(temporary, os.path.join(folder, DEMO_SCENE_RECORD))
    except OSError as err:
        raise MuscleMSSError(f"cannot write {os.path.join(folder, DEMO_SCENE_RECORD)}: "
                             f"{err.strerror or err}") from None


REGION_THIGH, REGION_ARM = "thigh", "arm"
DEMO_REGIONS = (REGION_THIGH, REGION_ARM)
"""The demo scenes: the thigh's walk (the default) and the elbow's flexion."""
DEMO_SIZES = ("full", "small")
"""The demo scene's sizes (``demo_scene(size)``): the full scene (the default) and a quick one."""


def demo_region_scene(region: str, size: str) -> Scene:
    """The demo scene of ``region`` (one of :data:`DEMO_REGIONS`) at ``size``."""
    if region == REGION_ARM:
        from muscle_mss.core.demo.arm import demo_arm_scene
        return demo_arm_scene(size)
    from muscle_mss.core.demo.scene import demo_scene
    return demo_scene(size)


def demo_region_motion(region: str):
    """The motion of the demo scene of ``region`` (what :func:`demo_region_scene` holds), without
    building the scene."""
    if region == REGION_ARM:
        from muscle_mss.core.demo.arm import flexion_motion
        return flexion_motion()
    from muscle_mss.core.demo.scene import gait_motion
    return gait_motion()


def write_demo_scene(out: str, size: str, region: str = REGION_THIGH) -> Scene:
    """Write the demo scene folder ``out`` of ``region`` and its ``preview.png``; return the
    scene as read back and checked from the files."""
    from .pictures import scene_preview
    from muscle_mss.filters.scene_io import load_scene, write_scene
    write_scene(demo_region_scene(region, size), out)
    scene = load_scene(out)
    scene_preview(scene, os.path.join(out, "preview.png"))
    return scene
