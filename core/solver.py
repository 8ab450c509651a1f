"""The MSS Collision Solver's stage on arrays: :func:`solve` a posed model against the bones.

:func:`solve` is the whole stage: fibre shortening (:mod:`~muscle_mss.core.fibre_shortening`),
the method the settings name with its final collision passes, the divergence check, the exact
push of free particles out of thin bones
(:func:`~muscle_mss.core.bones.exact_distance.particles_out_of_bones`) and the tissue's share.
Methods: ``paper relaxation`` (:mod:`~muscle_mss.core.relaxation`, the paper's explicit
iterations) and ``quasi-static`` (:mod:`~muscle_mss.core.quasi_static`, the static equilibrium).

A new method is a module with ``solve(model, bones, settings, *, prepared=None, start=None,
progress=None)`` returning a :class:`~muscle_mss.core.model.SolveResult`, named in
:data:`~muscle_mss.core.settings.METHOD_PARTS` (docs/ARCHITECTURE.md, "Where a new piece goes").
Only the chosen method's kernels are loaded and compiled.
"""
from __future__ import annotations

from importlib import import_module

from .connective_tissue import tissue_share
from .model import (NO_BONES, Bones, MSSModel, PreparedModel, SolveResult, prepare,
                    with_rest_state)
from .settings import METHOD_PARTS, METHOD_QUASI_STATIC, SPRINGS_COROTATIONAL, SolverSettings
from .divergence import check_solved, scene_size
from .solver_properties import check_settings

__all__ = ["Bones", "MSSModel", "PreparedModel", "SolveResult", "prepare", "solve"]



def solve(model: MSSModel, bones: Bones | None = None, settings: SolverSettings | None = None,
          *, prepared: PreparedModel | None = None, start=None, progress=None) -> SolveResult:
    """Solve the posed ``model`` against the posed ``bones`` (None: no bones) by
    ``settings.method``, the whole stage of the module docstring. ``prepared``: from
    :func:`~muscle_mss.core.model.prepare` for this model (its rest state is brought up to date
    when fibre shortening changes the rest lengths); ``start`` (n, 3) mm: the quasi-static
    warm start (the relaxation refuses one); ``progress(fraction) -> bool``, True aborts."""
    settings = settings or SolverSettings()
    bones = bones or NO_BONES
    check_settings(settings)
    if settings.fibre_shortening:
        from .fibre_shortening import shortened_springs
        model = shortened_springs(model)
        if prepared is not None:
            prepared = with_rest_state(prepared, model)
    method = import_module(f".{METHOD_PARTS[settings.method]}", __package__)
    result = method.solve(model, bones, settings, prepared=prepared, start=start,
                          progress=progress)
    check_solved(model, result.positions, settings.method,
                 scene_size(model.positions, model.radius, bones))
    tension = None
    if (settings.method == METHOD_QUASI_STATIC and settings.connective_tissue > 0.0
            and settings.quasi_static.springs == SPRINGS_COROTATIONAL):
        from .quasi_static.corotational import spring_tension
        tension = spring_tension(model, result.positions)
    result.tissue_share = tissue_share(model, result.positions, settings.connective_tissue,
                                       settings.tissue_along, tension)
    if bones.solids is not None:
        from .bones.exact_distance import particles_out_of_bones
        result.positions, result.collided = particles_out_of_bones(
            model, bones.solids, result.positions, result.collided)
    result.bone_contact = bones.contact
    return result
