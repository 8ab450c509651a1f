"""Numeric core of muscle-mss: NumPy / Numba / SciPy kernels on plain arrays.

Nothing here imports VTK or ParaView (DESIGN §2); the filters in ``muscle_mss.filters``
convert VTK data to the arrays these functions take.
"""
from .errors import MuscleMSSError

__all__ = ["MuscleMSSError"]
