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
"""
from __future__ import annotations

import zlib

import numpy as np

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.fibres import resample_fibres
from muscle_mss.core.scene import FIBRES_FILE
from muscle_mss.core.validation import far_point_problem

from . import array_names as A
from . import vtk_arrays as V
from .base import MuscleFilter, Port
from .properties import Property

DEFAULT_PARTICLES_PER_FIBRE = 20
"""N, the paper's coarsest resolution (its experiments use 20, 40, 60 and 80)."""


def muscle_seed(seed: int, name: str) -> list:
    """The ``numpy.random.default_rng`` seed of one muscle: the user's seed and the CRC-32 of
    the muscle's name."""
    return [int(seed), zlib.crc32(name.encode("utf-8"))]


def fibre_polylines(block, where: str):
    """The fibres of one block: ``(points (v, 3) float64 mm, offsets (F + 1,) int64, grid)``.

    ``grid`` is the (F, 2) int32 ``fibre_grid`` of the polylines, or None when absent.
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
    return points[connectivity], offsets, grid


class FibreResampler(MuscleFilter):
    """Samples every fibre of every muscle into N particles; see the module docstring."""

    LABEL = "Fibre Resampler"
    HELP = ("Samples every muscle fibre into N particles joined along the fibre, the start of the "
            "mass-spring model. The two end particles sit on the fibre's end points and are fixed "
            "(tendon attachment); the fibre is cut into N-1 equal arc-length intervals and every "
            "other particle is placed at a random place inside its own interval (or at the "
            "interval end points when Randomise is off). Output: one particle block per muscle "
            "with rest_position, fibre_id, fibre_index, fibre_grid (if present) and fixed.")
    INPUTS = (Port("Fibres", "vtkMultiBlockDataSet",
                   "fibres.vtm: one block per muscle, one polyline per fibre from origin to "
                   "insertion, optional cell data fibre_grid (row, col)"),)
    OUTPUTS = (Port("Particles", "vtkMultiBlockDataSet",
                    "particles per muscle, with the fibres as polylines through them"),)
    PROPERTIES = (
        Property("ParticlesPerFibre", "int", DEFAULT_PARTICLES_PER_FIBRE,
                 "Particles per fibre N, both fixed end particles included (at least 2). The "
                 "paper's experiments use 20, 40, 60 and 80.",
                 minimum=2, group="Sampling"),
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
        items = []
        for done, (name, block) in enumerate(blocks):
            where = f"{FIBRES_FILE} block '{name}'"
            points, offsets, grid = fibre_polylines(block, where)
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
            V.set_field(out, A.MUSCLE_NAME, name)
            for array in (A.ORIGIN_BONE, A.INSERTION_BONE):
                if V.field(block, array) is not None:
                    V.set_field(out, array, V.field(block, array))
            V.set_field(out, "ParticlesPerFibre", n)
            V.set_field(out, "Randomise", int(randomise))
            V.set_field(out, "Seed", seed)
            items.append((name, out))
            if self.progress((done + 1) / len(blocks)):
                raise MuscleMSSError(f"stopped by the user after {done + 1} of {len(blocks)} "
                                     "muscles")
        V.fill_multiblock(outputs[0], items)
