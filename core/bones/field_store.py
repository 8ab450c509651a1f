"""Bones' signed distance fields kept on disk between runs.

Sampling a bone's field (:func:`muscle_mss.core.bones.field_sampling.bone_distance_field`) takes
2-4 s per bone of the demo thigh, paid at the first time point of every ``muscle-mss run`` and
every ParaView session although the bones of a scene rarely change. A field is stored
per bone surface, keyed by its triangles and its points bitwise, in a
:class:`~muscle_mss.core.disk_store.DiskStore` keyed by the sampler's source
(:data:`SAMPLER_SOURCES`: the field's layout, the sampling and its defaults, the exact distance)
and the runtime, so that a changed sampler or another Numba or NumPy never reads another's
values: a loaded field is bitwise the one sampling would give.

The folder is ``bone-fields-<digest>-<runtime>`` under the package's cache folder
(:func:`~muscle_mss.core.kernel_cache.base_cache_dir`). The environment variable
``MUSCLE_MSS_BONE_FIELDS`` overrides it: a folder to use instead, or ``off`` to neither read nor
write (the test suite sets ``off`` so that its sampling counts are exact). A file that cannot be
written (read-only folder) is skipped; one that cannot be read is sampled again and rewritten.
At most :data:`MAX_FILES` fields are kept, the least recently used dropped.
"""
from __future__ import annotations

import os

from .distance import BoneDistanceField
from ..disk_store import DiskStore

ENVIRONMENT = "MUSCLE_MSS_BONE_FIELDS"
MAX_FILES = 64
_ARRAYS = ("origin", "dims", "coarse", "brick_index", "bricks")
SAMPLER_SOURCES = tuple(os.path.join(os.path.dirname(os.path.abspath(__file__)), name)
                        for name in ("distance.py", "field_sampling.py", "triangle_distance.py"))
"""The source files whose bytes key the store: a field sampled by other code is not read."""
STORE = DiskStore("bone-fields", ENVIRONMENT, SAMPLER_SOURCES, MAX_FILES)


def store_folder() -> str | None:
    """The folder fields are kept in, or None when the store is off."""
    return STORE.folder()


def load(key: str) -> BoneDistanceField | None:
    """The stored field of surface ``key`` (:func:`~muscle_mss.core.bones.triangle_distance.
    surface_digest`), or None when the store is off, holds none, or its file cannot be read."""
    stored = STORE.load(key, ("spacing",) + _ARRAYS)
    if stored is None:
        return None
    return BoneDistanceField(spacing=float(stored.pop("spacing")), **stored)


def save(key: str, field: BoneDistanceField) -> None:
    """Store ``field`` as surface ``key``'s (written whole or not at all); nothing when the store
    is off or its folder cannot be written."""
    STORE.save(key, {"spacing": field.spacing, **{name: getattr(field, name)
                                                   for name in _ARRAYS}})
