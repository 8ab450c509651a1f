"""Checks of triangle surfaces used for muscles and bones (DESIGN §4, §8).

A valid surface is closed (every edge shared by exactly two triangles), manifold and
consistently oriented (each directed edge used once), with finite coordinates, and
outward-oriented (positive signed volume).
"""
import numpy as np

from .errors import MuscleMSSError
from .volume import signed_volume


def structure_problem(points, triangles) -> str | None:
    """Why ``points`` (n, 3) and ``triangles`` (m, 3) are no triangle surface at all (none,
    dangling indices, a non-finite coordinate), or None."""
    if len(triangles) == 0:
        return "has no triangles; a surface must be a closed triangle mesh"
    if triangles.min() < 0 or triangles.max() >= len(points):
        return "has triangles referring to missing points"
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        return (f"point {int(np.flatnonzero(bad)[0])} has a NaN or infinite coordinate; "
                "every coordinate must be finite")
    return None


def checked_surface(points, triangles, where: str):
    """``(points (n, 3) float64, triangles (m, 3) int64)`` as contiguous arrays, or raise
    :class:`MuscleMSSError` naming ``where`` when :func:`structure_problem` finds a problem."""
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    triangles = np.ascontiguousarray(triangles, dtype=np.int64).reshape(-1, 3)
    problem = structure_problem(points, triangles)
    if problem:
        raise MuscleMSSError(f"{where}: {problem}")
    return points, triangles


def surface_problems(points, triangles):
    """Return a list of sentences describing why the surface is not a valid closed one.

    Parameters
    ----------
    points : (n, 3) float64
    triangles : (m, 3) int
    """
    points = np.asarray(points, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    problem = structure_problem(points, triangles)
    if problem:
        return [problem]
    problems = []
    directed = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    # one int64 key per edge: a 1-D unique is several times faster than unique(axis=0)
    # (1.7 s for the bones checked at the first time point of the demo thigh)
    width = len(points)
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected[:, 0] * width + undirected[:, 1], return_counts=True)
    if (counts == 1).any():
        problems.append(f"is open: {int((counts == 1).sum())} edges belong to one triangle only; "
                        "a surface must be closed")
    if (counts > 2).any():
        problems.append(f"is not manifold: {int((counts > 2).sum())} edges are shared by more "
                        "than two triangles")
    if not problems:
        _, dcounts = np.unique(directed[:, 0] * width + directed[:, 1], return_counts=True)
        if (dcounts > 1).any():
            problems.append("is not consistently oriented: neighbouring triangles run their "
                            "shared edge in the same direction")
    if not problems and signed_volume(points, triangles) <= 0.0:
        problems.append("is oriented inward (negative volume); triangles must be "
                        "counter-clockwise seen from outside")
    return problems
