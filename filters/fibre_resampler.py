"""Fibre Resampler: every fibre of every muscle into N particles (DESIGN §5–6, paper §3.1).

Input ``Fibres`` (``fibres.vtm``): one vtkPolyData block per muscle, one polyline cell per fibre
from origin to insertion, optional cell data ``fibre_grid`` (row, col). Output ``Particles``: the
same blocks in the same order, each a vtkPolyData whose points are the particles, fibre by fibre
from origin to insertion, one polyline cell per fibre through its particles (for display), point
data ``rest_position``, ``fibre_id``, ``fibre_index``, ``fixed`` and ``fibre_grid`` (when the
fibres have it), field data ``muscle_name``, the three properties, and ``origin_bone`` /
``insertion_bone`` when the fibres block names them (the Rigid Pose Transform reads them).

The random placement of a muscle is seeded by ``Seed`` together with the muscle's name, so each
muscle gets the same particles whatever the order or number of the other blocks.

Polylines that chain end to end (a fibre written in pieces, e.g. as two-point segments) are
joined into fibres first, with a warning (:mod:`muscle_mss.core.fibre_pieces`). Fibres
digitised in both directions are then oriented, on a copy, from the muscle's origin to
its insertion (:mod:`muscle_mss.core.fibre_direction`): by the distances of their ends to the
named ``origin_bone`` / ``insertion_bone`` (of the optional ``Attachments`` table,
``attachments.csv``, else of the block's field data) of the optional ``Bones`` input
(``bones.vtm``, rest pose), else with the muscle's mean fibre direction; a warning names the
block and how many fibres were reversed. Each fibre's midpoint (of the fibre, not of its
particles) is handed on as cell data ``fibre_midpoint`` of the display polylines, for the Spring
Builder's placement check.
"""
from __future__ import annotations

import zlib

import numpy as np

from vtkmodules.vtkCommonCore import vtkOutputWindow

from muscle_mss.core.attachment_areas import ATTACHMENTS_FILE, attachment_rows, bone_conflict
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.fibre_direction import (direction_warning, directions_by_bones,
                                             fibre_directions, reversed_fibres)
from muscle_mss.core.fibre_pieces import joined_fibres, joined_warning
from muscle_mss.core.fibres import check_fibres, resample_fibres
from muscle_mss.core.scene import BONES_FILE, FIBRES_FILE
from muscle_mss.core.validation import far_point_problem, fibre_midpoints

from . import array_names as A
from . import vtk_arrays as V
from .base import MuscleFilter, Port
from muscle_mss.core.properties import Option, Property

DEFAULT_PARTICLES_PER_FIBRE = 20
"""N, the paper's coarsest resolution (its experiments use 20, 40, 60 and 80)."""


def muscle_seed(seed: int, name: str) -> list:
    """The ``numpy.random.default_rng`` seed of one muscle: the user's seed and the CRC-32 of
    the muscle's name."""
    return [int(seed), zlib.crc32(name.encode("utf-8"))]


def fibre_polylines(block, where: str):
    """The fibres of one block: ``(points (v, 3) float64 mm, offsets (F + 1,) int64, grid,
    warning)``.

    ``grid`` is the (F, 2) int32 ``fibre_grid`` of the polylines, or None when absent.
    Polylines that chain end to end (a fibre written in pieces) are joined into fibres
    (:mod:`muscle_mss.core.fibre_pieces`) and ``warning`` says so (else None).
    """
    V.require_polydata(block, where, "a fibre block of polylines")
    offsets, connectivity = V.fibre_lines(block, where)
    if len(offsets) < 2:
        raise MuscleMSSError(f"{where} has no fibres; a muscle needs at least one fibre "
                             "polyline (line cell)")
    points = V.points_of(block)
    if len(connectivity) and connectivity.max() >= len(points):
        raise MuscleMSSError(f"{where}: a fibre refers to point {int(connectivity.max())} but "
                             f"the block has {len(points)} points")
    grid = V.cell_array(block, A.FIBRE_GRID, where, required=False)
    if grid is not None:
        n_fibres = len(offsets) - 1
        # cell data runs over vertices first, then lines (vtkPolyData's cell order)
        first = block.GetNumberOfVerts()
        grid = grid.reshape(len(grid), -1)[first:first + n_fibres]
        if grid.shape != (n_fibres, 2):
            raise MuscleMSSError(f"{where}: fibre_grid must give (row, col) for each of the "
                                 f"{n_fibres} fibres; it has shape {grid.shape}")
        if not np.isfinite(grid).all() or (grid != np.round(grid)).any():
            raise MuscleMSSError(f"{where}: fibre_grid must hold whole numbers (row, col)")
        grid = grid.astype(np.int32)
    problem = far_point_problem(points[connectivity], where, offsets)
    if problem:
        raise MuscleMSSError(problem)
    points, offsets, grid, pieces = joined_fibres(points[connectivity], offsets, grid, where)
    return points, offsets, grid, (joined_warning(where, pieces, len(offsets) - 1)
                                   if pieces else None)


