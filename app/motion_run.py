"""Run a whole motion through the six filters (DESIGN §7): build the pipeline, solve its time
points one by one and collect each one's outputs and summary rows.

Shared by ``muscle-mss demo`` / ``muscle-mss run`` and the pvpython/pvbatch entry point
``muscle_mss.plugin.batch``, so that all three compute the same for the same scene; what is
written, and how, is :mod:`muscle_mss.app.run_output`.

Time points are solved in time order, so that with the MSS Collision Solver's warm start
on the quasi-static method starts each from the one before it (the filter keeps its last
solution); :func:`run_motion` gives MPI rank k of K a contiguous block of time points, so that a
rank would warm start within its own block. By default every time point starts from its posed
state and the order does not matter.
"""
from __future__ import annotations

import os
import time as wallclock
from dataclasses import dataclass, field

import numpy as np
from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.attachment_areas import ATTACHMENTS_FILE
from muscle_mss.core.scene import MOTION_FILE

from muscle_mss.filters import array_names as A
from muscle_mss.filters import vtk_arrays as V
from muscle_mss.core.settings import BONE_CONTACT_SOLID, BONE_CONTACT_SPHERES
from muscle_mss.filters.collision_solver import MSSCollisionSolver
from muscle_mss.filters.fibre_resampler import FibreResampler
from muscle_mss.filters.mvc_surface_deformer import MVCSurfaceDeformer
from muscle_mss.filters.rigid_pose_transform import RigidPoseTransform
from muscle_mss.filters.scene_io import attachments_reader, scene_readers
from muscle_mss.filters.spring_builder import SpringBuilder
from muscle_mss.filters.volume_error_probe import SURFACE_COLUMNS, VolumeErrorProbe
from .run_output import DEFAULT_COMPRESSOR, SERIES, write_time_point


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
    frames: object = None
    """The frame cache the solver reads and fills (a
    :class:`~muscle_mss.filters.pipeline_frames.SolverFrames`), or None."""


class CachedCollisionSolver(MSSCollisionSolver):
    """The MSS Collision Solver that takes a frame from the frame cache (``frames``, a
    :class:`~muscle_mss.filters.pipeline_frames.SolverFrames`) when it holds it and stores each frame
    it solves: everything after the solve (the outputs, the bone depths, the warnings) runs as
    for a solved frame, so its outputs are the solved frame's."""

    frames = None

    def _solve(self, model, bones, prepared):
        time = self.requested_time()
        frames = self.frames if time is not None else None
        result = frames.load(time) if frames is not None else None
        if result is None:
            result = super()._solve(model, bones, prepared)
            if frames is not None:
                frames.save(time, result)
        return result


def build_pipeline(scene_folder, settings: dict | None = None,
                   cache: str | None = None) -> Pipeline:
    """Readers for ``scene_folder`` and the six filters wired as in DESIGN §5.

    ``settings`` maps property names to values (the solver's from
    :func:`~muscle_mss.core.solver_properties.by_name`); each is applied to every filter that
    has that property. ``cache``: the frame cache's folder
    (:func:`~muscle_mss.filters.frame_cache.chosen_folder`), or None: every frame solved.
    """
    resampler, springs, pose = FibreResampler(), SpringBuilder(), RigidPoseTransform()
    solver = CachedCollisionSolver() if cache else MSSCollisionSolver()
    deformer, probe = MVCSurfaceDeformer(), VolumeErrorProbe()
    muscles, fibres, bones, motion = scene_readers(scene_folder)
    attachments = attachments_reader(os.path.join(str(scene_folder), ATTACHMENTS_FILE))
    resampler.SetInputConnection(0, fibres.GetOutputPort())
    resampler.SetInputConnection(1, bones.GetOutputPort())
    if attachments is not None:
        resampler.SetInputConnection(2, attachments.GetOutputPort())
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
    frames = None
    if cache:
        from muscle_mss.filters.frame_cache import FrameStore
        from muscle_mss.filters.pipeline_frames import SolverFrames, SurfaceFrames
        frames = solver.frames = SolverFrames(FrameStore(cache), scene_folder, filters)
        deformer.frames = SurfaceFrames(frames.cache, scene_folder, filters, scene=frames.scene)
    return Pipeline(muscles, fibres, bones, motion, resampler, springs, pose, solver, deformer,
                    probe, times, frames)


def update_at(algorithm, port: int, t: float):
    """Update one output port of ``algorithm`` at time ``t``; return its data object."""
    algorithm.UpdateInformation()
    algorithm.GetOutputInformation(port).Set(
        vtkStreamingDemandDrivenPipeline.UPDATE_TIME_STEP(), float(t))
    algorithm.Update(port)
    return algorithm.GetOutputDataObject(port)


