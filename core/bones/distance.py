"""Signed distance to each bone: bones as solids, not shells of spheres.

The paper's §3.3 turns bones into sets of spheres on their surface; a point carried past that
shell is inside the bone with nothing to tell it which way is out. Here every bone gets a signed
distance field, sampled once in the bone's rest frame from its closed triangle surface and moved
rigidly with the bone's 3x4 transform: a query point is mapped to the rest frame
(``q = R^T (x - t)``) and looked up there.

Sampling (:func:`~muscle_mss.core.bones.field_sampling.bone_distance_field`): the bone's padded
bounding box is cut into bricks of ``BRICK`` x ``BRICK`` x ``BRICK`` cells of ``spacing`` mm; a
coarse grid of nodes ``COARSE * spacing`` mm apart covers the whole box, and the bricks near the
surface hold fine nodes ``spacing`` mm apart (:class:`BoneDistanceField`). Values are float32
exact signed distances (:mod:`.triangle_distance`).

Lookup (:func:`signed_distances`): trilinear interpolation of the fine brick holding the point,
else of the coarse grid, and the gradient of that interpolant. Outside the sampled box (which
extends ``padding`` mm beyond the bone) the value is the box's value at the nearest box point
plus the distance to it, an upper bound no smaller than ``padding``, with the gradient pointing
away from the box. Interpolation error: nil on a flat piece of surface, about ``spacing^2 /
(8 R)`` near a surface of radius of curvature ``R``, at most about ``spacing / 2`` next to a
sharp edge of the mesh.

Pushing out (:func:`push_out_of_bones`): each point moves along the distance gradient until it
is ``radius`` outside every bone it is checked against, from whatever depth it starts (Newton
steps ``x += (radius - d) grad d``: one step for an exact distance, a few for the
interpolated one). The module stands apart from the solver; ``muscle_mss.filters`` uses it to keep
deformed muscle surfaces out of bones.

For a solver: build the set once per rest bones
(:func:`~muscle_mss.core.bones.field_sampling.bone_field_set`, or the MVC
Surface Deformer's cached ``bone_fields``), and per pose call ``push_out_of_bones(fields,
centres, radii, transforms, active=~fixed)`` with the bones' (b, 3, 4) rest-to-posed
transforms (``muscle_mss.core.pose.pose_at``); add the returned (n, 3) displacements. Inside a
Numba loop, :func:`push_rest` / :func:`sample` take a bone index, a rest-frame point and the
packed fields as a :data:`FieldGrid` (``fields.grid()``), and :func:`to_rest` maps a posed point
to bone b's rest frame.
"""
from __future__ import annotations

import math
from collections import namedtuple
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ..errors import MuscleMSSError, checked_points

BRICK = 8
"""Cells per brick edge: a fine brick holds ``(BRICK + 1)^3`` float32 values."""
COARSE = 4
"""Fine cells per coarse cell (the coarse grid, ``COARSE * spacing`` mm, covers the whole box)."""
PUSH_STEPS = 32
"""Newton steps per point and bone at most in :func:`push_out_of_bones`."""
PUSH_SWEEPS = 4
"""Passes over the bones per point at most (a push out of one bone may lead into another)."""

# collections.namedtuple, not typing.NamedTuple: Numba 0.56 crashes building the latter in a
# kernel (solid_contacts_range builds a grid from its flat state).
FieldGrid = namedtuple("FieldGrid", ("origin", "spacing", "dims", "coarse_start", "coarse",
                                     "index_start", "brick_index", "bricks"))
FieldGrid.__doc__ = """The packed fields of b bones as the lookup kernels read them (the arrays
of :class:`BoneFieldSet`, which see): ``origin`` (b, 3) mm, ``spacing`` (b,) mm, ``dims`` (b, 3)
bricks, ``coarse_start`` (b,), ``coarse`` float32 mm, ``index_start`` (b,), ``brick_index``
int32, ``bricks`` (k, (BRICK + 1)^3) float32 mm. Kernels only read it: a parallel loop's
outputs are plain array arguments (Numba's parallel loops lost writes through tuples)."""


