"""Point normals of the deformed surfaces: the Numba kernel against VTK's vtkPolyDataNormals."""
import numpy as np
from test_collisions import icosphere_like
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkFiltersCore import vtkPolyDataNormals

from muscle_mss.core.surface_normals import point_normals
from muscle_mss.filters import vtk_arrays as V


def vtk_point_normals(points, triangles):
    """vtkPolyDataNormals with the settings the MVC Surface Deformer used (the reference)."""
    normals = vtkPolyDataNormals()
    normals.SetInputData(V.make_polydata(points, triangles))
    normals.SplittingOff()
    normals.ConsistencyOff()
    normals.AutoOrientNormalsOff()
    normals.ComputePointNormalsOn()
    normals.ComputeCellNormalsOff()
    normals.Update()
    return vtk_to_numpy(normals.GetOutput().GetPointData().GetNormals())


def test_point_normals_equal_vtks_on_a_bumpy_closed_surface():
    points, triangles = icosphere_like(radius=20.0, n=24)
    rng = np.random.default_rng(3)
    bumpy = points * (1.0 + 0.15 * rng.random((len(points), 1)))   # uneven triangles
    got = point_normals(bumpy, np.asarray(triangles, dtype=np.int64))
    want = vtk_point_normals(bumpy, triangles)
    assert got.dtype == np.float32 and got.shape == want.shape
    np.testing.assert_allclose(got, want, atol=2e-6)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-6)
    # outward on a sphere: the normal points away from the centre
    assert (np.einsum("ij,ij->i", got, bumpy) > 0.0).all()
    # reversed winding turns every normal round
    np.testing.assert_allclose(point_normals(bumpy, np.asarray(triangles)[:, ::-1].copy()), -got,
                               atol=1e-7)


def test_point_normals_of_an_unused_point_and_a_degenerate_triangle_are_harmless():
    points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5], [2, 0, 0]])
    triangles = np.array([[0, 1, 2], [0, 1, 4]])        # the second has no area
    got = point_normals(points, triangles)
    np.testing.assert_array_equal(got[3], [0, 0, 0])   # on no triangle
    np.testing.assert_allclose(got[[0, 1, 2]], [[0, 0, 1]] * 3)
    np.testing.assert_array_equal(got[4], [0, 0, 0])   # on the degenerate triangle only
