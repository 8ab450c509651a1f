"""Simulate once, review from the frame cache: the demo walk solved cold (an empty frame cache)
against the same demo again with the cache warm, then ``muscle-mss run`` of the demo's scene into
a new folder (every frame from the cache) and that run again into its finished folder.

Wall seconds of each command (the process, from start to exit: the kernels are compiled
before, so no compile is counted) and the frames it loaded from the cache and solved, as the
run prints them (``frame cache: L of T frames loaded, S solved``). The kernels, bone fields and
MVC weights come from the user's caches as in a user's second demo. Prints a table with the
machine and the load average and writes it to benchmarks/results/review.md.

    python benchmarks/bench_review.py
"""
from __future__ import annotations

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


def timed(command) -> tuple:
    """``(wall seconds, loaded, solved, last line)`` of one command (its exit checked)."""
    start = time.perf_counter()
    done = subprocess.run([str(c) for c in command], capture_output=True, text=True, cwd=REPO)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(map(str, command))} failed:\n{done.stderr[-2000:]}")
    found = COUNTS.search(done.stdout)
    loaded, solved = (int(found.group(1)), int(found.group(3))) if found else ("-", "-")
    return seconds, loaded, solved, done.stdout.strip().splitlines()[-1]


def main() -> int:
    subprocess.run([VENV / "python", "-m", "muscle_mss.app.warm_up", "--quiet"], check=True)
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as root:
        cache, demo, run = (os.path.join(root, name) for name in ("frames", "demo", "run"))
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
             "| command | wall s | frames loaded | solved |", "|---|---:|---:|---:|"]
    for name, (seconds, loaded, solved, _) in steps:
        lines.append(f"| {name} | {seconds:.1f} | {loaded} | {solved} |")
    lines += ["", f"The frame cache after: {entries} entries, {size / 2 ** 20:.1f} MiB "
              f"({size / max(entries, 1) / 2 ** 20:.2f} MiB a frame). The finished folder's "
              f"run printed: \"{steps[3][1][3]}\"."]
    write_result(lines, "review.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
