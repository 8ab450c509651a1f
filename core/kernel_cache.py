"""Where Numba keeps this package's compiled kernels (every kernel has ``cache=True``).

Numba checks a cached kernel against its own source file only: when a kernel inlines a kernel
of another module (the solver calls the spatial hash, the MSS step, the cage volume), a change
to that other module is not noticed and the stale machine code keeps running. The cache folder
is therefore keyed by a digest of all of ``core``'s sources: any change to the core starts a
fresh folder. It is keyed as well by the Python, Numba and NumPy versions
(:func:`runtime_tag`): Numba names its index files after the Python version only and discards an
index written by another Numba, so the venv (numba 0.68) and ParaView's Python (numba 0.56) in
one folder each threw the other's kernels away and recompiled everything (90 s instead of 5 s).
The base folder is ``NUMBA_CACHE_DIR`` when set (read-only installs, shared file systems), else
the user's cache folder.
"""
import hashlib
import os
import re
import statistics
import sys

_RESOLVED = re.compile(r"numba-[0-9a-f]{16}-")


def sources_digest(folder: str) -> str:
    """A short digest of the ``.py`` files of ``folder`` and its subpackages (relative paths
    and contents)."""
    digest = hashlib.sha1()
    for root, dirs, files in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if not d.startswith((".", "__")))
        for name in sorted(files):
            if name.endswith(".py"):
                path = os.path.join(root, name)
                digest.update(os.path.relpath(path, folder).replace(os.sep, "/").encode())
                with open(path, "rb") as f:
                    digest.update(f.read())
    return digest.hexdigest()[:16]


def runtime_tag() -> str:
    """The interpreter and the libraries compiled code depends on, as a folder-name part, e.g.
    ``cp311-numba0.68.1-numpy2.4.6``."""
    import numba
    import numpy
    python = f"{sys.implementation.cache_tag or 'py'}".replace("cpython-", "cp")
    return f"{python}-numba{numba.__version__}-numpy{numpy.__version__}"


def base_cache_dir() -> str:
    """``NUMBA_CACHE_DIR``, else ``$XDG_CACHE_HOME`` or ``~/.cache``, + ``muscle-mss``. A
    ``NUMBA_CACHE_DIR`` that is itself one of our folders (exported by
    :func:`use_kernel_cache_dir`, inherited by a child process) stands for its parent."""
    base = os.environ.get("NUMBA_CACHE_DIR")
    if base and _RESOLVED.match(os.path.basename(os.path.normpath(base))):
        return os.path.dirname(os.path.normpath(base))
    return base or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"),
        "muscle-mss")


def kernel_cache_dir(base: str | None = None, folder: str | None = None) -> str:
    """The cache folder for the kernels of ``folder`` (default: this package) under ``base``
    (default: :func:`base_cache_dir`): ``numba-<sources digest>-<runtime tag>``."""
    folder = folder or os.path.dirname(os.path.abspath(__file__))
    base = base_cache_dir() if base is None else base
    return os.path.join(base, f"numba-{sources_digest(folder)}-{runtime_tag()}")


def use_kernel_cache_dir() -> str:
    """Point Numba's cache at :func:`kernel_cache_dir`; called once when ``core`` is imported,
    before any kernel is defined (Numba reads the setting when a cached kernel is decorated).
    The folder is exported as ``NUMBA_CACHE_DIR`` too: Numba re-reads its whole configuration
    from the environment whenever the environment changed (a library setting a variable, a
    test's monkeypatch), and a value set only on ``numba.config`` was then reset to Numba's
    default, the ``__pycache__`` folders beside the sources."""
    import numba
    path = kernel_cache_dir()
    os.environ["NUMBA_CACHE_DIR"] = path
    numba.config.CACHE_DIR = path
    return path


EVERY_KERNEL, DEFAULT_KERNELS = "every kernel", "the default settings' kernels"
"""What a warm-up compiles (:mod:`muscle_mss.app.warm_up`): every kernel, or only those a
run with the default settings calls (the demo's, compiled first by ``./demo.sh``). Each has a
marker of its own; every kernel compiled covers the default settings' too."""
COMPILE_SECONDS = {EVERY_KERNEL: 85.0, DEFAULT_KERNELS: 50.0}
"""Seconds a cold compile took on the shared 2-core development machine (the warm-up's wall
time in one process, load average 1; benchmarks/results/compile.md): every kernel 72 s with
numba 0.68, 82 s with numba 0.56 (74 / 92 s in a fresh clone's ./setup.sh), the default
settings' 50 / 52 s (50 s in the demo's second process). The notice's estimate until this
machine has measured its own (:func:`compile_estimate`)."""
WARM_PREFIX = {EVERY_KERNEL: "warm-", DEFAULT_KERNELS: "defaults-warm-"}


