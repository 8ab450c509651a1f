"""Point normals of a triangle surface, for shading the deformed muscle surfaces.

What VTK's ``vtkPolyDataNormals`` gives with splitting, consistency and auto-orientation off
(the MVC Surface Deformer's settings before it computed them here): each point's normal is the
normalised sum of the unit normals of its triangles, oriented by the triangles' winding.
vtkPolyDataNormals cost 0.44 ms a demo muscle surface per time point, mostly its pipeline
around the arithmetic; this kernel takes a few microseconds.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .volume import vector_between


@njit(cache=True)
def point_normals(points, triangles):
    """(n, 3) float32 unit point normals of the surface ``points`` (n, 3) mm, ``triangles``
    (m, 3) int (counter-clockwise seen from outside: outward normals). A point on no triangle,
    or whose triangles' normals cancel, gets (0, 0, 0); a degenerate triangle adds nothing."""
    total = np.zeros((points.shape[0], 3))
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        ux, uy, uz = vector_between(points, b, points, a)
        vx, vy, vz = vector_between(points, c, points, a)
        nx = uy * vz - uz * vy
        ny = uz * vx - ux * vz
        nz = ux * vy - uy * vx
        length = np.sqrt(nx * nx + ny * ny + nz * nz)
        if length == 0.0:
            continue
        for p in (a, b, c):
            total[p, 0] += nx / length
            total[p, 1] += ny / length
            total[p, 2] += nz / length
    out = np.zeros((points.shape[0], 3), dtype=np.float32)
    for p in range(points.shape[0]):
        length = np.sqrt(total[p, 0] ** 2 + total[p, 1] ** 2 + total[p, 2] ** 2)
        if length > 0.0:
            for k in range(3):
                out[p, k] = total[p, k] / length
    return out
