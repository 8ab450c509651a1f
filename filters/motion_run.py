"""Run a whole motion through the six filters and write the results (DESIGN §7).

Shared by ``muscle-mss demo`` / ``muscle-mss run`` and the pvpython/pvbatch entry point
``muscle_mss.plugin.batch``, so that all three write the same files for the same scene:

* ``surfaces.pvd``, ``fibres.pvd``, ``particles.pvd``: time series (one ``.vtm`` per time point
  under ``series/``) of the deformed muscle surfaces, fibre polylines and solved particles;
* ``summary.csv``: one row per (time, muscle) with the columns of :data:`SUMMARY_COLUMNS`;
* ``convergence/convergence_<k>.csv``: the solver's per-iteration table of each time point.

Time points are solved in time order, so that the quasi-static method (``Method``)
warm starts each from the one before it (the MSS Collision Solver keeps its last solution);
:func:`run_motion` gives MPI rank k of K a contiguous block of time points, each rank warm
starting within its own block.
"""
from __future__ import annotations

import csv
import os
import re
import shutil
import tempfile
import time as wallclock
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from vtkmodules.vtkCommonCore import vtkVersion
from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline
from vtkmodules.vtkIOXML import vtkXMLMultiBlockDataWriter

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.scene import MOTION_FILE

from . import array_names as A
from . import vtk_arrays as V
from .scene_io import scene_readers
from .volume_error_probe import IN_BONE_COLUMNS

SUMMARY_COLUMNS = ("time", "muscle", "rest_volume", "volume", "volume_error_pct",
                   "mean_fibre_strain", "max_fibre_strain", "sphere_overlap_mm",
                   A.NEW_IN_BONE_VERTICES, A.NEW_IN_BONE_DEPTH_MM, A.NEW_IN_BONE_VERTICES_AFTER,
                   A.NEW_IN_BONE_DEPTH_AFTER_MM, *A.FREE_IN_BONE_FIELDS, "iterations",
                   "converged", "seconds")
"""``sphere_overlap_mm``: the deepest overlap of the muscle's collision spheres with spheres of
other muscles (:mod:`muscle_mss.core.penetration`) and with the bones as the solver saw them
(``BoneContact``: solids, by their distance fields, or sphere sets); ``new_in_bone_*``: deformed
surface vertices inside a bone they were outside at rest, before and after the MVC Surface
Deformer pushes them out; ``free_particle*``: solved particles that are not tendon attachments
with their centre inside a bone, and the deepest (by the bones' signed distance fields), all of
them and those not inside a bone at rest (``*new_in_bone*``), as the MSS Collision Solver
reports them."""
SERIES = ("surfaces", "fibres", "particles")
RUN_FILES = ("summary.csv", "surfaces.pvd", "fibres.pvd", "particles.pvd", "convergence.png",
             "poses.png", "series", "convergence")
"""What a run writes in its output folder (files and folders): another run's results."""
PARALLEL_WRITES = (vtkVersion.GetVTKMajorVersion(), vtkVersion.GetVTKMinorVersion()) > (9, 2)
"""Whether :func:`write_time_point` writes the series each by its own thread: the pip VTK (9.7)
lets go of Python's lock in a writer's ``Write()`` (the demo thigh's three series at N = 20:
30 → 25 ms alone, 40 → 33 ms in a run on two cores), ParaView 5.11's VTK 9.2 does not (60 →
63 ms with threads)."""
COMPRESSORS = ("lz4", "zlib", "none")
"""Compressors of the series' appended binary data: LZ4 (default: fast, readable by ParaView
5.x), ZLib (smaller, slower: VTK's own default) or none (fastest, largest)."""


@dataclass
class Pipeline:
    """The six filters wired to a scene's readers, as plain VTK algorithms."""

    muscles: object
    fibres: object
    bones: object
    motion: object
    resampler: object
    springs: object
    pose: object
    solver: object
    deformer: object
    probe: object
    times: list = field(default_factory=list)


