"""Run a whole motion in ParaView's Python, serially or spread over MPI ranks (DESIGN §7).

    pvpython -m muscle_mss.plugin.batch SCENE OUT [--resolution N] [--layout L] [--iterations K]
        [--method quasi-static|paper] [--tolerance MM]
    mpiexec -n K pvbatch --sym -m muscle_mss.plugin.batch SCENE OUT [...]

(with ``plugin/shim`` on PYTHONPATH for Debian's ParaView 5.11, see the README). Writes the
``.pvd`` series of deformed surfaces, fibres and particles and ``OUT/summary.csv``
(``muscle_mss.filters.motion_run``). Under MPI rank r of K computes the r-th of K contiguous
blocks of time points in time order, warm starting each from the one before it within its block
(the quasi-static method; with the paper's, the default, every time point starts from its posed
state and the ranks give the serial run's results).
"""
import argparse
import csv
import glob
import os
import sys


def parse_args(argv):
    parser = argparse.ArgumentParser(prog="muscle_mss.plugin.batch", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", help="scene folder")
    parser.add_argument("out", help="output folder")
    parser.add_argument("--resolution", type=int, help="particles per fibre N")
    parser.add_argument("--layout", help="spring layout: lattice-6, lattice-26, Delaunay, k-NN")
    parser.add_argument("--iterations", type=int, help="solver iterations per time point")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the results of an earlier run in OUT (refused without it)")
    # not cli.add_method_options: importing the package loads numba before NUMBA_NUM_THREADS
    parser.add_argument("--method", choices=("quasi-static", "paper"),
                        help="solver: the paper's relaxation (default) or the quasi-static "
                             "equilibrium")
    parser.add_argument("--tolerance", type=float,
                        help="quasi-static tolerance: largest particle move of a step, mm")
    parser.add_argument("--write", default="surfaces,fibres,particles",
                        help="series to write, comma-separated (default all three)")
    parser.add_argument("--compressor", choices=("lz4", "zlib", "none"), default="lz4",
                        help="compressor of the series' binary data (default lz4)")
    return parser.parse_args(argv)


def _controller():
    try:
        from vtkmodules.vtkParallelCore import vtkMultiProcessController
    except ImportError:
        return None
    return vtkMultiProcessController.GetGlobalController()


def main(argv=None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    controller = _controller()
    rank = controller.GetLocalProcessId() if controller else 0
    size = controller.GetNumberOfProcesses() if controller else 1
    # Ranks x Numba threads should not exceed the cores (paraview-python-plugins §8); set
    # before the core (and numba) is imported.
    os.environ.setdefault("NUMBA_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // size)))

    from muscle_mss.core.errors import MuscleMSSError
    from muscle_mss.filters import motion_run
    from muscle_mss.filters.cli import settings_from

    # Rank 0 compiles the kernels once (when this Python's cache is cold) while the others
    # wait in _any_rank below, then load them from the cache instead of each compiling.
    if rank == 0:
        from muscle_mss.filters.warm_up import ensure_compiled
        ensure_compiled(lambda text: print(text, file=sys.stderr, flush=True))
    # Rank 0 checks OUT (and clears an earlier run's results with --overwrite) before any
    # rank writes; all ranks stop if it refuses.
    failed = 0
    try:
        series_names = motion_run.parse_write_option(args.write)
    except MuscleMSSError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    if rank == 0:
        try:
            motion_run.check_output_folder(args.out, args.overwrite)
        except MuscleMSSError as err:
            print(f"error: {err}", file=sys.stderr)
            failed = 1
    if _any_rank(controller, size, failed):
        return 1
    partial = os.path.join(args.out, f".summary.rank{rank}.csv")
    try:
        pipeline, rows = motion_run.run_motion(
            args.scene, args.out, settings_from(args),
            part=(rank, size), series_names=series_names, compressor=args.compressor)
        motion_run.write_csv(partial, motion_run.SUMMARY_COLUMNS,
                             ([r[c] for c in motion_run.SUMMARY_COLUMNS] for r in rows))
    except MuscleMSSError as err:
        print(f"rank {rank}: error: {err}", file=sys.stderr)
        failed = 1
    failed = _any_rank(controller, size, failed)  # no summary or index after a failed rank
    if rank == 0 and not failed:
        rows = _merge(args.out, size)
        times = sorted({float(r["time"]) for r in rows})
        motion_run.write_summary(args.out, rows)
        motion_run.write_index(args.out, times, series_names=series_names)
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
    rows = []
    for path in sorted(glob.glob(os.path.join(out, ".summary.rank*.csv"))):
        with open(path, newline="") as f:
            rows += list(csv.DictReader(f))
        os.remove(path)
    rows.sort(key=lambda r: float(r["time"]))  # stable: scene order within a time point
    return rows


if __name__ == "__main__":
    sys.exit(main())
