"""Arrays kept on disk between runs, keyed by content: what the first time point of every
``muscle-mss run`` and every ParaView session would otherwise compute again from inputs that
rarely change.

A :class:`DiskStore` keeps one ``.npz`` file of named arrays per key in a folder named after the
store, a digest of the source files that compute what it holds and the runtime
(:func:`~muscle_mss.core.kernel_cache.runtime_tag`), under the package's cache folder
(:func:`~muscle_mss.core.kernel_cache.base_cache_dir`): changed code or another Numba or NumPy
never reads another's values, so what is loaded is bitwise what computing would give. Keys are
content digests made by the caller. An environment variable per store names a folder to use
instead, or ``off`` to neither read nor write (the test suite turns the stores off so that its
computation counts are exact). A file that cannot be written (read-only folder) is skipped; one
that cannot be read counts as absent and is computed and written again. At most ``max_files``
files are kept, the least recently used dropped.
"""
from __future__ import annotations

import functools
import hashlib
import os
import tempfile
import zipfile
from dataclasses import dataclass

import numpy as np

from .kernel_cache import base_cache_dir, runtime_tag


@dataclass(frozen=True)
class DiskStore:
    """``name``: the folder's prefix; ``environment``: the variable that overrides the folder
    (or turns the store ``off``); ``sources``: the files (paths) whose content decides the
    values stored; ``max_files``: files kept at most."""

    name: str
    environment: str
    sources: tuple
    max_files: int

    def folder(self) -> str | None:
        """The folder the store keeps its files in, or None when it is off."""
        chosen = os.environ.get(self.environment, "")
        if chosen.strip().lower() == "off":
            return None
        if chosen:
            return chosen
        return os.path.join(base_cache_dir(),
                            f"{self.name}-{_sources_digest(self.sources)}-{runtime_tag()}")

    def load(self, key: str, names) -> dict | None:
        """The arrays ``names`` stored under ``key``, or None when the store is off, holds no
        such file or cannot read it whole."""
        folder = self.folder()
        if folder is None:
            return None
        path = os.path.join(folder, key + ".npz")
        try:
            with np.load(path) as stored:
                arrays = {name: stored[name] for name in names}
            os.utime(path)                               # recently used
            return arrays
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
            return None

    def save(self, key: str, arrays: dict) -> None:
        """Store ``arrays`` (name → array) under ``key``, written whole or not at all; nothing
        when the store is off or its folder cannot be written."""
        folder = self.folder()
        if folder is None:
            return
        try:
            os.makedirs(folder, exist_ok=True)
            handle, staged = tempfile.mkstemp(dir=folder, prefix=".writing-", suffix=".npz")
        except OSError:
            return
        try:
            with os.fdopen(handle, "wb") as f:
                np.savez(f, **arrays)
            os.replace(staged, os.path.join(folder, key + ".npz"))
            kept = sorted((entry.stat().st_mtime, entry.path) for entry in os.scandir(folder)
                          if entry.name.endswith(".npz") and not entry.name.startswith("."))
            for _, path in kept[:max(0, len(kept) - self.max_files)]:
                os.remove(path)
        except OSError:
            if os.path.exists(staged):
                os.remove(staged)


@functools.lru_cache(maxsize=None)
def _sources_digest(sources: tuple) -> str:
    """A digest of the files ``sources``, read once per process (a store is asked for its
    folder at every load and save: one per muscle and bone)."""
    digest = hashlib.sha1()
    for source in sources:
        with open(source, "rb") as f:
            digest.update(f.read())
    return digest.hexdigest()[:16]


def array_digest(*arrays) -> str:
    """A content key for arrays: their dtypes, shapes and bytes."""
    digest = hashlib.blake2b(digest_size=16)
    for array in arrays:
        array = np.ascontiguousarray(array)
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()
