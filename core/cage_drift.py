"""How far each deformed surface vertex has left its cage: the safety net after the mean value
coordinates (:mod:`.mvc`).

A surface vertex follows its muscle's cage through its MVC weights. Where the cage folds tightly (a
thin, concave part of a lattice surface) a vertex close to it can carry weights of both signs much
larger than one, and then moves much more than the cage around it: on the small demo's rectus
femoris subdivided to 221,184 triangles, one vertex 0.03 mm inside the cage at rest ended 14 mm off
it at the most flexed pose. :func:`.mvc.bounded_coordinates` caps the absolute sum of every
vertex's weights at 8 (that vertex drifts 0.8 mm), but a vertex can still move up to 8 times as far
as the cage's non-affine motion around it. The rule: a vertex's *cage drift* is its distance to the
cage now minus its distance at rest (exact distances to the nearest cage triangle, the cage carried
by the particles); a vertex whose drift exceeds :data:`CAGE_DRIFT_LIMIT` mm has left its cage.
"""
from __future__ import annotations

import numpy as np

from .bones.triangle_distance import unsigned_distance

CAGE_DRIFT_LIMIT = 10.0
"""mm: the drift above which a vertex counts as having left its cage: twice the most that a
vertex of the demo scenes drifts over their motions at N = 20 (5.2 mm, the thigh's
semimembranosus and the elbow's biceps short head)."""


def cage_distances(cage_points, cage_triangles, points) -> np.ndarray:
    """(v,) mm: the distance of each surface vertex ``points`` (v, 3) mm to the cage
    ``cage_points`` (m, 3) mm, ``cage_triangles`` (t, 3) (indices into it)."""
    return unsigned_distance(np.ascontiguousarray(cage_points, dtype=np.float64),
                             np.ascontiguousarray(cage_triangles, dtype=np.int64), points)


def cage_drift(cage_now, cage_triangles, points, rest_distance) -> np.ndarray:
    """(v,) mm: the deformed vertices ``points`` (v, 3) mm, their distance to the cage at
    ``cage_now`` (m, 3) mm minus ``rest_distance`` (v,) mm, theirs at rest
    (:func:`cage_distances`)."""
    return cage_distances(cage_now, cage_triangles, points) - rest_distance