def surfaces_of_posed_model(p: Pipeline, t: float) -> None:
    """Run an MVC Surface Deformer and a Volume Error Probe wired as ``p``'s, but fed the posed,
    unsolved model, at time ``t``: their kernels compile and the surfaces are bound (the MVC
    weights kept in their disk store) without a solve."""
    deformer, probe = MVCSurfaceDeformer(), VolumeErrorProbe()
    for prop in deformer.PROPERTIES:
        getattr(deformer, "Set" + prop.name)(getattr(p.deformer, "Get" + prop.name)())
    for k in range(1, 5):
        deformer.SetInputConnection(k, p.deformer.GetInputConnection(k, 0))
    deformer.SetInputConnection(0, p.pose.GetOutputPort(0))
    probe.SetInputConnection(0, deformer.GetOutputPort(0))
    probe.SetInputConnection(1, p.probe.GetInputConnection(1, 0))
    for algorithm, port in ((probe, 0), (probe, 1), (deformer, 1)):
        update_at(algorithm, port, t)


def prepare_time_point(p: Pipeline, index: int) -> None:
    """Everything of time point ``index`` but the solve: the stages before the MSS Collision
    Solver (which ``p`` keeps for the solve) and :func:`surfaces_of_posed_model`. Run while
    the solver's kernels compile elsewhere (``warm_up.compiling_beside``)."""
    update_at(p.pose, 0, p.times[index])
    surfaces_of_posed_model(p, p.times[index])


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
    t = p.times[index]
    start = wallclock.perf_counter()
    particles = _held(update_at(p.solver, 0, t))
    convergence_table = update_at(p.solver, 1, t)
    convergence = V.table_columns(convergence_table)
    converged = int(V.field(convergence_table, A.CONVERGED, 0))
    solved = wallclock.perf_counter()
    surfaces = _held(update_at(p.probe, 0, t))
    table = V.table_columns(update_at(p.probe, 1, t))
    fibres = _held(update_at(p.deformer, 1, t))
    seconds = wallclock.perf_counter() - start

    blocks = dict(V.blocks(particles, "solved model"))
    penetration = sphere_overlaps(p.solver, particles)
    fibre_stats = {}
    for name, block in V.blocks(fibres, "deformed fibres"):
        strain = V.cell_array(block, A.FIBRE_STRAIN)
        fibre_stats[name] = {
            A.MEAN_FIBRE_STRAIN: float(strain.mean()), A.MAX_FIBRE_STRAIN: float(strain.max()),
            A.MEAN_END_TO_END_STRAIN: float(np.nanmean(V.cell_array(block, A.FIBRE_END_STRAIN))),
            A.MEAN_KEPT_SHAPE_STRAIN: float(V.cell_array(block, A.FIBRE_KEPT_SHAPE_STRAIN).mean()),
            A.MAX_ARC_CHORD: float(np.nanmax(V.cell_array(block, A.FIBRE_ARC_CHORD))),
            A.MAX_FIBRE_BEND: float(np.nanmax(V.cell_array(block, A.FIBRE_BEND)))}
    solve = {A.ITERATIONS: len(convergence[A.ITERATION]), A.CONVERGED: converged,
             A.SECONDS: seconds}
    by_muscle = {m: i for i, m in enumerate(table[A.MUSCLE])}
    rows = []
    for k, name in enumerate(blocks):
        r = by_muscle[name]
        rows.append({
            A.TIME: t, A.MUSCLE: name,
            A.REST_VOLUME: float(table[A.REST_VOLUME][r]), A.VOLUME: float(table[A.VOLUME][r]),
            A.VOLUME_ERROR_PCT: float(table[A.VOLUME_ERROR_PCT][r]),
            **fibre_stats[name],
            A.SPHERE_OVERLAP_MM: float(penetration[k]),
            A.TISSUE_SHARE_PCT: float(V.field(blocks[name], A.TISSUE_SHARE_PCT)),
            **{c: _count_or_depth(c, table[c][r]) for c in SURFACE_COLUMNS},
            **{key: (int if key in (A.FREE_IN_BONE, A.FREE_NEW_IN_BONE) else float)(
                V.field(blocks[name], key)) for key in A.FREE_IN_BONE_FIELDS},
            **solve,
        })
    timings = {"solve": solved - start, "surface": start + seconds - solved,
               "statistics": wallclock.perf_counter() - start - seconds}
    return TimePointResult(index, t, rows, surfaces, fibres, particles, convergence, seconds,
                           timings)


