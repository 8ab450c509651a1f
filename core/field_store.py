"""Bones' signed distance fields kept on disk between runs.

Sampling a bone's field (:func:`muscle_mss.core.bone_distance.bone_distance_field`) takes 2-4 s
per bone of the demo thigh, paid at the first time point of every ``muscle-mss run`` and every
ParaView session although the bones of a scene rarely change (issue 15). A field is stored per
bone surface, keyed by its triangles and its points bitwise, as an ``.npz`` file in a folder
keyed by the sampler's source (``bone_distance.py``, which holds the sampling defaults) and the
runtime (:func:`~muscle_mss.core.kernel_cache.runtime_tag`), so that a changed sampler or another
Numba or NumPy never reads another's values: a loaded field is bitwise the one sampling would
give.

The folder is ``bone-fields-<digest>-<runtime>`` under the package's cache folder
(:func:`~muscle_mss.core.kernel_cache.base_cache_dir`). The environment variable
``MUSCLE_MSS_BONE_FIELDS`` overrides it: a folder to use instead, or ``off`` to neither read nor
write (the test suite sets ``off`` so that its sampling counts are exact). A file that cannot be
written (read-only folder) is skipped; one that cannot be read is sampled again and rewritten.
At most :data:`MAX_FILES` fields are kept, the least recently used dropped.
"""
from __future__ import annotations

import hashlib
import os
import tempfile
import zipfile

import numpy as np

from .bone_distance import BoneDistanceField
from .kernel_cache import base_cache_dir, runtime_tag

ENVIRONMENT = "MUSCLE_MSS_BONE_FIELDS"
MAX_FILES = 64
_ARRAYS = ("origin", "dims", "coarse", "brick_index", "bricks")


def store_folder() -> str | None:
    """The folder fields are kept in, or None when the store is off."""
    chosen = os.environ.get(ENVIRONMENT, "")
    if chosen.strip().lower() == "off":
        return None
    if chosen:
        return chosen
    source = os.path.join(os.path.dirname(os.path.abspath(__file__)), "bone_distance.py")
    with open(source, "rb") as f:
        digest = hashlib.sha1(f.read()).hexdigest()[:16]
    return os.path.join(base_cache_dir(), f"bone-fields-{digest}-{runtime_tag()}")


def load(key: str) -> BoneDistanceField | None:
    """The stored field of surface ``key`` (:func:`~muscle_mss.core.bone_distance.
    surface_digest`), or None when the store is off,
    holds none, or its file cannot be read."""
    folder = store_folder()
    if folder is None:
        return None
    path = os.path.join(folder, key + ".npz")
    try:
        with np.load(path) as stored:
            field = BoneDistanceField(spacing=float(stored["spacing"]),
                                      **{name: stored[name] for name in _ARRAYS})
        os.utime(path)                               # recently used
        return field
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
        return None


def save(key: str, field: BoneDistanceField) -> None:
    """Store ``field`` as surface ``key``'s (written whole or not at all); nothing when the store
    is off or its folder cannot be written."""
    folder = store_folder()
    if folder is None:
        return
    try:
        os.makedirs(folder, exist_ok=True)
        handle, staged = tempfile.mkstemp(dir=folder, prefix=".writing-", suffix=".npz")
    except OSError:
        return
    try:
        with os.fdopen(handle, "wb") as f:
            np.savez(f, spacing=field.spacing, **{name: getattr(field, name) for name in _ARRAYS})
        os.replace(staged, os.path.join(folder, key + ".npz"))
        stored = sorted((entry.stat().st_mtime, entry.path) for entry in os.scandir(folder)
                        if entry.name.endswith(".npz") and not entry.name.startswith("."))
        for _, path in stored[:max(0, len(stored) - MAX_FILES)]:
            os.remove(path)
    except OSError:
        if os.path.exists(staged):
            os.remove(staged)
