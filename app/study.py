"""The paper's experiments (Janák & Kohout 2014, section 4) and its partner study's fibre lengths,
measured on one scene through the six filters: what ``muscle-mss study`` and
``muscle_mss.plugin.batch --study`` compute (:mod:`~muscle_mss.app.study_report` writes it).

* **Spring layouts** (the paper's Fig. 5 and 6) at one pose, by default the most flexed
  (:func:`~muscle_mss.core.motion.farthest_pose_index`): for each of the Spring Builder's layouts
  the paper relaxation's mean particle displacement per iteration per muscle, the slope of its
  later ("stabilisation") phase, the iterations it needs to fall below the solver's
  DisplacementThreshold, the quasi-static method's iterations and seconds to converge, springs
  per particle, the model's memory, volume error, and how far the layouts' solved shapes lie
  apart.
* **Fibre length over the motion**: per muscle and time point the fibres' length relative to
  rest (mean, least, largest over the fibres), beside the muscle-tendon path length (origin to
  insertion between the centroids of the fibres' posed end particles, which sit on the bones),
  and buckling as a number: each fibre's tortuosity (arc length over chord) and its bend (that
  over its tortuosity at rest), the fibres bent above :data:`BEND_LIMIT` counted.
* **Volume** per muscle over the motion, against the paper's :data:`PAPER_VOLUME_ERROR_PCT`
  mean and :data:`ACCEPTED_VOLUME_ERROR_PCT` accepted.
* **Time split**: the solver's seconds per part (the paper's Table 1 columns) over the motion.
"""
from __future__ import annotations

import math
import platform
import time as wallclock
from dataclasses import dataclass

import numpy as np

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.solver_properties import by_name
from muscle_mss.core.settings import (DEFAULT_CONNECTIVE_TISSUE, DEFAULT_DISPLACEMENT_THRESHOLD,
                                      DEFAULT_FIBRE_SHORTENING, DEFAULT_TIME_STEP,
                                      DEFAULT_TISSUE_ALONG, METHOD_QUASI_STATIC,
                                      METHOD_RELAXATION)

from muscle_mss.filters import array_names as A
from muscle_mss.filters import vtk_arrays as V
from muscle_mss.filters.spring_builder import DEFAULT_LAYOUT, LAYOUTS
from .motion_run import build_pipeline, solve_time_point
from .reference_lengths import read_reference_lengths

BEND_LIMIT = 1.1
"""A fibre whose arc length over chord (end-to-end distance) exceeds its own at rest by more
than 10 % is counted as buckled (a bound of 1.1 on arc/chord, taken relative to the
rest shape, which some fibres exceed at rest: the demo thigh's adductor brevis up to 1.15): a
fibre that keeps its shape stays at 1, a fibre folding instead of shortening goes above (1.3-1.7
at the elbow's 130 degrees without fibre shortening), as may one that wraps a bone."""
PAPER_VOLUME_ERROR_PCT = 2.71
"""The paper's mean volume error over its motion (%)."""
ACCEPTED_VOLUME_ERROR_PCT = 6.0
"""The volume error the paper accepts (%)."""
SLOPE_WINDOW = (0.5, 1.0)
"""The later phase of the paper relaxation whose slope Fig. 6 compares: these fractions of the
iterations (the second half), fitted as log10(mean displacement) against the iteration."""
PAPER_MODEL = by_name(method=METHOD_RELAXATION, connective_tissue=0.0, fibre_shortening=False)
"""The solver's properties of the layouts' paper relaxation: the paper's method and model (no
connective tissue, fibres that keep their rest lengths), whatever the defaults are
(the tissue's along-fibre fraction, which only the tissue reads, stays at its default: set, the solver would
warn that it has no effect)."""
DEFAULT_MODEL = by_name(method=METHOD_QUASI_STATIC, connective_tissue=DEFAULT_CONNECTIVE_TISSUE,
                        tissue_along=DEFAULT_TISSUE_ALONG,
                        fibre_shortening=DEFAULT_FIBRE_SHORTENING)
