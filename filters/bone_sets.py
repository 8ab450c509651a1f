"""Bones of an input multiblock as collision spheres (paper §3.3: bones are sphere sets too).

One place that turns a bones multiblock into the spheres of :func:`muscle_mss.core.bone_spheres.
bone_spheres`, so that the Spring Builder (clearing muscle radii at rest), the MSS Collision
Solver (collisions) and the motion runner (remaining penetration) see the same spheres.

Bones are rigid, so a bone's spheres are sampled once per bone shape and spacing and then moved
with the bone (issue 15: the Poisson-disc sampling of every posed bone at every time point was
0.2 s per time point on the demo leg). The cache is keyed by the bone's connectivity and the
spacing; an entry keeps the points it was sampled on. A later bone with the same connectivity
whose points are bitwise those points gets the cached spheres as they are (so the same input
always gives the same spheres); one whose points are a rigid motion of them (Kabsch fit, largest
residual below :data:`RIGID_TOLERANCE` of the bone's size) gets the cached spheres moved by that
motion; any other bone is sampled afresh. Sampling is itself equivariant under rigid motions
(candidates and their visiting order follow the triangles, not the coordinates), so a moved
cached set equals a fresh sampling of the moved bone up to rounding.
"""
import hashlib
from collections import OrderedDict

import numpy as np

from muscle_mss.core.bone_spheres import DEFAULT_SPACING, bone_spheres

from . import vtk_arrays as V

RIGID_TOLERANCE = 1e-9      # largest Kabsch residual / bone size that counts as the same bone
CACHE_ENTRIES = 64          # bone shapes kept (least recently used dropped)

#: What the cache did since :func:`clear_bone_cache`: ``sampled`` (fresh Poisson-disc
#: samplings), ``reused`` (same points, spheres returned as cached), ``moved`` (rigid copy).
cache_counts = {"sampled": 0, "reused": 0, "moved": 0}
_cache = OrderedDict()      # key -> list of (points (n, 3), centres (k, 3), radii (k,))


def clear_bone_cache():
    """Forget every cached bone and zero :data:`cache_counts`."""
    _cache.clear()
    for name in cache_counts:
        cache_counts[name] = 0


def rigid_fit(source, target):
    """Least-squares rigid motion taking ``source`` to ``target`` (both (n, 3) mm, same point
    order): ``(rotation (3, 3), translation (3,), residual mm)`` with ``target ≈ source @ R.T +
    t`` and ``residual`` the largest point distance left (Kabsch: SVD of the centred
    cross-covariance, reflection excluded)."""
    a = source.mean(axis=0)
    b = target.mean(axis=0)
    u, _, vt = np.linalg.svd((source - a).T @ (target - b))
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rotation = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    translation = b - a @ rotation.T
    moved = source @ rotation.T + translation
    return rotation, translation, float(np.sqrt(((moved - target) ** 2).sum(axis=1).max()))


def cached_bone_spheres(points, triangles, spacing=None, where: str = "bone", use_cache=True):
    """:func:`bone_spheres` of one bone surface (``points`` (n, 3) mm, ``triangles`` (m, 3)),
    through the rigid-bone cache described in the module docstring (``use_cache=False``: always
    sample). Returns ``(centres (k, 3) mm, radii (k,) mm)``, arrays the caller may keep."""
    spacing = DEFAULT_SPACING if spacing is None else spacing
    if not use_cache:
        return bone_spheres(points, triangles, spacing, where=where)
    points = np.ascontiguousarray(points, dtype=np.float64)
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    digest = hashlib.blake2b(triangles.tobytes(), digest_size=16)
    digest.update(np.asarray([len(points), float(spacing)]).tobytes())
    key = digest.hexdigest()
    entries = _cache.setdefault(key, [])
    _cache.move_to_end(key)
    for rest, centres, radii in entries:
        if rest.shape != points.shape:
            continue
        if np.array_equal(rest, points):
            cache_counts["reused"] += 1
            return centres.copy(), radii.copy()
        rotation, translation, residual = rigid_fit(rest, points)
        size = float(np.ptp(points, axis=0).max()) + 1.0
        if residual <= RIGID_TOLERANCE * size:
            cache_counts["moved"] += 1
            return centres @ rotation.T + translation, radii.copy()
    centres, radii = bone_spheres(points, triangles, spacing, where=where)
    cache_counts["sampled"] += 1
    entries.append((points.copy(), centres.copy(), radii.copy()))
    while len(_cache) > CACHE_ENTRIES:
        _cache.popitem(last=False)
    return centres, radii


def bone_sphere_set(bones, spacing=None, where: str = "bones", use_cache=True):
    """Spheres on every bone of a multiblock: ``(centres (k, 3) mm, radii (k,) mm, bone (k,)
    int)``, the bone being its block's index. ``spacing`` (mm) as in :func:`bone_spheres`
    (None: its default). Each bone goes through :func:`cached_bone_spheres`."""
    centres, radii, ids = [np.zeros((0, 3))], [np.zeros(0)], [np.zeros(0, dtype=np.int64)]
    for k, (name, block) in enumerate(V.polydata_blocks(bones, where, "a triangle surface")):
        block_where = f"{where} block '{name}'"
        c, r = cached_bone_spheres(V.points_of(block), V.triangles_of(block, block_where),
                                   spacing, block_where, use_cache)
        centres.append(c)
        radii.append(r)
        ids.append(np.full(len(c), k, dtype=np.int64))
    return np.concatenate(centres), np.concatenate(radii), np.concatenate(ids)
