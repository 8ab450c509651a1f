"""Every rule of the scene format (DESIGN §4) checked on arrays.

:func:`scene_problems` returns one sentence per broken rule, each naming the file, the block or
row and the rule, so that ``muscle-mss validate`` can list them all and the filters can refuse a
scene with the first one.
"""
import numpy as np

from .mesh_checks import surface_problems
from .motion import motion_problems, motion_rows
from .scene import BONES_FILE, FIBRES_FILE, MUSCLES_FILE, MOTION_FILE, Scene


def fibre_problems(muscle: str, fibres, where: str = FIBRES_FILE) -> list:
    """Rules for one muscle's :class:`FibreSet`: at least one fibre, >= 2 finite points and a
    non-zero length per fibre, and a (F, 2) integer ``fibre_grid`` with unique cells if given."""
    block = f"{where} block '{muscle}'"
    if fibres.count == 0:
        return [f"{block}: has no fibres; every muscle needs at least one fibre polyline"]
    problems = []
    sizes = np.diff(fibres.offsets)
    for f in np.flatnonzero(sizes < 2):
        problems.append(f"{block}: fibre {f} has {int(sizes[f])} point"
                        f"{'s' if sizes[f] != 1 else ''}; a fibre needs at least 2")
    finite = np.isfinite(fibres.points).all(axis=1)
    if not finite.all():
        p = int(np.flatnonzero(~finite)[0])
        f = int(np.searchsorted(fibres.offsets, p, side="right") - 1)
        problems.append(f"{block}: fibre {f} has a NaN or infinite coordinate (point {p}); "
                        "every coordinate must be finite")
    else:
        for f in np.flatnonzero(sizes >= 2):
            pts = fibres.fibre(f)
            if np.linalg.norm(np.diff(pts, axis=0), axis=1).sum() == 0.0:
                problems.append(f"{block}: fibre {f} has zero length; a fibre must run from "
                                "origin to insertion")
    if fibres.grid is not None:
        grid = np.asarray(fibres.grid)
        if grid.shape != (fibres.count, 2):
            problems.append(f"{block}: fibre_grid has shape {grid.shape}; it must hold one "
                            f"(row, col) pair per fibre, shape ({fibres.count}, 2)")
        elif len(np.unique(grid, axis=0)) != len(grid):
            problems.append(f"{block}: fibre_grid gives two fibres the same (row, col); "
                            "each grid cell holds at most one fibre")
    return problems


def scene_problems(scene: Scene, rows=None) -> list:
    """All broken rules of a scene, as sentences (empty when the scene is valid).

    ``rows`` = ``(times, bones, values (R, 12))`` checks the motion as read from the file, row
    by row; without it the rows are rebuilt from ``scene.motion``.
    """
    problems = []
    for name, surface in scene.muscles.items():
        problems += [f"{MUSCLES_FILE} block '{name}': surface {p}"
                     for p in surface_problems(surface.points, surface.triangles)]
    for name, surface in scene.bones.items():
        problems += [f"{BONES_FILE} block '{name}': surface {p}"
                     for p in surface_problems(surface.points, surface.triangles)]
    if not scene.muscles:
        problems.append(f"{MUSCLES_FILE}: has no blocks; a scene needs at least one muscle")
    if not scene.bones:
        problems.append(f"{BONES_FILE}: has no blocks; a scene needs at least one bone")
    if list(scene.fibres) != list(scene.muscles):
        problems.append(f"{FIBRES_FILE}: block names {list(scene.fibres)} do not match the "
                        f"blocks of {MUSCLES_FILE} {list(scene.muscles)}; they must be the "
                        "same names in the same order")
    for name, fibres in scene.fibres.items():
        problems += fibre_problems(name, fibres)
    if rows is None and scene.motion is not None:
        rows = motion_rows(scene.motion)
    if rows is None:
        problems.append(f"{MOTION_FILE}: missing; a scene needs a motion")
    else:
        problems += motion_problems(*rows, known_bones=list(scene.bones), source=MOTION_FILE)[1]
    return problems
