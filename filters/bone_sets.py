"""Bones of an input multiblock as collision spheres (paper §3.3: bones are sphere sets too), and
as solids (signed distance fields) for the quasi-static solver's contacts.

One place that turns a bones multiblock into the spheres of :func:`muscle_mss.core.bones.spheres.
bone_spheres`, so that the Spring Builder (clearing muscle radii at rest), the MSS Collision
Solver (collisions) and the motion runner (remaining penetration) see the same spheres.

Bones are rigid, so a bone's spheres are sampled once per bone shape and spacing and then moved
with the bone (the Poisson-disc sampling of every posed bone at every time point was
0.2 s per time point on the demo leg). The cache is keyed by the bone's connectivity and the
spacing; an entry keeps the points it was sampled on. A later bone with the same connectivity
whose points are bitwise those points gets the cached spheres as they are (so the same input
always gives the same spheres); one whose points are a rigid motion of them (Kabsch fit, largest
residual below :data:`SAME_BONE_RESIDUAL` of the bone's size) gets the cached spheres moved by that
motion; any other bone is sampled afresh. Sampling is itself equivariant under rigid motions
(candidates and their visiting order follow the triangles, not the coordinates), so a moved
cached set equals a fresh sampling of the moved bone up to rounding. The bones' signed distance
fields (:func:`bone_solids`) go through a cache of the same kind: sampled once per bone shape
(10 s for the three bones of the demo thigh), then placed by the fitted rigid motion; a shape
sampled by an earlier run is read from disk (:mod:`muscle_mss.core.bones.field_store`).
"""
import hashlib
from collections import OrderedDict

import numpy as np

from muscle_mss.core.bones.distance import (BoneFieldSet, BoneSolids, push_out_of_bones,
                                            signed_distances)
from muscle_mss.core.bones.field_sampling import bone_distance_field
from muscle_mss.core.bones.exact_distance import exact_signed_distances, push_out_exactly
from muscle_mss.core.bones.triangle_distance import (PreparedSurface, inside_surface,
                                                prepared_surface, surface_digest)
from muscle_mss.core.bones import field_store
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.bones.spheres import bone_spheres
from muscle_mss.core.mesh_checks import surface_problems
from muscle_mss.core.model import Bones
from muscle_mss.core.settings import BONE_CONTACT_SOLID, DEFAULT_BONE_SPHERE_SPACING
from muscle_mss.core.radii import SHRINK_MARGIN, clear_of_obstacles
from muscle_mss.core.rigid_fit import fitted_rigid_transform, rigid_fit

from . import array_names as A
from . import vtk_arrays as V

SAME_BONE_RESIDUAL = 1e-9
"""A bone whose points are a rigid motion of a cached entry's points (the Kabsch fit's largest
residual at most this fraction of the bone's size) gets the cached entry, moved."""
INSIDE_TOLERANCE = 1e-3
"""mm: a point (surface vertex, particle) counts as inside a bone when its signed distance is
below minus this."""
CACHE_ENTRIES = 64          # bone shapes kept (least recently used dropped)

#: What the cache did since :func:`clear_bone_cache`: ``sampled`` (fresh Poisson-disc
#: samplings), ``reused`` (same points, spheres returned as cached), ``moved`` (rigid copy).
cache_counts = {"sampled": 0, "reused": 0, "moved": 0}
_cache = OrderedDict()      # key -> list of (points (n, 3), (centres (k, 3), radii (k,)))
#: The same for the bones' distance fields (:func:`cached_bone_field`), with ``loaded``: read
#: from the disk store (:mod:`muscle_mss.core.bones.field_store`) instead of sampled, and
#: ``remembered``: bones that :func:`bone_solids` returned from its memory of the same,
#: unmodified blocks.
field_counts = {"sampled": 0, "loaded": 0, "reused": 0, "moved": 0, "remembered": 0}
_field_cache = OrderedDict()    # key -> list of (points (n, 3), BoneDistanceField)
_field_surfaces = OrderedDict()  # id(field) -> (field, its PreparedSurface), fields cached
_packed = {}                    # the last packed BoneFieldSet and the fields it holds
_solids = OrderedDict()         # the blocks' VTK identities -> bone_solids' result
_digests = OrderedDict()        # a cell array's VTK identity -> its triangles' digest
SOLIDS_ENTRIES = 4              # bone multiblocks remembered by bone_solids


