"""A run's hold on its output folder: the lock, the manifest of the files it wrote, and what
``--overwrite`` may remove.

* **Lock.** A run holds ``OUT/.muscle-mss.lock`` (``fcntl.flock``, the file holding its pid)
  from the check of the folder to its last write; a second run into the same folder is refused
  naming the folder and the pid of the run holding it. The kernel lets go of the lock when the
  process ends however it ends (an error, Ctrl-C, a kill), so a lock file left behind by a
  killed run is taken over, with a note naming the pid that left it.
* **Manifest.** ``OUT/.muscle-mss-manifest`` lists, one relative path a line, every file a run
  writes there; each writer adds its files before it creates them (:func:`claim`, appended
  with ``O_APPEND``, so that MPI ranks writing their own time points share it and an
  interrupted run leaves its partial files listed), and never writes over a file it does not
  list.
* **Overwrite.** ``--overwrite`` removes only the plain files the previous run's manifest lists
  (never a symbolic link, a folder, a file it does not list or a path outside the folder), then
  the folders that this left empty. A name a run writes that is taken by something the manifest
  does not list (a user's folder called ``summary.csv``, results of a version before manifests)
  is refused with or without ``--overwrite``: the user moves it, muscle-mss never deletes it.
  So is one deep in ``series/`` where the run will place a file or a time point's folder, and
  a file where it needs a folder: every place a run writes is checked before it solves.
* **Inputs.** A manifest line naming a file the run reads (its scene's, e.g. a manifest edited
  by hand in the scene folder) is refused with or without ``--overwrite``: a run never removes
  its input.
"""
from __future__ import annotations

import contextlib
import fcntl
import os
import stat
import tempfile

from muscle_mss.core.errors import MuscleMSSError

MANIFEST_FILE = ".muscle-mss-manifest"
LOCK_FILE = ".muscle-mss.lock"
_MANIFEST_HEAD = ("# files written by muscle-mss into this folder, one a line; --overwrite "
                  "removes these and nothing else\n")


def claim(out: str, *relative_paths: str) -> None:
    """Before writing ``relative_paths`` (relative to ``out``): refuse one that something the
    manifest does not list already takes (a file of an older run or of the user deep in
    ``series/``: never written over), then :func:`record` them."""
    listed = set(listed_files(out))
    for relative in relative_paths:
        if relative.replace(os.sep, "/") not in listed and os.path.lexists(
                os.path.join(out, relative)):
            raise MuscleMSSError(f"cannot write {os.path.join(out, relative)}: something "
                                 "muscle-mss did not write is there (its manifest "
                                 f"{MANIFEST_FILE} does not list it); move it away")
    record(out, *relative_paths)


def record(out: str, *relative_paths: str) -> None:
    """Add ``relative_paths`` (relative to ``out``) to ``out``'s manifest, before writing them."""
    lines = "".join(p.replace(os.sep, "/") + "\n" for p in relative_paths)
    try:
        fd = os.open(os.path.join(out, MANIFEST_FILE), os.O_WRONLY | os.O_APPEND | os.O_CREAT,
                     0o644)
        try:
            os.write(fd, lines.encode())
        finally:
            os.close(fd)
    except OSError as err:
        raise MuscleMSSError(f"cannot write {os.path.join(out, MANIFEST_FILE)}: "
                             f"{err.strerror or err}") from None


def listed_files(out: str) -> list:
    """The relative paths ``out``'s manifest lists (each once, in order), [] without one."""
    try:
        with open(os.path.join(out, MANIFEST_FILE)) as f:
            lines = [line.rstrip("\n") for line in f]
    except FileNotFoundError:
        return []
    return list(dict.fromkeys(line for line in lines if line and not line.startswith("#")))


def _inside(out: str, relative: str):
    """The path of ``relative`` under ``out``, or None when it is absolute, climbs out of it or
    goes through a link to elsewhere (a manifest edited by hand removes nothing outside)."""
    parts = os.path.normpath(relative).split(os.sep)
    if os.path.isabs(relative) or ".." in parts:
        return None
    path = os.path.join(out, *parts)
    root = os.path.realpath(out)
    if os.path.commonpath([root, os.path.realpath(os.path.dirname(path))]) != root:
        return None
    return path


