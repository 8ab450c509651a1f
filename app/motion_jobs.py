"""Whole motions on every core: the time points of a motion solved in worker processes, the
results taken in time order by the run's process (DESIGN §6 "Frame cache": every frame is a
pure function of the scene, every property and the time, so which process solves it, and in
what order, does not change it).

* **Processes**, started by :mod:`multiprocessing`'s "spawn" context: a fresh Python each, not a
  fork of this one (Numba's threading layer and VTK do not survive a fork). Each builds its own
  pipeline (:func:`~muscle_mss.app.motion_run.build_pipeline`, the same scene, settings and
  frame cache) and loads the kernels from Numba's cache: the run's process compiled them
  before it started the workers (:mod:`~muscle_mss.app.warm_up`).
* **Threads split**: each of J workers runs Numba's parallel loops, and sizes its BLAS thread
  pools, to ``cores // J`` threads (at least one).
* **Handed out as workers free up**, one time point at a time in time order (contiguous blocks
  would put the costly flexed frames on one worker).
* **In time order**: a worker returns what its ``work`` function made of the time point
  (:func:`stage_frame`: the series written into a private folder, the summary rows, the
  convergence table); the run's process takes them in time order (it places the files), so
  the outputs are the serial run's. The first failing time point in time order is the error
  raised, after the time points before it are taken, as the serial run would stop.
* **Nothing left behind**: Ctrl-C reaches the run's process only (the workers ignore it), which
  stops the workers; a worker whose run's process died ends itself.
"""
from __future__ import annotations

import contextlib
import multiprocessing
import os
import queue
import signal
import sys
import threading
import time as wallclock
import traceback

from muscle_mss.core.errors import MuscleMSSError

JOBS_ENVIRONMENT = "MUSCLE_MSS_JOBS"
"""The environment variable that sets ``--jobs``' default (the tests set 1)."""
POLL_SECONDS = 0.5
"""How often the run's process checks its workers are alive while it waits, and a worker
that its run's process is."""


def usable_cores() -> int:
    """The cores this process may run on: the size of its affinity mask where the system has
    one, else the machine's cores."""
    with contextlib.suppress(AttributeError, OSError):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def default_jobs() -> int:
    """``--jobs``' default: ``$MUSCLE_MSS_JOBS`` when set, else :func:`usable_cores`."""
    text = os.environ.get(JOBS_ENVIRONMENT, "").strip()
    if text:
        return checked_jobs(text, f"${JOBS_ENVIRONMENT}")
    return usable_cores()


def checked_jobs(text, what: str = "--jobs") -> int:
    """``text`` as a number of worker processes; :class:`MuscleMSSError` when it is not a
    whole number of at least 1."""
    try:
        jobs = int(text)
    except (TypeError, ValueError):
        jobs = 0
    if jobs < 1:
        raise MuscleMSSError(f"{what} {text}: give the number of processes that solve time "
                             "points at once, a whole number of at least 1")
    return jobs


