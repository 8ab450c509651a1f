"""Scene folders on disk (DESIGN §4): ``muscles.vtm``, ``fibres.vtm``, ``bones.vtm``, ``motion.csv``.

Files are read with the same VTK readers ParaView uses (XML multiblock reader, delimited-text
reader for the CSV), so what the filters see here is what they see in ParaView.
"""
from __future__ import annotations

import contextlib
import csv
import os
import re
from xml.etree import ElementTree

import numpy as np
from vtkmodules.vtkIOInfovis import vtkDelimitedTextReader
from vtkmodules.vtkCommonCore import vtkLogger, vtkOutputWindow, vtkStringOutputWindow
from vtkmodules.vtkIOXML import (vtkXMLMultiBlockDataReader, vtkXMLMultiBlockDataWriter,
                                 vtkXMLPolyDataReader)

from muscle_mss.core.attachment_areas import ATTACHMENTS_FILE, attachment_rows, bone_conflict
from muscle_mss.core.attachments import attachment_problems
from muscle_mss.core.errors import MuscleMSSError, first_problem
from muscle_mss.core.fibre_pieces import joined_fibres, joined_warning
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

def write_multiblock(data, path) -> None:
    """Write the multiblock ``data`` as the ``.vtm`` file ``path`` and its block files (in the
    folder named after it), binary appended."""
    writer = vtkXMLMultiBlockDataWriter()
    writer.SetFileName(str(path))
    writer.SetInputData(data)
    writer.SetDataModeToAppended()
    writer.EncodeAppendedDataOff()
    if not writer.Write():
        raise MuscleMSSError(f"{path}: could not be written")


def listed_block_files(path) -> list:
    """The block files that the ``.vtm`` file ``path`` lists and that are there ([] when it is
    absent or unreadable)."""
    if not os.path.isfile(path):
        return []
    with contextlib.suppress(MuscleMSSError):
        folder = os.path.dirname(path)
        return [p for p in (os.path.join(folder, block) for _, block in _blocks_listed(path))
                if os.path.isfile(p)]
    return []


