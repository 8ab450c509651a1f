"""Every conversion between VTK objects and NumPy arrays (STYLE "Layers that never leak").

The filters call these helpers and hand plain arrays to ``muscle_mss.core``. Arrays taken from
VTK are copies, so that a filter can never modify its input by writing into them.
"""
from __future__ import annotations

import numpy as np
from vtkmodules.util.numpy_support import (create_vtk_array, get_numpy_array_type,
                                          get_vtk_array_type, vtk_to_numpy)
from vtkmodules.vtkCommonCore import (vtkDoubleArray, vtkIdTypeArray, vtkOutputWindow, vtkPoints,
                                      vtkStringArray)
from vtkmodules.vtkCommonDataModel import (vtkCellArray, vtkCompositeDataSet,
                                           vtkMultiBlockDataSet, vtkPolyData, vtkTable)

from muscle_mss.core.errors import MuscleMSSError


# ---- points and cells --------------------------------------------------------------------

def points_of(dataset) -> np.ndarray:
    """Point coordinates as a new (n, 3) float64 array (empty for a dataset without points)."""
    pts = dataset.GetPoints()
    if pts is None or dataset.GetNumberOfPoints() == 0:
        return np.zeros((0, 3))
    return np.array(_numpy_view(pts.GetData()), dtype=np.float64).reshape(-1, 3)


def _cell_array_to_csr(cells: vtkCellArray):
    offsets = np.array(_numpy_view(cells.GetOffsetsArray()), dtype=np.int64)
    connectivity = np.array(_numpy_view(cells.GetConnectivityArray()), dtype=np.int64)
    if len(offsets) == 0:
        offsets = np.zeros(1, dtype=np.int64)
    return offsets, connectivity


def _csr_to_cell_array(offsets, connectivity) -> vtkCellArray:
    cells = vtkCellArray()
    cells.SetData(*(_vtk_copy(values, _ID_TYPE) for values in (offsets, connectivity)))
    return cells


_ID_TYPE = vtkIdTypeArray().GetDataType()
_NUMPY_TYPES = {}   # VTK data type -> NumPy dtype, as vtk_to_numpy chooses it


def _numpy_view(array) -> np.ndarray:
    """``vtk_to_numpy(array)`` (a NumPy view of a VTK data array's values, (n,) or (n, k)),
    without its per-call type tables (ParaView's VTK 9.2 builds two at every call: 8 us of a
    conversion made about 440 times a time point)."""
    dtype = _NUMPY_TYPES.get(array.GetDataType())
    if dtype is None:
        view = vtk_to_numpy(array)          # checks the type (bit arrays are refused)
        _NUMPY_TYPES[array.GetDataType()] = get_numpy_array_type(array.GetDataType())
        return view
    tuples, components = array.GetNumberOfTuples(), array.GetNumberOfComponents()
    if tuples == 0:
        return np.empty((0, components) if components > 1 else (0,), dtype=dtype)
    view = np.frombuffer(array, dtype=dtype)
    return view.reshape(tuples, components) if components > 1 else view


_VTK_TYPES = {}     # NumPy dtype -> VTK data type, as numpy_to_vtk chooses it


def _vtk_copy(values, vtk_type=None):
    """A new VTK array holding a copy of ``values`` ((n,) or (n, k)), of ``vtk_type`` (default:
    the type ``numpy_to_vtk`` gives the dtype). numpy_to_vtk's type lookup made each call 19 us
    in ParaView's Python against 7 us here, and a time point makes about 260 arrays."""
    values = np.asarray(values)
    if vtk_type is None:
        vtk_type = _VTK_TYPES.get(values.dtype)
        if vtk_type is None:
            vtk_type = _VTK_TYPES[values.dtype] = get_vtk_array_type(values.dtype)
    array = create_vtk_array(vtk_type)
    array.SetNumberOfComponents(1 if values.ndim == 1 else values.shape[1])
    array.SetNumberOfTuples(values.shape[0])
    if values.size:
        _numpy_view(array)[...] = values
    return array