def sphere_overlaps(solver, particles) -> np.ndarray:
    """The deepest overlap (mm) of each muscle's collision spheres in the solved ``particles``
    with spheres of other muscles and with the bones ``solver`` (the MSS Collision Solver) last
    solved against (its ``solved_bones``: solids or sphere sets); one value per muscle block."""
    from muscle_mss.core.bones.distance import signed_distances
    from muscle_mss.core.contacts.penetration import max_penetration_pairs
    centres, radii, owner, fixed = [], [], [], []
    muscles = V.blocks(particles, "solved model")
    for k, (_, block) in enumerate(muscles):
        radius = V.point_array(block, A.RADIUS)
        sphere = V.point_array(block, A.BOUNDARY).astype(bool) & (radius > 0)
        centres.append(V.points_of(block)[sphere])
        radii.append(radius[sphere])
        owner.append(np.full(sphere.sum(), k))
        fixed.append(V.point_array(block, A.FIXED).astype(bool)[sphere])
    centres, radii, owner, fixed = map(np.concatenate, (centres, radii, owner, fixed))
    bones = solver.solved_bones
    if bones.contact == BONE_CONTACT_SPHERES:
        bone_centres, bone_radii, _ = bones.spheres
        return max_penetration_pairs(centres, radii, owner, len(muscles), bone_centres,
                                     bone_radii, fixed)
    # the bones as the solver saw them: solids, which a sphere may touch
    penetration = max_penetration_pairs(centres, radii, owner, len(muscles), fixed=fixed)
    if bones.contact == BONE_CONTACT_SOLID and (~fixed).any():
        solids = bones.solids
        depth = radii[~fixed] - signed_distances(solids.fields, centres[~fixed],
                                                 solids.transforms)[0].min(axis=1)
        np.maximum.at(penetration, owner[~fixed], np.maximum(depth, 0.0))
    return penetration


def _count_or_depth(column, value):
    """A table value for summary.csv: counts as int, NaN (no bones connected) as empty."""
    if not np.isfinite(value):
        return ""
    return int(value) if column in (A.NEW_IN_BONE_VERTICES, A.NEW_IN_BONE_VERTICES_AFTER,
                                    A.IN_OTHER_MUSCLE_VERTICES, A.CAGE_DRIFT_VERTICES) \
        else float(value)


def _held(data):
    """A new multiblock of the blocks of a filter's output ``data``, to keep past the next
    update: a filter refills its output multiblock at every update but never changes the
    blocks it made before (each update makes new ones), so holding them is enough (a DeepCopy
    of the particles was 6 ms a time point at N = 80)."""
    return V.make_multiblock(V.blocks(data, "output"))


def time_block(count: int, k: int, parts: int) -> range:
    """The k-th of ``parts`` contiguous blocks of ``count`` time points (sizes differ by at
    most one, the first blocks the larger): a rank warm starts within its own block."""
    size, extra = divmod(count, parts)
    first = k * size + min(k, extra)
    return range(first, first + size + (1 if k < extra else 0))


def run_motion(scene_folder, out, settings=None, part=(0, 1), on_step=None,
               series_names=SERIES, compressor=DEFAULT_COMPRESSOR, pipeline=None, cache=None,
               jobs=1):
    """Compute the time points of a scene's motion and write their files.

    ``part = (k, K)`` computes the k-th of K contiguous blocks of time points (MPI rank k of
    K), in time order; default all.

    ``series_names`` and ``compressor``: what
    :func:`~muscle_mss.app.run_output.write_time_point` writes, and how.

    ``pipeline``: one :func:`build_pipeline` built for ``scene_folder`` and ``settings``
    already (its first time point prepared: :func:`prepare_time_point`), else a new one
    reading and filling the frame cache in the folder ``cache`` (None: none).

    ``jobs`` above 1: the time points are solved by that many worker processes, the files
    placed here in time order, the same files (:mod:`~muscle_mss.app.motion_jobs`; not for a
    solver whose frames depend on the one before or on the clock, nor in ParaView's Python: a
    note says so).

    ``on_step(result, done, total)`` is called after each time point (progress bars; with
    ``jobs``, as each arrives). Returns the pipeline and the summary rows in time-point order;
    the caller writes ``summary.csv`` and the ``.pvd`` index
    (:mod:`~muscle_mss.app.run_output`) once all time points exist.
    """
    pipeline = pipeline or build_pipeline(scene_folder, settings, cache)
    indices = time_block(len(pipeline.times), *part)
    os.makedirs(out, exist_ok=True)
    if jobs > 1 and len(indices) > 1:
        from . import motion_jobs
        if motion_jobs.workers_allowed(pipeline, jobs):
            return pipeline, motion_jobs.run_in_workers(
                pipeline, scene_folder, out, settings, indices, jobs, on_step, series_names,
                compressor)
    rows = []
    for done, index in enumerate(indices, start=1):
        result = solve_time_point(pipeline, index)
        write_time_point(result, out, series_names, compressor)
        rows += result.rows
        if on_step is not None:
            on_step(result, done, len(indices))
    return pipeline, rows


