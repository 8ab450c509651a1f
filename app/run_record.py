"""What an output folder remembers of the run that wrote it, so that the same run into it again
resumes or completes it instead of being refused (``muscle-mss run SCENE OUT``).

A run writes ``OUT/.muscle-mss-run.json`` (listed in the folder's manifest, so that
``--overwrite`` removes it) before it solves: a digest of the scene's files, every run option
with its effective value (defaults included), what it writes and how, the time asked
(``--time``) and the numerics' version (:func:`~muscle_mss.filters.frame_cache.numerics_version`);
then again with ``finished`` once its last file is written. A later run with the same record
(:func:`differences` empty) into the folder completes it: nothing to do when it finished and
every file it wrote is there, else it is run again into the folder, its frames coming back from
the frame cache. Another record is refused without ``--overwrite``, naming what differs.
"""
from __future__ import annotations

import json
import os

from muscle_mss.core.errors import MuscleMSSError

from . import output_folder as folder
from muscle_mss.filters.frame_cache import numerics_version, scene_digest
from .run_options import _shown, run_properties

RECORD_FILE = ".muscle-mss-run.json"


def run_record(scene_folder, settings: dict, writing, time=None) -> dict:
    """The record of a run of ``scene_folder`` with the filter ``settings`` (the options given,
    :func:`~.run_options.settings_from`), ``writing`` (:class:`~.run_output.Writing`) and
    ``time`` (``--time``, or None: the whole motion)."""
    options = {prop.option.flag: _shown(prop, settings.get(prop.name, prop.default))
               for prop in run_properties()}
    return {"scene": os.path.abspath(str(scene_folder)), "scene_digest": scene_digest(scene_folder),
            "options": options, "write": list(writing.series), "compressor": writing.compressor,
            "time": time, "numerics": numerics_version(), "finished": False}


def read_record(out: str) -> dict | None:
    """The record in ``out``, or None (none, or not readable as one)."""
    try:
        with open(os.path.join(out, RECORD_FILE)) as f:
            record = json.load(f)
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def write_record(out: str, record: dict) -> None:
    """Write ``record`` into ``out`` (listed in its manifest first), atomically."""
    folder.claim(out, RECORD_FILE)
    path = os.path.join(out, RECORD_FILE)
    staged = f"{path}.{os.getpid()}.tmp"
    try:
        with open(staged, "w") as f:
            json.dump(record, f, indent=1, sort_keys=True)
        os.replace(staged, path)
    except OSError as err:
        raise MuscleMSSError(f"cannot write {path}: {err.strerror or err}") from None


def differences(earlier: dict, now: dict) -> list:
    """What differs between the record ``earlier`` (in the folder) and ``now`` (this run), one
    phrase each, e.g. ``--iterations 60 there, 30 now``."""
    found = []
    if earlier.get("scene_digest") != now["scene_digest"]:
        found.append(f"the scene: {earlier.get('scene')} there, {now['scene']} now, and their "
                     "files differ" if earlier.get("scene") != now["scene"]
                     else f"the scene {now['scene']}: its files changed since")
    there = earlier.get("options", {})
    for flag, value in now["options"].items():
        if there.get(flag) != value:
            found.append(f"{flag} {there.get(flag, '(not recorded)')} there, {value} now")
    for key, flag in (("write", "--write"), ("compressor", "--compressor")):
        if earlier.get(key) != now[key]:
            shown = lambda v: ",".join(v) if isinstance(v, list) else v  # noqa: E731
            found.append(f"{flag} {shown(earlier.get(key))} there, {shown(now[key])} now")
    if earlier.get("time") != now["time"]:
        shown = lambda t: "the whole motion" if t is None else f"--time {t:g}"  # noqa: E731
        found.append(f"{shown(earlier.get('time'))} there, {shown(now['time'])} now")
    if earlier.get("numerics") != now["numerics"]:
        found.append("muscle-mss's numerics (its version or the sources of core/ and "
                     "filters/) changed since")
    return found


def is_complete(out: str, record: dict) -> bool:
    """Whether ``record`` says its run finished and every file it wrote is still in ``out``."""
    listed = folder.listed_files(out)
    return bool(record.get("finished")) and bool(listed) and all(
        os.path.isfile(os.path.join(out, p)) for p in listed)