"""The same properties for the layouts' quasi-static solves: the defaults' model."""
TIME_STEP_HALVINGS = 2
"""How often a layout's paper relaxation may halve the time step after a muscle diverged."""
LAYOUT_QUASI_STATIC_CAP = 1500
"""The iterations the layouts' quasi-static solves may take."""
PHASES = tuple(A.PHASE_SECONDS)
"""The solver's parts: MSS steps, muscle-muscle and muscle-bone collision detection and response,
final collision passes."""


@dataclass
class LayoutResult:
    """One layout at the study's pose. ``displacement`` (K, M) mm: the paper relaxation's mean
    particle displacement per iteration per muscle; ``slopes`` (M,) its later phase's slope
    (log10 mm per iteration, :data:`SLOPE_WINDOW`); ``to_threshold``: the first iteration at
    which every muscle moved less than the DisplacementThreshold (0: not within the
    iterations); ``paper_seconds`` the relaxation's; ``quasi_static`` (iterations, seconds,
    converged) of the quasi-static solve (:data:`DEFAULT_MODEL`);
    ``springs_per_particle``; ``memory_mb`` the Spring Builder's output (VTK's actual memory
    size); ``volume_error`` (M,) % of the relaxation's surfaces; ``positions`` (n, 3) mm its
    solved particles; ``time_step`` (s) the relaxation's."""

    layout: str
    displacement: np.ndarray
    slopes: np.ndarray
    to_threshold: int
    paper_seconds: float
    quasi_static: tuple
    springs_per_particle: float
    memory_mb: float
    volume_error: np.ndarray
    positions: np.ndarray
    time_step: float


@dataclass
class MotionSeries:
    """The whole motion at the default layout, (T, M) arrays over time points and muscles.
    ``fibre_strain`` (T, M, 3): the fibres' length over rest minus 1, mean / least / largest
    over the muscle's fibres; ``path_length`` (T, M) mm and ``path_strain`` (T, M) the
    muscle-tendon path (module docstring) and its change from rest; ``arc_chord`` (T, M) the
    largest fibre tortuosity, ``rest_arc_chord`` (M,) that at rest, ``bend`` (T, M) the largest
    fibre bend (tortuosity over its own at rest), ``buckled`` (T, M) fibres bent above
    :data:`BEND_LIMIT`;
    ``volume_error`` (T, M) %; ``phases`` (T, 4) s the solver's parts (:data:`PHASES`);
    ``rows`` the summary rows (``summary.csv``'s columns) in time order."""

    times: np.ndarray
    muscles: list
    fibre_strain: np.ndarray
    path_length: np.ndarray
    path_strain: np.ndarray
    arc_chord: np.ndarray
    rest_arc_chord: np.ndarray
    bend: np.ndarray
    buckled: np.ndarray
    volume_error: np.ndarray
    phases: np.ndarray
    rows: list


@dataclass
class Study:
    """A scene's study: its pose (``index``, ``time``), the particles per fibre, one
    :class:`LayoutResult` per layout, the :class:`MotionSeries`, the machine and seconds; the
    time asked for the pose (``--time``, None: the most flexed was studied), the most flexed
    pose's index, and the scene's ``reference_lengths.csv`` (an OpenSim model's muscle-tendon
    lengths, ``{muscle: (times s, lengths mm)}``, :mod:`.reference_lengths`; None or empty:
    the scene has none)."""

    scene: str
    index: int
    time: float
    resolution: int
    layouts: list
    motion: MotionSeries
    machine: str
    seconds: float
    asked_time: float | None = None
    flexed_index: int | None = None
    reference_lengths: dict | None = None


def fibre_statistics(block, limit: float = BEND_LIMIT):
    """One deformed fibre block (the MVC Surface Deformer's polylines): ``(mean, least,
    largest fibre strain, largest arc/chord, largest bend, fibres bent above limit)``."""
    strain = V.cell_array(block, A.FIBRE_STRAIN)
    bend = V.cell_array(block, A.FIBRE_BEND)
    return (float(strain.mean()), float(strain.min()), float(strain.max()),
            float(np.nanmax(V.cell_array(block, A.FIBRE_ARC_CHORD))), float(np.nanmax(bend)),
            int(np.count_nonzero(bend > limit)))