def write_scene(scene: Scene, folder) -> None:
    """Write a scene folder that stock ParaView readers open."""
    os.makedirs(folder, exist_ok=True)
    muscles, fibres, bones, _ = scene_to_vtk(scene)
    for data, filename in ((muscles, MUSCLES_FILE), (fibres, FIBRES_FILE), (bones, BONES_FILE)):
        write_multiblock(data, os.path.join(folder, filename))
    times, bone_names, values = motion_rows(scene.motion)
    with open(os.path.join(folder, MOTION_FILE), "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(MOTION_COLUMNS)
        for t, b, row in zip(times, bone_names, values):
            out.writerow([repr(float(t)), b] + [repr(float(v)) for v in row])


def scene_files(folder) -> list:
    """The files a run reads from the scene folder ``folder`` that are there: its three
    ``.vtm`` files, each one's block files (as listed in it), the motion table and the
    optional ``attachments.csv``."""
    files = []
    for filename in (MUSCLES_FILE, FIBRES_FILE, BONES_FILE):
        path = os.path.join(folder, filename)
        if os.path.isfile(path):
            files.append(path)
            with contextlib.suppress(MuscleMSSError):
                files += [os.path.join(folder, block) for _, block in _blocks_listed(path)]
    return files + [path for path in (os.path.join(folder, name)
                                      for name in (MOTION_FILE, ATTACHMENTS_FILE))
                    if os.path.isfile(path)]


def _require(folder, filename):
    path = os.path.join(folder, filename)
    if not os.path.isfile(path) and filename == FIBRES_FILE and \
            os.path.isfile(os.path.join(folder, MUSCLES_FILE)):
        raise MuscleMSSError(f"{path}: missing; generate the fibres from the muscles and bones "
                             f"with: muscle-mss fibres {folder}")
    if not os.path.isfile(path):
        raise MuscleMSSError(f"{path}: missing; a scene folder holds {MUSCLES_FILE}, "
                             f"{FIBRES_FILE}, {BONES_FILE} and {MOTION_FILE}")
    return path


@contextlib.contextmanager
def vtk_messages():
    """Collect VTK's error and warning text while reading instead of printing it (raw "ERR|"
    lines on stderr): yields a ``vtkStringOutputWindow`` whose ``GetOutput()`` holds it."""
    previous = vtkOutputWindow.GetInstance()
    cutoff = vtkLogger.GetCurrentVerbosityCutoff()
    window = vtkStringOutputWindow()
    vtkOutputWindow.SetInstance(window)
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
    try:
        yield window
    finally:
        vtkOutputWindow.SetInstance(previous)
        vtkLogger.SetStderrVerbosity(cutoff)


def vtk_error(text: str) -> str | None:
    """The first VTK error in collected output window text, without the source line and the
    object's address (``"Error opening file muscles/muscles_1.vtp"``), or None."""
    lines = text.splitlines()
    for k, line in enumerate(lines):
        if line.startswith("ERROR") and k + 1 < len(lines):
            return re.sub(r"^\w+ \(0x[0-9a-fA-F]+\): ", "", lines[k + 1]).strip()
    return None


def _blocks_listed(path) -> list:
    """``(name, file)`` of every dataset a ``.vtm`` file lists (``file`` relative to it)."""
    try:
        root = ElementTree.parse(path).getroot()
    except (ElementTree.ParseError, OSError) as err:
        raise MuscleMSSError(f"{path}: is not a readable VTK multiblock file ({err})") from None
    return [(d.get("name") or f"block {d.get('index')}", d.get("file"))
            for d in root.iter("DataSet") if d.get("file")]


def _check_block_file(path, name, filename):
    """Read one block's ``.vtp`` on its own: it must exist and read without a VTK error, and
    hold points. Returns its number of points."""
    where = f"{path} block '{name}'"
    full = os.path.join(os.path.dirname(path), filename)
    if not os.path.isfile(full):
        raise MuscleMSSError(f"{where}: its file {full} is missing; every block's file must "
                             "exist (the reader would show the previous block instead)")
    reader = vtkXMLPolyDataReader()
    reader.SetFileName(full)
    with vtk_messages() as messages:
        reader.Update()
    problem = vtk_error(messages.GetOutput())
    data = reader.GetOutput()
    if problem or data is None or data.GetNumberOfPoints() == 0:
        raise MuscleMSSError(f"{where}: its file {full} could not be read as VTK polydata ("
                             f"{problem or 'no points'}); every block must be a readable .vtp")
    return data.GetNumberOfPoints()


def multiblock_reader(path):
    """An updated VTK XML multiblock reader of a ``.vtm`` file (what ParaView uses), every
    block checked against its own file: a missing or unreadable ``.vtp`` is an error naming
    it (VTK's reader would carry the previous block's data into that block and print "ERR|"
    lines), and so is any VTK error while reading."""
    listed = _blocks_listed(path)
    points = [_check_block_file(path, name, filename) for name, filename in listed]
    reader = vtkXMLMultiBlockDataReader()
    reader.SetFileName(path)
    with vtk_messages() as messages:
        reader.Update()
    problem = vtk_error(messages.GetOutput())
    if problem:
        raise MuscleMSSError(f"{path}: could not be read ({problem})")
    data = reader.GetOutputDataObject(0)
    if data is None or data.GetNumberOfBlocks() == 0:
        raise MuscleMSSError(f"{path}: could not be read as a multiblock dataset or has no blocks")
    for k, (name, _) in enumerate(listed):
        block = data.GetBlock(k) if k < data.GetNumberOfBlocks() else None
        if block is None or block.GetNumberOfPoints() != points[k]:
            raise MuscleMSSError(f"{path} block '{name}': the reader did not give the data of "
                                 "its file; check the .vtm and its .vtp files")
    return reader


def check_motion_cells(path):
    """Every data row of ``motion.csv`` has a value in every column of its header: an empty or
    missing cell is an error naming its row (1 = the first data row, as the motion rules count)
    and column (VTK's reader would read it as 0: a bone moved by tens of millimetres)."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise MuscleMSSError(f"{path}: could not be read as CSV ({err})") from None
    if not rows:
        return
    header = [h.strip() for h in rows[0]]
    for r, row in enumerate(rows[1:], start=1):
        if not any(cell.strip() for cell in row):
            continue
        for c, name in enumerate(header):
            if c >= len(row) or not row[c].strip():
                what = "missing" if c >= len(row) else "empty"
                raise MuscleMSSError(f"{path} row {r} (line {r + 1}), column {name}: the cell is "
                                     f"{what}; every row needs a value in every column")


def csv_reader(path, numeric: bool):
    """An updated delimited-text reader of the CSV file ``path`` with a header row, set up as
    ParaView's CSV reader (``numeric``: numeric columns detected, empty cells read as NaN, not
    0; else every column read as text); VTK's reader errors become our error."""
    reader = vtkDelimitedTextReader()
    reader.SetFileName(path)
    reader.SetHaveHeaders(True)
    reader.SetDetectNumericColumns(numeric)
    reader.SetFieldDelimiterCharacters(",")
    reader.SetDefaultDoubleValue(float("nan"))
    with vtk_messages() as messages:
        reader.Update()
    problem = vtk_error(messages.GetOutput())
    if problem:
        raise MuscleMSSError(f"{path}: could not be read ({problem})")
    return reader


