"""The frame cache: solved frames kept on disk, keyed by everything that determines them
(DESIGN §6 "Frame cache").

A frame (what the MSS Collision Solver computes at one time) is a pure function of the scene,
the properties of the solver and of the filters before it, and the time, so it is stored under a
digest of exactly those and of the numerics' version, and any run that asks for the same frame
loads it instead of solving it again (``muscle-mss run`` / ``demo`` / ``study``, the batch, a
resumed run, the solver in ParaView through its ``FrameCache`` property:
:data:`FRAME_CACHE_PROPERTY`). Its deformed surfaces (what the MVC Surface Deformer computes of
it: :class:`~muscle_mss.filters.pipeline_frames.SurfaceFrames`) are kept beside it, keyed by the same and the deformer's
properties; the Volume-Error Probe, which has no property, measures every frame.

* **Key** (:func:`frame_key`): the cache format; the package version and a digest of the
  ``.py`` files of ``core/`` and ``filters/`` (the numerics); a digest of the bytes of every
  scene file the run reads (:func:`scene_digest`); every property of the Fibre Resampler, the
  Spring Builder, the Rigid Pose Transform and the solver (and for the surfaces, the MVC
  Surface Deformer) with its effective value, defaults included, but ``FrameCache``
  (:func:`filter_properties`); the time (its exact float). The
  same scene and properties give the same key in ``muscle-mss run`` and in ParaView.
  Not the Python, Numba or NumPy version: the venv and ParaView's Python share frames (their
  results agree to rounding, not bitwise); each entry records the runtime that solved it.
* **Entry** (one file ``<key digest>.frame``): a magic line, the length of a JSON header, the
  header (the full key, the SHA-256 and length of the payload, the solver result's scalars and
  class, the runtime), then the payload: the result's arrays as an uncompressed ``.npz``. An
  entry is loaded only when its magic, its key (compared whole, not only its digest), its
  length and its checksum are right; else it is reported, removed and the frame solved again.
* **Writes** go to a temporary file in the cache folder, are flushed to disk and renamed over
  the entry (``os.replace``): a reader sees no entry or a whole one, and two processes writing
  the same frame both write the same bytes, the last rename winning.
* **Bound**: the folder is kept under :data:`DEFAULT_BOUND` bytes (or
  :data:`BOUND_ENVIRONMENT`'s), the least recently used entries (loading touches an entry)
  removed after each write.
* **Where**: ``--cache DIR`` or ``--cache off`` (nothing read or written), else the
  environment variable :data:`ENVIRONMENT` (a folder or ``off``; the test suite turns it off),
  else ``$XDG_CACHE_HOME/muscle-mss/frames`` (``~/.cache/muscle-mss/frames``). The solver's
  ``FrameCache`` property: a folder, ``off``, or empty: the application's choice (in ParaView
  the one above without ``--cache``; in a plain VTK pipeline none, ``muscle-mss run`` gives
  its solver its ``--cache``).

Not cached: a solve whose answer depends on more than its key (the solver's
``history_dependence``: a warm start from the frame solved before, a time budget's clock).
Nothing here imports VTK.
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import struct
import sys
import tempfile
import time as wallclock
import zipfile

import numpy as np

from muscle_mss.core.properties import Property

FORMAT = 1
"""The entry format and key layout; a change starts new keys."""
MAGIC = b"muscle-mss frame\n"
SUFFIX = ".frame"
ENVIRONMENT = "MUSCLE_MSS_FRAME_CACHE"
BOUND_ENVIRONMENT = "MUSCLE_MSS_FRAME_CACHE_BOUND"
DEFAULT_BOUND = 2 * 1024 ** 3
"""Bytes the cache folder holds at most (2 GiB: the demo thigh's walk at the defaults is 21
solved frames of 0.8 MiB and their deformed surfaces of 0.56 MiB, 29 MiB, so some 70 walks;
benchmarks/results/review.md)."""
OFF = "off"
STALE_TEMPORARY_SECONDS = 3600.0
"""A temporary file older than this was left by a writer that was killed: removed."""
_PACKAGE_ROOT = os.path.dirname(os.path.dirname(os.path.realpath(__file__)))


FRAME_CACHE_PROPERTY = Property(
    "FrameCache", "string", "",
    "Where solved frames are kept and looked up: a frame solved before with the same scene "
    "files, the same properties of this filter and of the filters before it, and the same time "
    "is loaded instead of solved (from the frames muscle-mss run or demo solved, too); the MVC "
    "Surface Deformer after this filter keeps its deformed surfaces there too. Empty "
    "(the default): the user's frame cache, $MUSCLE_MSS_FRAME_CACHE if set, else "
    "~/.cache/muscle-mss/frames, where muscle-mss run keeps its frames (in a plain VTK "
    "pipeline outside ParaView: none); a folder; or off: every frame solved, nothing written. "
    "Not used with WarmStart or termination 'time budget', nor when the solver's inputs do "
    "not come from a scene folder's readers through the Muscle MSS filters.",
    group="Frame cache")
"""The MSS Collision Solver's ``FrameCache`` row (not in the key: where a frame is kept does
not change it)."""


class DamagedEntry(Exception):
    """An entry that cannot be loaded; the text says why."""


# ---- where --------------------------------------------------------------------------------

def default_folder() -> str:
    """``$XDG_CACHE_HOME/muscle-mss/frames``, else ``~/.cache/muscle-mss/frames``."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "muscle-mss", "frames")


