"""Surface files from segmentations and OpenSim models (STL, OBJ, PLY, legacy VTK, VTP) read
into arrays and made scene surfaces (DESIGN §4, §7 "Importers"): the VTK side of
:mod:`muscle_mss.core.mesh_cleaning` (reading, decimation, writing a multiblock of surfaces).
"""
from __future__ import annotations

import os

import numpy as np
from vtkmodules.vtkFiltersCore import vtkQuadricDecimation, vtkTriangleFilter
from vtkmodules.vtkIOGeometry import vtkOBJReader, vtkSTLReader
from vtkmodules.vtkIOLegacy import vtkPolyDataReader
from vtkmodules.vtkIOPLY import vtkPLYReader
from vtkmodules.vtkIOXML import vtkXMLPolyDataReader

from muscle_mss.core import mesh_cleaning as C
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.scene import Surface
from muscle_mss.core.volume import signed_volume

from . import vtk_arrays as V
from .scene_io import vtk_error, vtk_messages

READERS = {".stl": vtkSTLReader, ".obj": vtkOBJReader, ".ply": vtkPLYReader,
           ".vtk": vtkPolyDataReader, ".vtp": vtkXMLPolyDataReader}
"""The reader of each surface file suffix (lower case)."""

MESH_SUFFIXES = tuple(READERS)

DECIMATION_VOLUME_TOLERANCE = 0.02
"""The largest relative volume change decimation to :data:`~muscle_mss.core.mesh_cleaning.
MAX_MUSCLE_TRIANGLES` may cause; more is refused (the shape was lost: a muscle thinner than
its triangles). Quadric decimation with volume preservation changes a smooth muscle's volume
by well under 0.5 %; 2 % is a third of the volume error the paper accepts (6 %)."""


def read_mesh_file(path: str, where: str | None = None):
    """``(points (n, 3) float64, triangles (m, 3) int64)`` of a surface file (one of
    :data:`READERS`), polygons and strips split into triangles, in the file's own units. A
    missing, unreadable or triangle-less file is an error naming it (``where``: how to name it,
    default its path)."""
    where = where or path
    suffix = os.path.splitext(path)[1].lower()
    if suffix not in READERS:
        raise MuscleMSSError(f"{where}: unknown surface file type {suffix or '(none)'}; give "
                             f"one of {', '.join(MESH_SUFFIXES)}")
    if not os.path.isfile(path):
        raise MuscleMSSError(f"{where}: no such file")
    reader = READERS[suffix]()
    reader.SetFileName(path)
    triangulate = vtkTriangleFilter()
    triangulate.SetInputConnection(reader.GetOutputPort())
    triangulate.PassVertsOff()
    triangulate.PassLinesOff()
    with vtk_messages() as messages:
        triangulate.Update()
    data = triangulate.GetOutput()
    problem = vtk_error(messages.GetOutput()) or (None if data.GetNumberOfPolys() else
                                                  "no triangles")
    if problem:
        raise MuscleMSSError(f"{where}: could not be read as a triangle surface ({problem})")
    return V.points_of(data), V.triangles_of(data, where)


def decimated(points, triangles, target: int):
    """``(points, triangles)`` brought down to about ``target`` triangles by VTK's quadric
    decimation (Garland & Heckbert) with volume preservation; unchanged when already at most
    ``target``. The result may hold duplicate or unused points: clean it again."""
    if len(triangles) <= target:
        return points, triangles
    decimate = vtkQuadricDecimation()
    decimate.SetInputData(V.make_polydata(points, triangles=triangles))
    decimate.SetTargetReduction(1.0 - target / len(triangles))
    decimate.VolumePreservationOn()
    decimate.Update()
    out = decimate.GetOutput()
    return V.points_of(out), V.triangles_of(out)


def at_cage_density(points, triangles, where: str, attempts: int = 4):
    """``(points, triangles)`` of a clean muscle surface at the density the MVC cage follows:
    no edge longer than :data:`~muscle_mss.core.mesh_cleaning.MAX_EDGE_FRACTION` of its length
    and, when it had more, at most :data:`~muscle_mss.core.mesh_cleaning.MAX_MUSCLE_TRIANGLES`
    triangles (a coarse surface only has its long edges split, however many that makes).
    Decimation (cleaned again: it may leave repeated points) makes long thin triangles where
    the surface is flat, whose splitting can go over the maximum: then the decimation's target
    is lowered by twice the excess and it runs again from the original (``attempts`` in all;
    the last result is kept)."""
    limit = C.MAX_EDGE_FRACTION * C.principal_length(points)
    if len(triangles) <= C.MAX_MUSCLE_TRIANGLES:   # a coarse surface: its long edges split
        return C.split_long_edges(points, triangles, limit)
    volume = signed_volume(points, triangles)
    target = C.MAX_MUSCLE_TRIANGLES
    for _ in range(attempts):
        fewer = C.clean_surface(*decimated(points, triangles, target), f"{where} (decimated)",
                                single_piece=True)[:2]
        change = abs(signed_volume(*fewer) / volume - 1.0)
        if change > DECIMATION_VOLUME_TOLERANCE:
            raise MuscleMSSError(f"{where}: decimation to {target} triangles changed its volume "
                                 f"by {100 * change:.1f} %, more than "
                                 f"{100 * DECIMATION_VOLUME_TOLERANCE:g} %; give a smoother "
                                 "surface")
        split = C.split_long_edges(*fewer, limit)
        if len(split[1]) <= C.MAX_MUSCLE_TRIANGLES:
            break
        # coarser triangles are longer, so each split adds more: step twice the excess
        target = max(target - 2 * (len(split[1]) - C.MAX_MUSCLE_TRIANGLES),
                     C.MAX_MUSCLE_TRIANGLES // 4)
    return split


def muscle_from_file(path: str, units: str = "auto"):
    """``(Surface, note)``: the muscle surface file ``path`` in millimetres (``units``: m, mm
    or auto, :func:`~muscle_mss.core.mesh_cleaning.length_scale`), cleaned
    (:func:`~muscle_mss.core.mesh_cleaning.clean_surface`, one piece) and at the cage's density
    (:func:`at_cage_density`); ``note`` says what was done, for the importer's summary."""
    points, triangles = read_mesh_file(path)
    scale = C.length_scale(points[np.unique(triangles)], units, path)
    points, triangles, cleaning = C.clean_surface(points * scale, triangles, path,
                                                  single_piece=True)
    before = len(triangles)
    points, triangles = at_cage_density(points, triangles, path)
    unit = "m" if scale != 1.0 else "mm"
    done = cleaning.summary()
    note = (f"{unit}, {before} -> {len(triangles)} triangles"
            + (f"; {done}" if done else ""))
    return Surface(points, triangles), note


def block_files(filename: str, count: int) -> list:
    """The block files (relative to the ``.vtm``'s folder) that :func:`write_surfaces` writes
    for ``count`` blocks into ``filename`` (VTK's naming: ``bones/bones_0.vtp``, ...)."""
    stem = os.path.splitext(filename)[0]
    return [f"{stem}/{stem}_{k}.vtp" for k in range(count)]


def write_surfaces(surfaces: dict, path: str) -> None:
    """Write ``{name: Surface}`` as a ``.vtm`` multiblock of triangle surfaces (block name =
    name, in order) with its block files beside it, as ``scene_io.write_scene`` writes them."""
    from .scene_io import surfaces_to_vtk, write_multiblock
    write_multiblock(surfaces_to_vtk(surfaces), path)
