"""Numeric core of muscle-mss: NumPy / Numba / SciPy kernels on plain arrays.

Nothing here imports VTK or ParaView (DESIGN §2); the filters in ``muscle_mss.filters``
convert VTK data to the arrays these functions take.
"""
import os

# OpenMP threads that spin while waiting starve the working thread when the cores are shared
# (other processes, the ParaView GUI): a solve of the small demo took 24 s instead of 2 s on a
# busy 2-core machine. Must be set before the first parallel kernel runs; a user's value wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .errors import MuscleMSSError  # noqa: E402
from .kernel_cache import use_kernel_cache_dir  # noqa: E402

use_kernel_cache_dir()

__all__ = ["MuscleMSSError"]
