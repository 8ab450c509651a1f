"""Compile time of the numeric kernels, kernel by kernel, per Python (issue 27).

For each Python that runs the kernels (the venv's, and Debian's with plugin/shim on PYTHONPATH
as ./test.sh and ParaView run it), a fresh process with ``NUMBA_CACHE_DIR`` pointing at an empty
temporary folder runs the warm-up (``muscle_mss.app.warm_up``: tiny solves through the
whole filter chain for every variant, which call every kernel a run can reach, with a real run's
argument types) and records Numba's ``numba:compile`` events. A kernel compiles its callees
while it is typed, inside its own compile, so each kernel is given its own seconds: its compile
minus those of the kernels compiled within it (a parallel kernel's loops are part of it). The
seconds of every signature of a kernel are added up. The warm-up's wall time is given too: the
compiles, writing them to the cache, and the tiny solves themselves.

Prints a table of seconds per kernel and Python and the totals, with the machine, each Python's
Numba and the load average before and after each compile, and writes it to
benchmarks/results/compile.md. The compiles run one after the other: two at once on two cores
slowed each other by 60-80 % (issue 27).

    python benchmarks/bench_compile.py [venv|debian ...]        (default: both)
"""
from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_results import cpu_model, write_result

REPO = Path(__file__).resolve().parents[1]
PYTHONS = {
    "venv": ([str(REPO / ".venv" / "bin" / "python")], {}),
    "debian": (["/usr/bin/python3"], {"PYTHONPATH": str(REPO / "plugin" / "shim")}),
}
"""Name -> (command, environment added): the Pythons ./setup.sh compiles for."""
LABELS = {"venv": "venv", "debian": "Debian's Python (pvpython, pvbatch)"}


def measure() -> dict:
    """In this process (run with an empty ``NUMBA_CACHE_DIR``): the warm-up, timed, with each
    kernel's own compile seconds and signatures. Returns a JSON-able dict."""
    import numba
    import numpy
    from numba.core import event

    own: dict = {}
    signatures: dict = {}
    stack: list = []   # [kernel name, start, seconds of the compiles nested in it]

    class Own(event.Listener):
        """Each compile's seconds less those of the compiles it started."""

        def on_start(self, ev):
            stack.append([_kernel_name(ev.data["dispatcher"]), time.perf_counter(), 0.0])

        def on_end(self, ev):
            name, start, nested = stack.pop()
            seconds = time.perf_counter() - start
            own[name] = own.get(name, 0.0) + seconds - nested
            signatures[name] = signatures.get(name, 0) + 1
            if stack:
                stack[-1][2] += seconds

    start = time.perf_counter()
    from muscle_mss.app import warm_up    # imports VTK, NumPy, Numba: outside the compiles
    imported = time.perf_counter() - start
    with event.install_listener("numba:compile", Own()):
        start = time.perf_counter()
        warm_up.warm_up(warm_up.DEFAULT_VARIANTS)
        default_wall = time.perf_counter() - start
        default_own = sum(own.values())
        default_kernels = sorted(own)
        warm_up.warm_up(warm_up.OTHER_VARIANTS)
        wall = time.perf_counter() - start
    return {"numba": numba.__version__, "numpy": numpy.__version__,
            "python": platform.python_version(), "import": imported, "wall": wall,
            "default_wall": default_wall, "default_own": default_own,
            "default_kernels": default_kernels,
            "own": own, "signatures": signatures,
            "threading": _threading_layer(numba), "threads": numba.config.NUMBA_NUM_THREADS}


def _kernel_name(dispatcher) -> str:
    """``module.function`` without ``muscle_mss.``; an object-mode block (Numba compiles it as
    a code object of its own) is named after the kernel holding it."""
    from numba.core.dispatcher import LiftedCode
    if isinstance(dispatcher, LiftedCode):
        func_id = dispatcher.func_ir.func_id
        module, name = func_id.modname, f"{func_id.func_qualname} (object-mode block)"
    else:
        module, name = dispatcher.py_func.__module__, dispatcher.py_func.__qualname__
    return f"{(module or '?').removeprefix('muscle_mss.')}.{name}"


def _threading_layer(numba) -> str:
    try:
        return numba.threading_layer()
    except ValueError:
        return "no parallel kernel ran"