def build_pipeline(scene_folder, settings: dict | None = None) -> Pipeline:
    """Readers for ``scene_folder`` and the six filters wired as in DESIGN §5.

    ``settings`` maps property names to values, e.g. ``{"ParticlesPerFibre": 40,
    "Layout": "k-NN"}``; each is applied to every filter that has that property.
    """
    from .collision_solver import MSSCollisionSolver
    from .fibre_resampler import FibreResampler
    from .mvc_surface_deformer import MVCSurfaceDeformer
    from .rigid_pose_transform import RigidPoseTransform
    from .spring_builder import SpringBuilder
    from .volume_error_probe import VolumeErrorProbe

    resampler, springs, pose = FibreResampler(), SpringBuilder(), RigidPoseTransform()
    solver, deformer, probe = MSSCollisionSolver(), MVCSurfaceDeformer(), VolumeErrorProbe()
    muscles, fibres, bones, motion = scene_readers(scene_folder)
    resampler.SetInputConnection(0, fibres.GetOutputPort())
    springs.SetInputConnection(0, resampler.GetOutputPort())
    springs.SetInputConnection(1, muscles.GetOutputPort())
    springs.SetInputConnection(2, bones.GetOutputPort())
    pose.SetInputConnection(0, springs.GetOutputPort())
    pose.SetInputConnection(1, bones.GetOutputPort())
    pose.SetInputConnection(2, motion.GetOutputPort())
    pose.SetInputConnection(3, muscles.GetOutputPort())
    solver.SetInputConnection(0, pose.GetOutputPort(0))
    solver.SetInputConnection(1, pose.GetOutputPort(1))
    deformer.SetInputConnection(0, solver.GetOutputPort(0))
    deformer.SetInputConnection(1, muscles.GetOutputPort())
    deformer.SetInputConnection(2, springs.GetOutputPort())
    deformer.SetInputConnection(3, bones.GetOutputPort())
    deformer.SetInputConnection(4, pose.GetOutputPort(1))
    probe.SetInputConnection(0, deformer.GetOutputPort(0))
    probe.SetInputConnection(1, muscles.GetOutputPort())
    filters = (resampler, springs, pose, solver, deformer, probe)
    for name, value in (settings or {}).items():
        owners = [f for f in filters if any(p.name == name for p in f.PROPERTIES)]
        if not owners:
            raise KeyError(f"no filter has a property {name!r}")
        for f in owners:
            getattr(f, "Set" + name)(value)
    pose.UpdateInformation()
    info = pose.GetOutputInformation(0)
    sddp = vtkStreamingDemandDrivenPipeline
    times = list(info.Get(sddp.TIME_STEPS())) if info.Has(sddp.TIME_STEPS()) else []
    if not times:
        # no usable motion table: the pose filter's own error says why
        pose.Update()
        raise MuscleMSSError(f"{os.path.join(str(scene_folder), MOTION_FILE)} gave no time steps")
    return Pipeline(muscles, fibres, bones, motion, resampler, springs, pose, solver, deformer,
                    probe, times)


def update_at(algorithm, port: int, t: float):
    """Update one output port of ``algorithm`` at time ``t``; return its data object."""
    algorithm.UpdateInformation()
    algorithm.GetOutputInformation(port).Set(
        vtkStreamingDemandDrivenPipeline.UPDATE_TIME_STEP(), float(t))
    algorithm.Update(port)
    return algorithm.GetOutputDataObject(port)


@dataclass
class TimePointResult:
    """Everything computed for one time point (VTK objects are this step's own copies)."""

    index: int
    time: float
    rows: list
    surfaces: object
    fibres: object
    particles: object
    convergence: dict
    seconds: float
    timings: dict = field(default_factory=dict)
    """Seconds of this time point's parts: ``solve`` (pose and collision solver), ``surface``
    (MVC deformation and volume probe), ``statistics`` (summary rows) and, once written,
    ``write``."""


