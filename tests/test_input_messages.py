"""Inputs of issue 30 that a row of ``bad_input_cases`` cannot show: inputs now read right (a
motion.csv header with spaces, triangle strips), an unconnected input, and Ctrl-C wherever it
lands: each run ends right or with a message naming the cause."""
import numpy as np
import pytest

import bad_input_cases as B
from muscle_mss.core.errors import Interrupted, MuscleMSSError
from muscle_mss.app import motion_run
from muscle_mss.filters import vtk_arrays as V

CLEAN = B.Case("clean", "", "")


def _scene(tmp_path, files=None):
    return B.make_scene(B.Case("mutated", "", "", files=files), tmp_path / "scene")


def spaced_header(folder):
    lines = (folder / "motion.csv").read_text().splitlines()
    lines[0] = ", ".join(lines[0].split(","))
    (folder / "motion.csv").write_text("\n".join(lines) + "\n")


def test_a_motion_header_with_spaces_after_the_commas_is_read(tmp_path):
    """It said the columns were missing, before."""
    folder = _scene(tmp_path, spaced_header)
    assert (folder / "motion.csv").read_text().startswith("time, bone, m00, ")
    code, message, stderr = B.run_cli(CLEAN, folder, tmp_path / "out")
    assert code == 0 and message is None, stderr
    assert B.run_chain(CLEAN, folder) is None


def as_strips(relative):
    def mutate(folder):
        from vtkmodules.vtkFiltersCore import vtkStripper
        from vtkmodules.vtkIOXML import vtkXMLPolyDataReader, vtkXMLPolyDataWriter
        reader = vtkXMLPolyDataReader()
        reader.SetFileName(str(folder / relative))
        stripper = vtkStripper()
        stripper.SetInputConnection(reader.GetOutputPort())
        stripper.Update()
        assert stripper.GetOutput().GetNumberOfStrips() > 0
        assert stripper.GetOutput().GetNumberOfPolys() == 0
        writer = vtkXMLPolyDataWriter()
        writer.SetFileName(str(folder / relative))
        writer.SetInputData(stripper.GetOutput())
        writer.Write()
    return mutate


def test_strips_give_vtk_triangle_filters_triangles():
    from vtkmodules.vtkFiltersCore import vtkStripper, vtkTriangleFilter
    from vtkmodules.vtkFiltersSources import vtkSphereSource
    sphere = vtkSphereSource()
    sphere.SetThetaResolution(12)
    sphere.SetPhiResolution(9)
    stripper = vtkStripper()
    stripper.SetInputConnection(sphere.GetOutputPort())
    triangulated = vtkTriangleFilter()
    triangulated.SetInputConnection(stripper.GetOutputPort())
    triangulated.Update()
    strips = stripper.GetOutput()
    ours = V.strip_triangles(*V._cell_array_to_csr(strips.GetStrips()))
    theirs = V.triangles_of(triangulated.GetOutput())
    assert len(ours) == len(theirs) == sphere.GetOutput().GetNumberOfPolys()
    assert sorted(map(tuple, ours)) == sorted(map(tuple, theirs))   # orientation included


def test_a_surface_of_triangle_strips_is_read_as_triangles_with_a_warning(tmp_path):
    """It said "surface has no triangles" with no hint, before."""
    plain = _scene(tmp_path)
    stripped = B.make_scene(B.Case("strips", "", "", files=as_strips("muscles/muscles_0.vtp")),
                            tmp_path / "strips")
    code, message, output = B.run_cli(CLEAN, stripped, tmp_path / "out")
    assert code == 0 and message is None, output
    # run_cli's output holds stderr and VTK's output window, where the warning goes
    assert "warning: muscles.vtm block 'rectus_femoris': its " in output
    assert "triangle strips are read as" in output
    assert "apply ParaView's Triangulate filter" in output
    pipelines = [motion_run.build_pipeline(str(f)) for f in (plain, stripped)]
    volumes = [motion_run.solve_time_point(p, B.TIME_INDEX).rows[0]["volume"]
               for p in pipelines]
    assert volumes[0] == pytest.approx(volumes[1], rel=1e-6)


