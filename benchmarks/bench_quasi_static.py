"""Benchmark of the quasi-static solver (core/quasi_static/) on the full demo thigh (issue 11).

For the walking pose (a third into the motion, t = 0.35 s, as bench_solver.py) and the most
flexed pose (t = 0.75 s), at N = 20 and 80 particles per fibre (13 muscles x 64 fibres,
lattice-26, the filter's bone spheres and bone solids): iterations and seconds of the default
solve (Tolerance 1e-3 mm, bones as solids, capped), whether it converged, the distance of its
particles to a 10x tighter solve (Tolerance 1e-4 mm, a larger cap) mean / max mm, the same for
the solve against the bones' sphere sets and for the paper relaxation at 500 iterations. Then
the whole walk (21 time points, N = 20) solved in time order cold (from each posed state) and
warm (from the last solution carried by the pose change, as the filter does). Machine and
load in the table; written to benchmarks/results/quasi_static.md.

    python benchmarks/bench_quasi_static.py [--sizes 20 80] [--cap 1000] [--tight-cap 3000]
                                            [--walk-cap 300]
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

from muscle_mss.core import quasi_static as Q
from muscle_mss.core import solver as S
from muscle_mss.core.model import prepare
from muscle_mss.core.demo_scene import demo_scene
from muscle_mss.core.settings import DEFAULT_TOLERANCE, METHOD_QUASI_STATIC, SolverSettings
from muscle_mss.filters import vtk_arrays as V
from muscle_mss.filters.bone_sets import bone_sphere_set
from muscle_mss.filters.collision_solver import MSSCollisionSolver, _muscle_block, solid_bones
from muscle_mss.filters.motion_run import build_pipeline, update_at
from muscle_mss.filters.scene_io import write_scene

from bench_solver import machine, write_result

POSES = (("walking", 0.35), ("most flexed", 0.75))



def quasi_static(**values) -> SolverSettings:
    """Quasi-static settings from flat keywords (:meth:`SolverSettings.build`)."""
    return SolverSettings.build(method=METHOD_QUASI_STATIC, **values)

def workload(pipeline, t):
    """The solver's inputs at time ``t`` as the filter builds them: the model, its bone spheres
    and its bones as solids."""
    blocks = V.blocks(update_at(pipeline.pose, 0, t))
    posed_bones = update_at(pipeline.pose, 1, t)
    bones = bone_sphere_set(posed_bones)
    model = MSSCollisionSolver._model([b for b, _ in blocks],
                                      [_muscle_block(name, block) for name, block in blocks])
    return model, bones, solid_bones(posed_bones)


def distance(a, b):
    d = np.linalg.norm(a - b, axis=1)
    return float(d.mean()), float(d.max())


def main(args):
    scene = demo_scene("full")
    folder = tempfile.mkdtemp(prefix="bench_qs_scene_")
    write_scene(scene, folder)
    rows, walk_rows = [], []
    for n in args.sizes:
        pipeline = build_pipeline(folder, {"ParticlesPerFibre": n})
        prepared = None
        for label, t in POSES:
            model, bones, solids = workload(pipeline, t)
            if prepared is None:
                prepared = prepare(model)
                tick = time.perf_counter()
                Q.preconditioner(model, prepared)
                factor_seconds = time.perf_counter() - tick
                Q.solve(model, *bones, prepared=prepared, bone_solids=solids,
                        settings=quasi_static(iterations=2))   # compiled, warm
            tick = time.perf_counter()
            default = Q.solve(model, *bones, prepared=prepared, bone_solids=solids,
                              settings=quasi_static(iterations=args.cap))
            seconds = time.perf_counter() - tick
            tick = time.perf_counter()
            spheres = Q.solve(model, *bones, prepared=prepared,
                              settings=quasi_static(iterations=args.cap))
            sphere_seconds = time.perf_counter() - tick
            tight = Q.solve(model, *bones, prepared=prepared, bone_solids=solids,
                            settings=quasi_static(tolerance=DEFAULT_TOLERANCE / 10,
                                                           iterations=args.tight_cap))
            tick = time.perf_counter()
            paper = S.solve(model, *bones, prepared=prepared)
            paper_seconds = time.perf_counter() - tick
            row = (n, label, t, default.iterations, seconds, default.converged,
                   float(default.residual[-1]), *distance(default.positions, tight.positions),
                   tight.iterations, tight.converged, spheres.iterations, sphere_seconds,
                   spheres.converged, *distance(spheres.positions, tight.positions),
                   paper_seconds, *distance(paper.positions, tight.positions), factor_seconds,
                   os.getloadavg()[0])
            rows.append(row)
            print(row, flush=True)
    if args.walk_cap:
        pipeline = build_pipeline(folder, {"ParticlesPerFibre": 20})
        inputs = [workload(pipeline, float(t)) for t in scene.motion.times]
        prepared = prepare(inputs[0][0])
        Q.preconditioner(inputs[0][0], prepared)
        for mode in ("cold", "warm"):
            settings = quasi_static(iterations=args.walk_cap)
            last = None
            iterations, converged = 0, 0
            tick = time.perf_counter()
            for model, bones, solids in inputs:
                start = None if (mode == "cold" or last is None) else (
                    model.positions + (last[1] - last[0]))
                result = Q.solve(model, *bones, settings=settings, prepared=prepared,
                                 start=start, bone_solids=solids)
                last = (model.positions, result.positions)
                iterations += result.iterations
                converged += int(result.converged)
            walk_rows.append((mode, len(inputs), time.perf_counter() - tick, iterations,
                              converged, os.getloadavg()[0]))
            print(walk_rows[-1], flush=True)

    lines = [
        "# Quasi-static solver benchmark (full demo thigh, issue 11)", "",
        f"Machine: {machine()}. The machine is shared: the load average (1 min) after "
        "each row is given.", "",
        f"Default solve: Tolerance {DEFAULT_TOLERANCE} mm, cap {args.cap} iterations, bones "
        f"as solids (the filter's default). Tighter: Tolerance {DEFAULT_TOLERANCE / 10} mm, "
        f"cap {args.tight_cap}, solids. Sphere set: the default solve against the bones' "
        "sphere sets. Distances are per particle to the tighter solve, after the final "
        "collision passes, mean / max mm. Paper: the paper relaxation at its default 500 "
        "iterations. Factor: the one-off factorisation per topology (s).", "",
        "| N | pose | t s | iterations | seconds | converged | last residual mm | "
        "to tighter | tighter iterations (converged) | sphere set: iterations, seconds "
        "(converged) | sphere set to tighter | paper s | paper to tighter | factor s | load |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for (n, label, t, it, sec, conv, res, dm, dx, tit, tconv, sit, ssec, sconv, sm, sx, psec,
         pm, px, fsec, load) in rows:
        yes = {True: "yes", False: "no"}
        lines.append(f"| {n} | {label} | {t:.2f} | {it} | {sec:.2f} | {yes[conv]} | {res:.3g} "
                     f"| {dm:.3f} / {dx:.2f} | {tit} ({yes[tconv]}) | {sit}, {ssec:.2f} "
                     f"({yes[sconv]}) | {sm:.3f} / {sx:.2f} | {psec:.2f} | {pm:.3f} / {px:.2f} "
                     f"| {fsec:.2f} | {load:.2f} |")
    if walk_rows:
        lines += ["", f"Whole walk (N = 20, cap {args.walk_cap} iterations per time point, in "
                  "time order):", "",
                  "| start | time points | seconds | iterations | converged | load |",
                  "|---|---|---|---|---|---|"]
        for mode, count, sec, it, conv, load in walk_rows:
            lines.append(f"| {mode} | {count} | {sec:.1f} | {it} | {conv} | {load:.2f} |")
        if len(walk_rows) == 2:
            lines.append("")
            lines.append(f"Warm / cold seconds: {walk_rows[1][2] / walk_rows[0][2]:.2f}.")
    write_result(lines, "quasi_static.md")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[20, 80])
    parser.add_argument("--cap", type=int, default=1000)
    parser.add_argument("--tight-cap", type=int, default=3000)
    parser.add_argument("--walk-cap", type=int, default=300)
    main(parser.parse_args())