def clear_bone_cache():
    """Forget every cached bone and zero :data:`cache_counts` and :data:`field_counts`."""
    _cache.clear()
    _field_cache.clear()
    _field_surfaces.clear()
    _packed.clear()
    _solids.clear()
    _digests.clear()
    for counts in (cache_counts, field_counts):
        for name in counts:
            counts[name] = 0


def _cache_key(points, triangles, *extra, digest=None) -> str:
    """The cache key of a bone shape: its triangles' digest (``digest`` when the caller has it,
    :func:`_block_shape`), point count and ``extra``."""
    digest = digest or _triangles_digest(triangles)
    return digest + np.asarray([len(points), *extra], dtype=np.float64).tobytes().hex()


def _triangles_digest(triangles) -> str:
    return hashlib.blake2b(np.ascontiguousarray(triangles, dtype=np.int64).tobytes(),
                           digest_size=16).hexdigest()


def _block_shape(block, where):
    """``(points (n, 3) mm, triangles (m, 3), triangles' digest)`` of a bone block. The digest
    (0.6-0.9 ms a demo bone) is remembered for the same cell array unmodified (its VTK object
    and modification time): the Rigid Pose Transform hands on the rest bones' triangles at
    every time point."""
    polys = block.GetPolys()
    identity = (polys.__this__, polys.GetMTime())
    triangles = V.triangles_of(block, where)
    digest = _digests.get(identity)
    if digest is None:
        digest = _digests[identity] = _triangles_digest(triangles)
        while len(_digests) > CACHE_ENTRIES:
            _digests.popitem(last=False)
    return V.points_of(block), triangles, digest


def _cached(cache, key, points):
    """The entry of ``cache[key]`` (a list of ``(points, value)``) sampled on ``points`` (n, 3)
    mm or on a rigid motion of them: ``(value, rotation (3, 3) or None, translation (3,) or
    None)`` (None: the same points), or None. The key moves to the cache's recent end."""
    entries = cache.setdefault(key, [])
    cache.move_to_end(key)
    for rest, value in entries:
        if rest.shape != points.shape:
            continue
        if np.array_equal(rest, points):
            return value, None, None
        rotation, translation, residual, size = rigid_fit(rest, points)
        if residual <= SAME_BONE_RESIDUAL * (size + 1.0):
            return value, rotation, translation
    return None


def _store(cache, key, points, value):
    cache[key].append((points.copy(), value))
    while len(cache) > CACHE_ENTRIES:
        cache.popitem(last=False)


def cached_bone_spheres(points, triangles, spacing=None, where: str = "bone", use_cache=True,
                        digest=None):
    """:func:`bone_spheres` of one bone surface (``points`` (n, 3) mm, ``triangles`` (m, 3)),
    through the rigid-bone cache described in the module docstring (``use_cache=False``: always
    sample; ``digest``: the triangles' digest, :func:`_block_shape`). Returns ``(centres (k, 3)
    mm, radii (k,) mm)``, arrays the caller may keep."""
    spacing = DEFAULT_BONE_SPHERE_SPACING if spacing is None else spacing
    if not use_cache:
        return bone_spheres(points, triangles, spacing, where=where)
    points = np.ascontiguousarray(points, dtype=np.float64)
    key = _cache_key(points, triangles, float(spacing), digest=digest)
    found = _cached(_cache, key, points)
    if found is not None:
        (centres, radii), rotation, translation = found
        if rotation is None:
            cache_counts["reused"] += 1
            return centres.copy(), radii.copy()
        cache_counts["moved"] += 1
        return centres @ rotation.T + translation, radii.copy()
    centres, radii = bone_spheres(points, triangles, spacing, where=where)
    cache_counts["sampled"] += 1
    _store(_cache, key, points, (centres.copy(), radii.copy()))
    return centres, radii


