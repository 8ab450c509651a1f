"""Benchmark of one time point of a motion run, part by part.

The full demo thigh (13 muscles x 64 fibres, lattice-26, the solver's defaults) and the full
demo elbow (7 muscles, 4 bones) are run through the CLI's pipeline
(:mod:`muscle_mss.app.motion_run`) at N = 20 and 80 particles per fibre. For each time point the
pipeline is updated stage by stage and each stage timed: pose (Rigid Pose Transform), solver
setup (the MSS Collision Solver's update less its solve), solve (the core solve: either
method's iterations, the final passes, the push out of the bones), MVC (MVC Surface Deformer),
statistics (Volume-Error Probe and the runner's summary rows: penetration, strain) and writing
(the three series, appended raw LZ4, and the convergence table). The first time point (MVC
weights, kernel loads, bone sphere sampling) is listed apart from the steady state (mean of the
later ones). A second table times the parts that have a faster replacement, on the last time
point's data: bone spheres sampled afresh vs taken from the rigid-bone cache, the penetration
statistics' Python reference vs its Numba grid, and the writing with VTK's default ZLib
compressor vs LZ4. Writes benchmarks/results/time_point.md.

    python benchmarks/bench_time_point.py [N ...] [--points K] [--scenes thigh arm]
                                             (default: 20 80, K = 4, both scenes)
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from muscle_mss.core.contacts import penetration as P
from muscle_mss.filters import bone_sets, collision_solver
from muscle_mss.app import motion_run, run_output
from muscle_mss.app.demo_folder import DEMO_REGIONS, demo_region_scene
from muscle_mss.app.motion_run import build_pipeline, update_at
from muscle_mss.filters.mvc_surface_deformer import weight_counts
from muscle_mss.filters.scene_io import write_scene

from bench_solver import machine

PARTS = ("pose", "solver setup", "solve", "MVC", "statistics", "writing")


class SolveClock:
    """Seconds spent in the core solve the MSS Collision Solver calls (wraps the filter's
    ``core.solver.solve``: either method's iterations, its final passes and the push out of the
    bones); the rest of the filter's update is its setup (VTK to arrays, bones, preparation)."""

    def __init__(self):
        self.seconds = 0.0
        self.inner = collision_solver.solve

    def __call__(self, *args, **kwargs):
        start = time.perf_counter()
        try:
            return self.inner(*args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - start


def time_point_parts(pipeline, index, out, clock) -> dict:
    """Seconds of each of :data:`PARTS` for time point ``index`` (stages updated in order)."""
    t = pipeline.times[index]
    seconds = {}
    start = time.perf_counter()
    update_at(pipeline.pose, 0, t)
    update_at(pipeline.pose, 1, t)
    seconds["pose"] = time.perf_counter() - start
    clock.seconds = 0.0
    start = time.perf_counter()
    update_at(pipeline.solver, 0, t)
    update_at(pipeline.solver, 1, t)
    seconds["solve"] = clock.seconds
    seconds["solver setup"] = time.perf_counter() - start - clock.seconds
    start = time.perf_counter()
    update_at(pipeline.deformer, 0, t)
    update_at(pipeline.deformer, 1, t)
    seconds["MVC"] = time.perf_counter() - start
    start = time.perf_counter()
    result = motion_run.solve_time_point(pipeline, index)  # stages up to date: probe + rows
    seconds["statistics"] = time.perf_counter() - start
    start = time.perf_counter()
    run_output.write_time_point(result, out)
    seconds["writing"] = time.perf_counter() - start
    return seconds, result


def replaced_parts(pipeline, index, result, out) -> list:
    """``(part, old s, new s)`` on time point ``index``: bone spheres, penetration, writing."""
    t = pipeline.times[index]
    bones = update_at(pipeline.pose, 1, t)
    spacing = pipeline.solver.value("BoneSphereSpacing")
    rows = []
    start = time.perf_counter()
    bone_sets.bone_sphere_set(bones, spacing, use_cache=False)
    old = time.perf_counter() - start
    start = time.perf_counter()
    bone_sets.bone_sphere_set(bones, spacing)
    rows.append(("bone spheres of the posed bones (sampled / cached)", old,
                 time.perf_counter() - start))
    captured = {}
    kernel = P.max_penetration_pairs

    def capture(*args, **kwargs):
        captured["args"] = args, kwargs
        return kernel(*args, **kwargs)

    P.max_penetration_pairs = capture
    try:
        motion_run.solve_time_point(pipeline, index)
    finally:
        P.max_penetration_pairs = kernel
    args, kwargs = captured["args"]
    start = time.perf_counter()
    P.max_penetration_per_object(*args, **kwargs)
    old = time.perf_counter() - start
    start = time.perf_counter()
    kernel(*args, **kwargs)
    rows.append(("penetration statistics (Python reference / Numba grid)", old,
                 time.perf_counter() - start))
    start = time.perf_counter()
    run_output.write_time_point(result, os.path.join(out, run_output.COMPRESSOR_ZLIB),
                                compressor=run_output.COMPRESSOR_ZLIB)
    old = time.perf_counter() - start
    start = time.perf_counter()
    run_output.write_time_point(result, os.path.join(out, run_output.COMPRESSOR_LZ4),
                                compressor=run_output.COMPRESSOR_LZ4)
    rows.append(("writing the three series (ZLib / LZ4)", old, time.perf_counter() - start))
    return rows


def sizes_and_points(argv, description):
    """The command line of this benchmark and of bench_time_slider: ``sizes`` (N values,
    default 20 80), ``--points`` (time points per N, first + rest, default 4) and ``--scenes``
    (demo regions, default all of :data:`DEMO_REGIONS`: the thigh and the elbow)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("sizes", nargs="*", type=int, default=[20, 80])
    parser.add_argument("--points", type=int, default=4, help="time points per N (first + rest)")
    parser.add_argument("--scenes", nargs="+", choices=DEMO_REGIONS, default=list(DEMO_REGIONS),
                        help="demo scenes (default: all)")
    return parser.parse_args(argv)


SCENE_LABELS = {"thigh": "thigh (13 muscles)", "arm": "elbow (7 muscles)"}
"""How the tables name each demo scene (``--scenes``)."""


def spread(count, points) -> list:
    """``points`` indices spread evenly over ``count`` time points, the first one included."""
    step = max(1, (count - 1) // max(points - 1, 1))
    return list(range(0, count, step))[:points]


def main(argv=None):
    args = sizes_and_points(argv, __doc__.splitlines()[0])
    clock = SolveClock()
    collision_solver.solve = clock
    table, replaced = [], []
    with tempfile.TemporaryDirectory() as folder:
        for region in args.scenes:
            scene = os.path.join(folder, region)
            write_scene(demo_region_scene(region, "full"), scene)
            for n in args.sizes:
                bone_sets.clear_bone_cache()
                pipeline = build_pipeline(scene, {"ParticlesPerFibre": n})
                indices = spread(len(pipeline.times), args.points)
                out = os.path.join(folder, f"{region}{n}")
                runs = []
                loaded = (bone_sets.field_counts["loaded"], weight_counts["loaded"])
                for index in indices:
                    seconds, result = time_point_parts(pipeline, index, out, clock)
                    if not runs:
                        fields = ", ".join((
                            "bone fields " + ("from disk" if bone_sets.field_counts["loaded"]
                                              > loaded[0] else "sampled"),
                            "MVC weights " + ("from disk" if weight_counts["loaded"] > loaded[1]
                                              else "computed")))
                    runs.append(seconds)
                    print(f"{region} N={n} t={pipeline.times[index]:.3f}: "
                          + ", ".join(f"{k} {v:.3f}" for k, v in seconds.items())
                          + f"; load {os.getloadavg()[0]:.2f}", flush=True)
                steady = {k: float(np.mean([r[k] for r in runs[1:]])) for k in PARTS} \
                    if len(runs) > 1 else None
                label = SCENE_LABELS[region]
                table.append((label, n, runs[0], steady, len(runs) - 1, os.getloadavg()[0],
                              fields))
                replaced += [(label, n) + r
                             for r in replaced_parts(pipeline, indices[-1], result, out)]
    lines = [
        "# One time point of a motion run, part by part (issue 15)", "",
        f"Machine: {machine()}. Load average (1 min) after each N is given: the "
        "machine is shared, so the seconds are pessimistic and vary between runs.", "",
        "Full demo thigh (13 muscles x 64 fibres, 3 bones) and elbow (7 muscles, 4 bones), "
        "lattice-26, the solver's defaults (the quasi-static method), the CLI's pipeline; "
        "`python benchmarks/bench_time_point.py`. Steady state: mean of the time points after "
        "the first. The first time point reads the bones' distance fields and the muscles' "
        "MVC weights from the disk stores of an earlier run when they have them "
        "(core/bones/field_store.py, mvc_surface_deformer.WEIGHTS_STORE), else computes them; its "
        "row says which. 'solve' = the core solve (the method's iterations, final passes, "
        "push out of the bones); 'around' = all but the solve.", "",
        "| scene | N | time point | " + " | ".join(f"{p} s" for p in PARTS)
        + " | around s | total s | load |",
        "|---|---|---|" + "---|" * (len(PARTS) + 3)]
    for scene, n, first, steady, count, load, fields in table:
        for label, seconds in ((f"first ({fields})", first), (f"steady ({count})", steady)):
            if seconds is None:
                continue
            around = sum(v for k, v in seconds.items() if k != "solve")
            lines.append(f"| {scene} | {n} | {label} | "
                         + " | ".join(f"{seconds[p]:.3f}" for p in PARTS)
                         + f" | {around:.3f} | {around + seconds['solve']:.3f} "
                         f"| {load:.2f} |")
    lines += ["", "Parts replaced by issue 15, on the last time point's data (old / new):", "",
              "| scene | N | part | old s | new s | old / new |", "|---|---|---|---|---|---|"]
    for scene, n, part, old, new in replaced:
        lines.append(f"| {scene} | {n} | {part} | {old:.4f} | {new:.4f} "
                     f"| {old / max(new, 1e-9):.1f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    out = Path(__file__).resolve().parent / "results" / "time_point.md"
    out.write_text(text)


if __name__ == "__main__":
    sys.exit(main())