def triangles_of(polydata, where: str = "") -> np.ndarray:
    """The polygons of a vtkPolyData as (m, 3) int64, then the triangles of its triangle strips
    (:func:`strip_triangles`, with a warning naming ``where``); raise if any polygon is not a
    triangle."""
    offsets, connectivity = _cell_array_to_csr(polydata.GetPolys())
    sizes = np.diff(offsets)
    if (sizes != 3).any():
        bad = int(np.flatnonzero(sizes != 3)[0])
        raise MuscleMSSError(f"{where}: polygon {bad} has {int(sizes[bad])} points; "
                             "surfaces must be triangle meshes (apply Triangulate first)")
    triangles = connectivity.reshape(-1, 3)
    if polydata.GetNumberOfStrips() == 0:
        return triangles
    from_strips = strip_triangles(*_cell_array_to_csr(polydata.GetStrips()))
    warn_once(polydata.GetStrips(),
               f"{where}: its {polydata.GetNumberOfStrips()} triangle strips are read as "
               f"{len(from_strips)} triangles (the file is not changed); surfaces are triangle "
               "lists: apply ParaView's Triangulate filter and save the file to silence this")
    return np.concatenate([triangles, from_strips])


def strip_triangles(offsets, connectivity) -> np.ndarray:
    """The triangles (m, 3) int64 of triangle strips in CSR form, oriented as VTK orients them
    (the strip's odd triangles flipped, as ``vtkTriangleFilter`` gives them); the degenerate
    ones that join strips (a point used twice) left out."""
    out = []
    for first, end in zip(offsets[:-1], offsets[1:]):
        ids = connectivity[first:end]
        for k in range(len(ids) - 2):
            a, b, c = ids[k], ids[k + 1], ids[k + 2]
            if a != b and b != c and a != c:
                out.append((b, a, c) if k % 2 else (a, b, c))
    return np.array(out, dtype=np.int64).reshape(-1, 3)


_warned = set()


def warn_once(source, text: str) -> None:
    """Show ``text`` as a VTK warning (ParaView's output messages; stderr in Python) once per
    ``source`` (a VTK object) as modified: every filter reading the block would say it again."""
    key = (source.GetAddressAsString("vtkObject"), source.GetMTime())
    if key not in _warned:
        _warned.add(key)
        vtkOutputWindow.GetInstance().DisplayWarningText(f"warning: {text}\n")


def lines_of(polydata):
    """The line / polyline cells of a vtkPolyData as CSR ``(offsets (c+1,), connectivity)``."""
    return _cell_array_to_csr(polydata.GetLines())


def fibre_lines(polydata, where: str):
    """:func:`lines_of` a block of fibres; raise :class:`MuscleMSSError` naming ``where`` when it
    has no line cells but cells of another kind (poly-vertex cells are points without an order
    to follow, not fibres)."""
    offsets, connectivity = lines_of(polydata)
    kinds = [] if len(offsets) > 1 else [(count, kind) for count, kind in (
        (polydata.GetNumberOfVerts(), "vertex or poly-vertex cells (VTK_VERTEX, VTK_POLY_VERTEX)"),
        (polydata.GetNumberOfPolys(), "polygons"), (polydata.GetNumberOfStrips(), "strips"))
        if count]
    if kinds:
        raise MuscleMSSError(
            f"{where}: holds {' and '.join(f'{n} {kind}' for n, kind in kinds)}; fibres must be "
            "polylines (VTK_POLY_LINE), one line cell per fibre through its points from origin "
            "to insertion: convert the block's cells to polylines")
    return offsets, connectivity


def make_polydata(points, triangles=None, line_offsets=None, line_connectivity=None,
                  segments=None) -> vtkPolyData:
    """A new vtkPolyData from arrays.

    ``triangles`` (m, 3) int; polylines as CSR (``line_offsets``, ``line_connectivity``);
    or two-point lines (springs) as ``segments`` (s, 2) int.
    """
    pd = vtkPolyData()
    vpts = vtkPoints()
    vpts.SetData(_vtk_copy(np.asarray(points, dtype=np.float64).reshape(-1, 3)))
    pd.SetPoints(vpts)
    if triangles is not None:
        tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        pd.SetPolys(_csr_to_cell_array(np.arange(0, 3 * len(tri) + 1, 3), tri.reshape(-1)))
    if segments is not None:
        seg = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
        pd.SetLines(_csr_to_cell_array(np.arange(0, 2 * len(seg) + 1, 2), seg.reshape(-1)))
    elif line_offsets is not None:
        pd.SetLines(_csr_to_cell_array(line_offsets, line_connectivity))
    return pd


def with_points(polydata, points) -> vtkPolyData:
    """A copy of ``polydata`` (cells and arrays shared, never modified) with new coordinates."""
    out = vtkPolyData()
    out.ShallowCopy(polydata)
    vpts = vtkPoints()
    vpts.SetData(_vtk_copy(np.asarray(points, dtype=np.float64).reshape(-1, 3)))
    out.SetPoints(vpts)  # a new vtkPoints: the input's stay untouched
    return out


