"""Muscle particles against the bones as solids (each bone's signed distance field,
:mod:`~muscle_mss.core.bones.distance`), for the paper relaxation's iterations and both methods'
final collision passes.

A particle closer to a bone's surface than its sphere's radius plus the bone's clearance, or
inside the bone, is pushed the whole way out to that distance along the distance gradient, from
any depth: a sphere carried past a bone's shell of spheres would be pushed on through it by the
inner spheres, the distance gradient takes it out by the nearer side. The solids keep out every
free particle not inside a bone at rest (:func:`solid_points`), with or without a sphere.
"""
from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit, prange

from ..bones.distance import BRICK, NO_SOLIDS, BoneSolids, FieldGrid, push_rest, sample, to_rest
from ..model import PreparedModel

# A particle whose distance to every solid bone exceeds its reach by a slack plus its move since
# that distance was sampled times SOLID_LIPSCHITZ is clear of them without sampling: the
# trilinear interpolant of a distance (1-Lipschitz) changes by at most sqrt(3) per mm within the
# narrow band of fine bricks (continuous across them). It jumps where a fine brick meets a
# coarse one, by the coarse grid's interpolation error, but those faces lie farther than the
# band (4 mm) from the surface, beyond the reach of the demo's spheres; a contact missed there
# is found once the particle has moved, and the final passes test every particle afresh.
SOLID_LIPSCHITZ = np.sqrt(3.0)

SOLID_SLACK_CELLS = 1.0         # fine cells: the slack in mm is this times the field's spacing

SolidState = namedtuple("SolidState", (
    "transforms", "clearance", "tolerance", "x", "points", "radius", "anchor", "margin", "slack",
    "disp", "collided", "count", "pen", "ptr"))
SolidState.__doc__ = """The solid contacts' state for one solve, beside the bones' packed
fields (:data:`~muscle_mss.core.bones.distance.FieldGrid`, :func:`solid_grid`). Flat, and apart
from the grid: it goes to parallel loops, and Numba cannot hand them a tuple nested in a tuple,
nor (Numba 0.56) a named tuple of 16 fields or more ("CALL_FUNCTION_EX with **kwargs not
supported").

The bones (:meth:`~muscle_mss.core.bones.distance.BoneSolids.kernel_arguments`: ``transforms``
(b, 3, 4) field frame to posed, ``clearance`` (b,) mm and the push ``tolerance`` mm); the
positions ``x`` (3, n) mm they read; the particles ``points`` (k,) of :func:`solid_points` with
their sphere radii ``radius`` (k,) mm (0: none); the skip state of :func:`solid_contacts_range`
(``anchor`` (3, k) each particle's position when last sampled and ``margin`` (k,) its least
clearance of the bones then, mm; ``slack`` mm); the contact state (``disp`` (3, k) mm, ``collided``
(k,), ``count`` (k,) contacts, ``pen`` (k,) mm the deepest) and each muscle's first particle among
them ``ptr`` (M + 1,)."""


def kept_out_of_solids(fixed, boundary, radius, in_bone_at_rest) -> np.ndarray:
    """(n,) bool: the particles the bones as solids keep out — every free particle not inside
    a bone at rest (``in_bone_at_rest`` (n,) bool; a particle embedded in its attachment bone
    belongs there), with or without a sphere; when the model does not say which particles are
    inside a bone at rest (None), the free particles with a sphere (``boundary`` and ``radius``
    > 0). The arrays (n,) in any one order."""
    if in_bone_at_rest is None:
        keep = np.asarray(boundary, dtype=bool) & (np.asarray(radius) > 0.0)
    else:
        keep = ~np.asarray(in_bone_at_rest, dtype=bool)
    return keep & ~np.asarray(fixed, dtype=bool)


def solid_points(prep: PreparedModel) -> np.ndarray:
    """(k,) int64, solver order: the particles :func:`kept_out_of_solids`."""
    return np.flatnonzero(kept_out_of_solids(prep.fixed, prep.boundary, prep.radius,
                                             prep.in_bone_at_rest)).astype(np.int64)


def solid_grid(bone_solids: BoneSolids | None) -> FieldGrid:
    """The packed fields of ``bone_solids`` (None: no bone) as the kernels take them."""
    return (bone_solids if bone_solids is not None else NO_SOLIDS).fields.grid()


def solid_state(bone_solids: BoneSolids | None, x: np.ndarray,
                prep: PreparedModel) -> SolidState:
    """The :class:`SolidState` of ``bone_solids`` (checked; None: no bone as a solid) reading
    the positions ``x`` (3, n) mm, for the particles of :func:`solid_points` of ``prep``."""
    points = solid_points(prep) if bone_solids is not None else np.zeros(0, np.int64)
    if bone_solids is None:
        bone_solids = NO_SOLIDS
    bone_solids.check()
    k = len(points)
    slack = (SOLID_SLACK_CELLS * float(bone_solids.fields.spacing.max())
             if len(bone_solids.fields) else 0.0)
    return SolidState(
        *bone_solids.kernel_arguments(), x, points, prep.radius[points].copy(),
        np.zeros((3, k)), np.full(k, -np.inf), slack, np.zeros((3, k)),
        np.zeros(k, dtype=np.uint8), np.zeros(k, dtype=np.int64), np.zeros(k),
        np.searchsorted(points, prep.offsets).astype(np.int64))


