"""A scene's optional ``reference_lengths.csv``: an OpenSim model's muscle-tendon lengths over the
scene's motion (written by ``muscle-mss import-opensim``, :mod:`~muscle_mss.app.opensim_import`),
which the study plots beside the fibre strain of the muscles of the same name.

Header ``time,muscle,length_mm``: one row per (time s, muscle), the length in millimetres.
"""
from __future__ import annotations

import csv
import os

import numpy as np

from muscle_mss.core.errors import MuscleMSSError

from .run_output import write_csv

REFERENCE_LENGTHS_FILE = "reference_lengths.csv"
COLUMNS = ("time", "muscle", "length_mm")


def write_reference_lengths(path: str, times, lengths: dict) -> None:
    """Write ``lengths`` (``{muscle: (T,) mm}``) at ``times`` (T,) s, time by time."""
    write_csv(path, COLUMNS, ((float(t), name, float(values[k]))
                              for k, t in enumerate(times) for name, values in lengths.items()))


def read_reference_lengths(folder: str) -> dict:
    """``{muscle: (times (T,) s, lengths (T,) mm)}`` of ``folder``'s ``reference_lengths.csv``
    (times ascending), ``{}`` when the scene has none. A malformed file is an error naming its
    row and column."""
    path = os.path.join(folder, REFERENCE_LENGTHS_FILE)
    if not os.path.isfile(path):
        return {}
    rows = {}
    with open(path, newline="") as f:
        reader = csv.reader(f)
        header = [h.strip() for h in next(reader, [])]
        if tuple(header) != COLUMNS:
            raise MuscleMSSError(f"{path}: header {','.join(header)}; it must be "
                                 f"{','.join(COLUMNS)}")
        for r, row in enumerate(reader, start=1):
            try:
                time, muscle, length = float(row[0]), row[1].strip(), float(row[2])
            except (IndexError, ValueError):
                raise MuscleMSSError(f"{path} row {r} (line {r + 1}): {','.join(row)!r}; each row "
                                     "is a time (s), a muscle name and a length (mm)") from None
            rows.setdefault(muscle, []).append((time, length))
    out = {}
    for muscle, values in rows.items():
        values = np.array(sorted(values), dtype=np.float64)
        out[muscle] = (values[:, 0], values[:, 1])
    return out


def length_change_pct(lengths) -> np.ndarray:
    """The length change from the first time point (%): ``100 * (L / L[0] - 1)``."""
    lengths = np.asarray(lengths, dtype=np.float64)
    return 100.0 * (lengths / lengths[0] - 1.0)
