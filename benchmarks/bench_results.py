"""What every benchmark shares and that needs only the standard library (so that
bench_compile.py's parent process imports no Numba): the CPU's name and writing a result table."""
from __future__ import annotations

import platform
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def write_result(lines, name) -> None:
    """Print the table ``lines`` and write it to ``benchmarks/results/<name>``."""
    text = "\n".join(lines) + "\n"
    print(text)
    (Path(__file__).resolve().parent / "results" / name).write_text(text)
