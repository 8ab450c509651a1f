"""Which way each fibre runs: from its muscle's origin to its insertion.

The scene format has every fibre run from origin to insertion, and the lattice, the fixed ends
and the attachments rely on it: fibre index 0 is the origin. Fibres digitised in both directions
break that silently (every second fibre of one muscle reversed blew its surface out to 2 m, a
268 % volume error), so the Fibre Resampler orients a copy of each muscle's fibres before it
resamples them, and ``muscle-mss validate`` reports what it would reverse.

The rule: with the origin and insertion bones named (``origin_bone``, ``insertion_bone``) and
their rest surfaces at hand, a fibre is reversed when its ends are nearer the other way round,
i.e. when ``d_origin(last) + d_insertion(first) < d_origin(first) + d_insertion(last)`` (one
named bone: its term alone). A fibre whose two ways differ by less than
:data:`AMBIGUOUS_SHARE` of the distance between its ends is ambiguous (both ends equally near,
e.g. both bones the same); ambiguous fibres, and every fibre when no bone is known, run with the
muscle's mean fibre direction: the direction of the fibres the bones decided, or else the
principal axis of the fibres' end-to-end vectors, signed so that most fibres keep their
direction (on a tie, fibre 0 keeps its own).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .bones.weights import bone_distances
from .scene import BONES_FILE, FibreSet

AMBIGUOUS_SHARE = 0.1
"""A fibre is ambiguous when its two ways of attaching differ by less than this share of the
distance between its ends (both ends about equally near the bones)."""


@dataclass(frozen=True)
class FibreDirections:
    """What :func:`fibre_directions` found for one muscle: ``reversed`` (F,) bool, the fibres
    that run from insertion to origin; ``by_bones`` (F,) bool, the fibres whose direction the
    bones decided (the others ran with the mean direction); ``tie``: no bone decided any fibre
    and as many fibres ran each way, so fibre 0's direction was kept."""

    reversed: np.ndarray
    by_bones: np.ndarray
    tie: bool

    @property
    def count(self) -> int:
        return int(self.reversed.sum())


def fibre_end_points(points, offsets):
    """``(first (F, 3), last (F, 3))``: every fibre's first and last point, mm."""
    offsets = np.asarray(offsets)
    return points[offsets[:-1]], points[offsets[1:] - 1]


def fibre_directions(points, offsets, origin_distances=None,
                     insertion_distances=None) -> FibreDirections:
    """Which fibres run from insertion to origin (see the module docstring).

    Parameters
    ----------
    points, offsets : (v, 3) float64 mm, (F + 1,) int
        The fibres, laid out as :func:`.fibres.check_fibres` takes them.
    origin_distances, insertion_distances : (F, 2) float64 mm, or None
        Distance of each fibre's (first, last) point to the origin (insertion) bone's rest
        surface; None where that bone is not known.
    """
    first, last = fibre_end_points(np.asarray(points, dtype=np.float64), offsets)
    span = last - first
    score = np.zeros(len(span))
    if origin_distances is not None:
        score += origin_distances[:, 1] - origin_distances[:, 0]
    if insertion_distances is not None:
        score += insertion_distances[:, 0] - insertion_distances[:, 1]
    known = origin_distances is not None or insertion_distances is not None
    by_bones = known & (np.abs(score) > AMBIGUOUS_SHARE * np.linalg.norm(span, axis=1))
    reverse = by_bones & (score < 0.0)
    tie = False
    if not by_bones.all():
        if by_bones.any():
            direction = np.where(reverse[:, None], -span, span)[by_bones].sum(axis=0)
        else:
            direction, tie = _majority_direction(span)
        rest = ~by_bones
        reverse[rest] = span[rest] @ direction < 0.0
    return FibreDirections(reverse, by_bones, tie)


def _majority_direction(span):
    """``(direction (3,), tie)``: the principal axis of the end-to-end vectors ``span`` (F, 3),
    signed so that most fibres run along it (fibre 0's way on a tie)."""
    axis = np.linalg.eigh(span.T @ span)[1][:, -1]
    along = span @ axis
    forward, backward = int((along > 0).sum()), int((along < 0).sum())
    if forward == backward:
        return (axis if along[0] >= 0 else -axis), True
    return (axis if forward > backward else -axis), False