def rest_bone_meshes(bones) -> dict | None:
    """``{name: (vertices (v, 3), triangles (m, 3))}`` of the rest bones multiblock, or None
    when the input is not connected."""
    if bones is None:
        return None
    return {name: (V.points_of(block), V.triangles_of(block, f"{BONES_FILE} block '{name}'"))
            for name, block in V.polydata_blocks(bones, BONES_FILE)}


def attachment_bones(block, named, where: str) -> tuple:
    """``(origin, insertion)``: the bones of a fibres block, as the attachments table names
    them (``named``: a pair, or None) or else as its field data does (a name that is not one
    string is refused downstream, by the Rigid Pose Transform)."""
    given = tuple(V.field(block, array) for array in (A.ORIGIN_BONE, A.INSERTION_BONE))
    if named is None:
        return given
    for end, bone, name in zip(("origin", "insertion"), given, named):
        problem = bone_conflict(where, end, bone, name, ATTACHMENTS_FILE)
        if problem:
            raise MuscleMSSError(problem)
    return tuple(named)


def oriented_polylines(points, offsets, bones, where: str, origin, insertion):
    """``(points, warning or None)``: a muscle's fibre points with every fibre running from
    origin to insertion (a copy when a fibre was reversed), and the sentence that says so;
    ``origin``, ``insertion`` the names of its bones (or None)."""
    check_fibres(points, offsets, where)
    origin, insertion = (b if isinstance(b, str) else None for b in (origin, insertion))
    if bones is None:
        directions = fibre_directions(points, offsets)
    else:
        directions = directions_by_bones(points, offsets, origin, insertion, bones)
    if directions.count:
        points = reversed_fibres(points, offsets, directions.reversed)
    return points, direction_warning(where, directions, origin, insertion, bones is not None)