def compile_in_fresh_process(which: str) -> dict:
    """:func:`measure` in a new process of Python ``which`` with an empty kernel cache; the
    load average before and after."""
    command, extra = PYTHONS[which]
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONHOME", "VIRTUAL_ENV", "NUMBA_CACHE_DIR")}
    with tempfile.TemporaryDirectory(prefix="bench-compile-") as cache:
        env.update(extra, NUMBA_CACHE_DIR=cache)
        before = os.getloadavg()[0]
        proc = subprocess.run([*command, str(Path(__file__).resolve()), "--measure"], env=env,
                              cwd=REPO, capture_output=True, text=True)
        after = os.getloadavg()[0]
    if proc.returncode != 0:
        raise SystemExit(f"{which}: {' '.join(command)} exited {proc.returncode}\n"
                         f"{proc.stderr[-4000:]}")
    line = next(l for l in reversed(proc.stdout.splitlines()) if l.startswith("RESULT "))
    result = json.loads(line[len("RESULT "):])
    result["load"] = (before, after)
    return result


def table(results: dict) -> list:
    """The Markdown lines of the result file."""
    names = list(results)
    kernels = sorted({k for r in results.values() for k in r["own"]},
                     key=lambda k: -max(r["own"].get(k, 0.0) for r in results.values()))
    lines = ["# Compile time of the numeric kernels, per kernel and Python (issue 27)", "",
             f"Machine: {cpu_model()}, {os.cpu_count()} cores. "
             "`python benchmarks/bench_compile.py`: each Python in a fresh process with an empty "
             "kernel cache runs the warm-up (`python -m muscle_mss.app.warm_up`: tiny solves "
             "of every variant through the filter chain), one Python after the other. A "
             "kernel's seconds are its own compile's, less those of the kernels it compiled "
             "within it, over all its signatures (the count in brackets where more than one). "
             "The machine is shared: the load average (1 min) before and after is given, and "
             "the seconds are pessimistic. Kernels marked * compile for the default settings "
             "(in the warm-up's first part).", ""]
    for name in names:
        r = results[name]
        lines.append(f"- {LABELS[name]}: Python {r['python']}, numba {r['numba']} "
                     f"({r['threading']}, {r['threads']} threads), numpy {r['numpy']}; load "
                     f"{r['load'][0]:.2f} before, {r['load'][1]:.2f} after")
    lines += ["", "| | " + " | ".join(LABELS[n] for n in names) + " |",
              "|---|" + "---:|" * len(names)]
    lines.append("| **warm-up, wall s** (compiles, cache writes, the tiny solves) | "
                 + " | ".join(f"**{results[n]['wall']:.1f}**" for n in names) + " |")
    lines.append("| **all kernels' compiles, s** | "
                 + " | ".join(f"**{sum(results[n]['own'].values()):.1f}**" for n in names)
                 + " |")
    lines.append("| the default settings' kernels (what the demo needs; the warm-up compiles "
                 "them first): compiles s / wall s | "
                 + " | ".join(f"{results[n]['default_own']:.1f} / "
                              f"{results[n]['default_wall']:.1f}" for n in names) + " |")
    lines.append("| kernels compiled | "
                 + " | ".join(str(len(results[n]["own"])) for n in names) + " |")
    lines.append("| importing the filters (not compiling), s | "
                 + " | ".join(f"{results[n]['import']:.1f}" for n in names) + " |")
    default = {k for r in results.values() for k in r["default_kernels"]}
    for kernel in kernels:
        cells = []
        for n in names:
            seconds = results[n]["own"].get(kernel)
            count = results[n]["signatures"].get(kernel, 0)
            cells.append("—" if seconds is None else
                         f"{seconds:.2f}" + (f" ({count})" if count > 1 else ""))
        mark = " *" if kernel in default else ""
        lines.append(f"| `{kernel}`{mark} | " + " | ".join(cells) + " |")
    return lines


def main(which) -> int:
    results = {}
    for name in which:
        results[name] = compile_in_fresh_process(name)
        print(f"{name}: {sum(results[name]['own'].values()):.1f} s compiling, warm-up "
              f"{results[name]['wall']:.1f} s; the default settings' "
              f"{results[name]['default_own']:.1f} s, warm-up {results[name]['default_wall']:.1f} s",
              file=sys.stderr, flush=True)
    write_result(table(results), "compile.md")
    return 0


if __name__ == "__main__":
    if sys.argv[1:] == ["--measure"]:
        print("RESULT " + json.dumps(measure()))
        sys.exit(0)
    unknown = set(sys.argv[1:]) - set(PYTHONS)
    if unknown:
        sys.exit(f"unknown Python {', '.join(sorted(unknown))}: one of {', '.join(PYTHONS)}")
    sys.exit(main(sys.argv[1:] or list(PYTHONS)))
