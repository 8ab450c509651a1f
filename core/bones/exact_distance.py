"""Exact distances to the bones where the sampled fields are not exact enough.

The bones' sampled signed distance fields (:mod:`.bones.distance`) are within about half a fine
cell of the exact distance on smooth bone, but farther next to thin or sharp features: on an
elbow scene at 130 degrees the fields put every pushed surface vertex out of the forearm bones
while the bones' triangles found vertices 2.6 mm inside. So what is inside a bone, and how deep,
is decided by the triangles: the fields choose the candidates (every point whose looked-up
distance is not farther out than the field's error bound, :meth:`.BoneFieldSet.error_bounds`)
and :func:`.triangle_distance.closest_points` measures them in the bone's rest frame.

:func:`exact_signed_distances` is :func:`.bones.distance.signed_distances` with those values
exact; :func:`push_out_exactly` moves each point that is exactly inside a bone it is checked
against to the closest point of that bone's surface plus :data:`EXACT_CLEARANCE` (the exact
answer of "push it out onto the surface", in one step), bone after bone, until none is inside.
Both need the surfaces in the set (``BoneFieldSet.surfaces``); without them they are the
fields' answers. :func:`particles_out_of_bones` applies the push to a solve's particles.
"""
from __future__ import annotations

import numpy as np

from .distance import BoneFieldSet, signed_distances
from ..errors import checked_points
from ..contacts.solid_contacts import kept_out_of_solids
from .triangle_distance import closest_points

EXACT_CLEARANCE = 2e-3
"""mm beyond the bone's surface where :func:`push_out_exactly` puts a point: above the
reports' 1e-3 mm inside tolerance and the rounding of a rigid transform."""
SWEEPS = 4
"""Passes over the bones at most in :func:`push_out_exactly` (a point put out of one bone may
be inside another)."""


def _in_rest_frame(transforms, b, points) -> np.ndarray:
    """``points`` (n, 3) mm in bone b's field frame: ``R^T (x - t)``."""
    m = transforms[b]
    return (points - m[:, 3]) @ m[:, :3]


def _in_posed_frame(transforms, b, points) -> np.ndarray:
    m = transforms[b]
    return points @ m[:, :3].T + m[:, 3]


def exact_signed_distances(fields: BoneFieldSet, points, transforms=None) -> np.ndarray:
    """(n, b) mm: the signed distance (negative inside) of ``points`` (n, 3) mm to every posed
    bone (``transforms`` (b, 3, 4) from the fields' frames, None: rest), exact wherever the
    looked-up value is within its field's error bound of the surface or inside, the looked-up
    value elsewhere (farther out than the bound, so outside)."""
    points = checked_points(points)
    distance = signed_distances(fields, points, transforms)[0]
    if not fields.surfaces:
        return distance
    transforms = np.tile(np.eye(3, 4), (len(fields), 1, 1)) if transforms is None \
        else np.asarray(transforms, dtype=np.float64)
    for b, bound in enumerate(fields.error_bounds()):
        near = np.flatnonzero(~(distance[:, b] > bound))
        if len(near):
            distance[near, b] = closest_points(fields.surfaces[b],
                                               _in_rest_frame(transforms, b, points[near]),
                                               f"bone '{fields.names[b]}'")[0]
    return distance


def push_out_exactly(fields: BoneFieldSet, points, transforms=None, active=None) -> np.ndarray:
    """(n, 3) mm displacements that put every point of ``points`` (n, 3) mm out of every posed
    bone it is checked against (``active`` (n, b) bool, None: all): a point exactly inside a
    bone goes to the closest point of that bone's surface plus :data:`EXACT_CLEARANCE` along
    the way out; a point outside gets exactly 0. Bones without surfaces in ``fields`` push
    nothing."""
    points = checked_points(points)
    n, count = len(points), len(fields)
    moved = points.copy()
    if not fields.surfaces or not n:
        return moved - points
    transforms = np.tile(np.eye(3, 4), (count, 1, 1)) if transforms is None \
        else np.asarray(transforms, dtype=np.float64)
    active = np.ones((n, count), dtype=bool) if active is None \
        else np.broadcast_to(np.asarray(active, dtype=bool).reshape(n, -1), (n, count))
    candidates = np.flatnonzero(active.any(axis=1))
    for _ in range(SWEEPS):
        inside = (exact_signed_distances(fields, moved[candidates], transforms) < 0.0) \
            & active[candidates]
        if not inside.any():
            break
        for b in range(count):
            rows = candidates[inside[:, b]]
            if not len(rows):
                continue
            rest = _in_rest_frame(transforms, b, moved[rows])
            _, closest = closest_points(fields.surfaces[b], rest, f"bone '{fields.names[b]}'")
            outward = closest - rest
            length = np.linalg.norm(outward, axis=1, keepdims=True)
            step = np.divide(outward, length, out=np.zeros_like(outward), where=length > 0)
            moved[rows] = _in_posed_frame(transforms, b, closest + EXACT_CLEARANCE * step)
    return moved - points


def particles_out_of_bones(model, solids, positions, collided):
    """``(positions (n, 3) mm, collided (n,) bool)`` of a solve of ``model`` (an
    :class:`~muscle_mss.core.model.MSSModel`) against ``solids`` (a :class:`.BoneSolids`) with
    the centre of every particle the solids keep out
    (:func:`~.solid_contacts.kept_out_of_solids`) that is exactly inside a bone put on that
    bone's surface (:func:`push_out_exactly`): the solvers' contacts read the sampled fields,
    a few tenths of a millimetre off next to thin forearm bones. The moved particles count as
    collided."""
    active = kept_out_of_solids(model.fixed, model.boundary, model.radius,
                                model.in_bone_at_rest)
    push = push_out_exactly(solids.fields, positions, solids.transforms, active)
    moved = (push != 0.0).any(axis=1)
    if not moved.any():
        return positions, collided
    return positions + push, collided | moved