@dataclass(frozen=True)
class BoneDistanceField:
    """One bone's signed distance, sampled in its rest frame (see the module docstring).

    ``origin`` (3,) mm: the sampled box's lower corner; ``spacing`` mm between fine nodes;
    ``dims`` (3,) int64 bricks per axis (the box is ``dims * BRICK * spacing`` mm);
    ``coarse`` ((dims * BRICK // COARSE + 1).prod(),) float32 mm: the coarse nodes, x-major;
    ``brick_index`` (dims.prod(),) int32: each brick's fine block in ``bricks`` or -1;
    ``bricks`` (k, BRICK + 1, BRICK + 1, BRICK + 1) float32 mm: the fine nodes.
    """

    origin: np.ndarray
    spacing: float
    dims: np.ndarray
    coarse: np.ndarray
    brick_index: np.ndarray
    bricks: np.ndarray

    @property
    def nbytes(self) -> int:
        """Memory held by the sampled values (bytes)."""
        return self.coarse.nbytes + self.brick_index.nbytes + self.bricks.nbytes

    @property
    def error_bound(self) -> float:
        """mm: the most a looked-up value can differ from the exact signed distance. The
        distance changes by at most the move, so an interpolated value is within a cell's
        diagonal of the exact one (a coarse cell's, the larger), plus the float32 rounding of
        the values; outside the box the value is an upper bound of a positive distance."""
        return math.sqrt(3.0) * COARSE * self.spacing + 1e-6 * float(
            np.abs(self.coarse).max(initial=0.0))


@dataclass(frozen=True)
class BoneFieldSet:
    """The fields of several bones packed for the kernels: bone ``b``'s arrays start at
    ``coarse_start[b]``, ``index_start[b]``; ``brick_index`` entries are global rows of
    ``bricks`` (k, (BRICK + 1)^3) float32."""

    names: tuple
    origin: np.ndarray
    spacing: np.ndarray
    dims: np.ndarray
    coarse_start: np.ndarray
    coarse: np.ndarray
    index_start: np.ndarray
    brick_index: np.ndarray
    bricks: np.ndarray
    surfaces: tuple = ()
    """Each bone's closed triangle surface in its field's frame, prepared for exact distances
    (:class:`.triangle_distance.PreparedSurface`) where the fields are not exact enough
    (:mod:`.bones.exact_distance`); empty when the caller did not give them."""

    @classmethod
    def pack(cls, fields, names=None, surfaces=()) -> "BoneFieldSet":
        """Pack :class:`BoneDistanceField` objects (in bone order) into one set, with the
        surfaces they were sampled from (optional, in the same order)."""
        fields = list(fields)
        surfaces = tuple(surfaces)
        if surfaces and len(surfaces) != len(fields):
            raise MuscleMSSError(f"bone fields: {len(fields)} fields but {len(surfaces)} "
                                 "surfaces")
        names = tuple(names) if names is not None else tuple(str(i) for i in range(len(fields)))
        coarse_start = np.cumsum([0] + [len(f.coarse) for f in fields])[:-1].astype(np.int64)
        index_start = np.cumsum([0] + [len(f.brick_index) for f in fields])[:-1].astype(np.int64)
        brick_start = np.cumsum([0] + [len(f.bricks) for f in fields])[:-1]
        indices = [np.where(f.brick_index >= 0, f.brick_index + s, -1).astype(np.int32)
                   for f, s in zip(fields, brick_start)]
        nodes = (BRICK + 1) ** 3
        return cls(
            names=names,
            origin=np.array([f.origin for f in fields], dtype=np.float64).reshape(-1, 3),
            spacing=np.array([f.spacing for f in fields], dtype=np.float64),
            dims=np.array([f.dims for f in fields], dtype=np.int64).reshape(-1, 3),
            coarse_start=coarse_start,
            coarse=np.concatenate([f.coarse for f in fields] + [np.zeros(0, np.float32)]),
            index_start=index_start,
            brick_index=np.concatenate(indices + [np.zeros(0, np.int32)]),
            bricks=np.concatenate([f.bricks.reshape(-1, nodes) for f in fields]
                                  + [np.zeros((0, nodes), np.float32)]),
            surfaces=surfaces)

    def error_bounds(self) -> np.ndarray:
        """(b,) mm: :attr:`BoneDistanceField.error_bound` of each bone's field."""
        rounding = 1e-6 * float(np.abs(self.coarse).max(initial=0.0))
        return math.sqrt(3.0) * COARSE * self.spacing + rounding

    def __len__(self):
        return len(self.names)

    def grid(self) -> FieldGrid:
        """The packed arrays as the kernels take them."""
        return FieldGrid(self.origin, self.spacing, self.dims, self.coarse_start, self.coarse,
                         self.index_start, self.brick_index, self.bricks)


