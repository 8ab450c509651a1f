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
import sys


def sources_digest(folder: str) -> str:
    """A short digest of the ``.py`` files of ``folder`` (names and contents)."""
    digest = hashlib.sha1()
    for name in sorted(os.listdir(folder)):
        if name.endswith(".py"):
            digest.update(name.encode())
            with open(os.path.join(folder, name), "rb") as f:
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
    """``NUMBA_CACHE_DIR``, else ``$XDG_CACHE_HOME`` or ``~/.cache``, + ``muscle-mss``."""
    return os.environ.get("NUMBA_CACHE_DIR") or os.path.join(
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
    before any kernel is defined (Numba reads the setting when a cached kernel is decorated)."""
    import numba
    path = kernel_cache_dir()
    numba.config.CACHE_DIR = path
    return path