class FibreResampler(MuscleFilter):
    """Samples every fibre of every muscle into N particles; see the module docstring."""

    LABEL = "Fibre Resampler"
    HELP = ("Samples every muscle fibre into N particles joined along the fibre, the start of the "
            "mass-spring model. The two end particles sit on the fibre's end points and are fixed "
            "(tendon attachment); the fibre is cut into N-1 equal arc-length intervals and every "
            "other particle is placed at a random place inside its own interval (or at the "
            "interval end points when Randomise is off). Output: one particle block per muscle "
            "with rest_position, fibre_id, fibre_index, fibre_grid (if present) and fixed. "
            "Fibres that run from insertion to origin are reversed first, on a copy, with a "
            "warning: by the origin and insertion bones when Bones is connected, else with the "
            "muscle's mean fibre direction.")
    INPUTS = (Port("Fibres", "vtkMultiBlockDataSet",
                   "fibres.vtm: one block per muscle, one polyline per fibre from origin to "
                   "insertion, optional cell data fibre_grid (row, col)"),
              Port("Bones", "vtkMultiBlockDataSet",
                   "bones.vtm: the rest bone surfaces (optional, but connect it): fibres that "
                   "run from insertion to origin are reversed by the distances of their ends "
                   "to the block's origin_bone and insertion_bone; without it they follow the "
                   "muscle's mean fibre direction", optional=True),
              Port("Attachments", "vtkTable",
                   "attachments.csv: columns muscle, origin_bone, insertion_bone (optional): "
                   "each muscle's bones, instead of the fibres block's origin_bone and "
                   "insertion_bone field data or the nearest bones", optional=True))
    OUTPUTS = (Port("Particles", "vtkMultiBlockDataSet",
                    "particles per muscle, with the fibres as polylines through them"),)
    PROPERTIES = (
        Property("ParticlesPerFibre", "int", DEFAULT_PARTICLES_PER_FIBRE,
                 "Particles per fibre N, both fixed end particles included (at least 2). The "
                 "paper's experiments use 20, 40, 60 and 80.",
                 minimum=2, group="Sampling",
                 option=Option("--resolution", "particles per fibre N (default {default})",
                               study=True)),
        Property("Randomise", "bool", True,
                 "Place each free particle at a uniformly random arc-length place inside its own "
                 "one of the N-1 equal intervals (on), or at the interval end points (off). "
                 "Randomising avoids rows of particles across the muscle with gaps between them "
                 "when fibres have about equal lengths.", group="Sampling"),
        Property("Seed", "int", 0,
                 "Seed of the random placement: the same fibres and seed give the same particles. "
                 "Each muscle's stream also depends on its name, not on the block order.",
                 minimum=0, group="Sampling"),
    )

    def execute(self, inputs, outputs):
        n = self.value("ParticlesPerFibre")
        randomise = self.value("Randomise")
        seed = self.value("Seed")
        blocks = V.blocks(inputs[0], where=FIBRES_FILE)
        if not blocks:
            raise MuscleMSSError(f"{FIBRES_FILE} has no blocks; it needs one block per muscle")
        bones = rest_bone_meshes(inputs[1])
        named = {} if inputs[2] is None else attachment_rows(
            V.table_rows(inputs[2]), [name for name, _ in blocks],
            None if bones is None else list(bones), ATTACHMENTS_FILE)
        items = []
        for done, (name, block) in enumerate(blocks):
            where = f"{FIBRES_FILE} block '{name}'"
            points, offsets, grid, joined = fibre_polylines(block, where)
            ends = attachment_bones(block, named.get(name), where)
            points, warning = oriented_polylines(points, offsets, bones, where, *ends)
            for text in (joined, warning):
                if text:
                    vtkOutputWindow.GetInstance().DisplayWarningText(f"{self.LABEL}: {text}\n")
            particles, fibre_id, fibre_index, fixed = resample_fibres(
                points, offsets, n, randomise, muscle_seed(seed, name), where)
            out = V.make_polydata(particles, line_offsets=np.arange(0, len(particles) + 1, n),
                                  line_connectivity=np.arange(len(particles)))
            V.set_point_array(out, A.REST_POSITION, particles)
            V.set_point_array(out, A.FIBRE_ID, fibre_id)
            V.set_point_array(out, A.FIBRE_INDEX, fibre_index)
            if grid is not None:
                V.set_point_array(out, A.FIBRE_GRID, grid[fibre_id])
            V.set_point_array(out, A.FIXED, fixed)
            V.set_cell_array(out, A.FIBRE_MIDPOINT, fibre_midpoints(points, offsets))
            V.set_field(out, A.MUSCLE_NAME, name)
            for array, bone in zip((A.ORIGIN_BONE, A.INSERTION_BONE), ends):
                if bone is not None:
                    V.set_field(out, array, bone)
            V.set_field(out, "ParticlesPerFibre", n)
            V.set_field(out, "Randomise", int(randomise))
            V.set_field(out, "Seed", seed)
            items.append((name, out))
            if self.progress((done + 1) / len(blocks)):
                raise MuscleMSSError(f"stopped by the user after {done + 1} of {len(blocks)} "
                                     "muscles")
        V.fill_multiblock(outputs[0], items)