def path_lengths(block) -> tuple:
    """One solved muscle block: ``(posed, rest)`` mm, the distance between the centroid of its
    fibres' first (origin) end particles and that of their last (insertion) ones."""
    points = V.points_of(block)
    rest = V.point_array(block, A.REST_POSITION).reshape(-1, 3)
    index = V.point_array(block, A.FIBRE_INDEX).ravel()
    fixed = V.point_array(block, A.FIXED).ravel().astype(bool)
    origin = fixed & (index == 0)
    insertion = fixed & (index == index.max())
    return tuple(float(np.linalg.norm(x[insertion].mean(axis=0) - x[origin].mean(axis=0)))
                 for x in (points, rest))


FOLLOW_SPAN = 0.05
"""The least spread (max - min) of a muscle's mean end-to-end strain over a motion for
:func:`follow_slope` to give a slope."""


def follow_slope(rows, fibres: str = A.MEAN_FIBRE_STRAIN) -> float:
    """How a muscle's fibres follow its end-to-end length over the time points ``rows``: the
    least-squares slope of ``mean_fibre_strain`` against ``mean_end_to_end_strain`` (1: the
    fibres lengthen and shorten with the muscle; near 0: they keep their length, and a
    shortening muscle folds). NaN when the end-to-end strain spreads less than
    :data:`FOLLOW_SPAN` (one time point, a muscle the motion does not stretch). With
    ``fibres`` ``mean_kept_shape_strain``: the slope the muscle's rest shape would give,
    stretched with its volume kept (below 1 where its fibres are curved at rest)."""
    pairs = [(float(r[A.MEAN_END_TO_END_STRAIN]), float(r[fibres])) for r in rows
             if r.get(A.MEAN_END_TO_END_STRAIN, "") != "" and r.get(fibres, "") != ""]
    ends = [e for e, _ in pairs]
    if not pairs or max(ends) - min(ends) < FOLLOW_SPAN:
        return math.nan
    mean_e = sum(ends) / len(ends)
    mean_f = sum(f for _, f in pairs) / len(pairs)
    return (sum((e - mean_e) * (f - mean_f) for e, f in pairs)
            / sum((e - mean_e) ** 2 for e in ends))


def rest_arc_chord(block) -> float:
    """One solved muscle block: the largest arc length over chord of its fibres at rest (the
    polylines through its particles' rest positions in fibre order)."""
    rest = V.point_array(block, A.REST_POSITION).reshape(-1, 3)
    fibre = V.point_array(block, A.FIBRE_ID).ravel().astype(np.int64)
    order = np.lexsort((V.point_array(block, A.FIBRE_INDEX).ravel(), fibre))
    points, fibre = rest[order], fibre[order]
    starts = np.flatnonzero(np.r_[True, fibre[1:] != fibre[:-1]])
    ends = np.r_[starts[1:] - 1, len(fibre) - 1]
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    inside = fibre[1:] == fibre[:-1]
    arc = np.bincount(np.searchsorted(starts, np.arange(1, len(fibre)), side="right")[inside] - 1,
                      steps[inside], minlength=len(starts))
    chord = np.linalg.norm(points[ends] - points[starts], axis=1)
    return float(np.max(arc / chord))


def later_slope(displacement: np.ndarray, window=SLOPE_WINDOW) -> np.ndarray:
    """(M,) the least-squares slope of log10(displacement) against the iteration over the
    ``window`` fractions of the iterations, per column of ``displacement`` (K, M) mm; NaN for a
    muscle that stopped moving (a zero in the window)."""
    k = len(displacement)
    first, last = int(window[0] * k), max(int(window[1] * k), int(window[0] * k) + 2)
    rows = np.arange(first, min(last, k))
    values = displacement[rows]
    slopes = np.full(displacement.shape[1], np.nan)
    if len(rows) < 2:
        return slopes
    moving = (values > 0.0).all(axis=0)
    if moving.any():
        slopes[moving] = np.polyfit(rows + 1.0, np.log10(values[:, moving]), 1)[0]
    return slopes