def reversed_fibres(points, offsets, reverse) -> np.ndarray:
    """A copy of ``points`` (v, 3) with the fibres where ``reverse`` (F,) is set running the
    other way (their points in the opposite order); the same offsets describe it."""
    out = np.array(points, dtype=np.float64, copy=True)
    for f in np.flatnonzero(reverse):
        out[offsets[f]:offsets[f + 1]] = out[offsets[f]:offsets[f + 1]][::-1]
    return out


def bone_end_distances(points, offsets, bone) -> np.ndarray:
    """(F, 2) float64 mm: distance of each fibre's first and last point to ``bone`` =
    ``(vertices (v, 3), triangles (m, 3), label)``, a rest bone surface."""
    first, last = fibre_end_points(points, offsets)
    d = bone_distances(np.concatenate([first, last]), [bone[:2]], [bone[2]])[:, 0]
    return d.reshape(2, -1).T


def directions_by_bones(points, offsets, origin_bone, insertion_bone,
                        bones: dict) -> FibreDirections:
    """:func:`fibre_directions` with the distances to the named bones that ``bones`` (``{name:
    (vertices, triangles)}``, rest surfaces) holds; a bone not named, or not in ``bones``, is
    not known."""
    distances = []
    for name in (origin_bone, insertion_bone):
        if name is None or name not in bones:
            distances.append(None)
        else:
            vertices, triangles = bones[name]
            distances.append(bone_end_distances(points, offsets, (
                vertices, triangles, f"{BONES_FILE} block '{name}'")))
    return fibre_directions(points, offsets, *distances)


def direction_warning(where: str, directions: FibreDirections, origin_bone=None,
                      insertion_bone=None, bones_known: bool = True) -> str | None:
    """The sentence that says which fibres of ``where`` were reversed and by which rule, or None
    when every fibre kept its direction and the direction was not a coin toss.
    ``bones_known``: whether the bones' surfaces were at hand (the Fibre Resampler's Bones
    input connected)."""
    n, total = directions.count, len(directions.reversed)
    if n == 0 and not directions.tie:
        return None
    decided = int((directions.reversed & directions.by_bones).sum())
    parts = []
    if decided:
        parts.append(f"{decided} by their ends' distances to the origin bone '{origin_bone}' "
                     f"and the insertion bone '{insertion_bone}'")
    if n - decided or directions.tie:
        if not bones_known:
            why = "the bones are not known here (connect bones.vtm to the Bones input)"
        elif origin_bone is None and insertion_bone is None:
            why = "the block names no origin_bone or insertion_bone"
        else:
            why = "both ends of these fibres are about equally near the named bones"
        parts.append(f"{n - decided} to run as fibre 0 does, because {why} and half the fibres "
                     "run each way" if directions.tie else
                     f"{n - decided} to run with most of the muscle's fibres, because {why}")
    return (f"{where}: {n} of its {total} fibres ran from insertion to origin and were reversed "
            f"on a copy ({'; '.join(parts)}); every fibre must run from origin to insertion, "
            "and the input is unchanged")


def oriented_fibre_set(fibres: FibreSet, bones: dict) -> tuple:
    """``(FibreSet, FibreDirections)``: a copy of one muscle's fibres oriented from origin to
    insertion by :func:`directions_by_bones` (``bones``: ``{name: Surface}``), and what was
    found. The input is not changed."""
    surfaces = {name: (s.points, s.triangles) for name, s in bones.items()}
    directions = directions_by_bones(fibres.points, fibres.offsets, fibres.origin_bone,
                                     fibres.insertion_bone, surfaces)
    points = reversed_fibres(fibres.points, fibres.offsets, directions.reversed)
    return (FibreSet(points, np.array(fibres.offsets), fibres.grid, fibres.origin_bone,
                     fibres.insertion_bone), directions)
