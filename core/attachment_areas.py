"""Where a muscle's surface is attached to its bones (DESIGN §6 "Fibre generation").

The Fibre Generator needs, per muscle, the two patches of its surface that its fibres start and
end on: the origin and insertion attachment areas. A segmented muscle touches its bones where
its tendons insert; it may also lie on a bone along its belly (the vasti on the femur), which is
no attachment. So an area is the surface vertices within :data:`TOUCH_DISTANCE` of the bone
*and* within the end :data:`END_SHARE` of the muscle's length on that bone's side (its length
measured along its principal axis); where the surface does not come that close to its bone, the
last :data:`FALLBACK_SHARE` of that end.

Which bones: the scene names them (``attachments.csv``, or the fibres it had), else they are
inferred where unambiguous: each end of the muscle is nearest one bone, the two ends' bones
differ, and the bone listed first in ``bones.vtm`` (bones are listed from the trunk outwards,
as OpenSim models and the demo scenes list them) is the origin.

Arrays only (no VTK): distances come from :func:`.bones.weights.bone_distances`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import MuscleMSSError
from .scene import BONES_FILE, MUSCLES_FILE

ATTACHMENTS_FILE = "attachments.csv"
ATTACHMENT_COLUMNS = ("muscle", "origin_bone", "insertion_bone")

TOUCH_DISTANCE = 3.0
"""mm: a surface vertex this close to its attachment bone touches it (a segmentation's voxel is
0.5-1.5 mm; the demo muscles' ends lie 0.2-2 mm from their bones)."""
END_SHARE = 0.03
"""The share of the muscle's length, at each end, where its attachment area may lie. Fibres end
at an area's edge nearest the belly: with 3 % the demo elbow's generated fibres span 97-98 % of
its shipped fibres' end-to-end length (with 10 %, 83-92 %: the arm's slender ends lie on
their bones for 15-25 mm) and run within 1.5 degrees of them."""
FALLBACK_SHARE = 0.02
"""The share of the muscle's length at an end that is its area when the surface does not touch
the bone there."""
FAR_FROM_BONE = 20.0
"""mm: a muscle whose surface comes no closer than this to a bone it is attached to is refused
(the bone is the wrong one, or the muscle is placed in other coordinates)."""
CLEAR_MARGIN = 2.0
"""mm: an end is nearest one bone unambiguously when every other bone is at least this much
farther from it."""


@dataclass(frozen=True)
class AttachmentAreas:
    """One muscle's attachment areas: ``origin`` and ``insertion`` (n,) bool vertex masks of
    its surface, the bones, and whether each area touches its bone (False: the fallback end
    share)."""

    origin_bone: str
    insertion_bone: str
    origin: np.ndarray
    insertion: np.ndarray
    touching: tuple


def axial_position(points) -> np.ndarray:
    """(n,) in [0, 1]: each point's place along the principal axis of ``points`` (n, 3) mm."""
    centred = points - points.mean(axis=0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    t = centred @ axis
    return (t - t.min()) / max(float(np.ptp(t)), 1e-300)


def _far_problem(where: str, end: str, bone: str, distance: np.ndarray) -> str | None:
    closest = float(distance.min())
    if closest <= FAR_FROM_BONE:
        return None
    return (f"{where}: its surface comes no closer than {closest:.1f} mm to its {end} bone "
            f"'{bone}'; a muscle is attached where its surface meets its bone (within "
            f"{FAR_FROM_BONE:g} mm): move the muscle onto the bone (same coordinates and units "
            f"as {BONES_FILE}) or name the right bone in {ATTACHMENTS_FILE}")


def attachment_areas(points, origin_distance, insertion_distance, origin_bone: str,
                     insertion_bone: str, where: str) -> AttachmentAreas:
    """The areas of a muscle with surface vertices ``points`` (n, 3) mm, whose distances to its
    origin and insertion bones are ``origin_distance``, ``insertion_distance`` (n,) mm; raise
    :class:`MuscleMSSError` when the surface lies far from either bone."""
    for end, bone, distance in (("origin", origin_bone, origin_distance),
                                ("insertion", insertion_bone, insertion_distance)):
        problem = _far_problem(where, end, bone, distance)
        if problem:
            raise MuscleMSSError(problem)
    t = axial_position(points)
    # the origin end is the one its bone is nearest to
    if t[np.argmin(origin_distance)] > t[np.argmin(insertion_distance)]:
        t = 1.0 - t
    areas, touching = [], []
    for distance, at_end in ((origin_distance, t), (insertion_distance, 1.0 - t)):
        area = (distance <= TOUCH_DISTANCE) & (at_end <= END_SHARE)
        touching.append(bool(area.any()))
        areas.append(area if area.any() else at_end <= FALLBACK_SHARE)
    return AttachmentAreas(origin_bone, insertion_bone, areas[0], areas[1], tuple(touching))


def inferred_bones(points, distances, bone_names, where: str) -> tuple:
    """``(origin bone, insertion bone)`` of a muscle the scene names no bones for, from the
    distances (n, B) mm of its surface vertices ``points`` (n, 3) to every bone; raise
    :class:`MuscleMSSError` asking for ``attachments.csv`` when they are ambiguous."""
    t = axial_position(points)
    nearest = []
    for end in (t <= END_SHARE, t >= 1.0 - END_SHARE):
        closest = distances[end].min(axis=0)
        order = np.argsort(closest, kind="stable")
        ask = (f"{where}: its attachment bones cannot be told from the bones ({{}}); write "
               f"{ATTACHMENTS_FILE} in the scene folder with the header "
               f"{','.join(ATTACHMENT_COLUMNS)} and a row for it")
        if closest[order[0]] > FAR_FROM_BONE:
            raise MuscleMSSError(ask.format(f"an end lies {closest[order[0]]:.1f} mm from the "
                                            f"nearest bone, '{bone_names[order[0]]}'"))
        if len(order) > 1 and closest[order[1]] - closest[order[0]] < CLEAR_MARGIN:
            raise MuscleMSSError(ask.format(
                f"an end lies {closest[order[0]]:.1f} mm from '{bone_names[order[0]]}' and "
                f"{closest[order[1]]:.1f} mm from '{bone_names[order[1]]}'"))
        nearest.append(int(order[0]))
    if nearest[0] == nearest[1]:
        raise MuscleMSSError(f"{where}: its attachment bones cannot be told from the bones "
                             f"(both ends are nearest '{bone_names[nearest[0]]}'); write "
                             f"{ATTACHMENTS_FILE} in the scene folder with the header "
                             f"{','.join(ATTACHMENT_COLUMNS)} and a row for it")
    first, second = sorted(nearest)
    return bone_names[first], bone_names[second]


def bone_conflict(where: str, end: str, given: str | None, named: str, filename: str):
    """The sentence for a fibres block (``where``) whose ``{end}_bone`` field data ``given``
    differs from the bone ``named`` by the attachments table ``filename``, or None."""
    if given is None or given == named:
        return None
    return (f"{where}: {end}_bone is '{given}' but {filename} names '{named}'; name one bone "
            "in both, or leave it out of the fibres")


def attachment_rows(rows, muscle_names, bone_names, filename: str = ATTACHMENTS_FILE) -> dict:
    """``{muscle: (origin bone, insertion bone)}`` of the rows (dicts by column) of an
    attachments table; raise :class:`MuscleMSSError` naming the row and the rule for an
    unknown muscle or bone (``bone_names`` None: bones unchecked), a muscle listed twice, or a
    missing column."""
    named = {}
    for r, row in enumerate(rows, start=2):      # row 1 is the header
        missing = [c for c in ATTACHMENT_COLUMNS if c not in row]
        if missing:
            raise MuscleMSSError(f"{filename}: column(s) {', '.join(missing)} missing; the "
                                 f"header must be {','.join(ATTACHMENT_COLUMNS)}")
        muscle, origin, insertion = (str(row[c]).strip() for c in ATTACHMENT_COLUMNS)
        if muscle not in muscle_names:
            raise MuscleMSSError(f"{filename} row {r}: '{muscle}' is not a muscle of "
                                 f"{MUSCLES_FILE} (its blocks: {', '.join(muscle_names)})")
        if muscle in named:
            raise MuscleMSSError(f"{filename} row {r}: '{muscle}' is listed twice; one row per "
                                 "muscle")
        for column, bone in (("origin_bone", origin), ("insertion_bone", insertion)):
            if bone_names is not None and bone not in bone_names:
                raise MuscleMSSError(f"{filename} row {r}, column {column}: '{bone}' is not a "
                                     f"bone of {BONES_FILE} (its blocks: "
                                     f"{', '.join(bone_names)})")
        named[muscle] = (origin, insertion)
    return named


def scene_areas(muscles: dict, bones: dict, named: dict) -> dict:
    """``{muscle: AttachmentAreas}`` of every muscle of ``muscles`` (``{name: Surface}``, rest
    pose, mm) against ``bones`` (``{name: Surface}``); ``named`` gives ``{muscle: (origin
    bone, insertion bone)}`` where the scene names them, the others are inferred. The
    distances of every muscle vertex to every bone are measured in one call."""
    from .bones.weights import bone_distances
    bone_names = list(bones)
    if not bone_names:
        raise MuscleMSSError(f"{BONES_FILE} has no blocks; fibres are attached to bones")
    counts = [len(s.points) for s in muscles.values()]
    distances = np.split(bone_distances(
        np.concatenate([s.points for s in muscles.values()]),
        [(bones[b].points, bones[b].triangles) for b in bone_names],
        [f"{BONES_FILE} block '{b}'" for b in bone_names]), np.cumsum(counts)[:-1])
    areas = {}
    for (muscle, surface), d in zip(muscles.items(), distances):
        where = f"{MUSCLES_FILE} block '{muscle}'"
        origin, insertion = named.get(muscle) or inferred_bones(surface.points, d, bone_names,
                                                                where)
        areas[muscle] = attachment_areas(surface.points, d[:, bone_names.index(origin)],
                                         d[:, bone_names.index(insertion)], origin, insertion,
                                         where)
    return areas