@njit(cache=True)
def solid_contacts_range(first, last, solids, grid, box):
    """Particles ``first..last-1`` of ``solids`` (:class:`SolidState`: every free particle
    not inside a bone at rest, each with its sphere's radius or 0) against the bones as solids
    (their fields ``grid``, :func:`solid_grid`):
    a particle closer to bone b's surface than its radius plus the bone's clearance, or inside
    the bone, gets the displacement that takes it out to that distance along the distance
    gradient (the whole penetration, as against a bone sphere, from whatever depth) in the
    state's ``disp``, and ``collided`` set (:func:`respond_solids` applies them). A particle
    outside a bone's sampled box by its reach or more is clear of it (the field is at least the
    box's padding there); one that has moved little since it was last found clear of every bone
    by a margin is skipped (:data:`SOLID_LIPSCHITZ`); one outside ``box`` (2, 3) mm or not
    finite is left alone, and the return value is then False (diverged). One muscle's particles
    per call: a call passes the whole state, too dear per particle."""
    (transforms, clearance, tolerance, x, points, radius, anchor, margin, slack, disp, collided,
     count, pen, _) = solids
    origin, spacing, dims = grid.origin, grid.spacing, grid.dims
    inside = True
    for k in range(first, last):
        count[k] = 0
        pen[k] = 0.0
        collided[k] = 0
        p = points[k]
        cx, cy, cz = x[0, p], x[1, p], x[2, p]
        if not ((cx >= box[0, 0]) & (cx <= box[1, 0]) & (cy >= box[0, 1]) & (cy <= box[1, 1])
                & (cz >= box[0, 2]) & (cz <= box[1, 2])):
            inside = False
            continue
        ex, ey, ez = cx - anchor[0, k], cy - anchor[1, k], cz - anchor[2, k]
        room = margin[k] - slack
        if room > 0.0 and SOLID_LIPSCHITZ ** 2 * (ex * ex + ey * ey + ez * ez) < room * room:
            continue
        clear = np.inf
        for axis in range(3):
            disp[axis, k] = 0.0
        for b in range(transforms.shape[0]):
            qx, qy, qz = to_rest(transforms, b, cx, cy, cz)
            reach = radius[k] + clearance[b]
            h = spacing[b]
            ox = max(origin[b, 0] - qx, qx - origin[b, 0] - dims[b, 0] * BRICK * h, 0.0)
            oy = max(origin[b, 1] - qy, qy - origin[b, 1] - dims[b, 1] * BRICK * h, 0.0)
            oz = max(origin[b, 2] - qz, qz - origin[b, 2] - dims[b, 2] * BRICK * h, 0.0)
            away = np.sqrt(ox * ox + oy * oy + oz * oz)
            if away > 0.0 and away >= reach:
                clear = min(clear, away - reach)
                continue
            value = sample(b, qx, qy, qz, grid)[0]
            if value >= reach - tolerance:
                clear = min(clear, value - reach)
                continue
            clear = -np.inf
            px, py, pz, _ = push_rest(b, qx, qy, qz, reach, tolerance, grid)
            m = transforms[b]
            dx, dy, dz = px - qx, py - qy, pz - qz
            for axis in range(3):
                disp[axis, k] += m[axis, 0] * dx + m[axis, 1] * dy + m[axis, 2] * dz
            collided[k] = 1
            count[k] += 1
            pen[k] = max(pen[k], reach - value)
        anchor[0, k], anchor[1, k], anchor[2, k] = cx, cy, cz
        margin[k] = clear
    return inside


@njit(cache=True, parallel=True)
def solid_contacts(solids, grid, box):
    """:func:`solid_contacts_range` for every particle of ``solids``, muscle by muscle in parallel
    (the final passes; the relaxation's iterations run it inside their step's region, where
    there is no thread wake-up to pay)."""
    ptr = solids.ptr
    for m in prange(ptr.shape[0] - 1):
        solid_contacts_range(ptr[m], ptr[m + 1], solids, grid, box)


@njit(cache=True)
def respond_solids(x, v, solids, ever):
    """The response to :func:`solid_contacts`: each collided particle moves by its
    displacement (mm) and stops; ``ever`` (k,) gets it (the final passes' record)."""
    points, disp, collided = solids.points, solids.disp, solids.collided
    for k in range(points.shape[0]):
        if collided[k]:
            p = points[k]
            for axis in range(3):
                x[axis, p] += disp[axis, k]
                v[axis, p] = 0.0
            ever[k] = 1
