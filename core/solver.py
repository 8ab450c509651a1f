"""The MSS Collision Solver's stage on arrays: :func:`solve` a posed model against the bones.

:func:`solve` is the whole stage: fibre shortening (:mod:`~muscle_mss.core.fibre_shortening`),
the method the settings name with its final collision passes, the divergence check, the exact
push of free particles out of thin bones
(:func:`~muscle_mss.core.bones.exact_distance.particles_out_of_bones`) and the tissue's share.
Methods: ``paper relaxation`` (:mod:`~muscle_mss.core.relaxation`, the paper's explicit
iterations) and ``quasi-static`` (:mod:`~muscle_mss.core.quasi_static`, the static equilibrium).

A new method is a module with ``solve(model, bones, settings, *, prepared=None, start=None,
progress=None)`` returning a :class:`~muscle_mss.core.model.SolveResult`, its name in
:data:`~muscle_mss.core.settings.METHODS` and in :data:`METHOD_MODULES`. Only the chosen
method's kernels are loaded and compiled.
"""
from __future__ import annotations

from importlib import import_module

import numpy as np

from .connective_tissue import tissue_share
from .model import (NO_BONES, Bones, MSSModel, PreparedModel, SolveResult, prepare,
                    with_rest_state)
from .settings import (METHOD_QUASI_STATIC, METHOD_RELAXATION, METHODS, SPRINGS_COROTATIONAL,
                       SolverSettings)
from .errors import MuscleMSSError, PoseError

__all__ = ["Bones", "MSSModel", "PreparedModel", "SolveResult", "prepare", "solve"]

METHOD_MODULES = {METHOD_RELAXATION: "relaxation", METHOD_QUASI_STATIC: "quasi_static"}
"""Each method's module (relative to this package), imported when first used."""


def solve(model: MSSModel, bones: Bones | None = None, settings: SolverSettings | None = None,
          *, prepared: PreparedModel | None = None, start=None, progress=None) -> SolveResult:
    """Solve the posed ``model`` against the posed ``bones`` (None: no bones) by
    ``settings.method``, the whole stage of the module docstring. ``prepared``: from
    :func:`~muscle_mss.core.model.prepare` for this model (its rest state is brought up to date
    when fibre shortening changes the rest lengths); ``start`` (n, 3) mm: the quasi-static
    warm start (the relaxation refuses one); ``progress(fraction) -> bool``, True aborts."""
    settings = settings or SolverSettings()
    bones = bones or NO_BONES
    if settings.method not in METHOD_MODULES:
        raise MuscleMSSError(f"solver method {settings.method!r} is not one of "
                             f"{', '.join(METHODS)}")
    if settings.fibre_shortening:
        from .fibre_shortening import shortened_springs
        model = shortened_springs(model)
        if prepared is not None:
            prepared = with_rest_state(prepared, model)
    method = import_module(f".{METHOD_MODULES[settings.method]}", __package__)
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
                    "this time, the springs' stiffness and mass, BulkModulus, ConnectiveTissue "
                    "and the bone contact (BoneSphereSpacing)")
