"""The demo's first run on a machine that has compiled nothing yet (issue 27): seconds from the
demo's start (pip done) to its kernels compiled, to its first time point solved and to its end.

Each run gives ``muscle-mss demo`` an empty user cache folder (``XDG_CACHE_HOME``: no kernels,
no bone distance fields, no MVC weights), as on a new machine, and timestamps the lines it
prints (progress bars included). Two ways, one after the other:

- **as the demo runs it**: the default settings' kernels compile in a second process while the
  demo writes its scene and prepares its first time point (``warm_up.compiling_beside``);
- **compile first**: ``python -m muscle_mss.app.warm_up --defaults``, then the demo (the
  order before the overlap), for the ratio.

``./demo.sh`` adds its own checks (about a second when everything is installed) and the apt-get
and pip steps of a new machine, which are not measured here. Prints a table with the machine
and the load average, and writes it to benchmarks/results/first_run.md.

    python benchmarks/bench_first_run.py
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
EVENTS = (("compiled", re.compile(r"^compiled the numeric kernels in")),
          ("first time point", re.compile(r"^solving \[.*\] 1/\d+ ")),
          ("end", re.compile(r"^wrote ")))
"""What each timestamp marks: the first line that matches."""


def timed_lines(command, env) -> dict:
    """Run ``command``; return ``{event: seconds after its start}`` for :data:`EVENTS`, read
    from its output lines (stdout and stderr, progress lines ending in a carriage return)."""
    start = time.perf_counter()
    proc = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            cwd=REPO)
    seen, line = {}, b""
    while True:
        char = proc.stdout.read(1)
        if not char or char in b"\r\n":
            text = line.decode(errors="replace").strip()
            for name, pattern in EVENTS:
                if name not in seen and pattern.search(text):
                    seen[name] = time.perf_counter() - start
            line = b""
            if not char:
                break
        else:
            line += char
    if proc.wait() != 0:
        raise RuntimeError(f"{' '.join(map(str, command))} failed")
    return seen


def one_run(compile_first: bool) -> dict:
    """Seconds to each event of :data:`EVENTS` in an empty user cache folder."""
    with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as out:
        env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
        env.update(XDG_CACHE_HOME=cache, PYTHONUNBUFFERED="1")
        shift = 0.0
        if compile_first:
            shift = timed_lines([VENV / "python", "-m", "muscle_mss.app.warm_up",
                                 "--defaults"], env)["compiled"]
        seen = timed_lines([VENV / "muscle-mss", "demo", out], env)
        if compile_first:
            seen = {name: shift + s for name, s in seen.items()}
            seen["compiled"] = shift
        return seen


def main() -> int:
    load_before = os.getloadavg()[0]
    overlap = one_run(compile_first=False)
    first = one_run(compile_first=True)
    load_after = os.getloadavg()[0]
    lines = ["# The demo's first run, from an empty kernel cache (issue 27)", "",
             f"Machine: {cpu_model()}, {os.cpu_count()} cores; {platform.python_version()} "
             f"(the venv); load average (1 min) {load_before:.2f} before, {load_after:.2f} "
             "after. `python benchmarks/bench_first_run.py`: `muscle-mss demo` (the full "
             "thigh scene, 21 time points, the default settings) with an empty user cache "
             "folder (no kernels, bone distance fields or MVC weights), seconds after its "
             "start; `./demo.sh` adds about a second of checks, and the apt-get and pip steps "
             "of a new machine.", "",
             "| seconds after the start | as the demo runs it (kernels compiled beside the "
             "scene and the first time point's preparation) | compile first, then the demo "
             "| ratio |", "|---|---:|---:|---:|"]
    for name, _ in EVENTS:
        lines.append(f"| {name} | {overlap[name]:.1f} | {first[name]:.1f} | "
                     f"{overlap[name] / first[name]:.2f} |")
    write_result(lines, "first_run.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
