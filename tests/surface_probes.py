"""Geometric probes of closed triangle surfaces for the demo-scene tests (VTK only): which points
are inside, signed distances, the gap between two surfaces; and scene equality."""
import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkDoubleArray, vtkIdTypeArray, vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
from vtkmodules.vtkFiltersCore import vtkImplicitPolyDataDistance
from vtkmodules.vtkFiltersModeling import vtkSelectEnclosedPoints

from muscle_mss.core.mesh_checks import surface_problems
from muscle_mss.core.volume import signed_volume


def polydata(points, triangles):
    pd = vtkPolyData()
    vtk_points = vtkPoints()
    vtk_points.SetData(numpy_to_vtk(np.ascontiguousarray(points, dtype=np.float64), deep=True))
    pd.SetPoints(vtk_points)
    tri = np.asarray(triangles, dtype=np.int64)
    cells = vtkCellArray()
    id_type = vtkIdTypeArray().GetDataType()
    cells.SetData(numpy_to_vtk(np.arange(0, 3 * len(tri) + 1, 3, dtype=np.int64), deep=True,
                               array_type=id_type),
                  numpy_to_vtk(tri.reshape(-1).copy(), deep=True, array_type=id_type))
    pd.SetPolys(cells)
    return pd


def inside(surface, points):
    """Which ``points`` (n, 3) vtkSelectEnclosedPoints finds inside the closed ``surface``."""
    select = vtkSelectEnclosedPoints()
    select.SetSurfaceData(polydata(surface.points, surface.triangles))
    probe = vtkPolyData()
    vtk_points = vtkPoints()
    vtk_points.SetData(numpy_to_vtk(np.ascontiguousarray(points, dtype=np.float64), deep=True))
    probe.SetPoints(vtk_points)
    select.SetInputData(probe)
    select.SetTolerance(1e-6)
    select.Update()
    return vtk_to_numpy(select.GetOutput().GetPointData().GetArray("SelectedPoints")) == 1


_DISTANCES = {}


def signed_distance(surface, points):
    """Signed distance (mm) of ``points`` (n, 3) to ``surface``: negative inside."""
    key = id(surface)
    if key not in _DISTANCES:
        # Building the locator is the slow part: once per surface (the scenes live all module).
        _DISTANCES[key] = (surface, vtkImplicitPolyDataDistance())
        _DISTANCES[key][1].SetInput(polydata(surface.points, surface.triangles))
    distance = _DISTANCES[key][1]
    values = vtkDoubleArray()
    distance.FunctionValue(numpy_to_vtk(np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3),
                                        deep=True), values)
    return vtk_to_numpy(values).copy()


def gap(a, b):
    """Smallest distance (mm) between two closed surfaces, negative where they overlap;
    inf when their bounding boxes are more than 10 mm apart."""
    lo = np.maximum(a.points.min(axis=0), b.points.min(axis=0)) - 10.0
    hi = np.minimum(a.points.max(axis=0), b.points.max(axis=0)) + 10.0
    gaps = [np.inf]
    for one, other in ((a, b), (b, a)):
        near = one.points[((one.points > lo) & (one.points < hi)).all(axis=1)]
        if len(near):
            gaps.append(signed_distance(other, near).min())
    return min(gaps)


def assert_identical_scenes(a, b):
    """Every array of scenes ``a`` and ``b`` (surfaces, fibres, attachments, motion) is equal."""
    for group in ("muscles", "bones"):
        assert list(getattr(a, group)) == list(getattr(b, group))
        for name, surface in getattr(a, group).items():
            other = getattr(b, group)[name]
            assert np.array_equal(surface.points, other.points), name
            assert np.array_equal(surface.triangles, other.triangles), name
    for name, fibres in a.fibres.items():
        other = b.fibres[name]
        assert np.array_equal(fibres.points, other.points), name
        assert np.array_equal(fibres.offsets, other.offsets), name
        assert np.array_equal(fibres.grid, other.grid), name
        assert (fibres.origin_bone, fibres.insertion_bone) == (other.origin_bone,
                                                               other.insertion_bone)
    assert np.array_equal(a.motion.matrices, b.motion.matrices)
    assert np.array_equal(a.motion.times, b.motion.times)


def assert_closed_and_outward(scene):
    """Every bone and muscle surface of ``scene`` is closed, manifold and outward oriented."""
    for name, surface in list(scene.bones.items()) + list(scene.muscles.items()):
        assert surface.points.dtype == np.float64 and surface.triangles.dtype == np.int64
        assert surface_problems(surface.points, surface.triangles) == [], name
        assert signed_volume(surface.points, surface.triangles) > 0.0, name
