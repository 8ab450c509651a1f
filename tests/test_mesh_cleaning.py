"""Segmented surfaces made scene surfaces (:mod:`muscle_mss.core.mesh_cleaning`,
:mod:`muscle_mss.filters.mesh_files`): what an STL export gets wrong is repaired, what cannot be
repaired is refused naming it, and muscles come out at the density the cage follows. Runs in the
venv and in Debian's Python (VTK 9.2, numpy 1.24, scipy 1.10)."""
import numpy as np
import pytest
from scipy.spatial import ConvexHull

from muscle_mss.core import mesh_cleaning as C
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.mesh_checks import surface_problems
from muscle_mss.core.volume import signed_volume
from muscle_mss.filters.vtk_arrays import make_polydata


def ellipsoid(count: int, radii=(30.0, 30.0, 30.0)):
    """``(points, triangles)``: a closed outward triangle surface through ``count`` Fibonacci
    points of the unit sphere scaled by ``radii`` (mm)."""
    k = np.arange(count) + 0.5
    polar = np.arccos(1.0 - 2.0 * k / count)
    azimuth = np.pi * (1.0 + 5.0 ** 0.5) * k
    unit = np.column_stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth),
                            np.cos(polar)])
    triangles = ConvexHull(unit).simplices.astype(np.int64)
    normals = np.cross(unit[triangles[:, 1]] - unit[triangles[:, 0]],
                       unit[triangles[:, 2]] - unit[triangles[:, 0]])
    inward = (normals * unit[triangles].mean(axis=1)).sum(axis=1) < 0
    triangles[inward] = triangles[inward][:, [0, 2, 1]]
    return unit * np.asarray(radii), triangles


def as_stl(points, triangles, flip_share=0.3, seed=1):
    """The surface as an STL export has it: every triangle with its own three points (float32
    rounded), ``flip_share`` of them wound the other way."""
    rng = np.random.default_rng(seed)
    corners = points[triangles].reshape(-1, 3).astype(np.float32).astype(np.float64)
    own = np.arange(len(corners)).reshape(-1, 3)
    flip = rng.random(len(own)) < flip_share
    own[flip] = own[flip][:, [0, 2, 1]]
    return corners, own


def without_ring(triangles, vertex: int):
    """The triangles not touching ``vertex``: a hole of its one-ring."""
    return triangles[~(triangles == vertex).any(axis=1)]


def mass_properties_volume(points, triangles) -> float:
    from vtkmodules.vtkFiltersCore import vtkMassProperties
    mass = vtkMassProperties()
    mass.SetInputData(make_polydata(points, triangles=triangles))
    mass.Update()
    return mass.GetVolume()


def test_an_stl_export_with_flips_and_a_small_hole_comes_out_closed_and_outward():
    points, triangles = ellipsoid(2000)
    volume = signed_volume(points, triangles)
    corners, own = as_stl(points, without_ring(triangles, 7))
    cleaned, cleaned_triangles, report = C.clean_surface(corners, own, "sphere.stl")
    assert surface_problems(cleaned, cleaned_triangles) == []      # closed, manifold, outward
    assert len(cleaned) == len(points)      # the vertex taken out, the hole's centre added
    assert report.merged_points == len(corners) - (len(points) - 1)
    assert 0.25 < report.flipped_triangles / len(own) < 0.35
    assert len(report.holes) == 1 and report.holes[0][0] >= 5
    assert report.holes[0][1] < C.MAX_HOLE_SPAN_MM
    assert signed_volume(cleaned, cleaned_triangles) == pytest.approx(volume, rel=0.01)
    assert signed_volume(cleaned, cleaned_triangles) == pytest.approx(
        mass_properties_volume(cleaned, cleaned_triangles), rel=1e-6)
    assert "1 holes filled" in report.summary()


def test_an_inside_out_surface_is_turned_outward():
    points, triangles = ellipsoid(500)
    _, cleaned, report = C.clean_surface(points, triangles[:, [0, 2, 1]], "inside_out.obj")
    np.testing.assert_array_equal(cleaned, triangles)
    assert report.flipped_triangles == len(triangles)


def test_a_hole_above_the_limit_is_refused_naming_it():
    points, triangles = ellipsoid(2000)
    cap = (points[triangles][:, :, 2] > 24.0).any(axis=1)     # the top 6 mm: a 36 mm opening
    with pytest.raises(MuscleMSSError, match=r"cut_off\.stl: has a hole of \d+ edges spanning "
                                             r"3\d\.\d mm .* larger than the 10 mm filled"):
        C.clean_surface(points, triangles[~cap], "cut_off.stl")
    assert C.clean_surface(points, triangles[~cap], "cut_off.stl", max_hole_span=40.0)[2].holes


