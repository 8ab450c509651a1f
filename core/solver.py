"""The MSS Collision Solver's entry point: solve a posed model by the method its settings name.

Two methods share the model (:mod:`~muscle_mss.core.model`) and the contact code
(:mod:`~muscle_mss.core.contacts`, :mod:`~muscle_mss.core.solid_contacts`):

* ``paper relaxation`` (:mod:`~muscle_mss.core.relaxation`): the paper's explicit iterations,
  a mass-spring step then the collision response, stopped by a termination;
* ``quasi-static`` (:mod:`~muscle_mss.core.quasi_static`): the static equilibrium of the same
  model to a tolerance.

A new method is a module with a ``solve(model, bone_centres, bone_radius, bone_id, settings,
progress, prepared, bone_solids, ...)`` returning a :class:`~muscle_mss.core.model.SolveResult`,
its name in :data:`~muscle_mss.core.settings.METHODS` and its branch below. Only the chosen
method's kernels are loaded and compiled.
"""
from __future__ import annotations

import numpy as np

from .connective_tissue import tissue_share
from .model import MSSModel, PreparedModel, SolveResult, prepare
from .settings import (METHOD_QUASI_STATIC, METHOD_RELAXATION, METHODS, SPRINGS_COROTATIONAL,
                       SolverSettings)
from .errors import MuscleMSSError, PoseError

__all__ = ["MSSModel", "PreparedModel", "SolveResult", "prepare", "solve"]


def solve(model: MSSModel, bone_centres=None, bone_radius=None, bone_id=None,
          settings: SolverSettings | None = None, progress=None,
          prepared: PreparedModel | None = None, bone_solids=None, start=None) -> SolveResult:
    """Solve ``model`` by ``settings.method`` (arguments as
    :func:`muscle_mss.core.relaxation.solve`; ``start``, the quasi-static method's warm start,
    is refused by the relaxation, which always starts from rest at the posed positions)."""
    settings = settings or SolverSettings()
    if settings.method == METHOD_RELAXATION:
        if start is not None:
            raise MuscleMSSError("the paper relaxation starts from the posed particles; it "
                                 "takes no start positions")
        from .relaxation import solve as relax
        result = relax(model, bone_centres, bone_radius, bone_id, settings, progress, prepared,
                       bone_solids)
    elif settings.method == METHOD_QUASI_STATIC:
        from .quasi_static import solve as equilibrium
        result = equilibrium(model, bone_centres, bone_radius, bone_id, settings, progress,
                             prepared, start, bone_solids)
    else:
        raise MuscleMSSError(f"solver method {settings.method!r} is not one of "
                             f"{', '.join(METHODS)}")
    check_solved(model, result.positions, settings.method,
                 scene_size(model.positions, model.radius, bone_centres, bone_radius,
                            bone_solids))
    tension = None
    if (settings.method == METHOD_QUASI_STATIC and settings.connective_tissue > 0.0
            and settings.quasi_static.springs == SPRINGS_COROTATIONAL):
        from .quasi_static.corotational import spring_tension
        tension = spring_tension(model, result.positions)
    result.tissue_share = tissue_share(model, result.positions, settings.connective_tissue,
                                       settings.tissue_along, tension)
    return result


def scene_size(positions, radius=None, bone_centres=None, bone_radius=None,
               bone_solids=None) -> float:
    """mm: farther than any solve of a valid pose moves a particle from its posed place: the
    diagonal of the box of the posed particles ``positions`` (n, 3) mm and the bone sphere
    centres, plus twice the largest particle ``radius`` and bone sphere radius (the farthest
    one collision response pushes) and the bone solids' reach, plus 1 mm."""
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
                    "this time, the springs' stiffness and mass, BulkModulus, ConnectiveTissue "
                    "and the bone contact (BoneSphereSpacing)")
