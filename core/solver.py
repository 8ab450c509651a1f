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

from .connective_tissue import tissue_share
from .model import MSSModel, PreparedModel, SolveResult, prepare
from .settings import (METHOD_QUASI_STATIC, METHOD_RELAXATION, METHODS, SPRINGS_COROTATIONAL,
                       SolverSettings)
from .errors import MuscleMSSError

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
    tension = None
    if (settings.method == METHOD_QUASI_STATIC and settings.connective_tissue > 0.0
            and settings.quasi_static.springs == SPRINGS_COROTATIONAL):
        from .quasi_static.corotational import spring_tension
        tension = spring_tension(model, result.positions)
    result.tissue_share = tissue_share(model, result.positions, settings.connective_tissue,
                                       settings.tissue_along, tension)
    return result