def threads_per_worker(jobs: int) -> int:
    """Numba threads each of ``jobs`` workers runs: the cores shared out, at least one."""
    return max(1, usable_cores() // jobs)


def serial_reason(solver) -> str | None:
    """Why the time points must be solved one after another in one process, or None: the
    solver's :meth:`~muscle_mss.filters.collision_solver.MSSCollisionSolver.history_dependence`
    (a frame that starts from the one before it, or stops on the clock and so depends on the
    threads it gets)."""
    return solver.history_dependence()


def can_start_workers() -> bool:
    """Whether this process can start workers: its executable is a Python (not ParaView,
    pvpython or pvbatch)."""
    return os.path.basename(sys.executable).startswith("python")


THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
"""The thread pools of the BLAS libraries NumPy and SciPy may load: a worker's are sized like
its Numba's, unless the user set them."""


@contextlib.contextmanager
def worker_environment(threads: int):
    """The environment the workers start with (a new Python reads it before it imports NumPy
    and Numba): Numba's pool and the BLAS pools of ``threads`` each (the BLAS ones unless
    set), so that J workers do not start J pools of every core's threads."""
    import numba
    wanted = {"NUMBA_NUM_THREADS": str(min(threads, numba.config.NUMBA_NUM_THREADS)),
              **{name: str(threads) for name in THREAD_VARIABLES if name not in os.environ}}
    before = {name: os.environ.get(name) for name in wanted}
    os.environ.update(wanted)
    try:
        yield
    finally:
        for name, value in before.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


# ---- the workers -------------------------------------------------------------------------------

def _worker(number, build, work, threads, tasks, results, parent) -> None:
    """A worker's life: build the pipeline (``build``: scene folder, settings, frame cache
    folder), then for each time point index from ``tasks`` put ``(kind, number, index, value,
    loaded, solved)`` on ``results``: ``done`` with ``work(pipeline, index)``, ``error`` with
    a :class:`MuscleMSSError`'s ``(text, filter label)``, ``crash`` with another exception's
    traceback; ``loaded``, ``solved``: the frames its frame cache gave and took meanwhile.
    Ends at None, or when its run's process (pid ``parent``) is gone."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        import numba
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
        from .motion_run import build_pipeline
        pipeline = build_pipeline(*build)
    except BaseException as err:                                      # noqa: BLE001
        results.put(_failure(number, None, err))
        return
    frames = pipeline.frames
    while True:
        try:
            index = tasks.get(timeout=POLL_SECONDS)
        except queue.Empty:
            if os.getppid() != parent:
                return
            continue
        if index is None:
            return
        before = (frames.loaded, frames.solved) if frames is not None else (0, 0)
        try:
            value = work(pipeline, index)
        except BaseException as err:                                  # noqa: BLE001
            results.put(_failure(number, index, err))
            continue
        after = (frames.loaded, frames.solved) if frames is not None else (0, 0)
        results.put(("done", number, index, value, after[0] - before[0],
                     after[1] - before[1]))


def _failure(number, index, err) -> tuple:
    """A worker's report of ``err``: the text and filter label of a :class:`MuscleMSSError`
    (not the error itself: a subclass with its own arguments does not survive pickling), else
    the traceback."""
    if isinstance(err, MuscleMSSError):
        return "error", number, index, (str(err), getattr(err, "filter_label", None)), 0, 0
    return ("crash", number, index,
            "".join(traceback.format_exception(type(err), err, err.__traceback__)), 0, 0)


def _raised(kind, number, index, value) -> BaseException:
    """The error the run's process raises for a worker's failure report."""
    if kind == "error":
        text, label = value
        err = MuscleMSSError(text)
        if label:
            err.filter_label = label
        return err
    where = "preparing" if index is None else f"solving time point {index}"
    return RuntimeError(f"worker process {number} failed while {where}:\n{value}")


# ---- the run's process -------------------------------------------------------------------------

def solve_in_workers(build, indices, work, jobs: int, on_result=None, on_ready=None,
                     discard=None, meanwhile=None):
    """Solve the time points ``indices`` (in time order) in ``jobs`` worker processes, each
    building its pipeline from ``build`` = ``(scene folder, settings, frame cache folder or
    None)`` and returning ``work(pipeline, index)`` (a module-level function or a
    :func:`functools.partial` of one: it is pickled) for each index it is handed.

    ``on_result(index, value, received, total)`` as each arrives (progress);
    ``on_ready(index, value)`` in time order; ``discard(value)`` for one received but not
    taken (after a failure); ``meanwhile()``: this process's own work, done once the workers
    are started and handed their first time points (they spend their first seconds starting
    Python and reading the scene). Returns ``(loaded, solved)``: the frames the workers' frame
    caches gave and took. Raises the failure of the first failing time point in time order,
    after every time point before it is taken, a :class:`MuscleMSSError` as the serial run
    raises it; stops every worker on the way out, whatever happened."""
    indices = list(indices)
    jobs = max(1, min(jobs, len(indices)))
    context = multiprocessing.get_context("spawn")
    results = context.Queue()
    tasks = [context.Queue() for _ in range(jobs)]
    workers = [context.Process(
        target=_worker, name=f"muscle-mss worker {k}", daemon=True,
        args=(k, build, work, threads_per_worker(jobs), tasks[k], results, os.getpid()))
        for k in range(jobs)]
    waiting = list(indices)                     # not handed out yet, in time order
    busy = {}                                   # worker number -> index
    ready, failures = {}, {}                    # index -> value, index -> failure
    taken = received = loaded = solved = 0
    finished = False

    def hand_out(k):
        if waiting and not failures:
            busy[k] = waiting.pop(0)
            tasks[k].put(busy[k])

    def take_in_order():
        nonlocal taken
        while taken < len(indices) and indices[taken] in ready:
            if failures and indices[taken] > min(failures):
                return
            value = ready.pop(indices[taken])
            if on_ready is not None:
                on_ready(indices[taken], value)
            taken += 1

    try:
        # Ctrl-C reaches the workers' process group too: they start with it ignored (a
        # disposition a new Python keeps), so that only this process stops them
        main = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
        try:
            with worker_environment(threads_per_worker(jobs)):
                for w in workers:
                    w.start()
        finally:
            if main:
                signal.signal(signal.SIGINT, previous)
        for k in range(jobs):
            hand_out(k)
        if meanwhile is not None:
            meanwhile()
        while busy:
            kind, k, index, value, got, gave = _next_result(results, workers, busy)
            loaded, solved = loaded + got, solved + gave
            if index is None:                   # a worker could not start
                raise _raised(kind, k, index, value)
            del busy[k]
            if kind == "done":
                ready[index] = value
                received += 1
                if on_result is not None:
                    on_result(index, value, received, len(indices))
            else:
                failures[index] = (kind, k, index, value)
            hand_out(k)
            take_in_order()
        if failures:
            raise _raised(*failures[min(failures)])
        finished = True
        return loaded, solved
    finally:
        # done: each worker ends at the None; else (an error, Ctrl-C) they are stopped at once
        for q in tasks:
            with contextlib.suppress(Exception):
                q.put(None)
        for w in workers:
            if w.pid is not None:
                w.join(timeout=10 * POLL_SECONDS if finished else 0)
                if w.is_alive():
                    w.terminate()
                w.join()
        for value in ready.values():
            if discard is not None:
                discard(value)
        # drain what a worker put before it ended, so that the queue's thread can end
        with contextlib.suppress(Exception):
            while True:
                results.get_nowait()
        results.close()
        for q in tasks:
            q.cancel_join_thread()              # a stopped worker's unread task: no wait
            q.close()


def _next_result(results, workers, busy) -> tuple:
    """The next report on ``results``; :class:`MuscleMSSError` when a worker that holds a time
    point ended without reporting it (killed: out of memory, a signal)."""
    while True:
        try:
            return results.get(timeout=POLL_SECONDS)
        except queue.Empty:
            pass
        for k, index in busy.items():
            if not workers[k].is_alive():
                with contextlib.suppress(queue.Empty):      # its last words, if any
                    return results.get(timeout=POLL_SECONDS)
                raise MuscleMSSError(
                    f"worker process {k} (pid {workers[k].pid}) ended with exit code "
                    f"{workers[k].exitcode} while solving time point {index}, without a "
                    "result (killed: out of memory?); run again with fewer --jobs")


# ---- the work of a motion run ------------------------------------------------------------------

def stage_frame(out, series_names, compressor, pipeline, index):
    """A worker's part of a motion run's time point ``index``: solve it, write its series into
    a private folder under ``OUT/series`` (:func:`~muscle_mss.app.run_output.stage_time_point`)
    and return ``(result, staged)``, the result without its VTK objects (the run's process
    places the files and writes the convergence table:
    :func:`~muscle_mss.app.run_output.place_time_point`)."""
    from .motion_run import solve_time_point
    from .run_output import stage_time_point
    result = solve_time_point(pipeline, index)
    start = wallclock.perf_counter()
    staged = stage_time_point(result, out, series_names, compressor)
    result.timings["write"] = wallclock.perf_counter() - start
    result.surfaces = result.fibres = result.particles = None
    return result, staged


def workers_allowed(pipeline, jobs: int) -> bool:
    """Whether ``jobs`` worker processes may solve the time points of ``pipeline`` (a
    :class:`~muscle_mss.app.motion_run.Pipeline`); a note on stderr when not
    (:func:`serial_reason`, :func:`can_start_workers`)."""
    reason = serial_reason(pipeline.solver) or (
        None if can_start_workers()
        else f"{os.path.basename(sys.executable)} cannot start Python processes")
    if reason:
        print(f"note: --jobs {jobs} not used, the time points are solved one after another in "
              f"this process: {reason}", file=sys.stderr, flush=True)
    return reason is None


def run_in_workers(pipeline, scene_folder, out, settings, indices, jobs, on_step=None,
                   series_names=None, compressor=None) -> list:
    """``motion_run.run_motion``'s time points ``indices`` of ``pipeline`` (built for
    ``scene_folder`` and ``settings``; its frame cache's folder is the workers') solved by
    ``jobs`` worker processes, which write each one's series into a private folder
    (:func:`stage_frame`); here they are placed in time order and the convergence tables
    written, the frame cache's counts added to ``pipeline.frames``. ``on_step(result, done,
    total)`` as each arrives. The summary rows in time order."""
    from functools import partial
    from .run_output import (DEFAULT_COMPRESSOR, SERIES, discard_staged, place_time_point,
                             remove_stale_staging)
    rows = []
    frames = pipeline.frames

    def received(index, value, done, total):
        if on_step is not None:
            on_step(value[0], done, total)

    def ready(index, value):
        result, staged = value
        start = wallclock.perf_counter()
        place_time_point(result, staged, out)
        result.timings["write"] = result.timings.get("write", 0.0) + (
            wallclock.perf_counter() - start)
        rows.extend(result.rows)

    def meanwhile():
        # the stages before the solver, which do not change with the time (what the run's
        # pictures need of this process's pipeline), while the workers start
        from .motion_run import update_at
        update_at(pipeline.pose, 2, pipeline.times[indices[0]])

    build = (str(scene_folder), dict(settings or {}),
             frames.cache.folder if frames is not None else None)
    work = partial(stage_frame, os.path.abspath(out), tuple(series_names or SERIES),
                   compressor or DEFAULT_COMPRESSOR)
    try:
        loaded, solved = solve_in_workers(build, indices, work, jobs, received, ready,
                                          lambda value: discard_staged(value[1]), meanwhile)
    finally:
        remove_stale_staging(out)           # a stopped worker's, half written
    if frames is not None:
        frames.loaded += loaded
        frames.solved += solved
    return rows
