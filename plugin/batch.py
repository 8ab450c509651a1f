"""Run a whole motion in ParaView's Python, serially or spread over MPI ranks (DESIGN §7).

    pvpython -m muscle_mss.plugin.batch SCENE OUT [--resolution N] [--layout L] [--iterations K]
        [--method M] [--tolerance MM] [--write SERIES] [--compressor C] [--cache DIR|off]
        [--overwrite]
    mpiexec -n K pvbatch --sym -m muscle_mss.plugin.batch SCENE OUT [...]
    pvpython -m muscle_mss.plugin.batch --study SCENE OUT [--time T] [--resolution N]

(with ``plugin/shim`` on PYTHONPATH for Debian's ParaView 5.11, see the README). Writes the
``.pvd`` series of deformed surfaces, fibres and particles and ``OUT/summary.csv``
(``muscle_mss.app.run_output``). Under MPI rank r of K computes the r-th of K contiguous
blocks of time points in time order; every time point starts from its posed state, so the
ranks give the serial run's results (with the solver's warm start on, the quasi-static method
would start each from the one before it within its block). ``--study`` writes the paper's
experiments and the fibre-length study instead, as ``muscle-mss study`` does
(``OUT/report.html``, :mod:`muscle_mss.app.study`), in one process.
"""
import argparse
import contextlib
import csv
import glob
import os
import sys


