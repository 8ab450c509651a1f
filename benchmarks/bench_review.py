"""Simulate once, review from the frame cache: the demo walk solved cold (an empty frame cache)
against the same demo again with the cache warm, then ``muscle-mss run`` of the demo's scene into
a new folder (every frame from the cache) and that run again into its finished folder. Before
them, every core: the demo walk without the cache (``--cache off``) in one process
(``--jobs 1``) and in two worker processes of one thread each (``--jobs 2``), and from the
second run's per time point seconds (each frame's cost on one thread) the walk's wall projected
to 8 and 16 cores (:func:`projected`).

Wall seconds of each command (the process, from start to exit: the kernels are compiled
before, so no compile is counted) and the frames it loaded from the cache and solved, as the
run prints them (``frame cache: L of T frames loaded, S solved``). The kernels, bone fields and
MVC weights come from the user's caches as in a user's second demo. Prints a table with the
machine and the load average and writes it to benchmarks/results/review.md.

    python benchmarks/bench_review.py
"""
from __future__ import annotations

import csv
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_results import cpu_model, write_result

REPO = Path(__file__).resolve().parents[1]
VENV = REPO / ".venv" / "bin"
COUNTS = re.compile(r"frame cache: (\d+) of (\d+) frames loaded, (\d+) solved")
PROJECTED_CORES = (2, 8, 16)


def frame_seconds(out) -> list:
    """Each time point's seconds (pose, solve, surface and volume) in a run's summary.csv, in
    time order."""
    with open(os.path.join(out, "summary.csv"), newline="") as f:
        return list({float(r["time"]): float(r["seconds"]) for r in csv.DictReader(f)}.values())


def handed_out(costs, workers: int) -> float:
    """The seconds ``workers`` processes take for frames of ``costs`` handed out in time order,
    each to the first worker free (as ``--jobs`` does)."""
    free = [0.0] * workers
    for cost in costs:
        free[free.index(min(free))] += cost
    return max(free)


def projected(costs, measured_wall: float, measured_workers: int) -> dict:
    """``{cores: wall s}``: a run with one one-thread worker per core, its frames costing
    ``costs`` (one thread each), plus what does not shrink with the workers (the scene, the
    start of the workers, the pictures): the measured wall of ``measured_workers`` minus their
    frames' hand-out (:func:`handed_out`). Memory bandwidth shared by more workers is not
    modelled: an upper bound on the gain."""
    rest = measured_wall - handed_out(costs, measured_workers)
    return {cores: rest + handed_out(costs, cores) for cores in PROJECTED_CORES}


def timed(command) -> tuple:
    """``(wall seconds, loaded, solved, last line, load average before)`` of one command (its
    exit checked)."""
    load = os.getloadavg()[0]
    start = time.perf_counter()
    done = subprocess.run([str(c) for c in command], capture_output=True, text=True, cwd=REPO)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(map(str, command))} failed:\n{done.stderr[-2000:]}")
    found = COUNTS.search(done.stdout)
    loaded, solved = (int(found.group(1)), int(found.group(3))) if found else ("-", "-")
    return seconds, loaded, solved, done.stdout.strip().splitlines()[-1], load


def main() -> int:
    subprocess.run([VENV / "python", "-m", "muscle_mss.app.warm_up", "--quiet"], check=True)
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as root:
        cache, demo, run = (os.path.join(root, name) for name in ("frames", "demo", "run"))
        one, two = (os.path.join(root, f"jobs{jobs}") for jobs in (1, 2))
        jobs = [
            ("`muscle-mss demo --cache off --jobs 1` (one process, Numba's threads on every core)",
             timed([VENV / "muscle-mss", "demo", one, "--cache", "off", "--jobs", "1"])),
            ("`muscle-mss demo --cache off --jobs 2` (two worker processes, "
             f"{max(1, (os.cpu_count() or 1) // 2)} thread each)",
             timed([VENV / "muscle-mss", "demo", two, "--cache", "off", "--jobs", "2"])),
        ]
        costs, serial_costs = frame_seconds(two), frame_seconds(one)
        steps = [
            ("`muscle-mss demo` cold (empty frame cache)",
             timed([VENV / "muscle-mss", "demo", demo, "--cache", cache])),
            ("`muscle-mss demo` again, the cache warm",
             timed([VENV / "muscle-mss", "demo", demo, "--cache", cache])),
            ("`muscle-mss run` of the demo scene into a new folder",
             timed([VENV / "muscle-mss", "run", os.path.join(demo, "scene"), run,
                    "--cache", cache])),
            ("the same `muscle-mss run` into its finished folder",
             timed([VENV / "muscle-mss", "run", os.path.join(demo, "scene"), run,
                    "--cache", cache])),
        ]
        size = sum(f.stat().st_size for f in Path(cache).iterdir())
        entries = len(list(Path(cache).glob("*.frame")))
    load_after = os.getloadavg()[0]
    lines = ["# Review from the frame cache", "",
             f"Machine: {cpu_model()}, {os.cpu_count()} cores; Python "
             f"{platform.python_version()} (the venv); load average (1 min) {load_before:.2f} "
             f"before, {load_after:.2f} after. The machine is shared with other work, so the "
             "seconds vary from run to run. `python benchmarks/bench_review.py`: the full demo "
             "thigh walk (21 time points, the default settings), kernels compiled first; each "
             "command's wall seconds, process start to exit (the demo also writes its scene "
             "and pictures each time).", "",
             "| command | wall s | frames loaded | solved | load before |",
             "|---|---:|---:|---:|---:|"]
    for name, (seconds, loaded, solved, _, load) in jobs + steps:
        lines.append(f"| {name} | {seconds:.1f} | {loaded} | {solved} | {load:.2f} |")
    walls = projected(costs, jobs[1][1][0], 2)
    lines += ["", f"`--jobs 2` took {jobs[1][1][0] / jobs[0][1][0]:.2f} of `--jobs 1`'s wall. "
              f"The frames' seconds (summary.csv; pose, solve, surface and volume) sum to "
              f"{sum(serial_costs):.1f} s in the `--jobs 1` run (all threads) and to "
              f"{sum(costs):.1f} s in the `--jobs 2` run (one thread each: a frame's cost on "
              f"one core; the costliest {max(costs):.1f} s, the cheapest {min(costs):.1f} s).",
              "", "Projected to more cores (`--jobs` = the cores, one thread each): the frames "
              "handed out in time order to the first worker free, at their one-thread cost "
              "measured here, plus what does not shrink with the workers (the `--jobs 2` "
              "wall less its two workers' share of the frames: "
              f"{walls[2] - handed_out(costs, 2):.1f} s). Memory bandwidth shared by more "
              "workers is not modelled, and the costliest frame bounds the wall from below.",
              "", "| cores | frames' share, s | projected wall s |", "|---:|---:|---:|"]
    lines += [f"| {cores} | {handed_out(costs, cores):.1f} | {walls[cores]:.1f} |"
              for cores in PROJECTED_CORES]
    lines += ["", f"The frame cache after: {entries} entries (each time point's solved frame "
              f"and its deformed surfaces), {size / 2 ** 20:.1f} MiB "
              f"({size / max(len(costs), 1) / 2 ** 20:.2f} MiB a time point). The finished "
              f"folder's run printed: \"{steps[3][1][3]}\"."]
    write_result(lines, "review.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