def chosen_folder(option: str | None = None) -> str | None:
    """The cache folder ``--cache`` (``option``: a folder, ``off`` or None: not given) chooses:
    the option, else :data:`ENVIRONMENT`, else :func:`default_folder`; None when off."""
    for chosen in (option, os.environ.get(ENVIRONMENT)):
        if chosen is not None and chosen.strip():
            return None if chosen.strip().lower() == OFF else os.path.abspath(chosen)
    return default_folder()


def bound_bytes() -> int:
    """:data:`BOUND_ENVIRONMENT` (bytes) when set, else :data:`DEFAULT_BOUND`."""
    with contextlib.suppress(ValueError, TypeError, KeyError):
        return max(0, int(os.environ[BOUND_ENVIRONMENT]))
    return DEFAULT_BOUND


# ---- the key --------------------------------------------------------------------------------

def package_version() -> str:
    """The version in the checkout's ``pyproject.toml``, else the installed distribution's."""
    with contextlib.suppress(OSError):
        with open(os.path.join(_PACKAGE_ROOT, "pyproject.toml")) as f:
            for line in f:
                if line.startswith("version"):
                    return line.split("=", 1)[1].strip().strip('"')
    with contextlib.suppress(Exception):
        from importlib.metadata import version
        return version("muscle-mss")
    return "unknown"


_numerics = {}


def numerics_version() -> dict:
    """The package version and a digest of the sources that compute a frame (every ``.py``
    under ``core/`` and ``filters/``), read once per process."""
    if not _numerics:
        digest = hashlib.sha256()
        for part in ("core", "filters"):
            top = os.path.join(_PACKAGE_ROOT, part)
            for root, dirs, files in os.walk(top):
                dirs[:] = sorted(d for d in dirs if not d.startswith((".", "__")))
                for name in sorted(f for f in files if f.endswith(".py")):
                    path = os.path.join(root, name)
                    relative = os.path.relpath(path, _PACKAGE_ROOT).replace(os.sep, "/")
                    with open(path, "rb") as f:
                        data = f.read()
                    digest.update(f"{relative}\0{len(data)}\0".encode() + data)
        _numerics.update(package=package_version(), sources=digest.hexdigest())
    return dict(_numerics)


def scene_digest(folder) -> str:
    """A digest of the bytes of every file a run reads from the scene folder ``folder`` (the
    three ``.vtm`` files, their block files, the motion table), with their relative paths."""
    from muscle_mss.filters.scene_io import scene_files
    digest = hashlib.sha256()
    for path in sorted(scene_files(str(folder))):
        with open(path, "rb") as f:
            data = f.read()
        relative = os.path.relpath(path, folder).replace(os.sep, "/")
        digest.update(f"{relative}\0{len(data)}\0".encode() + data)
    return digest.hexdigest()


