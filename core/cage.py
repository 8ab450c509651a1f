"""The cage of a muscle and its fibres as polylines, from the particles (paper §3.2).

The cage is the closed triangle surface through the muscle's boundary particles that mean value
coordinates (:mod:`muscle_mss.core.mvc`) carry the muscle surface with. Two rules:

* **lattice** (the fibres carry a full ``fibre_grid`` of R x C >= 2 x 2 fibres with N >= 2
  particles each): the lattice's surface in grid order. The outer ring of fibres, walked around
  the grid, gives quads between neighbouring ring fibres at consecutive ``fibre_index``; the two
  end faces (``fibre_index`` 0 and N - 1) give the quads of the R x C grid of end particles.
  Each quad is split into two triangles. These are exactly the boundary particles of DESIGN §6,
  and the cage follows the muscle's shape however it bends.
* **convex hull** (no ``fibre_grid``, or one that is not a full grid, or fibres of different
  particle counts): the convex hull (Qhull) of the particles flagged ``boundary``. Its
  limitation: a concave or curved muscle gets a convex cage, so boundary particles inside the
  hull do not drive the surface and surface vertices in a concavity are carried by particles
  across it; the deformation stays smooth and exact for affine motions, but is less local
  than with the lattice.

Either cage is oriented outward (positive volume) in the rest pose, closed and manifold.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from .errors import MuscleMSSError
from .mesh_checks import surface_problems
from .volume import signed_volume

LATTICE = "lattice"
CONVEX_HULL = "convex hull"


@dataclass(frozen=True)
class Cage:
    """A muscle's cage.

    ``vertices`` (m,) int64: the particle index of each cage vertex; ``triangles`` (t, 3) int64:
    indices into ``vertices``, counter-clockwise seen from outside in the rest pose; ``kind``:
    :data:`LATTICE` or :data:`CONVEX_HULL`.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    kind: str


def fibre_polylines(fibre_id, fibre_index, where: str = "model"):
    """Group particles into fibres, each from origin (``fibre_index`` 0) to insertion.

    Parameters
    ----------
    fibre_id : (p,) int
    fibre_index : (p,) int
    where : names the muscle in error messages

    Returns
    -------
    order : (p,) int64
        Particle indices, fibre after fibre (ascending ``fibre_id``), each in ``fibre_index``
        order.
    offsets : (F + 1,) int64
        Fibre ``f`` is ``order[offsets[f]:offsets[f + 1]]``.
    ids : (F,) int64
        The ``fibre_id`` of each fibre.
    """
    fibre_id = np.asarray(fibre_id, dtype=np.int64).reshape(-1)
    fibre_index = np.asarray(fibre_index, dtype=np.int64).reshape(-1)
    if len(fibre_id) != len(fibre_index):
        raise MuscleMSSError(f"{where}: fibre_id has {len(fibre_id)} values and fibre_index "
                             f"{len(fibre_index)}; both need one per particle")
    order = np.lexsort((fibre_index, fibre_id))
    ids, starts, counts = np.unique(fibre_id[order], return_index=True, return_counts=True)
    offsets = np.append(starts, len(order)).astype(np.int64)
    expected = np.arange(len(order)) - np.repeat(starts, counts)
    wrong = np.flatnonzero(fibre_index[order] != expected)
    if len(wrong):
        f = int(np.searchsorted(offsets, wrong[0], side="right") - 1)
        raise MuscleMSSError(f"{where}: fibre {int(ids[f])} has fibre_index values "
                             f"{sorted(set(fibre_index[order[offsets[f]:offsets[f + 1]]].tolist()))}"
                             f"; they must be 0..{int(counts[f]) - 1}, each once")
    return order.astype(np.int64), offsets, ids.astype(np.int64)