def arrays_identity(polydata) -> tuple:
    """What identifies a vtkPolyData's cells and point and cell arrays, but not its coordinates:
    the number of points and each array's and cell array's VTK object with its modification
    time. :func:`with_points` keeps it (the arrays are shared), so the posed blocks of every
    time point of a motion have the same identity; a new, replaced or modified array (its
    ``Modified()``, as every VTK setter calls) changes it."""
    out = [polydata.GetNumberOfPoints()]
    for data in (polydata.GetPointData(), polydata.GetCellData()):
        for i in range(data.GetNumberOfArrays()):
            array = data.GetAbstractArray(i)
            out.append((array.GetName(), array.__this__, array.GetMTime()))
    for cells in (polydata.GetVerts(), polydata.GetLines(), polydata.GetPolys(),
                  polydata.GetStrips()):
        out.append(None if cells is None else (cells.__this__, cells.GetMTime()))
    return tuple(out)


# ---- data arrays ---------------------------------------------------------------------------

def _get(data, name, where, required):
    arr = data.GetAbstractArray(name)
    if arr is None:
        if required:
            raise MuscleMSSError(f"{where}: array '{name}' is missing")
        return None
    return arr


def point_array(dataset, name: str, where: str = "", required: bool = True, dtype=None):
    """A copy of a point-data array as NumPy (None when absent and not required)."""
    arr = _get(dataset.GetPointData(), name, where, required)
    return None if arr is None else np.array(_numpy_view(arr), dtype=dtype)


def cell_array(dataset, name: str, where: str = "", required: bool = True, dtype=None):
    """A copy of a cell-data array as NumPy (None when absent and not required)."""
    arr = _get(dataset.GetCellData(), name, where, required)
    return None if arr is None else np.array(_numpy_view(arr), dtype=dtype)


def _to_vtk(name, values):
    values = np.ascontiguousarray(values)
    if values.dtype == np.bool_:
        values = values.astype(np.uint8)
    arr = _vtk_copy(values)
    arr.SetName(name)
    return arr


def set_point_array(dataset, name: str, values) -> None:
    """Add (or replace) a point-data array; (n,) or (n, k) values."""
    dataset.GetPointData().AddArray(_to_vtk(name, values))


def set_normals(dataset, values) -> None:
    """Set ``values`` (n, 3) as the point normals (the ``Normals`` array, the active normals
    that shading uses)."""
    dataset.GetPointData().SetNormals(_to_vtk("Normals", values))


def shared_array(name: str, values):
    """A new VTK array of ``values`` ((n,) or (n, k)) to share among the outputs of several
    updates (as point data by :func:`add_point_arrays`, or cell data): the same array keeps the
    outputs' :func:`arrays_identity`, and is made once."""
    return _to_vtk(name, values)


def add_point_arrays(dataset, arrays) -> None:
    """Add (or replace, by name) the VTK ``arrays`` as point data, shared, not copied."""
    data = dataset.GetPointData()
    for array in arrays:
        data.AddArray(array)


def set_cell_array(dataset, name: str, values) -> None:
    """Add (or replace) a cell-data array; (c,) or (c, k) values."""
    dataset.GetCellData().AddArray(_to_vtk(name, values))


def point_arrays(dataset) -> dict:
    """All point-data arrays (copies) by name."""
    pdata = dataset.GetPointData()
    out = {}
    for i in range(pdata.GetNumberOfArrays()):
        arr = pdata.GetAbstractArray(i)
        if arr is not None and arr.GetName() and hasattr(arr, "GetNumberOfComponents") \
                and arr.IsNumeric():
            out[arr.GetName()] = np.array(_numpy_view(arr))
    return out


def set_field(dataset, name: str, value) -> None:
    """Store a string, a number, a sequence of strings or numbers in field data."""
    fd = dataset.GetFieldData()
    if isinstance(value, str):
        arr = vtkStringArray()
        arr.SetName(name)
        arr.InsertNextValue(value)
    elif isinstance(value, (list, tuple)) and value and isinstance(value[0], str):
        arr = vtkStringArray()
        arr.SetName(name)
        for v in value:
            arr.InsertNextValue(v)
    else:
        arr = vtkDoubleArray()
        arr.SetName(name)
        for v in np.atleast_1d(np.asarray(value, dtype=np.float64)):
            arr.InsertNextValue(float(v))
    fd.AddArray(arr)


def field(dataset, name: str, default=None):
    """A field-data value: a str (one string), a list of str, a float or a float array."""
    arr = dataset.GetFieldData().GetAbstractArray(name)
    if arr is None:
        return default
    if isinstance(arr, vtkStringArray):
        values = [arr.GetValue(i) for i in range(arr.GetNumberOfValues())]
        return values[0] if len(values) == 1 else values
    values = np.array(_numpy_view(arr), dtype=np.float64)
    return float(values[0]) if values.size == 1 else values