KEYED_FILTERS = ("FibreResampler", "SpringBuilder", "RigidPoseTransform", "MSSCollisionSolver")
"""The filters whose properties determine a solved frame: the solver and those upstream of it
(the solver in ParaView cannot see those after it)."""
SURFACE_KEYED_FILTERS = KEYED_FILTERS + ("MVCSurfaceDeformer",)
"""The filters whose properties determine a frame's deformed surfaces (:class:`~.pipeline_frames.SurfaceFrames`).
The Volume-Error Probe after them has no property and measures every frame, loaded or not."""
SURFACES = "surfaces"
"""The ``stage`` of a deformed surfaces' entry in its key (a solved frame's key has none)."""
NOT_KEYED = frozenset({"FrameCache"})
"""Properties that do not change a frame: where it is kept."""


def filter_name(f) -> str:
    """The name of the filter class ``f`` is or derives from (the ParaView proxy and the
    application's cached solver are subclasses): its name in the key."""
    from . import FILTER_NAMES
    return next((c.__name__ for c in type(f).__mro__ if c.__name__ in FILTER_NAMES),
                type(f).__name__)


def filter_properties(filters, keyed=KEYED_FILTERS) -> dict:
    """``{filter: {property: value}}``: every property of those of ``filters`` in ``keyed``
    but :data:`NOT_KEYED` with its effective value, an enum as its choice's text, a number as
    stored (a float's repr is exact)."""
    table = {}
    for f in filters:
        name = filter_name(f)
        if name not in keyed:
            continue
        values = {}
        for prop in f.PROPERTIES:
            if prop.name in NOT_KEYED:
                continue
            value = f.choice(prop.name) if prop.kind == "enum" else f.value(prop.name)
            values[prop.name] = value.item() if isinstance(value, np.generic) else value
        table[name] = values
    return table


def frame_key(scene: str, filters, time: float, stage: str | None = None) -> dict:
    """The key of the frame at ``time`` of the scene whose :func:`scene_digest` is ``scene``
    through ``filters`` (the pipeline's filters, their properties as they are now): its solved
    particles, or with ``stage`` :data:`SURFACES` its deformed surfaces."""
    key = {"format": FORMAT, "numerics": numerics_version(), "scene": scene,
           "properties": filter_properties(
               filters, SURFACE_KEYED_FILTERS if stage == SURFACES else KEYED_FILTERS),
           "time": float(time).hex()}
    return key if stage is None else {**key, "stage": stage}


def key_digest(key: dict) -> str:
    """The SHA-256 of the key's canonical JSON: the entry's file name."""
    return hashlib.sha256(_canonical(key)).hexdigest()


def _canonical(value) -> bytes:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=True).encode()


# ---- entries -------------------------------------------------------------------------------

def encode_entry(key: dict, arrays: dict, scalars: dict) -> bytes:
    """An entry's bytes: :data:`MAGIC`, the header's length (8 bytes, little endian), the JSON
    header (key, payload length and SHA-256, scalars, runtime, when), the ``.npz`` payload."""
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    payload = buffer.getvalue()
    from muscle_mss.core.kernel_cache import runtime_tag
    header = _canonical({"key": key, "payload_bytes": len(payload),
                         "payload_sha256": hashlib.sha256(payload).hexdigest(),
                         "scalars": scalars, "runtime": runtime_tag(),
                         "written": wallclock.strftime("%Y-%m-%d %H:%M:%S")})
    return MAGIC + struct.pack("<Q", len(header)) + header + payload


def decode_entry(data: bytes, key: dict) -> tuple:
    """``(arrays, scalars)`` of an entry's bytes, checked: :class:`DamagedEntry` saying why
    when the magic, the header, the key, the length or the checksum is wrong."""
    if not data.startswith(MAGIC):
        raise DamagedEntry("not a frame cache entry (its first bytes)" if data
                           else "empty file")
    start = len(MAGIC) + 8
    if len(data) < start:
        raise DamagedEntry("truncated in its header")
    (length,) = struct.unpack("<Q", data[len(MAGIC):start])
    try:
        header = json.loads(data[start:start + length])
    except ValueError:
        raise DamagedEntry("truncated or corrupt header") from None
    if _canonical(header.get("key")) != _canonical(key):
        raise DamagedEntry("its key is not the frame's (another frame under this name)")
    payload = data[start + length:]
    if len(payload) != header.get("payload_bytes"):
        raise DamagedEntry(f"truncated: {len(payload)} of {header.get('payload_bytes')} "
                           "payload bytes")
    if hashlib.sha256(payload).hexdigest() != header.get("payload_sha256"):
        raise DamagedEntry("checksum mismatch")
    try:
        with np.load(io.BytesIO(payload), allow_pickle=False) as stored:
            arrays = {name: stored[name] for name in stored.files}
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as err:
        raise DamagedEntry(f"unreadable arrays ({err})") from None
    return arrays, header["scalars"]


