"""Bad input gets our error naming its cause, through `muscle-mss run` and through the filter
chain, and never changes an input (issues 13 and 16). The cases are the table of
``tests/bad_input_cases.py`` (also ``docs/bad-input.md``); the tests after them pin what a
table cannot: no signal, no follow-on complaints, wrapped exceptions, Ctrl-C."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import bad_input_cases as B
from muscle_mss.core.errors import Interrupted, MuscleMSSError
from muscle_mss.core.solver_properties import ignored_settings

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """Each case's mutated scene folder, written once, with the digest of its files."""
    made = {}

    def get(case):
        if case.name not in made:
            folder = B.make_scene(case, tmp_path_factory.mktemp(case.name))
            made[case.name] = (folder, B.folder_digest(folder))
        return made[case.name]
    return get


@pytest.mark.parametrize("case", [c for c in B.CASES if c.cli], ids=lambda c: c.name)
def test_muscle_mss_run_names_the_cause(case, scenes, tmp_path):
    folder, digest = scenes(case)
    code, message, stderr = B.run_cli(case, folder, tmp_path / "out")
    assert code == (0 if case.warns else 2), stderr
    assert B.matches(case.expect, message), message
    assert B.folder_digest(folder) == digest


@pytest.mark.parametrize("case", [c for c in B.CASES if c.chain], ids=lambda c: c.name)
def test_the_filter_chain_names_the_cause(case, scenes):
    folder, digest = scenes(case)
    message = B.run_chain(case, folder)
    assert B.matches(case.chain_expect or case.expect, message), message
    assert B.folder_digest(folder) == digest


def test_the_docs_table_lists_every_case_with_its_message():
    text = (ROOT / "docs" / "bad-input.md").read_text()
    rows = {line.split("|")[1].strip().strip("`"): line for line in text.splitlines()
            if line.startswith("| `")}
    for case in B.CASES:
        assert case.name in rows, case.name
        cells = [c.strip().replace("\\|", "|") for c in rows[case.name].split(" | ")]
        if case.cli:
            assert B.matches(case.expect, cells[2]), (case.name, cells[2])
        if case.chain:
            assert B.matches(case.chain_expect or case.expect, cells[3]), (case.name, cells[3])


def test_an_upstream_error_is_the_only_message(scenes, tmp_path, capfd, caplog):
    """The filters downstream of a failed one empty their outputs without complaints of their
    own (they used to end the output with "Volume-Error Probe: DeformedSurfaces: has no muscle
    blocks"). VTK's messages reach stderr, or Python's logging once pyvista (the preview
    pictures) has taken over VTK's output window, or run_cli's output window: all are read."""
    case = next(c for c in B.CASES if c.name == "resolution-1")
    folder, _ = scenes(case)
    err = B.run_cli(case, folder, tmp_path / "out")[2] + capfd.readouterr().err + caplog.text
    assert "Fibre Resampler: property ParticlesPerFibre is 1" in err
    for downstream in ("Spring Builder", "MSS Collision Solver", "MVC Surface Deformer",
                       "Volume-Error Probe"):
        assert downstream not in err, err