def cached_bone_field(points, triangles, where: str = "bone", digest=None):
    """The signed distance field of one bone surface (:func:`muscle_mss.core.bones.field_sampling.
    bone_distance_field`, default spacing) through a rigid-bone cache like the spheres': the
    field of the first surface of this shape, and the (3, 4) transform from that field's frame
    to ``points``. A shape not in memory is read from the disk store of earlier runs
    (:mod:`muscle_mss.core.bones.field_store`) or sampled and stored there. Returns
    ``(BoneDistanceField, transform)``."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    key = _cache_key(points, triangles, digest=digest)
    found = _cached(_field_cache, key, points)
    if found is not None:
        field, rotation, translation = found
        field_counts["reused" if rotation is None else "moved"] += 1
        if rotation is None:
            return field, np.eye(3, 4)
        return field, np.hstack([rotation, translation[:, None]])
    stored = surface_digest(points, triangles)
    field = field_store.load(stored)
    if field is not None:
        field_counts["loaded"] += 1
    else:
        field = bone_distance_field(points, triangles, where=where)
        field_counts["sampled"] += 1
        field_store.save(stored, field)
    _store(_field_cache, key, points, field)
    _field_surfaces[id(field)] = (field, prepared_surface(points, triangles, where))
    if len(_field_surfaces) > CACHE_ENTRIES:        # forget the fields the cache dropped
        cached = {id(f) for entries in _field_cache.values() for _, f in entries}
        for key in [k for k in _field_surfaces if k not in cached]:
            del _field_surfaces[key]
    return field, np.eye(3, 4)


def field_surface(field) -> PreparedSurface:
    """The bone surface a field of :func:`cached_bone_field` was sampled from, in the field's
    frame, prepared for exact distances (:mod:`muscle_mss.core.bones.exact_distance`)."""
    return _field_surfaces[id(field)][1]


def bone_solids(bones, where: str = "bones"):
    """Every bone of a multiblock as a solid: ``(BoneFieldSet, transforms (b, 3, 4))``, bone b
    being its block's index, each field sampled once per bone shape (:func:`cached_bone_field`)
    and placed by its transform.

    The same blocks, unmodified since (VTK object and modification time), give the result of
    the last call without hashing and fitting the bones again: within one time point the solver,
    its per-muscle reports and the runner's statistics all ask for the same posed bones (45
    cache lookups of 3-5 ms each per demo time point)."""
    blocks = V.polydata_blocks(bones, where, "a triangle surface")
    identity = tuple((name, block.__this__, block.GetMTime()) for name, block in blocks)
    if identity in _solids:
        _solids.move_to_end(identity)
        field_counts["remembered"] += len(blocks)
        packed, transforms = _solids[identity]
        return packed, transforms.copy()
    fields, transforms, names = [], [], []
    for name, block in blocks:
        block_where = f"{where} block '{name}'"
        points, triangles, digest = _block_shape(block, block_where)
        field, transform = cached_bone_field(points, triangles, block_where, digest)
        fields.append(field)
        transforms.append(transform)
        names.append(name)
    key = tuple(id(f) for f in fields)
    if _packed.get("key") != key:
        _packed.clear()
        _packed.update(key=key, fields=BoneFieldSet.pack(
            fields, names, [field_surface(field) for field in fields]))
    transforms = np.array(transforms).reshape(-1, 3, 4)
    _solids[identity] = (_packed["fields"], transforms.copy())
    while len(_solids) > SOLIDS_ENTRIES:
        _solids.popitem(last=False)
    return _packed["fields"], transforms


def bone_sphere_set(bones, spacing=None, where: str = "bones", use_cache=True):
    """Spheres on every bone of a multiblock: ``(centres (k, 3) mm, radii (k,) mm, bone (k,)
    int)``, the bone being its block's index. ``spacing`` (mm) as in :func:`bone_spheres`
    (None: its default). Each bone goes through :func:`cached_bone_spheres`."""
    centres, radii, ids = [np.zeros((0, 3))], [np.zeros(0)], [np.zeros(0, dtype=np.int64)]
    for k, (name, block) in enumerate(V.polydata_blocks(bones, where, "a triangle surface")):
        block_where = f"{where} block '{name}'"
        points, triangles, digest = _block_shape(block, block_where)
        c, r = cached_bone_spheres(points, triangles, spacing, block_where, use_cache, digest)
        centres.append(c)
        radii.append(r)
        ids.append(np.full(len(c), k, dtype=np.int64))
    return np.concatenate(centres), np.concatenate(radii), np.concatenate(ids)


def bone_depths(points, bones, where: str = "bones") -> np.ndarray:
    """How deep (mm, (n,)) each of ``points`` (n, 3) mm lies inside a bone of the posed
    multiblock ``bones`` (:func:`bone_solids`, exact near the surfaces:
    :func:`~muscle_mss.core.bones.exact_distance.exact_signed_distances`): minus the smallest
    signed distance, negative outside every bone."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    fields, transforms = bone_solids(bones, where)
    return -exact_signed_distances(fields, points, transforms).min(axis=1, initial=np.inf)


