"""Numeric core of muscle-mss: NumPy / Numba / SciPy kernels on plain arrays.

Nothing here imports VTK or ParaView (DESIGN §2); the filters in ``muscle_mss.filters``
convert VTK data to the arrays these functions take.
"""
import ctypes
import os
import sys

# OpenMP threads that spin while waiting starve the working thread when the cores are shared
# (other processes, the ParaView GUI): a solve of the small demo took 24 s instead of 2 s on a
# busy 2-core machine. Must be set before the first parallel kernel runs; a user's value wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _load_tbb() -> None:
    """Load the library of the pip package ``tbb`` (a dependency; it lives in ``<venv>/lib``,
    which is not on the loader's path), so that Numba, which opens ``libtbb.so.12`` by name,
    finds it and runs the parallel kernels on TBB (its first choice when available; faster
    than OpenMP on an idle machine, the same results bitwise: docs/performance.md, "Threads").
    Debian's Numba has no TBB layer: OpenMP there."""
    library = os.path.join(sys.prefix, "lib", "libtbb.so.12")
    if sys.platform.startswith("linux") and os.path.exists(library):
        try:
            ctypes.CDLL(library, mode=ctypes.RTLD_GLOBAL)
        except OSError:
            pass    # Numba then takes OpenMP


_load_tbb()

from .errors import MuscleMSSError  # noqa: E402
from .kernel_cache import use_kernel_cache_dir  # noqa: E402

use_kernel_cache_dir()

__all__ = ["MuscleMSSError"]
