"""Every rule of the scene format (DESIGN §4) checked on arrays.

:func:`scene_problems` returns one sentence per broken rule, each naming the file, the block or
row and the rule, so that ``muscle-mss validate`` can list them all and the filters can refuse a
scene with the first one.
"""
import numpy as np

from .attachments import attachment_distance_problems
from .mesh_checks import surface_problems
from .motion import motion_problems, motion_rows
from .scene import BONES_FILE, FIBRES_FILE, MUSCLES_FILE, MOTION_FILE, Scene
from .volume import winding_numbers

# Plausibility of a scene in millimetres (DESIGN §4): a human or animal muscle is longer than
# MIN_MUSCLE_SIZE across, and a scene lies within MAX_DISTANCE of its origin. A scene in metres
# (every length 1000 times too small) makes spheres of zero radius and silently switches the
# collisions off; one offset by 1e12 mm loses every digit of its shape to rounding.
MIN_MUSCLE_SIZE = 5.0           # mm, bounding-box diagonal
MAX_DISTANCE = 1.0e4            # mm (10 m)
# A muscle's fibres run inside it, and a muscle lies outside the bones at rest: at least
# MIN_INSIDE of a muscle's fibre midpoints lie inside its surface (swapped fibre files, fibres
# placed 200 mm away), and no more than MAX_IN_BONE of its sampled surface vertices inside a
# bone. Fractions, not all points: fibre ends sit on the tendons, on or just off the surface,
# and muscles wrap their bones where tendons enter them: in the demo scenes up to 24.5 % of a
# muscle's surface vertices lie inside a bone at rest (the full thigh's biceps femoris short
# head in the femur; 12.7 % on the arm), so 30 % leaves room and refuses a muscle 40 % inside.
MIN_INSIDE = 0.5
MAX_IN_BONE = 0.3
SAMPLES = 256                   # surface vertices sampled per muscle for the bone test
# Muscles touch but do not overlap: at most MAX_IN_OTHER_MUSCLE of a muscle's fibre midpoints
# (which lie inside it) lie inside another muscle's surface; a muscle placed inside another, or
# two copies of one muscle, have all of them there.
MAX_IN_OTHER_MUSCLE = 0.5
# Accepted, with a warning: more than WARN_INSIDE of a muscle's fibre midpoints (its belly)
# inside one bone or another muscle at rest. Not the share of its surface: the demo scenes' surfaces
# lie up to 24.5 % inside a bone (tendons entering it, up to 8.9 mm deep) and up to 24 % inside
# a neighbour (touching muscles' coarse surfaces, up to 3.2 mm deep), with no fibre midpoint in
# a bone and at most one of 16 (6 %) in another muscle; a muscle moved until 27 % of its surface
# lies in the femur has 44 % of its midpoints there, 15 mm deep.
WARN_INSIDE = 0.1


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


def placement_problems(scene: Scene) -> list:
    """Rules of a plausible scene in millimetres (see :data:`MIN_MUSCLE_SIZE` and below): sizes
    and distances, fibres inside their muscle, muscles outside the bones at rest. Run on a scene
    whose surfaces and fibres passed their own rules. The rules are tried in turn and the first
    that finds problems gives them: a scene far away or in metres would break the later ones
    for that reason alone."""
    for rule in (far_point_problems, _too_small, _misplaced, _nested,
                 attachment_distance_problems):
        problems = rule(scene)
        if problems:
            return problems
    return []