def parse_args(argv):
    """The batch's options: the CLI's run options (:mod:`muscle_mss.app.run_options`) and
    ``--overwrite``. Imports the package, so that numba loads: set NUMBA_NUM_THREADS first."""
    from muscle_mss.app.run_options import add_run_options
    parser = argparse.ArgumentParser(prog="muscle_mss.plugin.batch", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", help="scene folder")
    parser.add_argument("out", help="output folder")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the results of an earlier run in OUT (refused without it)")
    parser.add_argument("--study", action="store_true",
                        help="write the study report (muscle-mss study) instead of the motion's "
                             "series; only --resolution and --time apply")
    parser.add_argument("--time", type=float,
                        help="with --study: the layouts' pose, the time point nearest this time "
                             "(s; default the most flexed)")
    add_run_options(parser)
    return parser.parse_args(argv)


def _study(args, size) -> int:
    """``--study``: the report of :mod:`muscle_mss.app.study`, in this one process."""
    from muscle_mss.core.errors import MuscleMSSError
    from muscle_mss.app.cli import held_output_folder, study_into
    from muscle_mss.app.run_options import cache_from, study_ignored
    ignored = study_ignored(args)
    problem = ("the study runs in one process: start it with pvpython, not under mpiexec"
               if size > 1 else f"{', '.join(ignored)} do not apply to --study (it runs "
               "every layout with the filters' defaults): drop them" if ignored else None)
    try:
        if problem:
            raise MuscleMSSError(problem)
        with held_output_folder(args.out, args.overwrite, study=True):
            path = study_into(args.scene, args.out, args.resolution, args.time,
                              cache_from(args))
    except MuscleMSSError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(f"wrote {path}")
    return 0


def _controller():
    try:
        from vtkmodules.vtkParallelCore import vtkMultiProcessController
    except ImportError:
        return None
    return vtkMultiProcessController.GetGlobalController()


def main(argv=None) -> int:
    controller = _controller()
    rank = controller.GetLocalProcessId() if controller else 0
    size = controller.GetNumberOfProcesses() if controller else 1
    # Ranks x Numba threads should not exceed the cores (paraview-python-plugins §8); set
    # before the core (and numba) is imported.
    os.environ.setdefault("NUMBA_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // size)))
    args = parse_args(sys.argv[1:] if argv is None else argv)

    from muscle_mss.core.errors import MuscleMSSError
    from muscle_mss.app import run_output
    from muscle_mss.app.run_options import settings_from, writing_from

    # Rank 0 compiles the kernels once (when this Python's cache is cold) while the others
    # wait in _any_rank below, then load them from the cache instead of each compiling.
    if rank == 0:
        from muscle_mss.app.warm_up import ensure_compiled, stderr_notice
        ensure_compiled(stderr_notice)
    if args.study or args.time is not None:
        if not args.study:
            print("error: --time applies only to --study", file=sys.stderr)
            return 1
        return _study(args, size) if rank == 0 else 1
    failed = 0
    try:
        writing, settings = writing_from(args), settings_from(args)
    except MuscleMSSError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    # Rank 0 checks OUT (every place the ranks will write, and that its manifest names none of
    # the scene's files) and removes an earlier run's files with --overwrite before any rank
    # writes, and alone holds OUT's lock until every rank is done (every rank adds its files
    # to the manifest); all ranks stop if it refuses.
    with contextlib.ExitStack() as held:
        if rank == 0:
            try:
                from muscle_mss.filters.scene_io import load_scene, scene_files
                count = len(load_scene(args.scene).motion.times)
                _, note = held.enter_context(run_output.output_folder(
                    args.out, args.overwrite,
                    places=run_output.run_places(range(count), writing.series),
                    inputs=scene_files(args.scene)))
                if note:
                    print(note, file=sys.stderr)
            except MuscleMSSError as err:
                print(f"error: {err}", file=sys.stderr)
                failed = 1
        if _any_rank(controller, size, failed):
            return 1
        try:
            return _run(args, controller, rank, size, settings, writing)
        except KeyboardInterrupt as err:    # the lock is released on the way out
            from muscle_mss.filters.base import interrupted_message
            print(f"rank {rank}: {interrupted_message(err, 'muscle_mss.plugin.batch')}",
                  file=sys.stderr)
            return 130


def _run(args, controller, rank, size, settings, writing) -> int:
    """Every rank's time points, then rank 0's summary and index; 1 when a rank failed."""
    from muscle_mss.core.errors import MuscleMSSError
    from muscle_mss.filters import array_names as A
    from muscle_mss.app import motion_run, output_folder, run_output
    from muscle_mss.app.run_options import cache_from
    failed = 0
    partial = f".summary.rank{rank}.csv"
    try:
        pipeline, rows = motion_run.run_motion(
            args.scene, args.out, settings,
            part=(rank, size), series_names=writing.series, compressor=writing.compressor,
            cache=cache_from(args))
        if pipeline.frames is not None:
            print(f"rank {rank}: {pipeline.frames.summary()}")
        output_folder.claim(args.out, partial)
        run_output.write_csv(os.path.join(args.out, partial), run_output.SUMMARY_COLUMNS,
                             ([r[c] for c in run_output.SUMMARY_COLUMNS] for r in rows))
    except MuscleMSSError as err:
        print(f"rank {rank}: error: {err}", file=sys.stderr)
        failed = 1
    failed = _any_rank(controller, size, failed)  # no summary or index after a failed rank
    if rank == 0 and not failed:
        rows = _merge(args.out, size)
        times = sorted({float(r[A.TIME]) for r in rows})
        run_output.write_summary(args.out, rows)
        run_output.write_index(args.out, times, series_names=writing.series)
        print(f"wrote {len(times)} time points x {len(rows) // max(len(times), 1)} muscles "
              f"to {args.out} on {size} rank{'s' if size > 1 else ''}")
    if controller is not None and size > 1:
        controller.Barrier()
    return int(failed)


def _any_rank(controller, size, flag) -> bool:
    """True on every rank when ``flag`` is set on any rank (a barrier as well)."""
    if controller is None or size == 1:
        return bool(flag)
    from vtkmodules.vtkCommonCore import vtkIntArray
    from vtkmodules.vtkParallelCore import vtkCommunicator
    sent, received = vtkIntArray(), vtkIntArray()
    sent.InsertNextValue(int(flag))
    controller.AllReduce(sent, received, vtkCommunicator.MAX_OP)
    return bool(received.GetValue(0))


def _merge(out, size):
    """Rows of every rank's partial summary, in time order (muscles keep scene order)."""
    from muscle_mss.filters import array_names as A
    rows = []
    for path in sorted(glob.glob(os.path.join(out, ".summary.rank*.csv"))):
        with open(path, newline="") as f:
            rows += list(csv.DictReader(f))
        os.remove(path)
    rows.sort(key=lambda r: float(r[A.TIME]))  # stable: scene order within a time point
    return rows


if __name__ == "__main__":
    sys.exit(main())