def machine() -> str:
    """The machine, for the report's tables."""
    import os
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
            f"{platform.system()} {platform.release()}, Python {platform.python_version()}, "
            f"numpy {np.__version__}")


def _displacements(convergence: dict, muscles) -> np.ndarray:
    return np.column_stack([np.asarray(convergence[A.MEAN_DISPLACEMENT + m], dtype=np.float64)
                            for m in muscles])


def _particles(particles) -> np.ndarray:
    return np.concatenate([V.points_of(block) for _, block in V.blocks(particles)])


def _paper_solve(scene_folder, layout: str, resolution: int, index: int, cache=None):
    """The pipeline and the paper relaxation's solve of time point ``index`` with ``layout``
    at the solver's time step, or at half or a quarter of it where a muscle diverges (Delaunay's
    stiffer springs need 0.025 s): ``(pipeline, result, time step s)``."""
    for halvings in range(TIME_STEP_HALVINGS + 1):
        step = DEFAULT_TIME_STEP / 2 ** halvings
        pipeline = build_pipeline(scene_folder, {
            "ParticlesPerFibre": resolution, "Layout": layout, **by_name(time_step=step),
            **PAPER_MODEL}, cache)
        try:
            return pipeline, solve_time_point(pipeline, index), step
        except MuscleMSSError:
            if halvings == TIME_STEP_HALVINGS:
                raise


def layout_result(scene_folder, layout: str, resolution: int, index: int,
                  cache=None) -> LayoutResult:
    """Solve the pose ``index`` with ``layout`` by the paper relaxation (its defaults and the
    paper's model, :data:`PAPER_MODEL`, the time step halved where it diverges) and by the
    quasi-static method (the solver's defaults)."""
    pipeline, paper, time_step = _paper_solve(scene_folder, layout, resolution, index, cache)
    muscles = [row[A.MUSCLE] for row in paper.rows]
    displacement = _displacements(paper.convergence, muscles)
    below = np.flatnonzero((displacement < DEFAULT_DISPLACEMENT_THRESHOLD).all(axis=1))
    model = pipeline.springs.GetOutputDataObject(0)
    springs = sum(block.GetNumberOfLines() for _, block in V.blocks(model))
    particles = _particles(paper.particles)
    memory = sum(block.GetActualMemorySize() for _, block in V.blocks(model)) / 1024.0
    for name, value in DEFAULT_MODEL.items():
        getattr(pipeline.solver, "Set" + name)(value)
    pipeline.solver.SetIterations(LAYOUT_QUASI_STATIC_CAP)
    solved = solve_time_point(pipeline, index)
    # the solver's own seconds, as the paper relaxation's: a frame from the frame cache keeps
    # the seconds of its solve
    seconds = float(solved.convergence[A.SECONDS][-1])
    converged = bool(solved.rows[0][A.CONVERGED])
    return LayoutResult(
        layout, displacement, later_slope(displacement),
        int(below[0]) + 1 if len(below) else 0, float(paper.convergence[A.SECONDS][-1]),
        (int(solved.rows[0][A.ITERATIONS]), seconds, converged),
        2.0 * springs / max(len(particles), 1), memory,
        np.array([row[A.VOLUME_ERROR_PCT] for row in paper.rows]), particles, time_step)