def polyline_lengths(points, order, offsets) -> np.ndarray:
    """Length (mm) of each polyline ``points[order[offsets[f]:offsets[f + 1]]]``; (F,) float64.

    ``points`` (p, 3) float64 mm; ``order``, ``offsets`` as from :func:`fibre_polylines`.
    """
    walked = np.asarray(points, dtype=np.float64)[order]
    segments = np.linalg.norm(np.diff(walked, axis=0), axis=1)
    # A segment from the last particle of one fibre to the first of the next is not a segment.
    segments[offsets[1:-1] - 1] = 0.0
    cumulative = np.concatenate([[0.0], np.cumsum(segments)])
    return cumulative[np.maximum(offsets[1:] - 1, offsets[:-1])] - cumulative[offsets[:-1]]


def polyline_chords(points, order, offsets) -> np.ndarray:
    """Distance (mm) from the first to the last point of each polyline (a fibre's end-to-end
    length, its chord); (F,) float64, the arguments as for :func:`polyline_lengths`."""
    walked = np.asarray(points, dtype=np.float64)[order]
    return np.linalg.norm(walked[offsets[1:] - 1] - walked[offsets[:-1]], axis=1)


def muscle_cage(rest_positions, boundary, fibre_id, fibre_index, fibre_grid=None,
                where: str = "model") -> Cage:
    """The cage of one muscle (see the module docstring for the two rules).

    Parameters
    ----------
    rest_positions : (p, 3) float64, mm
        Particle positions in the rest pose.
    boundary : (p,) bool or uint8
        The particles flagged ``boundary``; used by the convex-hull rule, and there must be some.
    fibre_id, fibre_index : (p,) int
    fibre_grid : (p, 2) int or None
        (row, col) of each particle's fibre.
    where : names the muscle in error messages
    """
    rest_positions = np.asarray(rest_positions, dtype=np.float64).reshape(-1, 3)
    boundary = np.asarray(boundary).reshape(-1).astype(bool)
    if len(boundary) != len(rest_positions):
        raise MuscleMSSError(f"{where}: boundary has {len(boundary)} values for "
                             f"{len(rest_positions)} particles; it needs one per particle")
    if not boundary.any():
        raise MuscleMSSError(f"{where}: has no boundary particles; the cage that carries the "
                             "surface is made of them (rebuild the model with the Spring Builder)")
    order, offsets, ids = fibre_polylines(fibre_id, fibre_index, where)
    lattice = None
    if fibre_grid is not None:
        lattice = _grid_lattice(np.asarray(fibre_grid, dtype=np.int64).reshape(-1, 2),
                                order, offsets, ids, where)
    if lattice is not None:
        vertices, triangles = _lattice_surface(lattice)
        kind = LATTICE
    else:
        vertices, triangles = _hull_surface(rest_positions, np.flatnonzero(boundary), where)
        kind = CONVEX_HULL
    corners = rest_positions[vertices]
    volume = signed_volume(corners, triangles)
    if volume < 0.0:
        triangles = np.ascontiguousarray(triangles[:, ::-1])
    size = float(np.linalg.norm(corners.max(axis=0) - corners.min(axis=0)))
    flat = abs(volume) <= 1e-9 * size ** 3
    problems = [] if flat else surface_problems(corners, triangles)
    if flat or problems:
        why = "encloses no volume" if flat else problems[0]
        raise MuscleMSSError(f"{where}: the {kind} cage of its {len(vertices)} boundary particles "
                             f"{why}; the particles must span a solid, not a sheet or a line")
    return Cage(vertices, triangles, kind)