def motion_reader(path):
    """An updated reader of ``motion.csv`` (:func:`csv_reader`, its empty cells named first)."""
    check_motion_cells(path)
    return csv_reader(path, numeric=True)


def attachments_reader(path):
    """An updated reader of ``attachments.csv`` (every column read as text, as bone names
    are), or None when the file is absent."""
    return csv_reader(path, numeric=False) if os.path.isfile(path) else None


def named_attachments(folder, muscles, bones) -> dict:
    """``{muscle: (origin bone, insertion bone)}`` of the scene's optional ``attachments.csv``
    (empty without one); its rows checked against the ``muscles`` and ``bones`` names."""
    path = os.path.join(folder, ATTACHMENTS_FILE)
    reader = attachments_reader(path)
    if reader is None:
        return {}
    return attachment_rows(V.table_rows(reader.GetOutput()), list(muscles),
                           list(bones), path)


def with_named_bones(fibres: dict, named: dict, filename: str) -> list:
    """Set the attachment bones ``named`` by ``attachments.csv`` on the ``fibres``
    (``{muscle: FibreSet}``) in place; one sentence per muscle whose ``fibres.vtm`` block
    names another bone."""
    problems = []
    for muscle, bones in named.items():
        fibres_of = fibres.get(muscle)
        if fibres_of is None:
            continue
        for end, bone in zip(("origin", "insertion"), bones):
            problem = bone_conflict(f"{FIBRES_FILE} block '{muscle}'", end,
                                    getattr(fibres_of, f"{end}_bone"), bone, filename)
            if problem:
                problems.append(problem)
            setattr(fibres_of, f"{end}_bone", bone)
    return problems


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
        offsets, connectivity = V.fibre_lines(block, where)
        grid = V.cell_array(block, A.FIBRE_GRID, where, required=False)
        if grid is not None:   # cell data runs over vertices first, then lines
            first = block.GetNumberOfVerts()
            grid = np.asarray(grid).reshape(len(grid), -1)[first:first + len(offsets) - 1]
            grid = grid.astype(np.int32)
        fibre_points, offsets, grid, pieces = joined_fibres(points[connectivity], offsets, grid,
                                                            where)
        if pieces:
            V.warn_once(block, joined_warning(where, pieces, len(offsets) - 1))
        out[name] = FibreSet(fibre_points, offsets, grid,
                             _attachment_name(block, A.ORIGIN_BONE, where),
                             _attachment_name(block, A.INSERTION_BONE, where))
    return out


def motion_rows_from_table(table, filename=MOTION_FILE):
    """``(times, bones, values (R, 12))`` of a motion table; raise if a column is missing."""
    # spaces around the header's names (``time, bone, m00``) are no part of them
    columns = {name.strip(): values for name, values in V.table_columns(table).items()}
    missing = [c for c in MOTION_COLUMNS if c not in columns]
    if missing:
        raise MuscleMSSError(f"{filename}: column(s) {', '.join(missing)} missing; the header "
                             f"must be {','.join(MOTION_COLUMNS)}")
    try:
        times = np.asarray(columns["time"], dtype=np.float64)
        values = np.column_stack([np.asarray(columns[c], dtype=np.float64)
                                  for c in MOTION_COLUMNS[2:]])
    except ValueError:
        for c in MOTION_COLUMNS[:1] + MOTION_COLUMNS[2:]:
            for r, value in enumerate(np.asarray(columns[c], dtype=object)):
                try:
                    float(value)
                except (TypeError, ValueError):
                    raise MuscleMSSError(f"{filename} row {r + 1}, column {c}: {value!r} is not a "
                                         "number; every time and matrix entry must be a "
                                         "number") from None
        raise MuscleMSSError(f"{filename}: a time or matrix entry is not a number") from None
    return times, [str(b).strip() for b in columns["bone"]], values


def check_scene(folder):
    """Read and check a scene folder: ``(scene or None, problems)``, one sentence per broken
    rule (DESIGN §4). The scene is returned only when there is no problem."""
    try:
        muscles_mb, fibres_mb, bones_mb, table = read_scene(folder)
        scene = Scene(surfaces_from_vtk(muscles_mb, MUSCLES_FILE),
                      fibres_from_vtk(fibres_mb, FIBRES_FILE),
                      surfaces_from_vtk(bones_mb, BONES_FILE))
        rows = motion_rows_from_table(table)
        named = named_attachments(folder, scene.muscles, scene.bones)
    except MuscleMSSError as err:
        return None, [str(err)]
    problems = with_named_bones(scene.fibres, named, os.path.join(folder, ATTACHMENTS_FILE))
    problems += scene_problems(scene, rows=rows) + attachment_problems(scene)
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