@dataclass
class BoneSolids:
    """Bones as solids for the solvers' muscle-bone contacts (instead of their sphere sets):
    ``fields`` a :class:`BoneFieldSet` of b bones sampled in their own frames, ``transforms``
    (b, 3, 4) each bone's field frame to its posed place, and ``clearance`` (b,) mm that every
    muscle sphere keeps from the bone's surface beyond its own radius (the radius of the bone's
    spheres, the paper's bone thickness: a sphere clear of the solid is clear of the sphere set
    too). Particles inside a bone at rest have no sphere (the Rigid Pose Transform clears them,
    :func:`muscle_mss.filters.bone_sets.clear_of_bones`), so no solid pushes them."""

    fields: BoneFieldSet
    transforms: np.ndarray
    clearance: np.ndarray

    def check(self) -> None:
        """Raise :class:`MuscleMSSError` unless there is one finite 3x4 transform and one finite
        clearance of 0 mm or more per bone."""
        b = len(self.fields)
        transforms = np.asarray(self.transforms)
        clearance = np.asarray(self.clearance)
        if transforms.shape != (b, 3, 4) or not np.isfinite(transforms).all():
            raise MuscleMSSError(f"the bone solids need one finite 3x4 transform per bone ({b}); "
                                 f"got shape {transforms.shape}")
        if clearance.shape != (b,) or not (np.isfinite(clearance).all()
                                           and (clearance >= 0).all()):
            raise MuscleMSSError(f"the bone solids need one finite clearance of 0 mm or more per "
                                 f"bone ({b}); got {clearance}")

    @property
    def reach(self) -> float:
        """mm: the farthest a push out of a bone can move a point (half the largest sampled
        box's diagonal plus the largest clearance; 0 without bones)."""
        if not len(self.fields):
            return 0.0
        boxes = self.fields.dims * BRICK * self.fields.spacing[:, None]
        return float(0.5 * np.linalg.norm(boxes, axis=1).max() + np.max(self.clearance))

    def kernel_arguments(self) -> tuple:
        """``(transforms, clearance, push tolerance mm)`` for the kernels, which take the
        fields as ``fields.grid()`` beside them; :data:`NO_SOLIDS` has the same types and no
        bone."""
        tolerance = 1e-3 * float(self.fields.spacing.min()) if len(self.fields) else 0.0
        return (np.ascontiguousarray(self.transforms, dtype=np.float64),
                np.ascontiguousarray(self.clearance, dtype=np.float64), tolerance)


# ---- lookup ----------------------------------------------------------------------------------

