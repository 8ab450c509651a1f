"""Bones of an input multiblock as collision spheres (paper §3.3: bones are sphere sets too).

One place that turns a bones multiblock into the spheres of :func:`muscle_mss.core.bone_spheres.
bone_spheres`, so that the Spring Builder (clearing muscle radii at rest), the MSS Collision
Solver (collisions) and the motion runner (remaining penetration) see the same spheres.
"""
import numpy as np

from muscle_mss.core.bone_spheres import bone_spheres

from . import vtk_arrays as V


def bone_sphere_set(bones, spacing=None, where: str = "bones"):
    """Spheres on every bone of a multiblock: ``(centres (k, 3) mm, radii (k,) mm, bone (k,)
    int)``, the bone being its block's index. ``spacing`` (mm) as in :func:`bone_spheres`
    (None: its default)."""
    centres, radii, ids = [np.zeros((0, 3))], [np.zeros(0)], [np.zeros(0, dtype=np.int64)]
    for k, (name, block) in enumerate(V.polydata_blocks(bones, where, "a triangle surface")):
        block_where = f"{where} block '{name}'"
        c, r = bone_spheres(V.points_of(block), V.triangles_of(block, block_where), spacing,
                            where=block_where)
        centres.append(c)
        radii.append(r)
        ids.append(np.full(len(c), k, dtype=np.int64))
    return np.concatenate(centres), np.concatenate(radii), np.concatenate(ids)
