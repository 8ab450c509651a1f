"""Scene folders on disk (DESIGN §4): ``muscles.vtm``, ``fibres.vtm``, ``bones.vtm``, ``motion.csv``.

Files are read with the same VTK readers ParaView uses (XML multiblock reader, delimited-text
reader for the CSV), so what the filters see here is what they see in ParaView.
"""
from __future__ import annotations

import csv
import os

import numpy as np
from vtkmodules.vtkIOInfovis import vtkDelimitedTextReader
from vtkmodules.vtkIOXML import vtkXMLMultiBlockDataReader, vtkXMLMultiBlockDataWriter

from muscle_mss.core.attachments import attachment_problems
from muscle_mss.core.errors import MuscleMSSError, first_problem
from muscle_mss.core.motion import motion_problems, motion_rows
from muscle_mss.core.scene import (BONES_FILE, FIBRES_FILE, MOTION_COLUMNS, MOTION_FILE,
                                   MUSCLES_FILE, FibreSet, Scene, Surface)
from muscle_mss.core.validation import scene_problems

from . import array_names as A
from . import vtk_arrays as V


# ---- arrays -> VTK ---------------------------------------------------------------------------

def surfaces_to_vtk(surfaces: dict):
    """A multiblock of triangle surfaces from ``{name: Surface}``."""
    return V.make_multiblock([(name, V.make_polydata(s.points, triangles=s.triangles))
                              for name, s in surfaces.items()])


def fibres_to_vtk(fibres: dict):
    """A multiblock of fibre polylines (+ cell data ``fibre_grid``) from ``{name: FibreSet}``."""
    items = []
    for name, fs in fibres.items():
        pd = V.make_polydata(fs.points, line_offsets=fs.offsets,
                             line_connectivity=np.arange(len(fs.points)))
        if fs.grid is not None:
            V.set_cell_array(pd, A.FIBRE_GRID, np.asarray(fs.grid, dtype=np.int32))
        for array, bone in ((A.ORIGIN_BONE, fs.origin_bone),
                            (A.INSERTION_BONE, fs.insertion_bone)):
            if bone is not None:
                V.set_field(pd, array, bone)
        items.append((name, pd))
    return V.make_multiblock(items)


def motion_to_vtk(motion):
    """The motion as a vtkTable with the columns of ``motion.csv``."""
    times, bones, values = motion_rows(motion)
    columns = {"time": times, "bone": bones}
    for c, name in enumerate(MOTION_COLUMNS[2:]):
        columns[name] = values[:, c]
    return V.make_table(columns)


def scene_to_vtk(scene: Scene):
    """``(muscles, fibres, bones, motion)``: three multiblocks and a vtkTable, as read from files."""
    return (surfaces_to_vtk(scene.muscles), fibres_to_vtk(scene.fibres),
            surfaces_to_vtk(scene.bones), motion_to_vtk(scene.motion))


# ---- files ---------------------------------------------------------------------------------