def solve_time_point(p: Pipeline, index: int) -> TimePointResult:
    """Run the pipeline at time point ``index`` and collect its outputs and summary rows."""
    from muscle_mss.core.bone_distance import signed_distances
    from muscle_mss.core.penetration import max_penetration_pairs
    from .bone_sets import bone_solids, bone_sphere_set
    t = p.times[index]
    start = wallclock.perf_counter()
    particles = _held(update_at(p.solver, 0, t))
    convergence_table = update_at(p.solver, 1, t)
    convergence = V.table_columns(convergence_table)
    converged = int(V.field(convergence_table, A.CONVERGED, 0))
    bones = update_at(p.pose, 1, t)
    solved = wallclock.perf_counter()
    surfaces = _held(update_at(p.probe, 0, t))
    table = V.table_columns(update_at(p.probe, 1, t))
    fibres = _held(update_at(p.deformer, 1, t))
    seconds = wallclock.perf_counter() - start

    blocks = dict(V.blocks(particles, "solved model"))
    names = list(blocks)
    centres, radii, owner, fixed = [], [], [], []
    for k, (name, block) in enumerate(V.blocks(particles, "solved model")):
        radius = V.point_array(block, A.RADIUS)
        sphere = V.point_array(block, A.BOUNDARY).astype(bool) & (radius > 0)
        centres.append(V.points_of(block)[sphere])
        radii.append(radius[sphere])
        owner.append(np.full(sphere.sum(), k))
        fixed.append(V.point_array(block, A.FIXED).astype(bool)[sphere])
    centres, radii, owner, fixed = map(np.concatenate, (centres, radii, owner, fixed))
    if p.solver.choice("BoneContact") == "solid":
        # the bones as the solver saw them: solids, which a sphere may touch
        penetration = max_penetration_pairs(centres, radii, owner, len(names), fixed=fixed)
        if p.solver.value("MuscleBone") and (~fixed).any():
            fields, transforms = bone_solids(bones, "posed bones")
            depth = radii[~fixed] - signed_distances(fields, centres[~fixed], transforms)[0].min(
                axis=1)
            np.maximum.at(penetration, owner[~fixed], np.maximum(depth, 0.0))
    else:
        bone_centres, bone_radii, _ = bone_sphere_set(bones, p.solver.value("BoneSphereSpacing"),
                                                      "posed bones")
        penetration = max_penetration_pairs(centres, radii, owner, len(names), bone_centres,
                                            bone_radii, fixed)

    fibre_stats = {}
    for name, block in V.blocks(fibres, "deformed fibres"):
        strain = V.cell_array(block, A.FIBRE_STRAIN)
        fibre_stats[name] = (float(strain.mean()), float(strain.max()))
    iterations = len(convergence["iteration"])
    rows = []
    by_muscle = {m: i for i, m in enumerate(table[A.MUSCLE])}
    for k, name in enumerate(names):
        r = by_muscle[name]
        rows.append({
            "time": t, "muscle": name,
            "rest_volume": float(table[A.REST_VOLUME][r]), "volume": float(table[A.VOLUME][r]),
            "volume_error_pct": float(table[A.VOLUME_ERROR_PCT][r]),
            "mean_fibre_strain": fibre_stats[name][0], "max_fibre_strain": fibre_stats[name][1],
            "sphere_overlap_mm": float(penetration[k]),
            **{c: _count_or_depth(c, table[c][r]) for c in IN_BONE_COLUMNS},
            **{key: (int if key in (A.FREE_IN_BONE, A.FREE_NEW_IN_BONE) else float)(
                V.field(blocks[name], key)) for key in A.FREE_IN_BONE_FIELDS},
            "iterations": iterations, "converged": converged, "seconds": seconds,
        })
    timings = {"solve": solved - start, "surface": start + seconds - solved,
               "statistics": wallclock.perf_counter() - start - seconds}
    return TimePointResult(index, t, rows, surfaces, fibres, particles, convergence, seconds,
                           timings)


def _count_or_depth(column, value):
    """A table value for summary.csv: counts as int, NaN (no bones connected) as empty."""
    if not np.isfinite(value):
        return ""
    return int(value) if column in (A.NEW_IN_BONE_VERTICES, A.NEW_IN_BONE_VERTICES_AFTER) \
        else float(value)


def _held(data):
    """A new multiblock of the blocks of a filter's output ``data``, to keep past the next
    update: a filter refills its output multiblock at every update but never changes the
    blocks it made before (each update makes new ones), so holding them is enough (a DeepCopy
    of the particles was 6 ms a time point at N = 80)."""
    return V.make_multiblock(V.blocks(data, "output"))


def series_file(name: str, index: int) -> str:
    """Relative path of one time point's file of a series."""
    return os.path.join("series", f"{name}_{index:04d}.vtm")


def previous_run(out: str) -> list:
    """The files and folders of a run (:data:`RUN_FILES`) that ``out`` holds already."""
    return [name for name in RUN_FILES if os.path.exists(os.path.join(out, name))]


def check_output_folder(out: str, overwrite: bool = False) -> list:
    """Check ``out`` before solving: it is created if missing and must be writable; when it
    holds another run's results they are refused, or removed with ``overwrite`` (so that no
    file of the earlier run, e.g. a time point it had in addition, stays beside the new ones).
    Returns the names removed. Raises :class:`MuscleMSSError` naming the folder and the cause."""
    if os.path.exists(out) and not os.path.isdir(out):
        raise MuscleMSSError(f"output folder {out} is a file; give a folder")
    found = previous_run(out)
    if found and not overwrite:
        raise MuscleMSSError(f"output folder {out} holds the results of another run "
                             f"({', '.join(found)}); choose another folder or pass --overwrite "
                             "to replace them")
    try:
        os.makedirs(out, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out, prefix=".write-test-"):
            pass
        for name in found:
            path = os.path.join(out, name)
            if os.path.isdir(path):
                shutil.rmtree(path)
            else:
                os.remove(path)
    except OSError as err:
        raise MuscleMSSError(f"output folder {out} cannot be written: "
                             f"{err.strerror or err}") from None
    return found


