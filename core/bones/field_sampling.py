"""Sampling each bone's signed distance field in its rest frame; the fields
are looked up and points pushed out of bones by :mod:`.bones.distance`.

The bone's padded bounding box is cut into bricks of ``BRICK`` x ``BRICK`` x ``BRICK`` cells of
``spacing`` mm. A coarse grid of nodes ``COARSE * spacing`` mm apart over the whole box holds the
exact signed distance (used deep inside and far outside); a brick whose centre is closer to the
surface than ``band`` plus half its diagonal also holds the exact distance at each of its
``(BRICK + 1)^3`` nodes (the narrow band, ``spacing`` apart), so every point within ``band`` mm
of the surface is looked up in a fine brick. Values are float32. The exact distance of a node is
:mod:`.triangle_distance`'s (the nearest triangle in a bounding volume hierarchy, each node
starting from its neighbour's nearest triangle, signed by pseudo-normals), exact for closed,
manifold, outward-oriented surfaces.
"""
import math

import numpy as np

from .distance import BRICK, COARSE, BoneDistanceField, BoneFieldSet
from ..errors import MuscleMSSError
from ..mesh_checks import checked_surface
from .triangle_distance import exact_at_bricks, exact_at_queries, prepared_surface, query_chunks

DEFAULT_SPACING = 1.0
"""mm between the fine nodes of the narrow band."""
DEFAULT_BAND = 4.0
"""mm: every point closer than this to the surface (inside or out) is looked up in a fine brick.
Collision sphere radii of the demo muscles are below it."""
DEFAULT_PADDING = 8.0
"""mm the sampled box extends beyond the bone's bounding box."""
MAX_VALUES = 2 ** 26
"""Sampled values one bone's field may hold (256 MiB of float32): a finer spacing is refused
with an error rather than exhausting memory."""


def bone_distance_field(points, triangles, spacing=DEFAULT_SPACING, band=DEFAULT_BAND,
                        padding=DEFAULT_PADDING, where="bone") -> BoneDistanceField:
    """Sample the signed distance of one bone in its rest frame (see the module docstring).

    Parameters
    ----------
    points : (n, 3) float64 mm, triangles : (m, 3) int
        The bone's closed, manifold, outward-oriented rest surface.
    spacing : float, mm
        Distance between the fine nodes near the surface.
    band : float, mm
        Every point closer than ``band`` to the surface is interpolated from fine nodes.
    padding : float, mm
        How far the sampled box extends beyond the bone's bounding box.
    where : str
        Names the bone in error messages, e.g. ``"bones.vtm block 'femur'"``.
    """
    for name, value in (("spacing", spacing), ("band", band), ("padding", padding)):
        if not (np.isfinite(value) and value > 0):
            raise MuscleMSSError(f"{where}: the distance field's {name} is {value}; it must be "
                                 "a positive number of mm")
    points, triangles = checked_surface(points, triangles, where)
    spacing = float(spacing)
    size = BRICK * spacing
    lower = points.min(axis=0) - padding
    dims = np.ceil((points.max(axis=0) + padding - lower) / size).astype(np.int64)
    surface = prepared_surface(points, triangles, where)
    _check_size(int(np.prod(dims * (BRICK // COARSE) + 1)), "coarse", spacing, where)
    axes = [lower[k] + COARSE * spacing * np.arange(dims[k] * BRICK // COARSE + 1)
            for k in range(3)]
    corners = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    coarse = np.empty(len(corners))
    exact_at_queries(corners, query_chunks(len(corners)), surface.mesh, surface.tree, coarse,
                     np.empty((len(corners), 3)))
    # Every point of a brick is within half a coarse cell's diagonal of one of the brick's
    # coarse nodes, and distance is 1-Lipschitz: a brick whose nodes are all farther than
    # band + that from the surface holds no point within band of it.
    per = BRICK // COARSE
    nodes = np.abs(coarse).reshape(tuple(dims * per + 1))
    nearest = np.full(tuple(dims), np.inf)
    for a in range(per + 1):
        for b in range(per + 1):
            for c in range(per + 1):
                nearest = np.minimum(nearest, nodes[a::per, b::per, c::per][:dims[0], :dims[1],
                                                                            :dims[2]])
    near = (nearest <= band + 0.5 * math.sqrt(3.0) * COARSE * spacing).reshape(-1)
    _check_size(int(near.sum()) * (BRICK + 1) ** 3, "fine", spacing, where)
    brick_index = np.full(len(near), -1, dtype=np.int32)
    brick_index[near] = np.arange(int(near.sum()), dtype=np.int32)
    coords = np.stack(np.unravel_index(np.flatnonzero(near), tuple(dims)), axis=1) \
        .astype(np.int64)
    fine = np.empty((len(coords), BRICK + 1, BRICK + 1, BRICK + 1), dtype=np.float64)
    if len(coords):
        exact_at_bricks(coords, lower, spacing, surface.mesh, surface.tree, fine)
    return BoneDistanceField(origin=lower, spacing=spacing, dims=dims,
                             coarse=coarse.astype(np.float32), brick_index=brick_index,
                             bricks=fine.astype(np.float32))


def _check_size(values, kind, spacing, where):
    if values > MAX_VALUES:
        raise MuscleMSSError(f"{where}: a distance field with spacing {spacing:g} mm would hold "
                             f"{values:,} {kind} values (at most {MAX_VALUES:,}); choose a "
                             "larger spacing")


def bone_field_set(bones, spacing=DEFAULT_SPACING, band=DEFAULT_BAND, padding=DEFAULT_PADDING,
                   labels=None) -> BoneFieldSet:
    """Fields of every bone of ``bones`` (a list of ``(points, triangles)`` rest surfaces),
    packed; ``labels`` name the bones in errors and in ``BoneFieldSet.names``."""
    labels = list(labels) if labels is not None else [f"bone {i}" for i in range(len(bones))]
    return BoneFieldSet.pack([bone_distance_field(p, t, spacing, band, padding, where=label)
                              for (p, t), label in zip(bones, labels)], labels)