def _is_plain_file(path: str) -> bool:
    try:
        return stat.S_ISREG(os.lstat(path).st_mode)
    except OSError:
        return False


def remove_listed(out: str) -> list:
    """Remove the plain files ``out``'s manifest lists, then the folders this emptied, then the
    manifest; return the relative paths removed."""
    removed = []
    for relative in listed_files(out):
        path = _inside(out, relative)
        if path is not None and _is_plain_file(path):
            os.remove(path)
            removed.append(relative)
            parent = os.path.dirname(path)
            while os.path.realpath(parent) != os.path.realpath(out):
                with contextlib.suppress(OSError):      # not empty: something else is there
                    os.rmdir(parent)
                if os.path.exists(parent):
                    break
                parent = os.path.dirname(parent)
    with contextlib.suppress(FileNotFoundError):
        os.remove(os.path.join(out, MANIFEST_FILE))
    return removed


def _taken(out: str, names, folders) -> list:
    """The names of ``names`` in ``out`` taken by what the manifest does not list, each with
    what it is: a run's file names must be free or its own files, its folders (``folders``)
    folders."""
    listed = set(listed_files(out))
    taken = []
    for name in names:
        path = os.path.join(out, name)
        if not os.path.lexists(path):
            continue
        if name in folders:
            if os.path.islink(path) or not os.path.isdir(path):
                taken.append(f"{name} (not a folder)")
        elif name not in listed or not _is_plain_file(path):
            kind = "a folder" if os.path.isdir(path) else (
                "a link" if os.path.islink(path) else "a file no manifest lists")
            taken.append(f"{name} ({kind})")
    return taken


@contextlib.contextmanager
def output_lock(out: str):
    """Hold ``out``'s lock (see the module docstring) for the ``with`` block; yields the note
    to print when a lock file left by a run that ended without releasing it was taken over
    (else None). Raises :class:`MuscleMSSError` when another run holds it."""
    path = os.path.join(out, LOCK_FILE)
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise MuscleMSSError(f"output folder {out} cannot be written: "
                                 f"{err.strerror or err}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 64).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise MuscleMSSError(f"output folder {out} is in use by another muscle-mss run "
                                 f"(pid {holder}, lock {path}); wait for it to end or choose "
                                 "another folder") from None
        except OSError as err:
            os.close(fd)
            raise MuscleMSSError(f"output folder {out} cannot be locked ({err.strerror or err}"
                                 "); choose a folder on a local file system") from None
        # the holder before us may have removed the file between our open and our lock
        if os.path.exists(path) and os.stat(path).st_ino == os.fstat(fd).st_ino:
            break
        os.close(fd)
    left = os.read(fd, 64).decode(errors="replace").strip()
    note = (f"note: took over the lock {path} left by pid {left}, which ended without "
            "releasing it" if left else None)
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    try:
        yield note
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.remove(path)
        os.close(fd)


def _left(out: str, relative: str, listed) -> bool:
    """Whether ``relative`` (under ``out``) would still be there after :func:`remove_listed`:
    anything but a listed plain file, and a folder unless everything in it goes."""
    path = os.path.join(out, relative)
    if not os.path.lexists(path):
        return False
    if _is_plain_file(path):
        return relative not in listed or _inside(out, relative) is None
    if os.path.islink(path) or not os.path.isdir(path):
        return True
    entries = os.listdir(path)
    return not entries or any(_left(out, f"{relative}/{e}", listed) for e in entries)


