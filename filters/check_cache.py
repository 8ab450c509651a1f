"""Checks of inputs that do not change between time points, run once per input content.

The Volume-Error Probe checks every rest surface it measures against (closed, manifold,
outward) at every time point, although the rest surfaces are the scene's and never change:
:func:`rest_surface_problems` remembers the answer per surface content (a digest of its points
and triangles), so a time slider or a motion run checks each rest surface once.

The Spring Builder's placement rules (fibres inside their muscle, muscles outside the bones
and each other at rest: winding numbers against every bone and muscle, 3 s on one core for the
demo thigh) give the same verdict for the same scene in every run, ParaView session and worker
process: :func:`placement_verdict` keeps it on disk (:data:`PLACEMENT_STORE`), keyed by the
scene's content bitwise and the rules' sources.
"""
import dataclasses
import hashlib
import os
from collections import OrderedDict

import numpy as np

from muscle_mss.core import attachments, fibre_direction, mesh_checks, scene, validation, volume
from muscle_mss.core.bones import triangle_distance, weights
from muscle_mss.core.disk_store import DiskStore
from muscle_mss.core.mesh_checks import surface_problems

CACHE_ENTRIES = 256         # surfaces remembered (least recently used dropped)

#: Since :func:`clear_check_cache`: ``checked`` (surfaces checked), ``reused`` (answers reused).
check_counts = {"checked": 0, "reused": 0}
_answers = OrderedDict()    # digest of (points, triangles) -> list of problem sentences


def clear_check_cache():
    """Forget every remembered answer and zero :data:`check_counts`."""
    _answers.clear()
    for name in check_counts:
        check_counts[name] = 0


def rest_surface_problems(points, triangles) -> list:
    """:func:`muscle_mss.core.mesh_checks.surface_problems` of ``points`` (n, 3) mm and
    ``triangles`` (m, 3), remembered per content: the same arrays (bitwise) get the same list
    without being checked again."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    digest = hashlib.blake2b(digest_size=16)
    for array in (points, triangles):
        digest.update(np.asarray(array.shape, dtype=np.int64).tobytes())
        digest.update(array.tobytes())
    key = digest.digest()
    if key in _answers:
        _answers.move_to_end(key)
        check_counts["reused"] += 1
        return list(_answers[key])
    problems = surface_problems(points, triangles)
    check_counts["checked"] += 1
    _answers[key] = list(problems)
    while len(_answers) > CACHE_ENTRIES:
        _answers.popitem(last=False)
    return problems


#: The placement verdicts of scenes, kept on disk between runs, sessions and worker processes
#: (``MUSCLE_MSS_PLACEMENT_CHECKS``: another folder, or ``off``), keyed by the sources of the
#: rules (a changed rule never reads an old verdict) and the runtime.
PLACEMENT_STORE = DiskStore(
    "placement-checks", "MUSCLE_MSS_PLACEMENT_CHECKS",
    tuple(os.path.abspath(m.__file__) for m in (validation, attachments, volume, mesh_checks,
                                                fibre_direction, scene, weights,
                                                triangle_distance)),
    max_files=64)
#: How each placement verdict was obtained, over this process: "checked" or "loaded".
verdict_counts = {"checked": 0, "loaded": 0}
_VERDICT = ("problems", "warnings")


def scene_content_digest(checked: scene.Scene) -> str:
    """A digest of everything the placement rules read of ``checked``: each muscle, fibre set
    and bone by name, in order, with every field (arrays bitwise, dtype and shape; names)."""
    digest = hashlib.blake2b(digest_size=16)
    for part in ("muscles", "fibres", "bones"):
        for name, item in getattr(checked, part).items():
            digest.update(f"{part}\0{name}\0".encode())
            for f in dataclasses.fields(item):
                value = getattr(item, f.name)
                if isinstance(value, np.ndarray):
                    value = np.ascontiguousarray(value)
                    digest.update(f"{f.name}\0{value.dtype.str}{value.shape}\0".encode())
                    digest.update(value.tobytes())
                else:
                    digest.update(f"{f.name}\0{value!r}\0".encode())
    return digest.hexdigest()


def placement_verdict(checked: scene.Scene) -> tuple:
    """``(problems, warnings)``: :func:`~muscle_mss.core.validation.placement_problems` of the
    scene ``checked`` and, when it has none,
    :func:`~muscle_mss.core.validation.placement_warnings` (lists of sentences), read from
    :data:`PLACEMENT_STORE` when a run checked the same content before, else checked and
    stored."""
    key = scene_content_digest(checked)
    stored = PLACEMENT_STORE.load(key, _VERDICT)
    if stored is not None:
        verdict_counts["loaded"] += 1
        return tuple([str(text) for text in stored[name]] for name in _VERDICT)
    problems = validation.placement_problems(checked)
    warnings = [] if problems else validation.placement_warnings(checked)
    verdict_counts["checked"] += 1
    PLACEMENT_STORE.save(key, {name: np.array(texts, dtype=str)
                               for name, texts in zip(_VERDICT, (problems, warnings))})
    return problems, warnings