def _core_folder() -> str:
    return os.path.dirname(os.path.abspath(__file__))


def core_stamps(folder: str | None = None) -> dict:
    """``{relative path: [mtime, size]}`` of the ``.py`` files of the core and its subpackages:
    what Numba checks a cached kernel against (besides its own folder key)."""
    folder = folder or _core_folder()
    stamps = {}
    for root, dirs, files in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if not d.startswith((".", "__")))
        for name in sorted(files):
            if name.endswith(".py"):
                path = os.path.join(root, name)
                st = os.stat(path)
                stamps[os.path.relpath(path, folder).replace(os.sep, "/")] = [st.st_mtime,
                                                                             st.st_size]
    return stamps


def warm_marker(folder: str | None = None, scope: str = EVERY_KERNEL) -> str:
    """The file that says the kernels of ``scope`` (:data:`EVERY_KERNEL` or
    :data:`DEFAULT_KERNELS`) of the core in ``folder`` (default: this package) are compiled in
    :func:`kernel_cache_dir`. Numba files its kernels under the absolute path of their
    sources, so two checkouts of the same core sharing a cache folder have a marker each."""
    folder = folder or _core_folder()
    where = hashlib.sha1(os.path.abspath(folder).encode()).hexdigest()[:12]
    return os.path.join(kernel_cache_dir(folder=folder), f"{WARM_PREFIX[scope]}{where}.json")


def is_warm(folder: str | None = None, scope: str = EVERY_KERNEL) -> bool:
    """True when :func:`mark_warm` recorded a compile of the kernels of ``scope`` (or of every
    kernel) for the current sources (the same files, modification times and sizes), i.e. Numba
    will load them from its cache."""
    import json
    for recorded in {scope, EVERY_KERNEL}:
        try:
            with open(warm_marker(folder, recorded)) as f:
                if json.load(f).get("stamps") == core_stamps(folder):
                    return True
        except (OSError, ValueError):
            continue
    return False


def mark_warm(seconds: float, folder: str | None = None, scope: str = EVERY_KERNEL) -> None:
    """Record that the kernels of ``scope`` were compiled (in ``seconds``) for the current
    sources. A cache folder that cannot be written is not an error: Numba then compiles in
    memory each time."""
    import json
    path = warm_marker(folder, scope)
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path + ".tmp", "w") as f:
            json.dump({"seconds": round(float(seconds), 1), "stamps": core_stamps(folder)}, f)
        os.replace(path + ".tmp", path)
    except OSError:
        pass


def recorded_seconds(folder: str | None = None, scope: str = EVERY_KERNEL) -> float:
    """The seconds :func:`mark_warm` recorded for the kernels of ``scope`` of the current
    sources (0 when none are recorded or the sources changed since)."""
    import json
    try:
        with open(warm_marker(folder, scope)) as f:
            record = json.load(f)
        return float(record["seconds"]) if record.get("stamps") == core_stamps(folder) else 0.0
    except (OSError, ValueError, KeyError, TypeError):
        return 0.0


FULL_COMPILE_SECONDS = 30.0
"""A recorded warm-up shorter than this found most kernels cached: not a cold compile."""


def compile_estimate(base: str | None = None, scope: str = EVERY_KERNEL) -> float:
    """Seconds a cold compile of the kernels of ``scope`` is expected to take: the median of
    those recorded on this machine for this Python, Numba and NumPy (any version of the
    sources; warm-ups under :data:`FULL_COMPILE_SECONDS` found their kernels cached), else
    :data:`COMPILE_SECONDS`. Not the longest: one compile beside other work took 1,287 s where
    the others took 200-290 s."""
    import glob
    import json
    base = base_cache_dir() if base is None else base
    recorded = []
    for path in glob.glob(os.path.join(base, f"numba-*-{runtime_tag()}",
                                       WARM_PREFIX[scope] + "*.json")):
        try:
            with open(path) as f:
                recorded.append(float(json.load(f)["seconds"]))
        except (OSError, ValueError, KeyError, TypeError):
            continue
    cold = sorted(s for s in recorded if s >= FULL_COMPILE_SECONDS)
    return float(statistics.median(cold)) if cold else COMPILE_SECONDS[scope]


def compile_notice(seconds: float | None = None, scope: str = EVERY_KERNEL) -> str:
    """The one-line notice shown while the kernels of ``scope`` compile."""
    seconds = compile_estimate(scope=scope) if seconds is None else seconds
    which = "" if scope == EVERY_KERNEL else f" ({scope}; the others when a run needs them)"
    return (f"compiling the numeric kernels once for this Python{which}; about {seconds:.0f} s "
            f"(cached in {kernel_cache_dir()})")