@pytest.mark.parametrize("setting", ["Mass=1e-8", "Stiffness=1e9"])
def test_diverging_springs_end_with_our_error_not_a_signal(setting, scenes):
    """These crashed the process in the spatial hash (exit 139) before (the paper relaxation,
    whose explicit steps the masses and stiffnesses limit)."""
    folder, digest = scenes(B.CASES[0])
    name, value = setting.split("=")
    script = ("import sys; from muscle_mss.app import motion_run as m\n"
              f"p = m.build_pipeline({str(folder)!r}, {{{name!r}: {value}, "
              "'Method': 'paper relaxation'})\n"
              "m.solve_time_point(p, 10)\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 1, (done.returncode, done.stderr[-2000:])
    assert "MuscleMSSError: the model cannot be solved with TimeStep 0.05 s" in done.stderr
    assert B.folder_digest(folder) == digest


def _probe_failing_with(monkeypatch, exception):
    from muscle_mss.filters import mvc_surface_deformer

    def execute(self, inputs, outputs):
        raise exception
    monkeypatch.setattr(mvc_surface_deformer.MVCSurfaceDeformer, "execute", execute)


@pytest.mark.parametrize("exception, expect", [
    (ZeroDivisionError("float division by zero"),
     r"MVC Surface Deformer: failed unexpectedly with ZeroDivisionError: float division by "
     r"zero at test_bad_input.py:\d+; this input is not checked"),
    (MemoryError("Unable to allocate 7.4 GiB for an array with shape (8000, 124000)"),
     r"MVC Surface Deformer: ran out of memory \(Unable to allocate 7.4 GiB for an array with "
     r"shape \(8000, 124000\)\)")])
def test_any_other_exception_in_a_filter_reaches_the_caller_as_ours(
        exception, expect, scenes, tmp_path, monkeypatch):
    _probe_failing_with(monkeypatch, exception)
    case = B.CASES[0]
    folder, _ = scenes(case)
    clean = B.Case("clean", "", "")
    assert B.matches(expect, B.run_chain(clean, folder))
    code, message, stderr = B.run_cli(clean, folder, tmp_path / "out")
    assert code == 2 and B.matches(expect, message), stderr


def test_ctrl_c_in_a_filter_stops_the_run_as_an_interruption(scenes, tmp_path, monkeypatch):
    _probe_failing_with(monkeypatch, KeyboardInterrupt())
    folder, _ = scenes(B.CASES[0])
    from muscle_mss.app import motion_run
    pipeline = motion_run.build_pipeline(str(folder))
    with pytest.raises(Interrupted, match="Ctrl-C while MVC Surface Deformer ran"):
        motion_run.solve_time_point(pipeline, B.TIME_INDEX)
    code, message, stderr = B.run_cli(B.Case("clean", "", ""), folder, tmp_path / "out")
    assert code == 130 and message is None
    assert "interrupted: Ctrl-C while MVC Surface Deformer ran" in stderr


def test_an_input_from_a_reader_of_a_missing_file_names_the_file(tmp_path):
    """ParaView's readers (a vtkFileSeriesReader around the XML reader) leave an empty output
    after their error when their file is missing (a state file loaded away from its data): the
    filter names the file, not "fibres.vtm has no blocks". A Python reader that does the same
    stands in for ParaView's here (tests/test_paraview.py loads the shipped state)."""
    from vtkmodules.util.vtkAlgorithm import VTKPythonAlgorithmBase
    from vtkmodules.vtkCommonDataModel import vtkMultiBlockDataSet
    from vtkmodules.vtkFiltersCore import vtkPassThrough
    from muscle_mss.filters import FibreResampler

    class Reader(VTKPythonAlgorithmBase):
        def __init__(self):
            super().__init__(nInputPorts=0, nOutputPorts=1, outputType="vtkMultiBlockDataSet")
            self.name = None

        def SetFileName(self, name):
            self.name = name
            self.Modified()

        def GetFileName(self):
            return self.name

        def RequestData(self, request, in_info, out_info):
            vtkMultiBlockDataSet.GetData(out_info).Initialize()
            return 1

    missing = tmp_path / "scene" / "fibres.vtm"
    reader, between = Reader(), vtkPassThrough()   # ParaView puts a vtkPVPostFilter between
    reader.SetFileName(str(missing))
    between.SetInputConnection(reader.GetOutputPort())
    resampler = FibreResampler()
    resampler.SetInputConnection(0, between.GetOutputPort())
    with pytest.raises(MuscleMSSError) as raised:
        resampler.Update()
    assert str(raised.value).startswith(
        f"fibres.vtm: the reader produced nothing for input 'Fibres': the file {missing} does "
        "not exist; if the pipeline comes from a state file, load it with its data folder")
    reader.SetFileName("")
    with pytest.raises(MuscleMSSError, match=r"^the reader produced nothing for input 'Fibres': "
                       r"the reader has no file name"):
        resampler.Update()
    missing.parent.mkdir()
    missing.write_text("")          # there, but empty: the filter's own check speaks
    reader.SetFileName(str(missing))
    with pytest.raises(MuscleMSSError, match=r"^fibres.vtm has no blocks"):
        resampler.Update()
    assert [p.name for p in tmp_path.rglob("*")] == ["scene", "fibres.vtm"]


def test_settings_a_solver_ignores_are_warned_once_not_at_every_time_point():
    """TissueAlongFibres without the tissue and BoneSphereSpacing with solid bones: a warning
    when set so (in ParaView one at a time, so not refused), again only when they change."""
    from muscle_mss.filters import MSSCollisionSolver
    from muscle_mss.filters.scene_io import vtk_messages
    solver = MSSCollisionSolver()

    def warned():
        with vtk_messages() as window:
            solver._warn_ignored_settings()
        return [line for line in window.GetOutput().splitlines() if "has no effect" in line]

    assert warned() == []
    solver.SetConnectiveTissue(0.0)
    assert warned() == []       # TissueAlongFibres at its default: nothing was asked of it
    solver.SetTissueAlongFibres(0.5)
    assert len(warned()) == 1 and warned() == []
    solver.SetBoneSphereSpacing(3.0)
    assert [line.split(":")[1] for line in warned()] == [" BoneSphereSpacing 3 mm has no effect"
                                                          " with BoneContact 'solid'"]
    solver.SetBoneContact("sphere set")
    solver.SetConnectiveTissue(0.1)
    assert warned() == [] and ignored_settings(solver.settings()) == []


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_a_double_property_refuses_nan_and_infinity_whatever_the_method(value):
    """A NaN compares false with both bounds of a range: TimeStep NaN was taken under the
    quasi-static method, which does not read it."""
    from muscle_mss.filters import MSSCollisionSolver, SpringBuilder
    for owner, name in ((MSSCollisionSolver, "TimeStep"), (MSSCollisionSolver, "TimeBudget"),
                        (SpringBuilder, "Mass")):
        prop = next(p for p in owner.PROPERTIES if p.name == name)
        assert prop.range_problem(value) == (f"property {name} is {value}; it must be a "
                                             "finite number")


def test_integer_properties_refuse_fractions():
    from muscle_mss.filters import FibreResampler, MSSCollisionSolver
    with pytest.raises(MuscleMSSError, match="ParticlesPerFibre: 2.7 is not a whole number"):
        FibreResampler().SetParticlesPerFibre(2.7)
    with pytest.raises(MuscleMSSError, match="Iterations: nan is not a whole number"):
        MSSCollisionSolver().SetIterations(float("nan"))
    solver = MSSCollisionSolver()
    solver.SetIterations(3.0)
    assert solver.GetIterations() == 3 and isinstance(solver.GetIterations(), int)


def test_sizes_too_large_for_memory_are_refused_before_allocating(monkeypatch):
    from scipy.spatial import ConvexHull
    from muscle_mss.core import errors
    from muscle_mss.core.mvc import mean_value_coordinates
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    triangles = ConvexHull(cube).simplices.copy()
    for t in triangles:   # outward
        a, b, c = cube[t]
        if np.dot(np.cross(b - a, c - a), a - 0.5) < 0:
            t[[1, 2]] = t[[2, 1]]
    inside = np.full((100, 3), 0.5)
    assert mean_value_coordinates(cube, triangles, inside).shape == (100, 8)
    monkeypatch.setattr(errors, "memory_limit", lambda: 1000)
    with pytest.raises(MuscleMSSError, match=r"muscle 'm': cage: the mean value coordinates of "
                       r"100 surface vertices on 8 cage vertices would need 5.96e-06 GiB, more "
                       r"than the 9.31e-07 GiB .*use fewer particles per fibre"):
        mean_value_coordinates(cube, triangles, inside, where="muscle 'm': cage")


def test_a_resolution_whose_surface_weights_exceed_memory_is_refused_before_the_solve(
        scenes, monkeypatch):
    from muscle_mss.core import errors
    from muscle_mss.app import motion_run
    folder, _ = scenes(B.CASES[0])
    monkeypatch.setattr(errors, "memory_limit", lambda: 100_000)
    pipeline = motion_run.build_pipeline(str(folder), {"ParticlesPerFibre": 40})
    with pytest.raises(MuscleMSSError, match=r"particles block 'rectus_femoris': the surface's "
                       r"mean value coordinates \(\d+ surface vertices on \d+ boundary "
                       r"particles\) would need .* GiB.*lower the Fibre Resampler's "
                       r"ParticlesPerFibre"):
        pipeline.springs.Update()