def write_time_point(result: TimePointResult, out: str, series_names=SERIES,
                     compressor: str = "lz4") -> None:
    """Write one time point's series files (those of ``series_names``, a subset of
    :data:`SERIES`) and convergence table under ``out``; the series as appended raw binary
    compressed with ``compressor`` (one of :data:`COMPRESSORS`). Adds the seconds taken to
    ``result.timings["write"]``.

    Each ``.vtm`` is written with its ``.vtp`` files into a private folder first, checked (the
    writer succeeded and every file the ``.vtm`` names exists), then renamed into ``series/``:
    a failed write raises :class:`MuscleMSSError` and never leaves a ``.vtm`` pointing at
    missing files. Where VTK lets it (:data:`PARALLEL_WRITES`) the series are written at the
    same time, each by its own thread (they share no array); this returns when all are
    written."""
    start = wallclock.perf_counter()
    series = os.path.join(out, "series")
    try:
        os.makedirs(series, exist_ok=True)
        os.makedirs(os.path.join(out, "convergence"), exist_ok=True)
        staging = tempfile.mkdtemp(dir=series, prefix=".writing-")
    except OSError as err:
        raise MuscleMSSError(f"cannot write {series}: {err.strerror or err}") from None

    def write(name, data):
        staged = os.path.join(staging, os.path.basename(series_file(name, result.index)))
        writer = vtkXMLMultiBlockDataWriter()
        writer.SetFileName(staged)
        writer.SetInputData(data)
        configure_writer(writer, compressor)
        return staged, writer.Write() == 1 and writer.GetErrorCode() == 0

    jobs = [(name, data) for name, data in
            zip(SERIES, (result.surfaces, result.fibres, result.particles))
            if name in series_names]
    try:
        with ThreadPoolExecutor(max(len(jobs), 1) if PARALLEL_WRITES else 1) as writers:
            written = list(writers.map(lambda job: write(*job), jobs))
        for (name, _), (staged, succeeded) in zip(jobs, written):
            final = os.path.join(out, series_file(name, result.index))
            _check_written(staged, final, succeeded)
            _move_into_place(staged, final)
    except OSError as err:
        raise MuscleMSSError(f"cannot write {series}: {err.strerror or err}") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    write_columns(os.path.join(out, "convergence", f"convergence_{result.index:04d}.csv"),
                  result.convergence)
    result.timings["write"] = wallclock.perf_counter() - start


def configure_writer(writer, compressor: str) -> None:
    """Appended raw binary (no base64) with ``compressor`` (one of :data:`COMPRESSORS`)."""
    writer.SetDataModeToAppended()
    writer.EncodeAppendedDataOff()
    {"lz4": writer.SetCompressorTypeToLZ4, "zlib": writer.SetCompressorTypeToZLib,
     "none": writer.SetCompressorTypeToNone}[compressor]()


