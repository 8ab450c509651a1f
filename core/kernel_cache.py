"""Where Numba keeps this package's compiled kernels (every kernel has ``cache=True``).

Numba checks a cached kernel against its own source file only: when a kernel inlines a kernel
of another module (the solver calls the spatial hash, the MSS step, the cage volume), a change
to that other module is not noticed and the stale machine code keeps running. The cache folder
is therefore keyed by a digest of all of ``core``'s sources: any change to the core starts a
fresh folder. The base folder is ``NUMBA_CACHE_DIR`` when set (read-only installs, shared file
systems, several Pythons), else the user's cache folder.
"""
import hashlib
import os


def sources_digest(folder: str) -> str:
    """A short digest of the ``.py`` files of ``folder`` (names and contents)."""
    digest = hashlib.sha1()
    for name in sorted(os.listdir(folder)):
        if name.endswith(".py"):
            digest.update(name.encode())
            with open(os.path.join(folder, name), "rb") as f:
                digest.update(f.read())
    return digest.hexdigest()[:16]


def kernel_cache_dir(base: str | None = None, folder: str | None = None) -> str:
    """The cache folder for the kernels of ``folder`` (default: this package) under ``base``
    (default: ``NUMBA_CACHE_DIR``, else ``$XDG_CACHE_HOME`` or ``~/.cache``, + ``muscle-mss``)."""
    folder = folder or os.path.dirname(os.path.abspath(__file__))
    if base is None:
        base = os.environ.get("NUMBA_CACHE_DIR") or os.path.join(
            os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"),
            "muscle-mss")
    return os.path.join(base, "numba-" + sources_digest(folder))


def use_kernel_cache_dir() -> str:
    """Point Numba's cache at :func:`kernel_cache_dir`; called once when ``core`` is imported,
    before any kernel is defined (Numba reads the setting when a cached kernel is decorated)."""
    import numba
    path = kernel_cache_dir()
    numba.config.CACHE_DIR = path
    return path