@njit(cache=True)
def _trilinear(values, base, sx, sy, fx, fy, fz):
    """Value and gradient (per cell) of the trilinear interpolant of the cell whose corner
    (0, 0, 0) is ``values[base]`` (strides ``sx``, ``sy``, 1) at fractions (fx, fy, fz)."""
    c000 = values[base]
    c001 = values[base + 1]
    c010 = values[base + sy]
    c011 = values[base + sy + 1]
    c100 = values[base + sx]
    c101 = values[base + sx + 1]
    c110 = values[base + sx + sy]
    c111 = values[base + sx + sy + 1]
    gx0, gy0, gz0 = 1.0 - fx, 1.0 - fy, 1.0 - fz
    c00 = c000 * gz0 + c001 * fz
    c01 = c010 * gz0 + c011 * fz
    c10 = c100 * gz0 + c101 * fz
    c11 = c110 * gz0 + c111 * fz
    c0 = c00 * gy0 + c01 * fy
    c1 = c10 * gy0 + c11 * fy
    value = c0 * gx0 + c1 * fx
    dx = c1 - c0
    dy = (c01 - c00) * gx0 + (c11 - c10) * fx
    dz = ((c001 - c000) * gy0 + (c011 - c010) * fy) * gx0 \
        + ((c101 - c100) * gy0 + (c111 - c110) * fy) * fx
    return value, dx, dy, dz


@njit(cache=True)
def _sample_inside_box(b, ux, uy, uz, grid):
    """Value and rest-frame gradient at (ux, uy, uz), in fine cells from the box's origin
    (inside the box)."""
    dims = grid.dims
    nx, ny, nz = dims[b, 0], dims[b, 1], dims[b, 2]
    bi = min(int(ux / BRICK), nx - 1)
    bj = min(int(uy / BRICK), ny - 1)
    bk = min(int(uz / BRICK), nz - 1)
    block = grid.brick_index[grid.index_start[b] + (bi * ny + bj) * nz + bk]
    h = grid.spacing[b]
    if block >= 0:
        lx, ly, lz = ux - bi * BRICK, uy - bj * BRICK, uz - bk * BRICK
        i = min(int(lx), BRICK - 1)
        j = min(int(ly), BRICK - 1)
        k = min(int(lz), BRICK - 1)
        n = BRICK + 1
        value, dx, dy, dz = _trilinear(grid.bricks[block], (i * n + j) * n + k, n * n, n,
                                       lx - i, ly - j, lz - k)
        return value, dx / h, dy / h, dz / h
    per = BRICK // COARSE
    cx, cy, cz = ux / COARSE, uy / COARSE, uz / COARSE
    i = min(int(cx), nx * per - 1)
    j = min(int(cy), ny * per - 1)
    k = min(int(cz), nz * per - 1)
    sy = nz * per + 1
    sx = (ny * per + 1) * sy
    value, dx, dy, dz = _trilinear(grid.coarse, grid.coarse_start[b] + i * sx + j * sy + k,
                                   sx, sy, cx - i, cy - j, cz - k)
    size = COARSE * h
    return value, dx / size, dy / size, dz / size


@njit(cache=True)
def sample(b, qx, qy, qz, grid):
    """Signed distance (mm) and its gradient at rest-frame point q of bone b of ``grid``
    (:data:`FieldGrid`)."""
    origin, dims = grid.origin, grid.dims
    h = grid.spacing[b]
    ux = (qx - origin[b, 0]) / h
    uy = (qy - origin[b, 1]) / h
    uz = (qz - origin[b, 2]) / h
    mx = dims[b, 0] * BRICK
    my = dims[b, 1] * BRICK
    mz = dims[b, 2] * BRICK
    cx = min(max(ux, 0.0), float(mx))
    cy = min(max(uy, 0.0), float(my))
    cz = min(max(uz, 0.0), float(mz))
    value, gx, gy, gz = _sample_inside_box(b, cx, cy, cz, grid)
    ox, oy, oz = (ux - cx) * h, (uy - cy) * h, (uz - cz) * h
    away = math.sqrt(ox * ox + oy * oy + oz * oz)
    if away > 0.0:
        return value + away, ox / away, oy / away, oz / away
    return value, gx, gy, gz