def parse_write_option(text: str) -> tuple:
    """The series named by a ``--write`` option (``surfaces,fibres,particles`` or a part of it,
    in any order), in :data:`SERIES` order; :class:`MuscleMSSError` naming an unknown one."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in SERIES]
    if unknown or not names:
        raise MuscleMSSError(f"--write {text!r}: {', '.join(unknown) or 'nothing'} is not a "
                             f"series; give one or more of {','.join(SERIES)}")
    return tuple(n for n in SERIES if n in names)


def _check_written(vtm: str, final: str, writer_ok: bool) -> None:
    """Raise unless the writer reported success and wrote ``vtm`` and every file it names."""
    missing = [] if os.path.isfile(vtm) else [os.path.basename(final)]
    if not missing:
        with open(vtm) as f:
            named = re.findall(r'file="([^"]+)"', f.read())
        missing = [n for n in named if not os.path.isfile(os.path.join(os.path.dirname(vtm), n))]
    if missing or not writer_ok:
        raise MuscleMSSError(f"writing {final} failed"
                             + (f": {', '.join(missing)} not written" if missing else "")
                             + "; check the free space and permissions of the output folder")


def _move_into_place(staged_vtm: str, final_vtm: str) -> None:
    """Rename a staged ``.vtm`` and its folder of ``.vtp`` files over the final ones; the
    ``.vtm`` last, so that it never names files that are not there."""
    staged_dir, final_dir = os.path.splitext(staged_vtm)[0], os.path.splitext(final_vtm)[0]
    if os.path.exists(final_vtm):
        os.remove(final_vtm)
    if os.path.isdir(final_dir):
        shutil.rmtree(final_dir)
    if os.path.isdir(staged_dir):
        os.replace(staged_dir, final_dir)
    os.replace(staged_vtm, final_vtm)


def _write_atomically(path: str, text_lines) -> None:
    """Write ``path`` through a temporary file renamed over it; raise :class:`MuscleMSSError`
    naming the file when it cannot be written."""
    temporary = f"{path}.{os.getpid()}.tmp"
    try:
        with open(temporary, "w", newline="") as f:
            text_lines(f)
        os.replace(temporary, path)
    except OSError as err:
        if os.path.exists(temporary):
            os.remove(temporary)
        raise MuscleMSSError(f"cannot write {path}: {err.strerror or err}") from None


def write_csv(path, header, rows) -> None:
    """Write a CSV file (atomically: a reader sees the old file or the whole new one)."""
    def lines(f):
        out = csv.writer(f)
        out.writerow(header)
        for row in rows:
            out.writerow([_csv_value(v) for v in row])
    _write_atomically(path, lines)


def write_columns(path, columns: dict) -> None:
    """Write a table of ``columns`` (name → NumPy array or list) as :func:`write_csv` would
    write its rows (the same bytes), column by column: a time point's convergence table (500 x
    17 values) took 11 ms through ``csv.writer``, most of it per-value Python calls."""
    texts = [[str(name) for name in columns]]
    for values in columns.values():
        if isinstance(values, np.ndarray) and values.dtype.kind == "f":
            texts.append(list(map(repr, values.tolist())))     # float repr, as _csv_value
        elif isinstance(values, np.ndarray) and values.dtype.kind in "iub":
            texts.append(list(map(str, values.tolist())))           # ints; bools as True
        else:
            texts.append(None)
    if any(t is None for t in texts[1:]):        # text or mixed columns: the csv module
        write_csv(path, list(columns), zip(*columns.values()))
        return
    header, *cells = texts
    rows = [",".join(header)] + [",".join(row) for row in zip(*cells)]
    _write_atomically(path, lambda f: f.write("\r\n".join(rows) + "\r\n"))


def _csv_value(v):
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, np.integer):
        return int(v)
    return v


def write_index(out: str, times, indices=None, series_names=SERIES) -> None:
    """Write the ``.pvd`` index of each series of ``series_names`` for time points ``indices``
    (default ``0..len(times)-1``) at ``times``."""
    indices = range(len(times)) if indices is None else indices
    for name in series_names:
        entries = "\n".join(f'    <DataSet timestep="{t!r}" group="" part="0" '
                            f'file="{series_file(name, i)}"/>' for i, t in zip(indices, times))
        _write_atomically(os.path.join(out, f"{name}.pvd"), lambda f: f.write(
            '<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n'
            f"  <Collection>\n{entries}\n  </Collection>\n</VTKFile>\n"))


def write_summary(out: str, rows) -> str:
    """Write ``summary.csv`` (rows sorted by time point, muscles in scene order)."""
    path = os.path.join(out, "summary.csv")
    write_csv(path, SUMMARY_COLUMNS, ([r[c] for c in SUMMARY_COLUMNS] for r in rows))
    return path


def time_block(count: int, k: int, parts: int) -> range:
    """The k-th of ``parts`` contiguous blocks of ``count`` time points (sizes differ by at
    most one, the first blocks the larger): a rank warm starts within its own block."""
    size, extra = divmod(count, parts)
    first = k * size + min(k, extra)
    return range(first, first + size + (1 if k < extra else 0))


def run_motion(scene_folder, out, settings=None, part=(0, 1), on_step=None,
               series_names=SERIES, compressor="lz4"):
    """Compute the time points of a scene's motion and write their files.

    ``part = (k, K)`` computes the k-th of K contiguous blocks of time points (MPI rank k of
    K), in time order; default all.

    ``series_names`` and ``compressor``: what :func:`write_time_point` writes, and how.

    ``on_step(result, done, total)`` is called after each time point (progress bars). Returns the
    summary rows in time-point order; the caller writes ``summary.csv`` and the ``.pvd`` index
    (:func:`write_summary`, :func:`write_index`) once all time points exist.
    """
    pipeline = build_pipeline(scene_folder, settings)
    indices = time_block(len(pipeline.times), *part)
    os.makedirs(out, exist_ok=True)
    rows = []
    for done, index in enumerate(indices, start=1):
        result = solve_time_point(pipeline, index)
        write_time_point(result, out, series_names, compressor)
        rows += result.rows
        if on_step is not None:
            on_step(result, done, len(indices))
    return pipeline, rows


