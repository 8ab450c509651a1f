"""Which bone each end of a muscle is attached to (DESIGN §6 "Attachments").

A muscle's fibres run from its origin to its insertion; the fixed particles at the fibres' ends
are the tendon attachments and follow their bone rigidly, not a blend of nearby bones. A scene
names the two bones in optional field data of each ``fibres.vtm`` block (``origin_bone``,
``insertion_bone``); when a name is absent it is inferred here as the bone whose rest surface is
nearest, on average over the muscle's fibres, to that end's points.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .bones.weights import bone_distances
from .fibre_direction import fibre_directions
from .scene import BONES_FILE, FIBRES_FILE, Scene

ORIGIN, INSERTION = "origin", "insertion"
"""The two ends of a muscle: fibre index 0 and the last fibre index."""
ATTACHMENT_REACH = 20.0
"""mm: a named attachment bone whose rest surface lies farther than this on average from its
end's fibre points, while another bone lies within it, is the wrong bone (the demo scenes'
ends lie at most 0.6 mm from their named bones on average, and 12.4 mm or more from the
others)."""


@dataclass(frozen=True)
class Attachment:
    """One end of one muscle: its bone, whether the scene named it or it was inferred, and the
    mean distance (mm) of the end's fibre points to that bone's rest surface."""

    bone: str
    inferred: bool
    mean_distance: float


def nearest_bone(end_points, bones, labels=None):
    """``(bone index, mean distance mm)``: the bone whose rest surface is nearest on average to
    the end points (n, 3) mm of one muscle end; ``bones`` as in :func:`.bones.weights.bone_distances`."""
    mean = bone_distances(end_points, bones, labels).mean(axis=0)
    b = int(np.argmin(mean))
    return b, float(mean[b])


def fibre_ends(fibres):
    """``(origins (F, 3), insertions (F, 3))``: the first and last point of every fibre, mm."""
    return fibres.points[fibres.offsets[:-1]], fibres.points[fibres.offsets[1:] - 1]


def unknown_bone_problem(where: str, end: str, bone: str, bone_names) -> str | None:
    """The message for an attachment naming a bone that is not in ``bone_names``, or None."""
    if bone in bone_names:
        return None
    return (f"{where}: {end}_bone '{bone}' is not a bone of {BONES_FILE} (its blocks: "
            f"{', '.join(bone_names)}); name one of them or leave {end}_bone out to infer it")


def attachment_problems(scene: Scene) -> list:
    """One sentence per attachment bone a ``fibres.vtm`` block names that is not a bone."""
    problems = []
    for name, fibres in scene.fibres.items():
        for end, bone in ((ORIGIN, fibres.origin_bone), (INSERTION, fibres.insertion_bone)):
            if bone is not None:
                problem = unknown_bone_problem(f"{FIBRES_FILE} block '{name}'", end, bone,
                                               list(scene.bones))
                if problem:
                    problems.append(problem)
    return problems


def attachment_distance_problems(scene: Scene) -> list:
    """One sentence per named attachment bone that lies far from its end's fibre points while
    another bone lies near them (:data:`ATTACHMENT_REACH`), the fibres taken oriented from
    origin to insertion (:func:`.fibre_direction.fibre_directions`). The distances of every
    fibre end to every bone are measured in one call (one call per muscle and end took 4 s on
    the full demo thigh)."""
    names = list(scene.bones)
    labels = [f"{BONES_FILE} block '{b}'" for b in names]
    muscles = [(m, f) for m, f in scene.fibres.items()
               if f.count and (f.origin_bone in names or f.insertion_bone in names)]
    if not muscles:
        return []
    ends = [np.concatenate(fibre_ends(f)) for _, f in muscles]
    distances = np.split(bone_distances(
        np.concatenate(ends), [(scene.bones[b].points, scene.bones[b].triangles) for b in names],
        labels), np.cumsum([len(e) for e in ends])[:-1])
    problems = []
    for (muscle, fibres), d in zip(muscles, distances):
        first, last = d[:fibres.count], d[fibres.count:]        # (F, B) each
        given = (fibres.origin_bone, fibres.insertion_bone)
        known = [np.c_[first[:, names.index(b)], last[:, names.index(b)]] if b in names
                 else None for b in given]
        reverse = fibre_directions(fibres.points, fibres.offsets, *known).reversed[:, None]
        for end, bone, at_end in zip((ORIGIN, INSERTION), given,
                                     (np.where(reverse, last, first),
                                      np.where(reverse, first, last))):
            if bone not in names:
                continue
            mean = at_end.mean(axis=0)
            g, b = names.index(bone), int(np.argmin(mean))
            if mean[g] > ATTACHMENT_REACH >= mean[b]:
                problems.append(
                    f"{FIBRES_FILE} block '{muscle}': {end}_bone is '{bone}', but the fibres' "
                    f"{end} ends lie {mean[g]:.0f} mm from it on average and {mean[b]:.1f} mm "
                    f"from {labels[b]}; a fibre end is attached to a bone it lies on (within "
                    f"{ATTACHMENT_REACH:g} mm on average): name '{names[b]}' as {end}_bone, or "
                    f"leave {end}_bone out to infer it")
    return problems


def scene_attachments(scene: Scene) -> dict:
    """``{muscle: {"origin": Attachment, "insertion": Attachment}}`` of a checked scene: the
    bones it names, the nearest bones where it names none."""
    names = list(scene.bones)
    surfaces = [(scene.bones[b].points, scene.bones[b].triangles) for b in names]
    labels = [f"{BONES_FILE} block '{b}'" for b in names]
    out = {}
    for muscle, fibres in scene.fibres.items():
        out[muscle] = {}
        for end, given, points in zip((ORIGIN, INSERTION),
                                      (fibres.origin_bone, fibres.insertion_bone),
                                      fibre_ends(fibres)):
            if given is not None:
                g = names.index(given)
                d = bone_distances(points, [surfaces[g]], [labels[g]])
                out[muscle][end] = Attachment(given, False, float(d.mean()))
            else:
                b, distance = nearest_bone(points, surfaces, labels)
                out[muscle][end] = Attachment(names[b], True, distance)
    return out


def fixed_particle_bones(fibre_id, fibre_index, fixed, origin: int, insertion: int) -> np.ndarray:
    """Attachment bone index of every particle (n,) int64: ``origin`` for fixed particles at
    fibre index 0, ``insertion`` for fixed particles at their fibre's last index, -1 for the
    others (free particles, and fixed ones inside a fibre)."""
    fibre_id = np.asarray(fibre_id, dtype=np.int64)
    fibre_index = np.asarray(fibre_index, dtype=np.int64)
    last = np.zeros(fibre_id.max() + 1 if len(fibre_id) else 0, dtype=np.int64)
    np.maximum.at(last, fibre_id, fibre_index)
    out = np.full(len(fibre_id), -1, dtype=np.int64)
    fixed = np.asarray(fixed) != 0
    out[fixed & (fibre_index == 0)] = origin
    out[fixed & (fibre_index == last[fibre_id]) & (fibre_index > 0)] = insertion
    return out
