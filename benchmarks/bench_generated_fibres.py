"""Generated fibres against the shipped ones on the full demo scenes (elbow and thigh): the demo
scene written twice, its fibres replaced in the second by ``muscle-mss fibres --overwrite``
(the bones from the replaced fibres.vtm, 8 x 8 fibres of 30 points as shipped), both motions
solved with ``muscle-mss run --cache off``.

Per muscle: the seconds the Fibre Generator took (after a first muscle that includes the bone
distances of the whole scene and, in a fresh Python, compiling), the angle between the generated
and the shipped fibres' mean origin-to-insertion directions, the generated fibres' mean
end-to-end length over the shipped ones', and from each run's summary.csv the mean volume error
and `follows` (the slope of fibre strain on end-to-end strain; for muscles that shorten by over
3 %). Prints the tables with the machine and the load average and writes them to
benchmarks/results/generated_fibres.md.

    python benchmarks/bench_generated_fibres.py
"""
from __future__ import annotations

import csv
import os
import platform
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from bench_results import cpu_model, write_result

REPO = Path(__file__).resolve().parents[1]
CLI = str(REPO / ".venv" / "bin" / "muscle-mss")
REGIONS = ("arm", "thigh")


def mean_direction(fibres):
    """(unit mean origin-to-insertion direction, mean end-to-end length mm) of a FibreSet."""
    d = fibres.points[fibres.offsets[1:] - 1] - fibres.points[fibres.offsets[:-1]]
    mean = d.mean(axis=0)
    return mean / np.linalg.norm(mean), float(np.linalg.norm(d, axis=1).mean())


def generator_seconds(scene) -> tuple:
    """``(fibres, seconds per muscle)`` of the core call the filter makes, on a loaded scene
    whose fibres name their bones."""
    from muscle_mss.core.fibre_generation import generate_scene_fibres
    named = {m: (f.origin_bone, f.insertion_bone) for m, f in scene.fibres.items()}
    marks = [time.perf_counter()]
    fibres = generate_scene_fibres(scene.muscles, scene.bones, named,
                                   progress=lambda done, total: marks.append(time.perf_counter()))
    return fibres, np.diff(marks)


def run_summary(scene: Path, out: Path) -> dict:
    """``{muscle: rows}`` of ``muscle-mss run SCENE OUT --cache off``'s summary.csv."""
    subprocess.run([CLI, "run", str(scene), str(out), "--cache", "off", "--write", "surfaces"],
                   check=True, stdout=subprocess.DEVNULL)
    by_muscle = {}
    with open(out / "summary.csv", newline="") as f:
        for row in csv.DictReader(f):
            by_muscle.setdefault(row["muscle"], []).append(row)
    return by_muscle


def region_table(region: str, folder: Path) -> list:
    from muscle_mss.app.study import follow_slope
    from muscle_mss.filters.scene_io import load_scene
    shipped, generated = folder / "shipped", folder / "generated"
    subprocess.run([CLI, "demo-scene", str(shipped), "--region", region], check=True,
                   stdout=subprocess.DEVNULL)
    shutil.copytree(shipped, generated)
    scene = load_scene(str(shipped))
    fibres, seconds = generator_seconds(scene)
    start = time.perf_counter()
    subprocess.run([CLI, "fibres", str(generated), "--overwrite"], check=True,
                   stdout=subprocess.DEVNULL)
    command = time.perf_counter() - start
    runs = {name: run_summary(path, folder / f"out-{name}")
            for name, path in (("shipped", shipped), ("generated", generated))}
    lines = [f"### {region}: `muscle-mss fibres` {command:.1f} s for {len(fibres)} muscles",
             "", "| muscle | bones | s | direction ° | end-to-end | vol err % shipped | "
                 "generated | follows shipped | generated |", "|---|---|---|---|---|---|---|---|---|"]
    errors = {name: [] for name in runs}
    for k, (muscle, made) in enumerate(fibres.items()):
        (gd, gl), (sd, sl) = mean_direction(made), mean_direction(scene.fibres[muscle])
        angle = np.degrees(np.arccos(np.clip(gd @ sd, -1.0, 1.0)))
        cells = []
        for name, rows in runs.items():
            mean = float(np.mean([float(r["volume_error_pct"]) for r in rows[muscle]]))
            errors[name].append(mean)
            cells.append(f"{mean:.2f}")
        for name, rows in runs.items():
            shortens = min(float(r["mean_end_to_end_strain"]) for r in rows[muscle]) < -0.03
            cells.append(f"{follow_slope(rows[muscle]):.2f}" if shortens else "-")
        lines.append(f"| {muscle} | {made.origin_bone} → {made.insertion_bone} | "
                     f"{seconds[k]:.2f} | {angle:.1f} | {gl / sl:.3f} | " + " | ".join(cells)
                     + " |")
    lines.append(f"| mean | | {seconds[1:].mean():.2f} (after the first) | | | "
                 f"{np.mean(errors['shipped']):.2f} | {np.mean(errors['generated']):.2f} | | |")
    return lines + [""]


def main() -> None:
    lines = ["# Generated fibres on the demo scenes", "",
             f"Machine: {cpu_model()}, {os.cpu_count()} cores, {platform.python_version()}; "
             f"load average before: {os.getloadavg()[0]:.2f}. "
             "`python benchmarks/bench_generated_fibres.py`.", "",
             "Direction: angle between the generated and shipped fibres' mean origin-to-insertion "
             "directions; end-to-end: generated / shipped mean fibre end-to-end length; vol err: "
             "the muscle's mean volume error over the motion; follows: slope of fibre strain on "
             "end-to-end strain over the motion, for muscles shortening by over 3 %.", ""]
    with tempfile.TemporaryDirectory() as tmp:
        for region in REGIONS:
            lines += region_table(region, Path(tmp) / region)
    lines.append(f"Load average after: {os.getloadavg()[0]:.2f}.")
    write_result(lines, "generated_fibres.md")


if __name__ == "__main__":
    main()