def _obstacles(out: str, places, skip) -> list:
    """What stands where a run places ``places`` (``(relative path, is_folder)``: files, and the
    folders it moves into place whole) after :func:`remove_listed`, each with what it is: a
    thing no manifest lists on such a path, or anything but a folder on a folder above one.
    Paths in ``skip`` are left out (:func:`_taken` names them)."""
    listed = set(listed_files(out))
    found, above = [], {}
    for relative, is_folder in places:
        relative = relative.replace(os.sep, "/")
        parts = relative.split("/")
        for k in range(1, len(parts)):
            above.setdefault("/".join(parts[:k]), relative)
        if relative in skip or not _left(out, relative, listed):
            continue
        path = os.path.join(out, relative)
        if os.path.islink(path):
            kind = "a link"
        elif os.path.isdir(path):
            kind = ("a folder holding what no manifest lists, where the run writes its own"
                    if is_folder else "a folder where the run writes a file")
        else:
            kind = ("a file where the run writes a folder" if is_folder
                    else "a file no manifest lists")
        found.append(f"{relative} ({kind})")
    for relative in above:
        path = os.path.join(out, relative)
        if relative not in skip and os.path.lexists(path) and (
                os.path.islink(path) or not os.path.isdir(path)) and _left(out, relative, listed):
            found.append(f"{relative} (a {'link' if os.path.islink(path) else 'file'} where the "
                         f"run writes a folder, for {above[relative]})")
    return found


def _unwritable(out: str, places) -> list:
    """The folders under ``out`` that hold places of ``places`` and exist but cannot be
    written in."""
    folders = dict.fromkeys(os.path.dirname(p.replace(os.sep, "/")) for p, _ in places)
    return [f for f in folders if f and os.path.isdir(os.path.join(out, f))
            and not os.access(os.path.join(out, f), os.W_OK | os.X_OK)]


def _listed_inputs(out: str, inputs) -> list:
    """``(relative, input)``: the manifest's paths that are (resolved) one of ``inputs``."""
    real = {os.path.realpath(p): p for p in inputs}
    found = []
    for relative in listed_files(out):
        path = _inside(out, relative)
        if path is not None and os.path.realpath(path) in real:
            found.append((relative, real[os.path.realpath(path)]))
    return found


def prepare(out: str, overwrite: bool, names, folders, places=(), inputs=()) -> list:
    """Check ``out`` (held by :func:`output_lock`) before a run that writes ``names`` there
    (``folders`` among them are folders) and places ``places`` (``(relative path, is_folder)``,
    every file and moved folder it will write, :func:`run_output.run_places`), reading
    ``inputs`` (its scene's files): created if missing, writable, no manifest line naming an
    input (a run never removes what it reads), no name or place taken by something its
    manifest does not list, no folder on the way that cannot be written in, and no previous
    run's files unless ``overwrite``, which removes them (:func:`remove_listed`). Everything
    is checked before anything is removed. Returns the relative paths removed."""
    clash = _listed_inputs(out, inputs)
    if clash:
        (relative, path), more = clash[0], len(clash) - 1
        raise MuscleMSSError(
            f"output folder {out}: its manifest {MANIFEST_FILE} lists {relative}, which is "
            f"{path}, an input of this run{f' (and {more} more inputs)' if more else ''}; a run "
            "never removes a file it reads, whatever the manifest says: remove those lines "
            "from the manifest or choose another output folder")
    taken = _taken(out, names, folders)
    taken += _obstacles(out, places, skip=set(names))
    if taken:
        raise MuscleMSSError(
            f"output folder {out} holds {', '.join(taken)}, which the run would write but "
            f"muscle-mss did not write (its manifest {MANIFEST_FILE} does not list it: your "
            "own, or results of a version before manifests); muscle-mss never removes what it "
            "did not write: move it away or choose another folder")
    unwritable = _unwritable(out, places)
    if unwritable:
        raise MuscleMSSError(f"output folder {out}: the run writes into {unwritable[0]}, which "
                             "cannot be written (no write permission); make it writable or "
                             "choose another folder")
    previous = [p for p in listed_files(out) if os.path.lexists(os.path.join(out, p))]
    if previous and not overwrite:
        shown = dict.fromkeys(p.split("/")[0] for p in previous)
        raise MuscleMSSError(f"output folder {out} holds the results of another run "
                             f"({', '.join(shown)}); choose another folder or pass --overwrite "
                             "to replace them")
    try:
        with tempfile.NamedTemporaryFile(dir=out, prefix=".write-test-"):
            pass
        removed = remove_listed(out)
        with open(os.path.join(out, MANIFEST_FILE), "w") as f:   # this run's, empty
            f.write(_MANIFEST_HEAD)
        return removed
    except OSError as err:
        raise MuscleMSSError(f"output folder {out} cannot be written: "
                             f"{err.strerror or err}") from None
