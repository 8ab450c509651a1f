"""Benchmark of the quasi-static solver (core/quasi_static/) with the connective tissue, on both
demo scenes: the thigh (13 muscles) at its walking pose (t = 0.35 s, as bench_solver.py) and
most flexed pose (t = 0.75 s), the elbow (7 muscles) at 70 and 130 degrees of flexion; lattice-26,
the filter's bone spheres and bones as solids.

Every quasi-static solve uses the spring energy ``--springs`` and the contact weight
``--contact-weight`` (the solver's defaults unless given).
Table 1, per scene, pose and N (particles per fibre), at ConnectiveTissue ``--ratio``:
iterations and seconds of the solve (the default Tolerance, cap ``--cap``), whether it converged,
its last step, the distance of its particles to a 10x tighter solve, to the solve without
tissue at the same cap and to the paper relaxation (500 iterations, no tissue), mean / max mm,
and the tissue's share of each muscle's load (median / max %).
Table 2, the ratio sweep (``--sweep``) at N = 20: iterations, seconds, converged, distance to
the solve at the first ratio of the sweep and the volume error of the muscles' cages (mean /
max %).
Table 3, each scene's motion (thigh walk 21 time points, elbow 13; N ``--walk-sizes``,
``--ratio``) solved in time order cold (each from its posed state) and warm (from the last
solution carried by the pose change): seconds, iterations, converged, and how far the two
answers are apart at the most flexed pose.
Table 4 (``--levers``), per scene, pose and N: the solve in one stage (the default) and with the
contacts softened first (``soft_start``, ``--soft-start``), each with and without the contacts between
muscles in the preconditioner (``contact_preconditioner``), and the one-stage solve at the
former default Tolerance 0.001 mm (the answer before these levers): iterations, seconds of the
solver filter's first update of the pose, the ratio to the paper's 500 relaxation iterations on
the same pose in the same run, distance to a 10x tighter solve, energy and distance against the
one-stage solve without the contacts in the preconditioner, volume error, the muscle pairs
left overlapping.
Machine and load in the tables; written to benchmarks/results/ (``--out``).

    python benchmarks/bench_quasi_static.py [--scenes thigh arm] [--sizes 20 80]
        [--ratio 0.1] [--sweep 0 0.001 0.003 0.01 0.03 0.1] [--cap 2000] [--walk-cap 2000]
        [--[no-]fibre-shortening] [--springs Hooke|co-rotational] [--contact-weight 1.0]
        [--walk-sizes 20 80] [--walk-modes cold warm] [--[no-]table1] [--[no-]levers]
        [--soft-start 0.3]
        [--out quasi_static.md]

Every option defaults to the solver's default (the model a user gets).
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

from muscle_mss.core import solver as S
from muscle_mss.core.demo.arm import demo_arm_scene, flexion_angles
from muscle_mss.core.demo.scene import demo_scene
from muscle_mss.core.model import Bones, prepare
from muscle_mss.core.fibre_shortening import shortened_springs
from muscle_mss.core.settings import (DEFAULT_CONNECTIVE_TISSUE, DEFAULT_FIBRE_SHORTENING,
                                      DEFAULT_ITERATIONS, DEFAULT_SPRINGS,
                                      DEFAULT_TISSUE_ALONG, DEFAULT_TOLERANCE,
                                      METHOD_QUASI_STATIC, METHOD_RELAXATION, SPRING_ENERGIES,
                                      QuasiStaticSettings, SolverSettings)
from muscle_mss.filters import vtk_arrays as V
from muscle_mss.filters.bone_sets import bone_sphere_set
from muscle_mss.filters.bone_sets import solid_bones
from muscle_mss.filters.collision_solver import MSSCollisionSolver
from muscle_mss.filters.model_blocks import muscle_block
from muscle_mss.app.motion_run import build_pipeline, update_at
from muscle_mss.filters.scene_io import write_scene

from bench_solver import machine, write_result

THIGH_POSES = (("walking", 0.35), ("most flexed", 0.75))
# mm: the quasi-static solve's default tolerance before it became 0.1 mm (docs/solver-notes.md,
# "The tolerance"); Table 4 solves each pose at it too, the answer the levers are held against
FORMER_TOLERANCE = 1e-3
ARM_ANGLES = (70.0, 130.0)


def quasi_static(**values) -> SolverSettings:
    """Quasi-static settings from flat keywords (:meth:`SolverSettings.build`)."""
    return SolverSettings.build(method=METHOD_QUASI_STATIC,
                                **{"fibre_shortening": False, **values})


def chosen(args, **values) -> SolverSettings:
    """:func:`quasi_static` with the spring energy and contact weight of the command line."""
    return quasi_static(springs=args.springs, contact_weight=args.contact_weight, **values)


def workload(pipeline, t, fibre_shortening=DEFAULT_FIBRE_SHORTENING):
    """The solver's inputs at time ``t`` as the filter builds them: the model (its springs'
    rest state shortened with the pose when ``fibre_shortening``, as the filter's
    FibreShortening does), its bone spheres and its bones as solids."""
    blocks = V.blocks(update_at(pipeline.pose, 0, t))
    posed_bones = update_at(pipeline.pose, 1, t)
    bones = bone_sphere_set(posed_bones)
    model = MSSCollisionSolver._model([b for b, _ in blocks],
                                      [muscle_block(name, block) for name, block in blocks])
    if fibre_shortening:
        model = shortened_springs(model)
    return model, bones, solid_bones(posed_bones)


def thigh_workload(t, n, fibre_shortening=False):
    """:func:`workload` of the full demo thigh at time ``t`` with ``n`` particles per fibre
    (the scene written to a temporary folder for the pipeline's readers); the rest lengths
    those of the rest pose unless ``fibre_shortening``."""
    with tempfile.TemporaryDirectory() as folder:
        write_scene(demo_scene("full"), folder)
        return workload(build_pipeline(folder, {"ParticlesPerFibre": n}), t,
                        fibre_shortening)


def distance(a, b):
    d = np.linalg.norm(a - b, axis=1)
    return float(d.mean()), float(d.max())


def cage_volume_error(prep, positions):
    """(mean, max) % of the muscles' cage volume change from rest at ``positions`` (n, 3)."""
    x = np.asarray(positions)[prep.order]
    ptr, triangles, rest = prep.cages.arrays
    errors = []
    for m in range(len(ptr) - 1):
        tri = triangles[ptr[m]:ptr[m + 1]]
        if len(tri):
            a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
            volume = np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0
            errors.append(100.0 * abs(volume / rest[m] - 1.0))
    return float(np.mean(errors)), float(np.max(errors))


def scenes(names):
    """(scene name, scene, poses as (label, t)) for the demo scenes ``names``."""
    for name in names:
        if name == "thigh":
            yield name, demo_scene("full"), THIGH_POSES
        else:
            scene = demo_arm_scene("full")
            angles = flexion_angles(scene.motion.times)
            yield name, scene, tuple((f"{a:.0f} deg", float(scene.motion.times[
                int(np.argmin(np.abs(angles - a)))])) for a in ARM_ANGLES)


def timed(model, bones, solids, prepared, settings):
    tick = time.perf_counter()
    result = S.solve(model, Bones(bones, solids), settings, prepared=prepared)
    return result, time.perf_counter() - tick


def pose_row(model, bones, solids, prepared, args, paper_model):
    """Table 1's measurements of one pose; the paper relaxation's on ``paper_model`` (the rest
    pose's rest lengths)."""
    result, seconds = timed(model, bones, solids, prepared,
                            chosen(args, iterations=args.cap, connective_tissue=args.ratio))
    tight, _ = timed(model, bones, solids, prepared, chosen(
        args, iterations=3 * args.cap, tolerance=DEFAULT_TOLERANCE / 10,
        connective_tissue=args.ratio))
    free, _ = timed(model, bones, solids, prepared,
                    chosen(args, iterations=args.cap, connective_tissue=0.0))
    paper, _ = timed(paper_model, bones, solids, prepare(paper_model), SolverSettings.build(
        method=METHOD_RELAXATION, iterations=500, connective_tissue=0.0, tissue_along=1.0,
        fibre_shortening=False))
    share = result.tissue_share
    return (result.iterations, seconds, result.converged, float(result.residual[-1]),
            *distance(result.positions, tight.positions), tight.converged,
            *distance(result.positions, free.positions), free.converged,
            *distance(result.positions, paper.positions),
            float(np.median(share)), float(np.max(share)), os.getloadavg()[0])


def first_update(model, bones, solids, settings):
    """A solve as the solver filter's first update of a pose does it, its preparation (the
    particle order, the factorisation, the columns of its inverse) timed with it:
    ``(result, seconds)``."""
    tick = time.perf_counter()
    result = S.solve(model, Bones(bones, solids), settings, prepared=prepare(model))
    return result, time.perf_counter() - tick


def levers(soft_start) -> tuple:
    """Table 4's solver configurations ``(label, settings)``: the one-stage solve without the
    contacts in the preconditioner first (the reference of the energy and distance columns),
    each lever alone (the first stage at ``soft_start``), both, and the one-stage solve at
    :data:`FORMER_TOLERANCE` (the answer before the levers and the looser tolerance); the
    defaults' row marked."""
    rows = (("one stage", dict(soft_start=1.0, contact_preconditioner=False)),
            ("soft start", dict(soft_start=soft_start, contact_preconditioner=False)),
            ("contacts in preconditioner", dict(soft_start=1.0, contact_preconditioner=True)),
            ("both", dict(soft_start=soft_start, contact_preconditioner=True)),
            (f"one stage, Tolerance {FORMER_TOLERANCE:g} mm (the former default)",
             dict(soft_start=1.0, contact_preconditioner=False, tolerance=FORMER_TOLERANCE)))
    default = QuasiStaticSettings()
    return tuple((label + (" (default)" if all(getattr(default, k) == v for k, v in
                                                 lever.items()) else ""), lever)
                 for label, lever in rows)


def lever_rows(model, bones, solids, args, paper_model):
    """Table 4's rows of one pose: the quasi-static solve in each of :func:`levers` (each a
    first update), its distance to a 10x tighter solve of the same configuration, and the
    paper's 500 relaxation iterations on the same pose in the same run."""
    def paper_settings(iterations):
        return SolverSettings.build(method=METHOD_RELAXATION, iterations=iterations,
                                    connective_tissue=0.0, tissue_along=1.0,
                                    fibre_shortening=False)

    # the kernels of both methods and both preconditioners loaded before anything is timed
    first_update(paper_model, bones, solids, paper_settings(2))
    for _, lever in levers(args.soft_start):
        first_update(model, bones, solids, chosen(args, iterations=2, **lever))
    paper, paper_seconds = first_update(paper_model, bones, solids, paper_settings(500))
    rows, before = [], None
    for label, lever in levers(args.soft_start):
        settings = chosen(args, iterations=args.cap, connective_tissue=args.ratio, **lever)
        result, seconds = first_update(model, bones, solids, settings)
        tighter = dict(lever, tolerance=lever.get("tolerance", DEFAULT_TOLERANCE) / 10)
        tight, _ = first_update(model, bones, solids, chosen(
            args, iterations=3 * args.cap, connective_tissue=args.ratio, **tighter))
        prepared = prepare(model)
        before = before or result
        rows.append((label, result.iterations, seconds, seconds / paper_seconds,
                     result.converged, *distance(result.positions, tight.positions),
                     100.0 * (result.energy[-1] / before.energy[-1] - 1.0),
                     *distance(result.positions, before.positions),
                     *cage_volume_error(prepared, result.positions),
                     int(result.muscle_pairs[-1]), paper_seconds, os.getloadavg()[0]))
    return rows


def sweep_rows(model, bones, solids, prepared, args):
    """Table 2's rows of one pose, the first ratio being the reference for the distances."""
    rows, untethered = [], None
    for ratio in args.sweep:
        result, seconds = timed(model, bones, solids, prepared,
                                chosen(args, iterations=args.cap, connective_tissue=ratio))
        untethered = result if untethered is None else untethered
        rows.append((ratio, result.iterations, seconds, result.converged,
                     *distance(result.positions, untethered.positions),
                     *cage_volume_error(prepared, result.positions), os.getloadavg()[0]))
    return rows


def walk_rows(name, scene, folder, args, flexed_time, n):
    """Table 3: the motion of ``scene`` (called ``name``) at ``n`` particles per fibre, cold and
    warm (``args.walk_modes``), and the two answers' distance at its most flexed pose (the time
    point nearest ``flexed_time``; None with one mode)."""
    pipeline = build_pipeline(folder, {"ParticlesPerFibre": n})
    inputs = [workload(pipeline, float(t), args.fibre_shortening)
              for t in scene.motion.times]
    settings = chosen(args, iterations=args.walk_cap, connective_tissue=args.ratio)
    flexed = int(np.argmin(np.abs(scene.motion.times - flexed_time)))
    rows, answers = [], []
    for mode in args.walk_modes:
        last, iterations, converged, seconds = None, [], 0, []
        for k, (model, bones, solids) in enumerate(inputs):
            start = None if (mode == "cold" or last is None) else (
                model.positions + (last[1] - last[0]))
            tick = time.perf_counter()
            result = S.solve(model, Bones(bones, solids), settings, prepared=prepare(model),
                             start=start)
            seconds.append(time.perf_counter() - tick)
            last = (model.positions, result.positions)
            iterations.append(result.iterations)
            converged += int(result.converged)
            print(f"  {name} N={n} {mode} t={scene.motion.times[k]:.3f}: {result.iterations} "
                  f"iterations, {seconds[-1]:.2f} s, converged {int(result.converged)}",
                  flush=True)
            if k == flexed:
                answers.append(result.positions)
        rows.append((n, mode, len(inputs), sum(seconds), max(seconds), sum(iterations),
                     int(np.median(iterations)), max(iterations), converged,
                     os.getloadavg()[0]))
        print(rows[-1], flush=True)
    return rows, distance(*answers) if len(answers) == 2 else None


def main(args):
    yes = {True: "yes", False: "no"}
    table1, table2, walks, table4 = [], [], [], []
    for name, scene, poses in scenes(args.scenes):
        folder = tempfile.mkdtemp(prefix=f"bench_qs_{name}_")
        write_scene(scene, folder)
        for n in args.sizes:
            pipeline = build_pipeline(folder, {"ParticlesPerFibre": n})
            for label, t in poses:
                model, bones, solids = workload(pipeline, t, args.fibre_shortening)
                paper_model = workload(pipeline, t, False)[0]
                prepared = prepare(model)
                S.solve(model, Bones(bones, solids), quasi_static(iterations=2),
                        prepared=prepared)        # compiled, warm
                if args.table1:
                    table1.append((name, n, label, t, *pose_row(model, bones, solids,
                                                                 prepared, args, paper_model)))
                    print(table1[-1], flush=True)
                if args.levers:
                    for row in lever_rows(model, bones, solids, args, paper_model):
                        table4.append((name, n, label, *row))
                        print(table4[-1], flush=True)
                if n == 20 and args.sweep:
                    for row in sweep_rows(model, bones, solids, prepared, args):
                        table2.append((name, label, *row))
                        print(table2[-1], flush=True)
        if args.walk_cap:
            for n in args.walk_sizes:
                walks.append((name, *walk_rows(name, scene, folder, args, poses[-1][1], n)))

    lines = [
        "# Quasi-static solver with the connective tissue (both demo scenes)", "",
        f"Machine: {machine()}. The machine is shared: the load average (1 min) after "
        "each row is given."]
    table1_lines = [
        "", f"Table 1: Springs {args.springs}, contact weight "
        f"{chosen(args).quasi_static.weight:g}, ConnectiveTissue {args.ratio:g} "
        f"(TissueAlongFibres {DEFAULT_TISSUE_ALONG:g}), FibreShortening "
        f"{'on' if args.fibre_shortening else 'off'}, Tolerance {DEFAULT_TOLERANCE} mm, cap "
        f"{args.cap} iterations, bones as solids. Tighter: Tolerance "
        f"{DEFAULT_TOLERANCE / 10} mm, cap {3 * args.cap}. No tissue: the same solve at "
        "ConnectiveTissue 0. Paper: the paper relaxation, 500 iterations, no tissue. "
        "Distances per particle, after the final collision passes, mean / max mm. Tissue "
        "share: its force over the springs', median / max over the muscles.", "",
        "| scene | N | pose | t s | iterations | seconds | converged | last step mm | "
        "to tighter (converged) | to no tissue (converged) | to paper | tissue share % | "
        "load |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    if table1:
        lines += table1_lines
    for (scene, n, label, t, it, sec, conv, last, tm, tx, tconv, fm, fx, fconv, pm, px,
         share_median, share_max, load) in table1:
        lines.append(f"| {scene} | {n} | {label} | {t:.2f} | {it} | {sec:.2f} | {yes[conv]} "
                     f"| {last:.2g} | {tm:.3f} / {tx:.2f} ({yes[tconv]}) | {fm:.2f} / "
                     f"{fx:.1f} ({yes[fconv]}) | {pm:.2f} / {px:.1f} | {share_median:.1f} / "
                     f"{share_max:.1f} | {load:.2f} |")
    if table2:
        lines += ["", f"Table 2: the ratio sweep at N = 20 (cap {args.cap}). Distance to the "
                  f"solve at ConnectiveTissue {args.sweep[0]:g}, mean / max mm; volume error "
                  "of the muscles' cages (the particles' boundary, not the MVC surface), "
                  "mean / max %.", "",
                  f"| scene | pose | ratio | iterations | seconds | converged | to ratio "
                  f"{args.sweep[0]:g} | "
                  "cage volume error % | load |", "|---|---|---|---|---|---|---|---|---|"]
        for scene, label, ratio, it, sec, conv, dm, dx, vm, vx, load in table2:
            lines.append(f"| {scene} | {label} | {ratio:g} | {it} | {sec:.2f} | {yes[conv]} "
                         f"| {dm:.2f} / {dx:.1f} | {vm:.2f} / {vx:.2f} | {load:.2f} |")
    if walks:
        lines += ["", f"Table 3: each motion (ConnectiveTissue {args.ratio:g}, cap "
                  f"{args.walk_cap} iterations per time point, in time order), cold (each time "
                  "point from its posed state) or warm (from the last answer carried by the "
                  "pose change); iterations in all and per time point (median, max); cold to "
                  "warm: the two answers' distance at the most flexed pose, mean / max mm.", "",
                  "| scene | N | start | time points | seconds | slowest point s | iterations | "
                  "per point median / max | converged | load | cold to warm |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for scene, rows, apart in walks:
            gap = "—" if apart is None else f"{apart[0]:.2f} / {apart[1]:.1f}"
            for n, mode, count, sec, slowest, it, median, most, conv, load in rows:
                lines.append(f"| {scene} | {n} | {mode} | {count} | {sec:.1f} | {slowest:.1f} "
                             f"| {it} | {median} / {most} | {conv} | {load:.2f} | {gap} |")
    if table4:
        lines += ["", "Table 4: the levers on the iteration count (docs/solver-notes.md): "
                  "the contacts softened in a first stage (QuasiStaticSettings.soft_start, "
                  "\"Soft contacts first\"; one stage: soft_start 1) and the contacts between "
                  "muscles in the preconditioner (contact_preconditioner, \"Contacts in the "
                  "preconditioner\"), each alone and both, and the one-stage solve at the "
                  f"former default Tolerance {FORMER_TOLERANCE:g} mm; each pose's solve as "
                  "the solver filter's first update (preparation included), the defaults "
                  "otherwise. x "
                  "paper: its seconds "
                  "over the paper's 500 relaxation iterations on the same pose in the same run "
                  "(their seconds in the last column). To tighter: to the same solve at "
                  f"a tenth of its Tolerance (the default's {DEFAULT_TOLERANCE:g} mm unless "
                  "the row says). Energy and distance against the "
                  "one-stage solve without the contacts in the preconditioner (the default's "
                  "answer; mean / max mm, after the final passes); "
                  "cage volume error mean / max %; muscle pairs overlapping at the end.", "",
                  "| scene | N | pose | solver | iterations | seconds | "
                  "x paper | converged | to tighter | energy vs one stage % | to one stage | "
                  "cage volume error % | muscle pairs | paper 500 it. s | load |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for (scene, n, label, lever, it, sec, ratio, conv, tm, tx, energy, om, ox, vm, vx,
             pairs, paper, load) in table4:
            lines.append(f"| {scene} | {n} | {label} | {lever} | {it} | "
                         f"{sec:.2f} | {ratio:.1f} | {yes[conv]} | {tm:.3f} / {tx:.2f} | "
                         f"{energy:+.2f} | {om:.2f} / {ox:.1f} | {vm:.2f} / {vx:.2f} | "
                         f"{pairs} | {paper:.2f} | {load:.2f} |")
    write_result(lines, args.out)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", choices=("thigh", "arm"),
                        default=["thigh", "arm"])
    parser.add_argument("--sizes", type=int, nargs="*", default=[20, 80],
                        help="particles per fibre of Table 1 (none: no Table 1)")
    parser.add_argument("--ratio", type=float, default=DEFAULT_CONNECTIVE_TISSUE)
    parser.add_argument("--sweep", type=float, nargs="*", default=[0, 1e-3, 3e-3, 1e-2, 3e-2, DEFAULT_CONNECTIVE_TISSUE])
    parser.add_argument("--cap", type=int, default=DEFAULT_ITERATIONS)
    parser.add_argument("--fibre-shortening", action=argparse.BooleanOptionalAction,
                        default=DEFAULT_FIBRE_SHORTENING,
                        help="the springs' rest state shortened with the pose (the filter's "
                        "FibreShortening)")
    parser.add_argument("--springs", choices=SPRING_ENERGIES, default=DEFAULT_SPRINGS)
    parser.add_argument("--contact-weight", type=float,
                        help="the contact penalty's weight (default: the spring energy's)")
    parser.add_argument("--walk-cap", type=int, default=DEFAULT_ITERATIONS,
                        help="iterations per time point of Table 3 (0: no Table 3)")
    parser.add_argument("--walk-sizes", type=int, nargs="+", default=[20],
                        help="particles per fibre of Table 3's motions")
    parser.add_argument("--walk-modes", nargs="+", choices=("cold", "warm"),
                        default=["cold", "warm"], help="Table 3's starts")
    parser.add_argument("--table1", action=argparse.BooleanOptionalAction, default=True,
                        help="Table 1 (the tissue's effect on each pose)")
    parser.add_argument("--soft-start", type=float, default=0.3,
                        help="Table 4's first-stage contact stiffness, a fraction of the full "
                        "(QuasiStaticSettings.soft_start; docs/solver-notes.md)")
    parser.add_argument("--levers", action=argparse.BooleanOptionalAction, default=True,
                        help="Table 4 (the levers on the iteration count, each alone and both)")
    parser.add_argument("--out", default="quasi_static.md",
                        help="file name in benchmarks/results/")
    main(parser.parse_args())