@njit(cache=True)
def to_rest(transforms, b, x, y, z):
    """``R^T (x - t)`` for bone b's rest-to-posed transform ``transforms[b]`` (3, 4)."""
    m = transforms[b]
    dx, dy, dz = x - m[0, 3], y - m[1, 3], z - m[2, 3]
    return (m[0, 0] * dx + m[1, 0] * dy + m[2, 0] * dz,
            m[0, 1] * dx + m[1, 1] * dy + m[2, 1] * dz,
            m[0, 2] * dx + m[1, 2] * dy + m[2, 2] * dz)


@njit(parallel=True, cache=True)
def _signed_distances(points, transforms, grid, distance, gradient):
    for p in prange(points.shape[0]):
        for b in range(transforms.shape[0]):
            qx, qy, qz = to_rest(transforms, b, points[p, 0], points[p, 1], points[p, 2])
            value, gx, gy, gz = sample(b, qx, qy, qz, grid)
            distance[p, b] = value
            m = transforms[b]
            for axis in range(3):
                gradient[p, b, axis] = m[axis, 0] * gx + m[axis, 1] * gy + m[axis, 2] * gz


def _checked_transforms(fields: BoneFieldSet, transforms) -> np.ndarray:
    if transforms is None:
        transforms = np.tile(np.eye(3, 4), (len(fields), 1, 1))
    transforms = np.ascontiguousarray(transforms, dtype=np.float64)
    if transforms.shape != (len(fields), 3, 4):
        raise MuscleMSSError(f"bone transforms must be ({len(fields)}, 3, 4), one rigid 3x4 "
                             f"per bone; got shape {transforms.shape}")
    if not np.isfinite(transforms).all():
        raise MuscleMSSError("bone transforms have NaN or infinite values")
    return transforms


def signed_distances(fields: BoneFieldSet, points, transforms=None):
    """Signed distance of ``points`` (n, 3) mm to every posed bone, and its gradient.

    ``transforms`` (b, 3, 4): each bone's rest-to-posed rigid transform ``x' = M[:, :3] x +
    M[:, 3]`` (None: the rest pose). Returns ``distance`` (n, b) float64 mm (negative inside)
    and ``gradient`` (n, b, 3) float64, unit length up to interpolation, in posed coordinates.
    """
    points = checked_points(points)
    transforms = _checked_transforms(fields, transforms)
    distance = np.empty((len(points), len(fields)))
    gradient = np.empty((len(points), len(fields), 3))
    if len(points) and len(fields):
        _signed_distances(points, transforms, fields.grid(), distance, gradient)
    return distance, gradient


# ---- pushing points out ----------------------------------------------------------------------

@njit(cache=True)
def push_rest(b, qx, qy, qz, radius, tolerance, grid):
    """Move rest-frame point q of bone b of ``grid`` (:data:`FieldGrid`) along the distance
    gradient until its distance is at least ``radius - tolerance``; returns the new q and
    whether it moved."""
    moved = False
    for _ in range(PUSH_STEPS):
        value, gx, gy, gz = sample(b, qx, qy, qz, grid)
        if value >= radius - tolerance:
            break
        norm = math.sqrt(gx * gx + gy * gy + gz * gz)
        if norm < 1e-9:
            # A point on a ridge of the field (e.g. a box's centre): the gradient cancels; go
            # the way, of the six axis directions one node away, the distance grows most.
            h = grid.spacing[b]
            best = -np.inf
            for axis in range(6):
                sign = 1.0 if axis < 3 else -1.0
                ex = sign * h if axis % 3 == 0 else 0.0
                ey = sign * h if axis % 3 == 1 else 0.0
                ez = sign * h if axis % 3 == 2 else 0.0
                trial = sample(b, qx + ex, qy + ey, qz + ez, grid)[0]
                if trial > best:
                    best, gx, gy, gz = trial, ex / h, ey / h, ez / h
            norm = 1.0
        step = (radius - value + 0.5 * tolerance) / norm
        qx += step * gx
        qy += step * gy
        qz += step * gz
        moved = True
    return qx, qy, qz, moved