# ---- multiblocks -----------------------------------------------------------------------------

def blocks(multiblock, where: str = "") -> list:
    """The leaves of a multiblock as ``[(name, dataset), …]`` in order, empty leaves skipped.

    Every leaf must have a name (``vtkCompositeDataSet.NAME()``) that is unique.
    """
    items = []
    name_key = vtkCompositeDataSet.NAME()
    it = multiblock.NewTreeIterator()
    it.VisitOnlyLeavesOn()
    it.SkipEmptyNodesOn()
    it.InitTraversal()
    while not it.IsDoneWithTraversal():
        name = ""
        if it.HasCurrentMetaData():
            md = it.GetCurrentMetaData()
            if name_key.Has(md):        # the key's methods: vtkInformation's overloaded
                name = name_key.Get(md)   # Has/Get/Set took 10-14 us a call in pvpython
        items.append((name, it.GetCurrentDataObject()))
        it.GoToNextItem()
    names = [n for n, _ in items]
    for i, n in enumerate(names):
        if not n:
            raise MuscleMSSError(f"{where}: block {i} has no name; every block must be named "
                                 "after its muscle or bone")
        if names.index(n) != i:
            raise MuscleMSSError(f"{where}: two blocks are named '{n}'; names must be unique")
    return items


def require_polydata(block, where: str, what: str = "a vtkPolyData"):
    """``block`` itself when it is a vtkPolyData; otherwise raise naming ``where`` and ``what``
    it must be (e.g. "a triangle surface")."""
    if not block.IsA("vtkPolyData"):
        raise MuscleMSSError(f"{where}: is a {block.GetClassName()}; it must be {what} "
                             "(a vtkPolyData)")
    return block


def polydata_blocks(multiblock, where: str, what: str = "a vtkPolyData") -> list:
    """:func:`blocks`, each checked by :func:`require_polydata`."""
    items = blocks(multiblock, where=where)
    for name, block in items:
        require_polydata(block, f"{where} block '{name}'", what)
    return items


def fill_multiblock(out: vtkMultiBlockDataSet, items) -> vtkMultiBlockDataSet:
    """Make ``out`` a flat multiblock of the named ``items`` ``[(name, dataset), …]``."""
    out.Initialize()
    out.SetNumberOfBlocks(len(items))
    name_key = vtkCompositeDataSet.NAME()
    for i, (name, data) in enumerate(items):
        out.SetBlock(i, data)
        name_key.Set(out.GetMetaData(i), name)     # not GetMetaData(i).Set: see blocks()
    return out


def make_multiblock(items) -> vtkMultiBlockDataSet:
    """A new flat multiblock of the named ``items``."""
    return fill_multiblock(vtkMultiBlockDataSet(), items)


# ---- tables ----------------------------------------------------------------------------------

def table_columns(table) -> dict:
    """The columns of a vtkTable by name: numeric ones as NumPy, string ones as lists of str."""
    out = {}
    for i in range(table.GetNumberOfColumns()):
        col = table.GetColumn(i)
        name = table.GetColumnName(i)
        if isinstance(col, vtkStringArray):
            out[name] = [col.GetValue(j) for j in range(col.GetNumberOfValues())]
        elif col.IsNumeric():
            out[name] = np.array(_numpy_view(col))
        else:  # a vtkVariantArray, as some readers make
            out[name] = [col.GetValue(j).ToString() for j in range(col.GetNumberOfValues())]
    return out


def table_rows(table) -> list:
    """The rows of a vtkTable as dicts by column name (names stripped of spaces)."""
    columns = {name.strip(): list(values) for name, values in table_columns(table).items()}
    count = max((len(v) for v in columns.values()), default=0)
    return [{name: values[r] for name, values in columns.items()} for r in range(count)]


def fill_table(out: vtkTable, columns: dict) -> vtkTable:
    """Make ``out`` a table of ``columns`` (name → numbers or strings), in order."""
    out.Initialize()
    for name, values in columns.items():
        values = list(values) if not isinstance(values, np.ndarray) else values
        if len(values) and isinstance(values[0], str):
            arr = vtkStringArray()
            arr.SetName(name)
            for v in values:
                arr.InsertNextValue(v)
        else:
            arr = _to_vtk(name, np.asarray(values))
        out.AddColumn(arr)
    return out


def make_table(columns: dict) -> vtkTable:
    """A new vtkTable of ``columns``."""
    return fill_table(vtkTable(), columns)