def far_point_problem(points, where: str, offsets=None):
    """Why the points (n, 3) mm of block ``where`` are implausibly far from the origin (farther
    than :data:`MAX_DISTANCE` in a coordinate), or None. Most of them far: the scene is offset;
    a few: those points are wrong (one vertex at 1e12 mm otherwise shows up later as a surface
    "oriented inward" or a failed kernel). ``offsets`` (F + 1,): the points are fibres, named
    by fibre."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not len(points):
        return None
    # a NaN or infinite coordinate is a rule of its own (fibre_problems, surface_problems)
    distance = np.abs(np.where(np.isfinite(points), points, 0.0)).max(axis=1)
    far = distance > MAX_DISTANCE
    if not far.any():
        return None
    p = int(np.argmax(distance))
    if far.mean() > 0.5:
        return (f"{where}: a vertex lies {distance[p]:.3g} mm from the origin; a scene farther "
                f"than {MAX_DISTANCE:g} mm (10 m) from its origin is implausible (lengths are in "
                "millimetres); move the scene near the origin")
    point = f"point {p}"
    if offsets is not None:
        f = int(np.searchsorted(offsets, p, side="right") - 1)
        point = f"fibre {f}'s point {p - int(offsets[f])}"
    count = int(far.sum())
    return (f"{where}: {point} lies {distance[p]:.3g} mm from the origin; a point farther than "
            f"{MAX_DISTANCE:g} mm (10 m) from the origin is implausible (lengths are in "
            f"millimetres) and {count} of the block's {len(points)} points "
            f"{'is' if count == 1 else 'are'}, the rest not: correct or remove "
            f"{'it' if count == 1 else 'them'}")


def far_point_problems(scene: Scene) -> list:
    """:func:`far_point_problem` of every muscle, bone and fibre block of ``scene``."""
    problems = [far_point_problem(surface.points, f"{file} block '{name}'")
                for file, surfaces in ((MUSCLES_FILE, scene.muscles), (BONES_FILE, scene.bones))
                for name, surface in surfaces.items()]
    problems += [far_point_problem(fibres.points, f"{FIBRES_FILE} block '{name}'",
                                   fibres.offsets) for name, fibres in scene.fibres.items()]
    return [p for p in problems if p]


def _too_small(scene: Scene) -> list:
    sizes = {name: float(np.linalg.norm(surface.points.max(axis=0) - surface.points.min(axis=0)))
             for name, surface in scene.muscles.items()}
    return [f"{MUSCLES_FILE} block '{name}': the muscle is {size:.3g} mm across; lengths are in "
            f"millimetres and a muscle smaller than {MIN_MUSCLE_SIZE:g} mm is implausible (is "
            "the scene in metres? scale it by 1000)"
            for name, size in sizes.items() if size < MIN_MUSCLE_SIZE]


def fibre_midpoints(points, offsets) -> np.ndarray:
    """(F, 3) float64 mm: each fibre's middle vertex (the mean of the two middle ones for an
    even count of vertices); the Fibre Resampler hands them on as ``fibre_midpoint``."""
    points, offsets = np.asarray(points), np.asarray(offsets)
    sizes = np.diff(offsets)
    first = offsets[:-1]
    return 0.5 * (points[first + (sizes - 1) // 2] + points[first + sizes // 2])


def _misplaced(scene: Scene) -> list:
    problems = []
    for name, surface in scene.muscles.items():
        fibres = scene.fibres.get(name)
        if fibres is not None and fibres.count:
            middle = fibre_midpoints(fibres.points, fibres.offsets)
            inside = winding_numbers(middle, surface.points, surface.triangles) > 0.5
            if inside.mean() < MIN_INSIDE:
                problems.append(
                    f"{FIBRES_FILE} block '{name}': {100 * inside.mean():.0f} % of its fibres' "
                    f"midpoints lie inside {MUSCLES_FILE} block '{name}'; a muscle's fibres "
                    f"must run inside its surface (at least {100 * MIN_INSIDE:.0f} %): are the "
                    "fibre files of two muscles swapped, or the fibres moved?")
        step = max(len(surface.points) // SAMPLES, 1)
        sample = surface.points[::step]
        for bone, bone_surface in scene.bones.items():
            low, high = bone_surface.points.min(axis=0), bone_surface.points.max(axis=0)
            near = ((sample >= low) & (sample <= high)).all(axis=1)
            if near.mean() <= MAX_IN_BONE:
                continue
            in_bone = winding_numbers(sample[near], bone_surface.points,
                                      bone_surface.triangles) > 0.5
            if in_bone.sum() > MAX_IN_BONE * len(sample):
                problems.append(
                    f"{MUSCLES_FILE} block '{name}': {100 * in_bone.sum() / len(sample):.0f} % "
                    f"of its surface lies inside {BONES_FILE} block '{bone}' at rest; a muscle "
                    "must lie outside the bones in the rest pose (at most "
                    f"{100 * MAX_IN_BONE:.0f} % of its surface inside one, where its tendons "
                    "enter their bone)")
    return problems


def _nested(scene: Scene) -> list:
    """A muscle inside another one, or two copies of one muscle: most of one's fibre midpoints
    inside the other's surface (see :data:`MAX_IN_OTHER_MUSCLE`); each pair named once."""
    problems, named = [], set()
    for name, fibres in scene.fibres.items():
        if name not in scene.muscles or not fibres.count:
            continue
        middle = fibre_midpoints(fibres.points, fibres.offsets)
        for other, surface in scene.muscles.items():
            if other == name or frozenset((name, other)) in named:
                continue
            low, high = surface.points.min(axis=0), surface.points.max(axis=0)
            near = ((middle >= low) & (middle <= high)).all(axis=1)
            if near.mean() <= MAX_IN_OTHER_MUSCLE:
                continue
            inside = winding_numbers(middle[near], surface.points, surface.triangles) > 0.5
            share = inside.sum() / len(middle)
            if share > MAX_IN_OTHER_MUSCLE:
                named.add(frozenset((name, other)))
                problems.append(
                    f"{MUSCLES_FILE} blocks '{name}' and '{other}': {100 * share:.0f} % of the "
                    f"fibre midpoints of '{name}' lie inside the surface of '{other}'; muscles "
                    f"may touch but not overlap (at most {100 * MAX_IN_OTHER_MUSCLE:.0f} % "
                    "inside another muscle): is one muscle a copy of the other, or placed "
                    "inside it?")
    return problems