def test_a_collision_solver_without_bones_names_the_input():
    """It gave an empty output without an error, before."""
    from muscle_mss.filters import MSSCollisionSolver
    solver = MSSCollisionSolver()
    solver.SetInputData(0, V.make_multiblock([]))
    with pytest.raises(MuscleMSSError, match=r"input 'PosedBones' is not connected; this input is "
                                             r"required: the posed bone surfaces"):
        solver.Update()


def _raise_in_solver(monkeypatch, exception):
    from muscle_mss.filters import collision_solver

    def execute(self, inputs, outputs):
        raise exception()
    monkeypatch.setattr(collision_solver.MSSCollisionSolver, "execute", execute)


def ctrl_c_in_a_kernel():
    """What Python raises when a compiled kernel returns with a Ctrl-C pending."""
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt as err:
        raise SystemError("<function solve> returned a result with an exception set") from err


@pytest.mark.parametrize("raised", [KeyboardInterrupt, ctrl_c_in_a_kernel])
def test_ctrl_c_in_a_solve_is_an_interruption_naming_the_filter(raised, small_scene_dir,
                                                               tmp_path, monkeypatch):
    """Ctrl-C in a kernel became "failed unexpectedly with SystemError … please report it"."""
    _raise_in_solver(monkeypatch, raised)
    pipeline = motion_run.build_pipeline(str(small_scene_dir))
    with pytest.raises(Interrupted, match="^Ctrl-C while MSS Collision Solver ran$"):
        motion_run.solve_time_point(pipeline, B.TIME_INDEX)
    code, message, stderr = B.run_cli(CLEAN, small_scene_dir, tmp_path / "out")
    assert code == 130 and message is None
    assert "interrupted: Ctrl-C while MSS Collision Solver ran;" in stderr
    assert "SystemError" not in stderr and "report" not in stderr


def test_ctrl_c_stops_the_batch_naming_the_filter_and_releases_the_folder(
        small_scene_dir, tmp_path, monkeypatch, capsys):
    from muscle_mss.app.output_folder import LOCK_FILE
    from muscle_mss.plugin.batch import main as batch
    _raise_in_solver(monkeypatch, KeyboardInterrupt)
    assert batch([str(small_scene_dir), str(tmp_path), "--iterations", "3"]) == 130
    assert "rank 0: interrupted: Ctrl-C while MSS Collision Solver ran;" \
        in capsys.readouterr().err
    assert not (tmp_path / LOCK_FILE).exists()


def test_ctrl_c_before_a_filters_own_handling_names_the_filter(small_scene_dir, monkeypatch):
    from muscle_mss.filters import base

    def interrupted(algorithm):
        raise KeyboardInterrupt
    pipeline = motion_run.build_pipeline(str(small_scene_dir))
    monkeypatch.setattr(base, "upstream_error", interrupted)
    with pytest.raises(Interrupted, match="^Ctrl-C while (Fibre Resampler|Spring Builder) ran$"):
        pipeline.springs.Update()
    assert base.running_filter() is None


def test_ctrl_c_outside_the_filters_names_the_command(small_scene_dir, tmp_path, monkeypatch):
    """Such a Ctrl-C said "interrupted: ;", before."""
    from muscle_mss.app import run_output

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(run_output, "write_time_point", interrupted)
    code, message, stderr = B.run_cli(CLEAN, small_scene_dir, tmp_path / "out")
    assert code == 130
    assert "interrupted: Ctrl-C while muscle-mss run ran;" in stderr
    assert "interrupted: ;" not in stderr


def test_far_points_name_block_and_point_and_a_far_scene_says_so():
    from muscle_mss.core.validation import far_point_problem
    points = np.zeros((10, 3))
    assert far_point_problem(points, "b") is None
    points[4, 2] = -2e4
    assert far_point_problem(points, "b").startswith("b: point 4 lies 2e+04 mm from the origin")
    assert far_point_problem(points, "f", offsets=np.array([0, 3, 10])).startswith(
        "f: fibre 1's point 1 lies 2e+04 mm")
    assert "move the scene near the origin" in far_point_problem(points + 1e5, "b")
    points[4] = np.nan                       # its own rule: not a far point
    assert far_point_problem(points, "b") is None
