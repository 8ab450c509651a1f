"""Run a whole motion through the six filters and write the results (DESIGN §7).

Shared by ``muscle-mss demo`` / ``muscle-mss run`` and the pvpython/pvbatch entry point
``muscle_mss.plugin.batch``, so that all three write the same files for the same scene:

* ``surfaces.pvd``, ``fibres.pvd``, ``particles.pvd``: time series (one ``.vtm`` per time point
  under ``series/``) of the deformed muscle surfaces, fibre polylines and solved particles;
* ``summary.csv``: one row per (time, muscle) with the columns of :data:`SUMMARY_COLUMNS`;
* ``convergence/convergence_<k>.csv``: the solver's per-iteration table of each time point.

Each time point starts from the rest pose (paper §3.1), so time points are independent and can
be spread over MPI ranks (:func:`run_motion` takes a rank and the number of ranks).
"""
from __future__ import annotations

import csv
import os
import time as wallclock
from dataclasses import dataclass, field

import numpy as np
from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline
from vtkmodules.vtkIOXML import vtkXMLMultiBlockDataWriter

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.scene import MOTION_FILE

from . import array_names as A
from . import vtk_arrays as V
from .scene_io import scene_readers

SUMMARY_COLUMNS = ("time", "muscle", "rest_volume", "volume", "volume_error_pct",
                   "mean_fibre_strain", "max_fibre_strain", "max_penetration_mm",
                   "iterations", "seconds")
SERIES = ("surfaces", "fibres", "particles")


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
    from . import (FibreResampler, MSSCollisionSolver, MVCSurfaceDeformer, RigidPoseTransform,
                   SpringBuilder, VolumeErrorProbe)

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


def solve_time_point(p: Pipeline, index: int) -> TimePointResult:
    """Run the pipeline at time point ``index`` and collect its outputs and summary rows."""
    from muscle_mss.core.penetration import max_penetration_per_object
    from .bone_sets import bone_sphere_set
    t = p.times[index]
    start = wallclock.perf_counter()
    surfaces = _copy(update_at(p.probe, 0, t))
    table = V.table_columns(update_at(p.probe, 1, t))
    fibres = _copy(update_at(p.deformer, 1, t))
    particles = _copy(update_at(p.solver, 0, t))
    convergence = V.table_columns(update_at(p.solver, 1, t))
    bones = update_at(p.pose, 1, t)
    seconds = wallclock.perf_counter() - start

    names = [n for n, _ in V.blocks(particles, "solved model")]
    centres, radii, owner, fixed = [], [], [], []
    for k, (name, block) in enumerate(V.blocks(particles, "solved model")):
        radius = V.point_array(block, A.RADIUS)
        sphere = V.point_array(block, A.BOUNDARY).astype(bool) & (radius > 0)
        centres.append(V.points_of(block)[sphere])
        radii.append(radius[sphere])
        owner.append(np.full(sphere.sum(), k))
        fixed.append(V.point_array(block, A.FIXED).astype(bool)[sphere])
    bone_centres, bone_radii, _ = bone_sphere_set(bones, p.solver.value("BoneSphereSpacing"), "posed bones")
    penetration = max_penetration_per_object(
        np.concatenate(centres), np.concatenate(radii), np.concatenate(owner), len(names),
        bone_centres, bone_radii, np.concatenate(fixed))

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
            "max_penetration_mm": float(penetration[k]),
            "iterations": iterations, "seconds": seconds,
        })
    return TimePointResult(index, t, rows, surfaces, fibres, particles, convergence, seconds)


def _copy(data):
    out = data.NewInstance()
    out.DeepCopy(data)
    return out


def series_file(name: str, index: int) -> str:
    """Relative path of one time point's file of a series."""
    return os.path.join("series", f"{name}_{index:04d}.vtm")


def write_time_point(result: TimePointResult, out: str) -> None:
    """Write one time point's series files and convergence table under ``out``."""
    os.makedirs(os.path.join(out, "series"), exist_ok=True)
    os.makedirs(os.path.join(out, "convergence"), exist_ok=True)
    for name, data in zip(SERIES, (result.surfaces, result.fibres, result.particles)):
        writer = vtkXMLMultiBlockDataWriter()
        writer.SetFileName(os.path.join(out, series_file(name, result.index)))
        writer.SetInputData(data)
        writer.Write()
    write_csv(os.path.join(out, "convergence", f"convergence_{result.index:04d}.csv"),
              list(result.convergence), zip(*result.convergence.values()))


def write_csv(path, header, rows) -> None:
    with open(path, "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(header)
        for row in rows:
            out.writerow([_csv_value(v) for v in row])


def _csv_value(v):
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, np.integer):
        return int(v)
    return v


def write_index(out: str, times) -> None:
    """Write the ``.pvd`` index of each series for time points ``0..len(times)-1``."""
    for name in SERIES:
        entries = "\n".join(f'    <DataSet timestep="{t!r}" group="" part="0" '
                            f'file="{series_file(name, i)}"/>' for i, t in enumerate(times))
        with open(os.path.join(out, f"{name}.pvd"), "w") as f:
            f.write('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n'
                    f"  <Collection>\n{entries}\n  </Collection>\n</VTKFile>\n")


def write_summary(out: str, rows) -> str:
    """Write ``summary.csv`` (rows sorted by time point, muscles in scene order)."""
    path = os.path.join(out, "summary.csv")
    write_csv(path, SUMMARY_COLUMNS, ([r[c] for c in SUMMARY_COLUMNS] for r in rows))
    return path


def run_motion(scene_folder, out, settings=None, part=(0, 1), on_step=None):
    """Compute the time points of a scene's motion and write their files.

    ``part = (k, K)`` computes time points k, k+K, k+2K, … (MPI rank k of K); default all.

    ``on_step(result, done, total)`` is called after each time point (progress bars). Returns the
    summary rows in time-point order; the caller writes ``summary.csv`` and the ``.pvd`` index
    (:func:`write_summary`, :func:`write_index`) once all time points exist.
    """
    pipeline = build_pipeline(scene_folder, settings)
    indices = range(part[0], len(pipeline.times), part[1])
    os.makedirs(out, exist_ok=True)
    rows = []
    for done, index in enumerate(indices, start=1):
        result = solve_time_point(pipeline, index)
        write_time_point(result, out)
        rows += result.rows
        if on_step is not None:
            on_step(result, done, len(indices))
    return pipeline, rows