@njit(parallel=True, cache=True)
def _push_out_of_bones(points, radii, active, transforms, tolerance, grid, displacement):
    for p in prange(points.shape[0]):
        x, y, z = points[p, 0], points[p, 1], points[p, 2]
        for _ in range(PUSH_SWEEPS):
            any_moved = False
            for b in range(transforms.shape[0]):
                if active[p, b] == 0:
                    continue
                qx, qy, qz = to_rest(transforms, b, x, y, z)
                qx, qy, qz, moved = push_rest(b, qx, qy, qz, radii[p], tolerance, grid)
                if moved:
                    m = transforms[b]
                    x = m[0, 0] * qx + m[0, 1] * qy + m[0, 2] * qz + m[0, 3]
                    y = m[1, 0] * qx + m[1, 1] * qy + m[1, 2] * qz + m[1, 3]
                    z = m[2, 0] * qx + m[2, 1] * qy + m[2, 2] * qz + m[2, 3]
                    any_moved = True
            if not any_moved:
                break
        displacement[p, 0] = x - points[p, 0]
        displacement[p, 1] = y - points[p, 1]
        displacement[p, 2] = z - points[p, 2]


def push_out_of_bones(fields: BoneFieldSet, points, radii=None, transforms=None, active=None,
                      tolerance=None) -> np.ndarray:
    """Displacements that put every point ``radius`` outside every posed bone it is checked
    against, along the distance gradient, from whatever depth it starts.

    Parameters
    ----------
    fields : BoneFieldSet
        The bones' fields (:func:`.bones.field_sampling.bone_field_set`), b bones.
    points : (n, 3) float64 mm
        Posed positions: collision sphere centres, or surface vertices.
    radii : (n,) float64 mm, optional
        Clearance each point needs (its sphere radius); None or 0 puts a point on the surface.
    transforms : (b, 3, 4) float64, optional
        Each bone's rest-to-posed rigid transform (None: the rest pose).
    active : (n,) or (n, b) bool, optional
        Which points (or which point-bone pairs) to push; the others get a zero displacement
        (tendon attachments that belong inside their bone, surface vertices already inside a
        bone at rest). None: all.
    tolerance : float, mm, optional
        A point counts as out when its interpolated distance is at least ``radius -
        tolerance`` (default 1e-3 of the finest spacing).

    Returns
    -------
    (n, 3) float64 mm
        ``points + displacement`` is out of every checked bone (the interpolated distance at
        least ``radius - tolerance``) unless a point is held between two bones closer together
        than twice its radius; the displacement of a point already out is exactly 0.

    A point deeper than half the bone's thickness leaves by the nearer side, which is then the
    far side from where it came in: callers that move points into bones by small steps (a
    solver iteration) push them every step.
    """
    points = checked_points(points)
    n, b = len(points), len(fields)
    radii = np.zeros(n) if radii is None else \
        np.array(np.broadcast_to(np.asarray(radii, dtype=np.float64), (n,)))
    if not np.isfinite(radii).all() or (radii < 0).any():
        raise MuscleMSSError("push out of bones: radii must be finite and 0 or more (mm)")
    transforms = _checked_transforms(fields, transforms)
    if active is None:
        mask = np.ones((n, b), dtype=np.uint8)
    else:
        active = np.asarray(active, dtype=bool)
        if active.shape not in ((n,), (n, b)):
            raise MuscleMSSError(f"push out of bones: active must have shape ({n},) or "
                                 f"({n}, {b}); got {active.shape}")
        mask = np.ascontiguousarray(np.broadcast_to(active.reshape(n, -1), (n, b)),
                                    dtype=np.uint8)
    if tolerance is None:
        tolerance = 1e-3 * float(fields.spacing.min()) if b else 0.0
    displacement = np.zeros((n, 3))
    if n and b:
        _push_out_of_bones(points, radii, mask, transforms, float(tolerance), fields.grid(),
                           displacement)
    return displacement


NO_SOLIDS = BoneSolids(BoneFieldSet.pack([]), np.zeros((0, 3, 4)), np.zeros(0))
"""No bone as a solid (the kernels' argument when the bones are sphere sets)."""