def test_non_manifold_edges_and_two_large_pieces_are_refused():
    points, triangles = ellipsoid(200)
    a, b = triangles[0, 0], triangles[0, 1]
    fin = np.vstack([points, [[0.0, 0.0, 0.0]]])
    with pytest.raises(MuscleMSSError, match="finned.ply: 1 edges are shared by more than two "
                                             "triangles"):
        C.clean_surface(fin, np.vstack([triangles, [[a, b, len(points)]]]), "finned.ply")
    twin = np.vstack([points, points + 100.0])
    pair = np.vstack([triangles, triangles + len(points)])
    with pytest.raises(MuscleMSSError, match="twins.stl: has 2 separate pieces"):
        C.clean_surface(twin, pair, "twins.stl", single_piece=True)
    assert len(C.clean_surface(twin, pair, "two_bones.vtp")[1]) == 2 * len(triangles)


def test_a_segmentation_speck_is_dropped():
    points, triangles = ellipsoid(400)
    speck, speck_triangles = ellipsoid(20, (1.0, 1.0, 1.0))
    joined = np.vstack([points, speck + 60.0])
    cleaned, cleaned_triangles, report = C.clean_surface(
        joined, np.vstack([triangles, speck_triangles + len(points)]), "speckled.stl",
        single_piece=True)
    assert report.dropped_pieces == 1 and "1 specks dropped" in report.summary()
    np.testing.assert_array_equal(cleaned, points)


def test_metres_and_millimetres():
    metres = ellipsoid(50, (0.02, 0.03, 0.15))[0]
    assert C.length_scale(metres, "auto", "m.stl") == 1000.0
    assert C.length_scale(metres * 1000.0, "auto", "mm.stl") == 1.0
    assert C.length_scale(metres, "mm", "tiny.stl") == 1.0
    assert C.length_scale(metres * 1000.0, "m", "huge.stl") == 1000.0
    with pytest.raises(MuscleMSSError, match="units 'cm'"):
        C.length_scale(metres, "cm", "x.stl")


def test_long_edges_are_split_without_changing_the_shape():
    points, triangles = ellipsoid(60, (15.0, 15.0, 120.0))
    length = C.principal_length(points)
    assert length == pytest.approx(240.0, rel=0.02)
    limit = C.MAX_EDGE_FRACTION * length
    split, split_triangles = C.split_long_edges(points, triangles, limit)
    edges = np.concatenate([split_triangles[:, [0, 1]], split_triangles[:, [1, 2]],
                            split_triangles[:, [2, 0]]])
    assert np.linalg.norm(split[edges[:, 0]] - split[edges[:, 1]], axis=1).max() <= limit
    assert len(split_triangles) > 2 * len(triangles)
    assert surface_problems(split, split_triangles) == []
    assert signed_volume(split, split_triangles) == pytest.approx(
        signed_volume(points, triangles), rel=1e-12)


def test_a_dense_muscle_file_is_brought_to_the_cage_density(tmp_path):
    from vtkmodules.vtkIOGeometry import vtkSTLWriter
    from muscle_mss.filters.mesh_files import DECIMATION_VOLUME_TOLERANCE, muscle_from_file
    points, triangles = ellipsoid(12000, (0.02, 0.03, 0.15))        # metres, 24 000 triangles
    path = tmp_path / "dense.stl"
    writer = vtkSTLWriter()
    writer.SetFileName(str(path))
    writer.SetInputData(make_polydata(points, triangles=triangles))
    assert writer.Write()
    before = path.read_bytes()
    surface, note = muscle_from_file(str(path))
    assert path.read_bytes() == before
    assert len(surface.triangles) <= C.MAX_MUSCLE_TRIANGLES
    assert note.startswith(f"m, {len(triangles)} -> {len(surface.triangles)} triangles")
    assert surface_problems(surface.points, surface.triangles) == []
    change = signed_volume(surface.points, surface.triangles) / signed_volume(
        points * 1000.0, triangles) - 1.0
    assert abs(change) < DECIMATION_VOLUME_TOLERANCE / 4


def test_quads_are_split_and_files_are_named(tmp_path):
    from muscle_mss.filters.mesh_files import read_mesh_file
    cube = tmp_path / "cube.obj"
    corners = [(x, y, z) for x in (0, 10) for y in (0, 10) for z in (0, 10)]
    faces = [(1, 2, 4, 3), (5, 7, 8, 6), (1, 5, 6, 2), (3, 4, 8, 7), (1, 3, 7, 5), (2, 6, 8, 4)]
    cube.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in corners)
                    + "".join("f " + " ".join(map(str, f)) + "\n" for f in faces))
    points, triangles = read_mesh_file(str(cube))
    assert len(triangles) == 12
    cleaned, cleaned_triangles, _ = C.clean_surface(points, triangles, "cube.obj")
    assert signed_volume(cleaned, cleaned_triangles) == pytest.approx(1000.0)
    with pytest.raises(MuscleMSSError, match="gone.stl: no such file"):
        read_mesh_file(str(tmp_path / "gone.stl"))
    with pytest.raises(MuscleMSSError, match="unknown surface file type .off"):
        read_mesh_file(str(tmp_path / "shape.off"))