def particles_in_bones(depth, free, in_bone_at_rest) -> tuple:
    """``(count, deepest mm, new count, new deepest mm)`` of the ``free`` (n,) bool particles
    whose centre is inside a bone by more than :data:`INSIDE_TOLERANCE`, their ``depth`` (n,)
    mm as :func:`bone_depths` gives it, all of them and those not ``in_bone_at_rest`` (n,)
    bool (None: not known, all count as new)."""
    free = np.asarray(free, dtype=bool)
    depth = np.asarray(depth, dtype=np.float64)[free]
    inside = depth > INSIDE_TOLERANCE
    new = inside if in_bone_at_rest is None else inside & ~np.asarray(in_bone_at_rest,
                                                                       dtype=bool)[free]
    return tuple(v for mask in (inside, new)
                 for v in (int(mask.sum()), float(np.where(mask, depth, 0.0).max(initial=0.0))))


def clear_of_bones(centres, radii, bones, where: str = "bones"):
    """``(radii (n,) mm, inside (n,) bool)``: the ``radii`` of muscle spheres at ``centres``
    (n, 3) mm, in the rest pose of the bones multiblock ``bones``, lowered until no sphere
    overlaps a bone sphere
    (:func:`bone_sphere_set` at the default spacing, the MSS Collision Solver's sphere sets) nor
    reaches into a bone as a solid (its cached distance field, :func:`cached_bone_field`, as
    the solver's solid contacts see it); a particle inside a bone gets 0 (no sphere: it is
    embedded in the bone, near a tendon, and the solver would push it out of the bone it
    belongs to); ``inside`` says which (the exact signed distance below 0). Then nothing moves a
    rest pose: DESIGN §6, no two spheres of different objects overlap at rest. Applying it to
    cleared radii changes nothing, so the Spring Builder (with its Bones input) and the Rigid
    Pose Transform (always) both apply it. A bone that is not closed and consistently oriented
    has no inside: only its spheres count."""
    centres = np.ascontiguousarray(centres, dtype=np.float64).reshape(-1, 3)
    bone_centres, bone_radii, _ = bone_sphere_set(bones, where=where)
    radii = clear_of_obstacles(centres, radii, bone_centres, bone_radii)
    inside = np.zeros(len(centres), dtype=bool)
    for name, block in V.polydata_blocks(bones, where, "a triangle surface"):
        block_where = f"{where} block '{name}'"
        vertices, triangles = V.points_of(block), V.triangles_of(block, block_where)
        if surface_problems(vertices, triangles):
            continue
        field, transform = cached_bone_field(vertices, triangles, block_where)
        distance = signed_distances(BoneFieldSet.pack([field]), centres, transform[None])[0]
        radii = np.minimum(radii, np.maximum(distance[:, 0], 0.0) * (1.0 - SHRINK_MARGIN))
        inside |= inside_surface(vertices, triangles, centres, distance[:, 0],
                                 field.error_bound, where=block_where)
    radii[inside] = 0.0
    return radii, inside


POSED_BONES = "PosedBones"
"""The MSS Collision Solver's bones input, named in the messages about its blocks."""


def solid_bones(posed_bones) -> BoneSolids:
    """The posed bones multiblock as solids for the solvers' contacts. A muscle sphere may
    touch a solid bone (clearance 0): the sphere sets' radius thickens the bones by the
    spacing only because a shell of spheres needs it to be closed."""
    fields, transforms = bone_solids(posed_bones, POSED_BONES)
    return BoneSolids(fields, transforms, np.zeros(len(fields)))


def contact_bones(posed_bones, contact: str, spacing: float = DEFAULT_BONE_SPHERE_SPACING,
                  muscle_bone: bool = True) -> Bones:
    """The posed bones multiblock as the solver's :class:`~muscle_mss.core.model.Bones` for the
    bone ``contact`` (one of :data:`~muscle_mss.core.settings.BONE_CONTACTS`): the sphere sets at
    ``spacing`` mm, or the solids (none when ``muscle_bone`` is off: nothing would read them)."""
    if contact != BONE_CONTACT_SOLID:
        return Bones(spheres=bone_sphere_set(posed_bones, spacing, POSED_BONES))
    return Bones(solids=solid_bones(posed_bones) if muscle_bone else None)


