"""Benchmark of the MSS Collision Solver on the paper's workload (DESIGN §9, paper §4.3).

13 muscles of the full demo thigh, 64 fibres each (8 x 8 grid), lattice-26 springs, three bones
sampled into exactly 8527 / 1568 / 1709 spheres, 500 iterations, at the walking pose a third into
the motion. The paper's particle counts (1344 / 2624 / 3904 / 5184 per muscle for its "N = 20,
40, 60, 80") are 64 * (N + 1): its N counts intervals, so this runs N + 1 particles per fibre to
compare like with like. Prints a table of MSS, muscle-muscle CD and muscle-bone CD seconds for
both collision structures, the total, the speed-up over the paper's Table 1 (i7-3770, one
thread) and the machine, and writes it to benchmarks/results/solver.md. Each configuration is
solved three times and the median reported: on a shared virtual machine single runs vary by
a fifth.

    python benchmarks/bench_solver.py [N ...]        (default: 20 40 60 80)
"""
from __future__ import annotations

import os
import platform
import sys
import tempfile
import time

import numba
import numpy as np

from muscle_mss.core import solver as S
from muscle_mss.core.model import Bones, prepare
from muscle_mss.core.bones.spheres import bone_spheres
from muscle_mss.core.demo.scene import demo_scene
from muscle_mss.core.settings import METHOD_RELAXATION, STRUCTURES, SolverSettings
from muscle_mss.filters import vtk_arrays as V
from muscle_mss.filters.collision_solver import MSSCollisionSolver
from muscle_mss.filters.model_blocks import muscle_block
from muscle_mss.app.motion_run import build_pipeline, update_at
from muscle_mss.filters.scene_io import write_scene

from bench_results import cpu_model, write_result

PAPER = {20: (18.66, 8.15, 30.03, 56.84), 40: (39.97, 13.50, 37.43, 90.90),
         60: (60.53, 24.00, 56.03, 140.56), 80: (80.70, 29.53, 67.10, 177.33)}
BONE_COUNTS = {"pelvis": 8527, "femur": 1568, "tibia": 1709}
ITERATIONS = 500
REPEATS = 3


def machine() -> str:
    """The machine and the numeric stack, for a benchmark's table: CPU, cores, Numba with the
    threading layer it runs its parallel kernels on (call after one has run) and its threads,
    NumPy, Python."""
    try:
        layer = numba.threading_layer()
    except ValueError:          # no parallel kernel has run yet
        layer = "threading layer not chosen yet"
    return (f"{cpu_model()}, {os.cpu_count()} cores, numba {numba.__version__} ({layer}, "
            f"{numba.config.NUMBA_NUM_THREADS} threads), numpy {np.__version__}, Python "
            f"{platform.python_version()}")


def posed_workload(scene_folder, time_point, n):
    """The solver's inputs at ``time_point`` from the real pipeline (motion_run's wiring: the
    Spring Builder clears radii of the bones), with the paper's bone sphere counts."""
    pipeline = build_pipeline(scene_folder, {"ParticlesPerFibre": n + 1, "Randomise": True})
    blocks = V.blocks(update_at(pipeline.pose, 0, time_point))
    posed_bones = update_at(pipeline.pose, 1, time_point)
    model = MSSCollisionSolver._model([b for b, _ in blocks],
                                      [muscle_block(name, block) for name, block in blocks])
    centres, radii, ids = [], [], []
    for k, (name, bone) in enumerate(V.blocks(posed_bones)):
        c, r = bone_spheres(V.points_of(bone), V.triangles_of(bone), count=BONE_COUNTS[name])
        centres.append(c), radii.append(r), ids.append(np.full(len(c), k))
    return model, Bones((np.concatenate(centres), np.concatenate(radii), np.concatenate(ids)))


def main(sizes):
    scene = demo_scene("full")
    folder = tempfile.mkdtemp(prefix="bench_scene_")
    write_scene(scene, folder)
    time_point = float(scene.motion.times[len(scene.motion.times) // 3])
    rows = []
    for n in sizes:
        model, bones = posed_workload(folder, time_point, n)
        prepared = prepare(model)
        per_muscle = int(np.diff(model.offsets)[0])
        boundary = int(model.boundary.sum() / len(model.names))
        for structure in STRUCTURES:
            # the paper's method and model (no connective tissue, the paper's springs),
            # whatever the defaults
            settings = SolverSettings.build(method=METHOD_RELAXATION, iterations=ITERATIONS,
                                            structure=structure, connective_tissue=0.0,
                                            fibre_shortening=False)
            S.solve(model, bones, SolverSettings.build(
                method=METHOD_RELAXATION, iterations=2, structure=structure,
                fibre_shortening=False), prepared=prepared)
            runs = []
            for _ in range(REPEATS):
                start = time.perf_counter()
                result = S.solve(model, bones, settings, prepared=prepared)
                runs.append((time.perf_counter() - start, result.phase_seconds,
                             result.projection_passes))
            runs.sort(key=lambda run: run[0])
            total, p, passes = runs[len(runs) // 2]
            spread = f"{runs[0][0]:.2f}-{runs[-1][0]:.2f}"
            rows.append((n, per_muscle, boundary, structure, p["mss"], p["muscle_cd"],
                         p["bone_cd"], p["projection"], passes, total, spread,
                         PAPER[n][3] / total, os.getloadavg()[0]))
            print(f"N={n} ({per_muscle} particles/muscle) {structure}: median total {total:.2f} s "
                  f"of {spread} (MSS {p['mss']:.2f}, muscle CD {p['muscle_cd']:.2f}, bone CD "
                  f"{p['bone_cd']:.2f}, {passes} final passes {p['projection']:.2f}), load "
                  f"{os.getloadavg()[0]:.2f}", flush=True)
    lines = [
        "# MSS Collision Solver benchmark (paper's workload, 500 iterations)", "",
        f"Machine: {machine()}.",
        "Load average (1 min) after each run is given: on a shared machine the numbers are "
        "pessimistic.", "",
        f"Each row is the median of {REPEATS} solves (their range beside it); MSS includes "
        "applying the collision displacements and measuring the mean displacement, final "
        "passes are the collision passes after "
        "the last iteration (until no overlap is above 0.01 mm). The total is the wall time of "
        "the whole solve.", "",
        "| N | particles / muscle | boundary / muscle | structure | MSS s | muscle CD s | "
        "bone CD s | final passes (s) | total s | range s | paper total s | speed-up | load |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for n, per, bnd, st, a, b, c, proj, passes, tot, spread, speed, load in rows:
        lines.append(f"| {n} | {per} | {bnd} | {st} | {a:.2f} | {b:.2f} | {c:.2f} | "
                     f"{passes} ({proj:.2f}) | {tot:.2f} | {spread} | {PAPER[n][3]:.2f} | "
                     f"{speed:.0f}x | {load:.2f} |")
    write_result(lines, "solver.md")


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [20, 40, 60, 80])
