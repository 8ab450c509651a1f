"""A scene as plain arrays (DESIGN §4): muscle and bone surfaces, fibres, motion.

Lengths are in millimetres. The file layer (``muscle_mss.filters.scene_io``) reads and writes
these objects; the demo generator (``muscle_mss.core.demo.scene``) builds one.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MUSCLES_FILE = "muscles.vtm"
FIBRES_FILE = "fibres.vtm"
BONES_FILE = "bones.vtm"
MOTION_FILE = "motion.csv"
MOTION_COLUMNS = ("time", "bone",
                  "m00", "m01", "m02", "m03",
                  "m10", "m11", "m12", "m13",
                  "m20", "m21", "m22", "m23")


@dataclass
class Surface:
    """A triangle surface: ``points`` (n, 3) float64 mm, ``triangles`` (m, 3) int64."""

    points: np.ndarray
    triangles: np.ndarray


@dataclass
class FibreSet:
    """The fibres of one muscle, each a polyline from origin to insertion.

    ``points`` (n, 3) float64 holds all fibre vertices; fibre ``f`` is
    ``points[offsets[f]:offsets[f + 1]]``. ``grid`` (F, 2) int32 is the optional
    ``fibre_grid`` (row, col) of each fibre, or None. ``origin_bone`` and ``insertion_bone``
    name the bones the fibres' first and last points are attached to, or None when the scene
    does not say (then :mod:`.attachments` infers them).
    """

    points: np.ndarray
    offsets: np.ndarray
    grid: np.ndarray | None = None
    origin_bone: str | None = None
    insertion_bone: str | None = None

    @property
    def count(self) -> int:
        return len(self.offsets) - 1

    def fibre(self, f: int) -> np.ndarray:
        return self.points[self.offsets[f]:self.offsets[f + 1]]

    @classmethod
    def from_polylines(cls, polylines, grid=None) -> "FibreSet":
        polylines = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in polylines]
        offsets = np.zeros(len(polylines) + 1, dtype=np.int64)
        offsets[1:] = np.cumsum([len(p) for p in polylines])
        points = np.concatenate(polylines) if polylines else np.zeros((0, 3))
        return cls(points, offsets, None if grid is None else np.asarray(grid, dtype=np.int32))


@dataclass
class Motion:
    """Rigid bone transforms over time.

    ``times`` (T,) float64 ascending; ``bones`` the bone names; ``matrices`` (T, B, 3, 4)
    float64 mapping rest to posed coordinates: ``x' = M[:, :3] @ x + M[:, 3]``.
    """

    times: np.ndarray
    bones: list
    matrices: np.ndarray


@dataclass
class Scene:
    """Muscles, fibres and bones by name (insertion order = block order) and the motion."""

    muscles: dict = field(default_factory=dict)
    fibres: dict = field(default_factory=dict)
    bones: dict = field(default_factory=dict)
    motion: Motion | None = None