# ---- the deformed surfaces kept out of the posed bones (the MVC Surface Deformer) -----------

def posed_bone_transforms(rest_points: dict, posed_bones) -> np.ndarray:
    """(b, 3, 4) rest-to-posed transforms of the bones ``rest_points`` ({name: (n, 3) mm}),
    fitted to the blocks of the same names in ``posed_bones``."""
    posed = dict(V.polydata_blocks(posed_bones, "PosedBones", "a bone's triangle surface"))
    transforms = []
    for name, points in rest_points.items():
        if name not in posed:
            raise MuscleMSSError(f"PosedBones: has no block '{name}'; it must hold the bones of "
                                 "RestBones (block names must match)")
        transforms.append(fitted_rigid_transform(points, V.points_of(posed[name]),
                                                 where=f"PosedBones block '{name}'"))
    return np.array(transforms).reshape(-1, 3, 4)


def composed_transforms(outer, inner) -> np.ndarray:
    """(b, 3, 4) transforms: each of ``inner`` (b, 3, 4) followed by the same bone's ``outer``."""
    rotation = outer[:, :, :3] @ inner[:, :, :3]
    shift = np.einsum("bij,bj->bi", outer[:, :, :3], inner[:, :, 3]) + outer[:, :, 3]
    return np.concatenate([rotation, shift[:, :, None]], axis=2)


def new_in_bones(fields, transforms, points, outside):
    """``(inside (n,) bool, depth (n,) mm)`` of the ``points`` (n, 3): which are inside a posed
    bone they were ``outside`` (n, b) at rest, and how deep (0 for the others), by the bones'
    exact distance near their surfaces."""
    distance = exact_signed_distances(fields, points, transforms)
    new = (distance < -INSIDE_TOLERANCE) & outside
    return new.any(axis=1), np.where(new, -distance, 0.0).max(axis=1, initial=0.0)


def keep_out_of_bones(deformed: list, fields, transforms, outside, push):
    """The muscles' ``deformed`` surface vertices (a list of (v_i, 3) arrays, mm) with those
    newly inside a bone pushed out (when ``push``), and for each muscle what to report:
    ``{array or field name: value}``. ``outside`` (sum v_i, b) bool: which vertex was outside
    which bone at rest, the muscles' in turn. All muscles go through each kernel at once (one
    parallel region each, not one per muscle)."""
    sizes = np.array([len(d) for d in deformed])
    starts = np.concatenate([[0], np.cumsum(sizes)])
    muscle = np.repeat(np.arange(len(sizes)), sizes)
    points = np.concatenate(deformed)
    inside, depth = new_in_bones(fields, transforms, points, outside)
    count = np.bincount(muscle[inside], minlength=len(sizes))
    deepest = np.maximum.reduceat(depth, starts[:-1])
    count_after, deepest_after = count, deepest
    if push and inside.any():
        # only the vertices newly inside move (a vertex already out gets exactly 0)
        points[inside] += push_out_of_bones(fields, points[inside], None, transforms,
                                            active=outside[inside], tolerance=INSIDE_TOLERANCE)
        # the fields' push leaves a vertex up to their error inside a thin bone: finish exactly
        points[inside] += push_out_exactly(fields, points[inside], transforms, outside[inside])
        still, depth_after = new_in_bones(fields, transforms, points[inside], outside[inside])
        count_after = np.bincount(muscle[inside][still], minlength=len(sizes))
        deepest_after = np.zeros(len(sizes))
        np.maximum.at(deepest_after, muscle[inside], depth_after)
    reports = [{A.NEW_IN_BONE_DEPTH: depth[a:b], A.NEW_IN_BONE_VERTICES: int(count[i]),
                A.NEW_IN_BONE_DEPTH_MM: float(deepest[i]),
                A.NEW_IN_BONE_VERTICES_AFTER: int(count_after[i]),
                A.NEW_IN_BONE_DEPTH_AFTER_MM: float(deepest_after[i])}
               for i, (a, b) in enumerate(zip(starts[:-1], starts[1:]))]
    return [points[a:b] for a, b in zip(starts[:-1], starts[1:])], reports