def series_frame(pipeline, k: int) -> tuple:
    """What the motion series keeps of time point ``k`` of ``pipeline``: ``(time, muscles,
    fibre statistics, rest arc/chord (time point 0 only, else None), path lengths, volume
    errors, solver phase seconds, summary rows)``; a worker process's part of it
    (:mod:`~muscle_mss.app.motion_jobs`), as the serial loop's."""
    result = solve_time_point(pipeline, k)
    muscles = [row[A.MUSCLE] for row in result.rows]
    stats = dict((name, fibre_statistics(block))
                 for name, block in V.blocks(result.fibres, "deformed fibres"))
    blocks = dict(V.blocks(result.particles, "solved model"))
    rest = np.array([rest_arc_chord(blocks[m]) for m in muscles]) if k == 0 else None
    table = pipeline.solver.GetOutputDataObject(1)
    return (result.time, muscles, [stats[m] for m in muscles], rest,
            [path_lengths(blocks[m]) for m in muscles],
            [row[A.VOLUME_ERROR_PCT] for row in result.rows],
            [float(V.field(table, A.PHASE_SECONDS[p], 0.0)) for p in PHASES], result.rows)


def motion_series(scene_folder, resolution: int, progress=None, cache=None,
                  jobs: int = 1) -> MotionSeries:
    """Every time point of the scene's motion through the six filters at their defaults (the
    default layout) and ``resolution`` particles per fibre; ``progress(done, total)``;
    ``jobs``: worker processes that solve the time points (:mod:`~.motion_jobs`; the same
    series)."""
    from . import motion_jobs
    settings = {"ParticlesPerFibre": resolution, "Layout": DEFAULT_LAYOUT}
    pipeline = build_pipeline(scene_folder, settings, cache)
    total = len(pipeline.times)
    frames = {}
    if jobs > 1 and total > 1 and motion_jobs.workers_allowed(pipeline, jobs):
        folder = pipeline.frames.cache.folder if pipeline.frames is not None else None
        motion_jobs.solve_in_workers(
            (str(scene_folder), settings, folder), range(total), series_frame, jobs,
            on_result=lambda k, frame, done, total: progress and progress(done, total),
            on_ready=frames.__setitem__)
    else:
        for k in range(total):
            frames[k] = series_frame(pipeline, k)
            if progress is not None:
                progress(k + 1, total)
    times, muscles, fibres, rests, paths, volume, phases, rows = zip(
        *(frames[k] for k in range(total)))
    rows = [row for frame in rows for row in frame]
    fibres = np.asarray(fibres, dtype=np.float64)          # (T, M, 6)
    paths = np.asarray(paths, dtype=np.float64)            # (T, M, 2)
    return MotionSeries(np.asarray(times), muscles[-1], fibres[:, :, :3], paths[:, :, 0],
                        paths[:, :, 0] / paths[:, :, 1] - 1.0, fibres[:, :, 3], rests[0],
                        fibres[:, :, 4], fibres[:, :, 5].astype(np.int64),
                        np.asarray(volume, dtype=np.float64),
                        np.asarray(phases), rows)


def run_study(scene_folder, resolution: int, index: int | None = None,
              progress=None, asked_time: float | None = None, cache=None,
              jobs: int = 1) -> Study:
    """The whole study of the scene in ``scene_folder`` at ``resolution`` particles per fibre,
    its layouts at time point ``index`` (default the most flexed: the bones farthest from rest),
    the one nearest ``asked_time`` when that was asked (the report says so).
    ``progress(label, done, total)`` after each step; ``cache``: the frame cache's folder
    (:func:`~muscle_mss.filters.frame_cache.chosen_folder`; None: every frame solved);
    ``jobs``: worker processes that solve the motion's time points."""
    from muscle_mss.core.motion import farthest_pose_index
    from muscle_mss.filters.scene_io import load_scene
    start = wallclock.perf_counter()
    scene = load_scene(scene_folder)
    flexed = farthest_pose_index(scene.motion)
    index = flexed if index is None else index
    say = progress or (lambda label, done, total: None)
    series = motion_series(scene_folder, resolution,
                           lambda done, total: say("motion", done, total), cache, jobs)
    layouts = []
    for k, layout in enumerate(LAYOUTS):
        layouts.append(layout_result(scene_folder, layout, resolution, index, cache))
        say("layouts", k + 1, len(LAYOUTS))
    return Study(str(scene_folder), index, float(series.times[index]), resolution, layouts,
                 series, machine(), wallclock.perf_counter() - start, asked_time, flexed,
                 read_reference_lengths(scene_folder))
