"""Fibre Generator: fibres for muscles that have only a surface (DESIGN §6 "Fibre generation").

Inputs ``Muscles`` (``muscles.vtm``, rest pose), ``Bones`` (``bones.vtm``, rest pose) and the
optional ``Attachments`` table (``attachments.csv``: ``muscle,origin_bone,insertion_bone``).
Output ``Fibres``: blocks shaped like ``fibres.vtm`` (one polyline per fibre from origin to
insertion, cell data ``fibre_grid``, field data ``origin_bone`` / ``insertion_bone``), ready for
the Fibre Resampler or to be saved as the scene's ``fibres.vtm`` (``muscle-mss fibres SCENE``).
The algorithm is :func:`muscle_mss.core.fibre_generation.generate_scene_fibres`; the attachment
areas :mod:`muscle_mss.core.attachment_areas`.
"""
from __future__ import annotations

from muscle_mss.core.attachment_areas import ATTACHMENTS_FILE, attachment_rows
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.fibre_generation import generate_scene_fibres
from muscle_mss.core.mesh_checks import checked_surface
from muscle_mss.core.properties import Property
from muscle_mss.core.scene import BONES_FILE, MUSCLES_FILE

from . import vtk_arrays as V
from .base import MuscleFilter, Port
from .scene_io import fibres_to_vtk, surfaces_from_vtk

DEFAULT_FIBRE_COUNT = 64
"""Fibres per muscle: the demo scenes' 8 x 8 grid (the paper's 64 per muscle)."""
DEFAULT_SAMPLES = 30
"""Points per generated fibre polyline (the demo scenes' fibres have 30)."""


def checked_surfaces(multiblock, filename: str) -> dict:
    """``{name: Surface}`` of a multiblock of closed triangle surfaces, each checked (DESIGN
    §8)."""
    surfaces = surfaces_from_vtk(multiblock, filename)
    if not surfaces:
        raise MuscleMSSError(f"{filename} has no blocks")
    for name, surface in surfaces.items():
        checked_surface(surface.points, surface.triangles, f"{filename} block '{name}'")
    return surfaces


class FibreGenerator(MuscleFilter):
    """Generates each muscle's fibres from its surface and its bones; see the module
    docstring."""

    LABEL = "Fibre Generator"
    HELP = ("Generates fibres for muscles that have only a surface (a segmentation): per muscle, "
            "the streamlines of a harmonic field that is 0 on the origin attachment area, 1 on "
            "the insertion area and has no flux through the rest of the surface (Choi & "
            "Blemker 2013), seeded on a rows x cols grid across the muscle's belly (cell data "
            "fibre_grid, so lattice layouts work). An attachment area is where the surface lies "
            "within 3 mm of its bone in the tenth of the muscle's length at that end (else the "
            "last 3 % of that end). The bones come from the Attachments table "
            "(attachments.csv: muscle,origin_bone,insertion_bone), else each end's nearest bone "
            "when that is unambiguous (the bone listed first in bones.vtm is the origin).")
    INPUTS = (Port("Muscles", "vtkMultiBlockDataSet",
                   "muscles.vtm: the rest muscle surfaces, closed and outward"),
              Port("Bones", "vtkMultiBlockDataSet", "bones.vtm: the rest bone surfaces"),
              Port("Attachments", "vtkTable",
                   "attachments.csv: columns muscle, origin_bone, insertion_bone (optional: "
                   "without it each muscle's bones are inferred where unambiguous)",
                   optional=True))
    OUTPUTS = (Port("Fibres", "vtkMultiBlockDataSet",
                    "one block per muscle as in fibres.vtm: a polyline per fibre from origin "
                    "to insertion, cell data fibre_grid, field data origin_bone and "
                    "insertion_bone"),)
    PROPERTIES = (
        Property("FibreCount", "int", DEFAULT_FIBRE_COUNT,
                 "Fibres per muscle, laid on the most nearly square rows x cols grid (64: 8 x 8, "
                 "60: 6 x 10).", minimum=1, group="Fibres"),
        Property("PointsPerFibre", "int", DEFAULT_SAMPLES,
                 "Points of each fibre polyline, at equal arc lengths from origin to insertion "
                 "(the Fibre Resampler samples its particles from them).", minimum=2,
                 group="Fibres"),
    )

    def execute(self, inputs, outputs):
        muscles = checked_surfaces(inputs[0], MUSCLES_FILE)
        bones = checked_surfaces(inputs[1], BONES_FILE)
        rows = V.table_rows(inputs[2]) if inputs[2] is not None else []
        named = attachment_rows(rows, list(muscles), list(bones), ATTACHMENTS_FILE)

        def progress(done, total):
            if self.progress(done / total):
                raise MuscleMSSError(f"stopped by the user after {done} of {total} muscles")
        fibres = generate_scene_fibres(muscles, bones, named, self.value("FibreCount"),
                                       self.value("PointsPerFibre"), progress)
        V.fill_multiblock(outputs[0], list(V.blocks(fibres_to_vtk(fibres))))
