"""How far the deformed muscle surfaces lie inside each other (what a user sees).

The solver keeps the muscles' collision spheres apart (``sphere_overlap_mm``), but the surfaces
between the spheres may still pass into a neighbour, and a scene whose muscles overlap at rest
(accepted up to half of a muscle's fibre midpoints, :mod:`.validation`) keeps that overlap.
Each muscle's vertices inside another muscle's surface are counted and the deepest measured, by
the exact signed distance to that surface (its triangles' bounding volume hierarchy and
pseudo-normals, :mod:`.triangle_distance`, built for this time point's surfaces only: not through
its cache of prepared surfaces, which holds the bones), for the vertices inside its bounding box;
inside a folded surface, by their winding numbers (:func:`vertices_in_other_muscles`).
"""
from __future__ import annotations

import numpy as np

from ..bones.triangle_distance import (TriangleMesh, _hierarchy, _pseudo_normals, exact_at_queries,
                                query_chunks)
from ..volume import winding_numbers

INSIDE_DEPTH = 1e-3
"""mm: a vertex counts as inside another muscle when deeper than this (as for the bones)."""


def turned_over(points, rest_points, triangles) -> bool:
    """Whether a deformed surface (``points`` (v, 3) mm; ``rest_points`` at rest, the same
    ``triangles``) has a triangle facing against its rest normal: a fold, where it may pass
    through itself."""
    def normals(p):
        return np.cross(p[triangles[:, 1]] - p[triangles[:, 0]],
                        p[triangles[:, 2]] - p[triangles[:, 0]])
    return bool((np.einsum("ij,ij->i", normals(points), normals(rest_points)) < 0.0).any())


def vertices_in_other_muscles(surfaces, rest_points=None) -> tuple:
    """``(count (M,) int64, depth (M,) mm)``: for each of the closed, outward-oriented muscle
    ``surfaces`` (a list of ``(points (v, 3) mm, triangles (m, 3))``) how many of its vertices
    lie inside another muscle's surface, and the deepest of them (0 when none).

    The pseudo-normals' sign is exact for a surface that does not pass through itself; a
    deformed one may where it folds (the small arm demo at 130 degrees: brachialis vertices
    27 mm outside the biceps, triceps vertices 70 mm outside it, read as inside). A vertex
    placed inside a surface that is :func:`turned_over` from its ``rest_points`` (a list like
    ``surfaces``' points; None: every surface) is therefore confirmed by its winding number,
    which doubles the time where all are confirmed (the demo thigh, 13 muscles: 146 -> 321 ms
    on two busy cores)."""
    prepared = []
    for k, (points, triangles) in enumerate(surfaces):
        points = np.ascontiguousarray(points, dtype=np.float64)
        triangles = np.ascontiguousarray(triangles, dtype=np.int64)
        folded = rest_points is None or turned_over(points, rest_points[k], triangles)
        prepared.append((TriangleMesh(points, triangles, *_pseudo_normals(points, triangles)),
                         _hierarchy(points, triangles), points.min(axis=0), points.max(axis=0),
                         folded))
    count, deepest = np.zeros(len(surfaces), dtype=np.int64), np.zeros(len(surfaces))
    for a, (mesh_a, _, low_a, high_a, _) in enumerate(prepared):
        depth = np.zeros(len(mesh_a.points))
        for b, (mesh_b, tree_b, low_b, high_b, folded) in enumerate(prepared):
            if a == b or (low_a > high_b).any() or (low_b > high_a).any():
                continue
            near = np.flatnonzero(((mesh_a.points >= low_b) & (mesh_a.points <= high_b))
                                  .all(axis=1))
            if not len(near):
                continue
            queries = np.ascontiguousarray(mesh_a.points[near])
            distance, closest = np.empty(len(near)), np.empty((len(near), 3))
            exact_at_queries(queries, query_chunks(len(near)), mesh_b, tree_b, distance,
                             closest)
            inside = distance < -INSIDE_DEPTH
            if folded and inside.any():
                inside[inside] = winding_numbers(queries[inside], mesh_b.points,
                                                 mesh_b.triangles) > 0.5
            depth[near[inside]] = np.maximum(depth[near[inside]], -distance[inside])
        inside = depth > INSIDE_DEPTH
        count[a], deepest[a] = int(inside.sum()), float(depth.max(initial=0.0)) if inside.any() \
            else 0.0
    return count, deepest