def write_scene(scene: Scene, folder) -> None:
    """Write a scene folder that stock ParaView readers open."""
    os.makedirs(folder, exist_ok=True)
    muscles, fibres, bones, _ = scene_to_vtk(scene)
    for data, filename in ((muscles, MUSCLES_FILE), (fibres, FIBRES_FILE), (bones, BONES_FILE)):
        writer = vtkXMLMultiBlockDataWriter()
        writer.SetFileName(os.path.join(folder, filename))
        writer.SetInputData(data)
        writer.SetDataModeToAppended()
        writer.EncodeAppendedDataOff()
        if not writer.Write():
            raise MuscleMSSError(f"{os.path.join(folder, filename)}: could not be written")
    times, bone_names, values = motion_rows(scene.motion)
    with open(os.path.join(folder, MOTION_FILE), "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(MOTION_COLUMNS)
        for t, b, row in zip(times, bone_names, values):
            out.writerow([repr(float(t)), b] + [repr(float(v)) for v in row])


def _require(folder, filename):
    path = os.path.join(folder, filename)
    if not os.path.isfile(path):
        raise MuscleMSSError(f"{path}: missing; a scene folder holds {MUSCLES_FILE}, "
                             f"{FIBRES_FILE}, {BONES_FILE} and {MOTION_FILE}")
    return path


def multiblock_reader(path):
    """An updated VTK XML multiblock reader of a ``.vtm`` file (what ParaView uses)."""
    reader = vtkXMLMultiBlockDataReader()
    reader.SetFileName(path)
    reader.Update()
    data = reader.GetOutputDataObject(0)
    if data is None or data.GetNumberOfBlocks() == 0:
        raise MuscleMSSError(f"{path}: could not be read as a multiblock dataset or has no blocks")
    return reader


def motion_reader(path):
    """An updated delimited-text reader of ``motion.csv`` set up as ParaView's CSV reader."""
    reader = vtkDelimitedTextReader()
    reader.SetFileName(path)
    reader.SetHaveHeaders(True)
    reader.SetDetectNumericColumns(True)
    reader.SetFieldDelimiterCharacters(",")
    reader.Update()
    return reader


def scene_readers(folder):
    """``(muscles, fibres, bones, motion)`` readers of a scene folder, updated, to connect
    filters to (as a ParaView pipeline starts from its readers)."""
    return (multiblock_reader(_require(folder, MUSCLES_FILE)),
            multiblock_reader(_require(folder, FIBRES_FILE)),
            multiblock_reader(_require(folder, BONES_FILE)),
            motion_reader(_require(folder, MOTION_FILE)))


def read_scene(folder):
    """``(muscles, fibres, bones, motion)`` of a scene folder: three vtkMultiBlockDataSets and
    the motion vtkTable, read with ParaView's readers. Checks only that the files exist and
    read; :func:`check_scene` checks the rules."""
    return tuple(r.GetOutputDataObject(0) for r in scene_readers(folder))


# ---- VTK -> arrays -------------------------------------------------------------------------

def surfaces_from_vtk(multiblock, filename) -> dict:
    """``{name: Surface}`` of a multiblock of triangle surfaces."""
    out = {}
    for name, block in V.polydata_blocks(multiblock, filename, "a triangle surface"):
        out[name] = Surface(V.points_of(block),
                            V.triangles_of(block, f"{filename} block '{name}'"))
    return out


def _attachment_name(block, array: str, where: str):
    """The bone named by the optional string field data ``array`` of a fibres block, or None."""
    value = V.field(block, array)
    if value is not None and not isinstance(value, str):
        raise MuscleMSSError(f"{where}: field data '{array}' must be one string, the name of a "
                             f"bone of {BONES_FILE}")
    return value


def fibres_from_vtk(multiblock, filename=FIBRES_FILE) -> dict:
    """``{name: FibreSet}`` of a multiblock of fibre polylines."""
    out = {}
    for name, block in V.polydata_blocks(multiblock, filename, "a block of fibre polylines"):
        where = f"{filename} block '{name}'"
        points = V.points_of(block)
        offsets, connectivity = V.lines_of(block)
        grid = V.cell_array(block, A.FIBRE_GRID, where, required=False)
        if grid is not None:
            grid = np.asarray(grid).reshape(len(offsets) - 1, -1).astype(np.int32)
        out[name] = FibreSet(points[connectivity], offsets, grid,
                             _attachment_name(block, A.ORIGIN_BONE, where),
                             _attachment_name(block, A.INSERTION_BONE, where))
    return out


def motion_rows_from_table(table, filename=MOTION_FILE):
    """``(times, bones, values (R, 12))`` of a motion table; raise if a column is missing."""
    columns = V.table_columns(table)
    missing = [c for c in MOTION_COLUMNS if c not in columns]
    if missing:
        raise MuscleMSSError(f"{filename}: column(s) {', '.join(missing)} missing; the header "
                             f"must be {','.join(MOTION_COLUMNS)}")
    try:
        times = np.asarray(columns["time"], dtype=np.float64)
        values = np.column_stack([np.asarray(columns[c], dtype=np.float64)
                                  for c in MOTION_COLUMNS[2:]])
    except ValueError as err:
        raise MuscleMSSError(f"{filename}: a time or matrix entry is not a number ({err})") from None
    return times, [str(b) for b in columns["bone"]], values


def check_scene(folder):
    """Read and check a scene folder: ``(scene or None, problems)``, one sentence per broken
    rule (DESIGN §4). The scene is returned only when there is no problem."""
    try:
        muscles_mb, fibres_mb, bones_mb, table = read_scene(folder)
        scene = Scene(surfaces_from_vtk(muscles_mb, MUSCLES_FILE),
                      fibres_from_vtk(fibres_mb, FIBRES_FILE),
                      surfaces_from_vtk(bones_mb, BONES_FILE))
        rows = motion_rows_from_table(table)
    except MuscleMSSError as err:
        return None, [str(err)]
    problems = scene_problems(scene, rows=rows) + attachment_problems(scene)
    if problems:
        return None, problems
    scene.motion = motion_problems(*rows, known_bones=list(scene.bones))[0]
    return scene, []


def load_scene(folder) -> Scene:
    """A checked scene folder as arrays; raise :class:`MuscleMSSError` naming the first broken
    rule (and how many more there are)."""
    scene, problems = check_scene(folder)
    if problems:
        raise first_problem(problems)
    return scene