class FrameStore:
    """The entries in one folder: :meth:`load`, :meth:`save`, :meth:`info`, :meth:`clear`.
    ``warn(text)`` reports a damaged entry (default: stderr); ``bound``: bytes kept at most."""

    def __init__(self, folder: str, bound: int | None = None, warn=None):
        self.folder = folder
        self.bound = bound_bytes() if bound is None else bound
        self.warn = warn or (lambda text: print(text, file=sys.stderr, flush=True))
        self.damaged = 0

    def path(self, key: dict) -> str:
        return os.path.join(self.folder, key_digest(key) + SUFFIX)

    def load(self, key: dict):
        """``(arrays, scalars)`` stored under ``key``, or None: no entry, or a damaged one
        (reported, removed: the caller solves the frame and saves it again)."""
        path = self.path(key)
        try:
            with open(path, "rb") as f:
                data = f.read()
        except OSError:
            return None
        try:
            parts = decode_entry(data, key)
        except DamagedEntry as err:
            self.damaged += 1
            self.warn(f"warning: frame cache entry {path} is damaged ({err}); solving the "
                      "frame again")
            with contextlib.suppress(OSError):
                os.remove(path)
            return None
        with contextlib.suppress(OSError):
            os.utime(path)                          # recently used
        return parts

    def save(self, key: dict, arrays: dict, scalars: dict) -> bool:
        """Store an entry under ``key`` atomically (temporary file, fsync, rename), then keep
        the folder under the bound; False (and a warning) when the folder cannot be written."""
        data = encode_entry(key, arrays, scalars)
        staged = None
        try:
            os.makedirs(self.folder, exist_ok=True)
            handle, staged = tempfile.mkstemp(dir=self.folder, prefix=".writing-")
            with os.fdopen(handle, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.replace(staged, self.path(key))
        except OSError as err:
            if staged is not None:
                with contextlib.suppress(OSError):
                    os.remove(staged)
            self.warn(f"warning: frame cache {self.folder} cannot be written "
                      f"({err.strerror or err}); the frame is not kept")
            return False
        self.evict()
        return True

    def entries(self) -> list:
        """``(last used, bytes, path)`` of every entry, least recently used first."""
        found = []
        with contextlib.suppress(FileNotFoundError):
            for entry in os.scandir(self.folder):
                if entry.name.endswith(SUFFIX) and not entry.name.startswith("."):
                    with contextlib.suppress(FileNotFoundError):
                        st = entry.stat()
                        found.append((st.st_mtime, st.st_size, entry.path))
        return sorted(found)

    def evict(self) -> int:
        """Remove the least recently used entries until the folder holds at most the bound,
        and temporary files a killed writer left; the number of entries removed."""
        entries = self.entries()
        total, removed = sum(size for _, size, _ in entries), 0
        for _, size, path in entries:
            if total <= self.bound:
                break
            with contextlib.suppress(FileNotFoundError):   # another process removed it
                os.remove(path)
                removed += 1
            total -= size
        now = wallclock.time()
        with contextlib.suppress(FileNotFoundError):
            for entry in os.scandir(self.folder):
                if entry.name.startswith(".writing-"):
                    with contextlib.suppress(FileNotFoundError):
                        if now - entry.stat().st_mtime > STALE_TEMPORARY_SECONDS:
                            os.remove(entry.path)
        return removed

    def info(self) -> dict:
        """``entries``, ``bytes``, ``bound`` and ``folder``."""
        entries = self.entries()
        return {"folder": self.folder, "entries": len(entries),
                "bytes": sum(size for _, size, _ in entries), "bound": self.bound}

    def clear(self) -> tuple:
        """Remove every entry (and temporary file); ``(entries, bytes)`` removed."""
        count = size = 0
        with contextlib.suppress(FileNotFoundError):
            for entry in os.scandir(self.folder):
                if entry.name.endswith(SUFFIX) or entry.name.startswith(".writing-"):
                    with contextlib.suppress(FileNotFoundError):
                        size += entry.stat().st_size
                        os.remove(entry.path)
                        count += entry.name.endswith(SUFFIX)
        return count, size
