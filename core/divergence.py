"""Whether a solve diverged: the scene's size, farther than any solve of a valid pose moves a
particle, and the check of the solved particles against it (both methods also watch their
iterations; this catches what gets past them, the final collision passes included)."""
from __future__ import annotations

import numpy as np

from .errors import PoseError
from .model import NO_BONES, Bones, MSSModel
from .solver_properties import name_of


def scene_size(positions, radius=None, bones: Bones | None = None) -> float:
    """mm: farther than any solve of a valid pose moves a particle from its posed place: the
    diagonal of the box of the posed particles ``positions`` (n, 3) mm and the bone sphere
    centres, plus twice the largest particle ``radius`` and bone sphere radius (the farthest
    one collision response pushes) and the bone solids' reach, plus 1 mm."""
    bone_centres, bone_radius, _ = (bones or NO_BONES).sphere_arrays
    bone_solids = (bones or NO_BONES).solids
    points = [np.asarray(p, dtype=np.float64).reshape(-1, 3)
              for p in (positions, bone_centres) if p is not None]
    points = np.concatenate(points) if points else np.zeros((0, 3))
    size = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) if len(points) else 0.0
    largest = [float(np.max(r, initial=0.0)) for r in (radius, bone_radius) if r is not None]
    return (size + 2.0 * sum(largest)
            + (bone_solids.reach if bone_solids is not None else 0.0) + 1.0)


def check_solved(model: MSSModel, positions, method: str, size: float | None = None) -> None:
    """Raise :class:`~muscle_mss.core.errors.PoseError` naming the muscle when a solved
    particle of ``positions`` (n, 3) mm is not finite or lies farther from its posed place
    than ``size`` mm (:func:`scene_size`; default that of the posed model alone): no solve of a
    valid pose moves a particle that far (both methods check their iterations too; this
    catches what gets past them, the final collision passes included)."""
    posed = np.asarray(model.positions, dtype=np.float64).reshape(-1, 3)
    if not len(posed):
        return
    if size is None:
        size = scene_size(posed, model.radius)
    moved = np.linalg.norm(np.asarray(positions, dtype=np.float64) - posed, axis=1)
    if np.all(moved <= size):     # False for NaN
        return
    k = int(np.argmax(np.where(np.isnan(moved), np.inf, moved)))
    m = int(np.searchsorted(np.asarray(model.offsets), k, side="right") - 1)
    raise PoseError(model.names[m], f" diverged in the {method} solve: a particle of it ended "
                    f"{moved[k]:.3g} mm from its posed place, farther than the scene's size "
                    f"({size:.3g} mm: the posed muscles and bones across, plus the contacts' "
                    "reach): the model has no rest state near this pose; check the motion at "
                    "this time, the springs' stiffness and mass, "
                    f"{name_of('bulk_modulus')}, {name_of('connective_tissue')} and the bone "
                    f"contact ({name_of('contacts.bone_sphere_spacing')})")