def _grid_lattice(grid, order, offsets, ids, where):
    """The (R, C, N) particle indices of a full fibre grid, or None if the grid is not full."""
    counts = np.diff(offsets)
    fibre_cell = grid[order[offsets[:-1]]]
    mixed = np.flatnonzero((grid[order] != np.repeat(fibre_cell, counts, axis=0)).any(axis=1))
    if len(mixed):
        f = int(np.searchsorted(offsets, mixed[0], side="right") - 1)
        raise MuscleMSSError(f"{where}: the particles of fibre {int(ids[f])} have different "
                             "fibre_grid cells; a fibre has one (row, col)")
    rows, row_of = np.unique(fibre_cell[:, 0], return_inverse=True)
    cols, col_of = np.unique(fibre_cell[:, 1], return_inverse=True)
    n = int(counts[0])
    cells = row_of.reshape(-1) * len(cols) + col_of.reshape(-1)
    if (len(rows) < 2 or len(cols) < 2 or n < 2 or (counts != n).any()
            or len(ids) != len(rows) * len(cols) or len(np.unique(cells)) != len(ids)):
        return None
    lattice = np.empty((len(rows), len(cols), n), dtype=np.int64)
    lattice[row_of.reshape(-1), col_of.reshape(-1)] = order.reshape(len(ids), n)
    return lattice


def _quads_to_triangles(q0, q1, q2, q3):
    q0, q1, q2, q3 = (np.asarray(q).reshape(-1) for q in (q0, q1, q2, q3))
    return np.concatenate([np.stack([q0, q1, q2], axis=1), np.stack([q0, q2, q3], axis=1)])


def _lattice_surface(lattice):
    """Triangles of the surface of an (R, C, N) particle lattice, as ``(vertices, triangles)``.

    In index space (x = col, y = row, z = fibre_index) every triangle is counter-clockwise seen
    from outside; the caller flips them all if the grid is left-handed in space.
    """
    r_count, c_count, _ = lattice.shape
    ring_rows = np.concatenate([np.zeros(c_count - 1, int), np.arange(r_count - 1),
                                np.full(c_count - 1, r_count - 1), np.arange(r_count - 1, 0, -1)])
    ring_cols = np.concatenate([np.arange(c_count - 1), np.full(r_count - 1, c_count - 1),
                                np.arange(c_count - 1, 0, -1), np.zeros(r_count - 1, int)])
    here = lattice[ring_rows, ring_cols]          # (P, N): the ring fibres in walking order
    ahead = np.roll(here, -1, axis=0)
    sides = _quads_to_triangles(here[:, :-1], ahead[:, :-1], ahead[:, 1:], here[:, 1:])
    first, last = lattice[:, :, 0], lattice[:, :, -1]
    origin_end = _quads_to_triangles(first[:-1, :-1], first[1:, :-1], first[1:, 1:],
                                     first[:-1, 1:])
    insertion_end = _quads_to_triangles(last[:-1, :-1], last[:-1, 1:], last[1:, 1:],
                                        last[1:, :-1])
    triangles = np.concatenate([sides, origin_end, insertion_end])
    vertices, local = np.unique(triangles, return_inverse=True)
    return vertices.astype(np.int64), local.reshape(-1, 3).astype(np.int64)


def _hull_surface(rest_positions, candidates, where):
    """Convex hull of the particles ``candidates`` as ``(vertices, triangles)``, outward."""
    if len(candidates) < 4:
        raise MuscleMSSError(f"{where}: has {len(candidates)} boundary particles; a cage needs "
                             "at least 4 that span a solid")
    points = rest_positions[candidates]
    try:
        hull = ConvexHull(points)
    except QhullError as err:
        raise MuscleMSSError(f"{where}: the convex hull of its {len(candidates)} boundary "
                             "particles is degenerate (they lie in a plane or on a line): "
                             f"{str(err).splitlines()[0]}") from None
    triangles = hull.simplices.astype(np.int64)
    p0, p1, p2 = (points[triangles[:, k]] for k in range(3))
    inward = np.einsum("ij,ij->i", np.cross(p1 - p0, p2 - p0), hull.equations[:, :3]) < 0.0
    triangles[inward] = triangles[inward][:, ::-1]
    vertices, local = np.unique(triangles, return_inverse=True)
    return candidates[vertices].astype(np.int64), local.reshape(-1, 3).astype(np.int64)