def _inside_share(middle, surface_points, triangles):
    """How many of the fibre midpoints ``middle`` (F, 3) lie inside a closed surface; the
    winding numbers only of those within its bounding box."""
    low, high = surface_points.min(axis=0), surface_points.max(axis=0)
    near = ((middle >= low) & (middle <= high)).all(axis=1)
    if near.mean() <= WARN_INSIDE:
        return 0
    return int((winding_numbers(middle[near], surface_points, triangles) > 0.5).sum())


def _surface_inside(points, surface_points, triangles, where):
    """``(share, depth mm)``: the share of the vertices ``points`` (v, 3) inside a closed
    surface and the deepest of them (its distance to the surface's triangles)."""
    from .bones.triangle_distance import unsigned_distance
    inside = winding_numbers(points, surface_points, triangles) > 0.5
    if not inside.any():
        return 0.0, 0.0
    depth = unsigned_distance(surface_points, triangles, points[inside], where)
    return float(inside.mean()), float(depth.max())


def placement_warnings(scene: Scene) -> list:
    """Sentences for muscles accepted but implausibly placed at rest: more than
    :data:`WARN_INSIDE` of a muscle's fibre midpoints inside a bone or another muscle (each pair
    of muscles named once), with that share, the share of its surface vertices inside and the
    deepest of them (mm). Run on a scene that passed :func:`placement_problems`."""
    warnings, named = [], set()
    for name, fibres in scene.fibres.items():
        surface = scene.muscles.get(name)
        if surface is None or not fibres.count:
            continue
        middle = fibre_midpoints(fibres.points, fibres.offsets)
        others = [(BONES_FILE, bone, s) for bone, s in scene.bones.items()]
        others += [(MUSCLES_FILE, other, s) for other, s in scene.muscles.items()
                   if other != name and frozenset((name, other)) not in named]
        for file, other, other_surface in others:
            count = _inside_share(middle, other_surface.points, other_surface.triangles)
            if count <= WARN_INSIDE * len(middle):
                continue
            share, depth = _surface_inside(surface.points, other_surface.points,
                                           other_surface.triangles, f"{file} block '{other}'")
            whose = "its fibre midpoints" if file == BONES_FILE \
                else f"the fibre midpoints of '{name}'"
            inside = (f"{100 * count / len(middle):.0f} % of {whose} ({count} of {len(middle)}) "
                      f"and {100 * share:.0f} % of its surface vertices lie inside")
            if file == BONES_FILE:
                warnings.append(
                    f"{MUSCLES_FILE} block '{name}': {inside} {BONES_FILE} block '{other}' at "
                    f"rest, up to {depth:.1f} mm deep; a muscle's belly lies outside the bones "
                    f"(more than {100 * WARN_INSIDE:.0f} % of its fibre midpoints in one is "
                    "implausible; only its tendons enter them): is the muscle or the bone "
                    "misplaced?")
            else:
                named.add(frozenset((name, other)))
                warnings.append(
                    f"{MUSCLES_FILE} blocks '{name}' and '{other}': {inside} the surface of "
                    f"'{other}' at rest, up to {depth:.1f} mm deep; muscles may touch but not "
                    f"overlap (more than {100 * WARN_INSIDE:.0f} % of one's fibre midpoints in "
                    "another is implausible), and their surfaces overlap as much after solving "
                    "(summary.csv in_other_muscle_vertices): is one of them misplaced?")
    return warnings


def scene_problems(scene: Scene, rows=None) -> list:
    """All broken rules of a scene, as sentences (empty when the scene is valid).

    ``rows`` = ``(times, bones, values (R, 12))`` checks the motion as read from the file, row
    by row; without it the rows are rebuilt from ``scene.motion``.
    """
    # a point implausibly far breaks every geometric rule after it for that reason alone
    far = far_point_problems(scene)
    problems = list(far)
    for name, surface in (() if far else scene.muscles.items()):
        problems += [f"{MUSCLES_FILE} block '{name}': surface {p}"
                     for p in surface_problems(surface.points, surface.triangles)]
    for name, surface in (() if far else scene.bones.items()):
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
    if not problems:
        problems += placement_problems(scene)
    if rows is None and scene.motion is not None:
        rows = motion_rows(scene.motion)
    if rows is None:
        problems.append(f"{MOTION_FILE}: missing; a scene needs a motion")
    else:
        problems += motion_problems(*rows, known_bones=list(scene.bones), source=MOTION_FILE)[1]
    return problems
