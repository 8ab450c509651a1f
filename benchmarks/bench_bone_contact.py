"""Benchmark of the muscle-bone contact: bones as sphere sets (the paper) vs as solids (issue 14).

1. Contact time on the paper's workload (bench_solver.py's: the full demo thigh, 13 muscles x 64
   fibres, lattice-26, the paper's bone sphere counts 8527 / 1568 / 1709, 500 iterations of the
   paper relaxation, spatial hash) at N = 20 and 80, at the walking pose (a third into the
   motion, as Table 1) and at the most flexed pose: seconds of the whole solve (the median of
   three) and of its muscle-bone contacts, for the sphere sets, for the solids (each bone's
   signed distance field, core/bones/distance.py) against the spheres only (the same work as
   the sphere sets) and for the solids against every free particle not inside a bone at rest
   (the default); and the one-off sampling of each representation (once per bone shape: both
   are cached and moved with the bone).
2. What a user sees: both demo scenes (full) at their most flexed pose through the six filters
   (``muscle-mss run``'s pipeline, defaults, N = 20), for each method and BoneContact: free
   (non-tendon) particles whose centre ends inside a bone they were outside of at rest, and the
   deepest (goal 0), all free particles inside a bone (those embedded at rest included), the
   deepest sphere overlap left, and the mean / max volume error.

Prints the table with the machine and the load and writes benchmarks/results/bone_contact.md.

    python benchmarks/bench_bone_contact.py [--sizes 20 80]
"""
from __future__ import annotations

import argparse
import os
from dataclasses import replace
import tempfile
import time

import numpy as np

from muscle_mss.core import solver as S
from muscle_mss.core.bones.field_sampling import bone_distance_field
from muscle_mss.core.bones.spheres import bone_spheres
from muscle_mss.core.demo.arm import demo_arm_scene
from muscle_mss.core.demo.scene import demo_scene
from muscle_mss.core.model import Bones, prepare
from muscle_mss.core.motion import farthest_pose_index
from muscle_mss.core.contacts.solid_contacts import solid_points
from muscle_mss.core.settings import METHOD_RELAXATION, SolverSettings
from muscle_mss.filters.bone_sets import solid_bones
from muscle_mss.core.settings import BONE_CONTACT_SOLID, BONE_CONTACT_SPHERES
from muscle_mss.app.motion_run import build_pipeline, solve_time_point, update_at
from muscle_mss.filters.scene_io import write_scene

from bench_solver import (BONE_COUNTS, ITERATIONS, REPEATS, machine, posed_workload,
                          write_result)

CONTACTS = (BONE_CONTACT_SPHERES, BONE_CONTACT_SOLID)
METHODS = ("paper relaxation", "quasi-static")
PAPER_SETTINGS = SolverSettings.build(method=METHOD_RELAXATION, iterations=ITERATIONS,
                                      connective_tissue=0.0, fibre_shortening=False)
"""The paper's method and model (no connective tissue), whatever the defaults."""


def median_solve(model, prepared, bones):
    """``(median total s, its MSS s, its muscle-bone CD s, bone contacts in the last
    iteration)`` of :data:`REPEATS` paper solves."""
    runs = []
    for _ in range(REPEATS):
        tick = time.perf_counter()
        result = S.solve(model, bones, PAPER_SETTINGS, prepared=prepared)
        runs.append((time.perf_counter() - tick, result.phase_seconds["mss"],
                     result.phase_seconds["bone_cd"], int(result.bone_pairs[-1])))
    return sorted(runs)[len(runs) // 2]


def sampling_seconds(scene):
    """One-off seconds to sample the thigh's bones into the paper's sphere counts and into
    distance fields."""
    tick = time.perf_counter()
    for name, bone in scene.bones.items():
        bone_spheres(bone.points, bone.triangles, count=BONE_COUNTS[name])
    spheres = time.perf_counter() - tick
    tick = time.perf_counter()
    for name, bone in scene.bones.items():
        bone_distance_field(bone.points, bone.triangles, where=name)
    return spheres, time.perf_counter() - tick


def contact_rows(folder, scene, sizes):
    poses = (("walking", len(scene.motion.times) // 3),
             ("most flexed", farthest_pose_index(scene.motion)))
    rows = []
    for n in sizes:
        pipeline = build_pipeline(folder, {"ParticlesPerFibre": n + 1, "Randomise": True})
        for label, index in poses:
            t = float(scene.motion.times[index])
            model, bones = posed_workload(folder, t, n)
            solids = solid_bones(update_at(pipeline.pose, 1, t))
            prepared = prepare(model)
            spheres_only = replace(model, in_bone_at_rest=None)
            prepared_spheres = prepare(spheres_only)
            for kind in (bones, Bones(solids=solids)):    # compiled, warm
                S.solve(model, kind, SolverSettings.build(method=METHOD_RELAXATION, iterations=2,
                                                          fibre_shortening=False),
                        prepared=prepared)
            spheres = median_solve(model, prepared, bones)
            row = [n, label, t, len(solid_points(prepared_spheres)),
                   len(solid_points(prepared)), spheres[0], spheres[2], spheres[3]]
            for m, p in ((spheres_only, prepared_spheres), (model, prepared)):
                total, mss, bone_cd, pairs = median_solve(m, p, Bones(solids=solids))
                # the solid contacts run in the MSS step's parallel region: their cost is
                # the MSS time above the sphere-set solve's (the same model, the same steps)
                row += [total, mss - spheres[1] + bone_cd, pairs]
            rows.append((*row, os.getloadavg()[0]))
            print(rows[-1], flush=True)
    return rows


def user_rows(scenes):
    rows = []
    for region, folder, scene in scenes:
        index = farthest_pose_index(scene.motion)
        for method in METHODS:
            for contact in CONTACTS:
                pipeline = build_pipeline(folder, {"Method": method, "BoneContact": contact})
                tick = time.perf_counter()
                result = solve_time_point(pipeline, index)
                seconds = time.perf_counter() - tick
                r = result.rows
                rows.append((
                    region, float(scene.motion.times[index]), method, contact,
                    sum(row["free_particles_new_in_bone"] for row in r),
                    max(row["free_particle_new_in_bone_depth_mm"] for row in r),
                    sum(row["free_particles_in_bone"] for row in r),
                    max(row["free_particle_bone_depth_mm"] for row in r),
                    max(row["sphere_overlap_mm"] for row in r),
                    float(np.mean([abs(row["volume_error_pct"]) for row in r])),
                    max(abs(row["volume_error_pct"]) for row in r),
                    seconds, os.getloadavg()[0]))
                print(rows[-1], flush=True)
    return rows


def main(args):
    thigh = demo_scene("full")
    arm = demo_arm_scene("full")
    folders = {}
    for region, scene in (("thigh", thigh), ("arm", arm)):
        folders[region] = tempfile.mkdtemp(prefix=f"bench_contact_{region}_")
        write_scene(scene, folders[region])
    sample_spheres, sample_fields = sampling_seconds(thigh)
    contacts = contact_rows(folders["thigh"], thigh, args.sizes)
    users = user_rows([("thigh", folders["thigh"], thigh), ("arm", folders["arm"], arm)])

    lines = [
        "# Muscle-bone contact: sphere sets vs solids (issue 14)", "",
        f"Machine: {machine()}. The machine is shared: the load average (1 min) after "
        "each row is given.", "",
        "## Contact time on the paper's workload", "",
        f"Full demo thigh, paper relaxation, {ITERATIONS} iterations, spatial hash, the paper's "
        "bone sphere counts (8527 / 1568 / 1709) for the sphere sets. Seconds are the median "
        f"of {REPEATS} solves. Contact: muscle-bone detection and response in the iterations; "
        "for the solids, which run inside the MSS step's parallel region (a region of their own "
        "costs a thread wake-up), the MSS step's time above the sphere-set solve's. Contacts: "
        "particle-bone contacts in the last iteration. Solid, spheres: the solids against the "
        "muscle spheres only (the sphere sets' work); solid, all: against every free particle "
        "not inside a bone at rest, spheres or not (the default). Sampling (once per bone "
        f"shape, then cached and moved with the bone): sphere sets {sample_spheres:.2f} s, "
        f"distance fields {sample_fields:.2f} s for the three bones.", "",
        "| N | pose | t s | spheres / all free particles | sphere set: total s | contact s | "
        "contacts | solid, spheres: total s | contact s | contacts | solid, all: total s | "
        "contact s | contacts | total solid all / sphere set | load |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for (n, label, t, n_spheres, n_all, s_total, s_contact, s_pairs, o_total, o_contact,
         o_pairs, a_total, a_contact, a_pairs, load) in contacts:
        lines.append(f"| {n} | {label} | {t:.2f} | {n_spheres} / {n_all} | {s_total:.2f} | "
                     f"{s_contact:.3f} | {s_pairs} | {o_total:.2f} | {o_contact:.3f} | "
                     f"{o_pairs} | {a_total:.2f} | {a_contact:.3f} | {a_pairs} | "
                     f"{a_total / s_total:.2f} | {load:.2f} |")
    lines += ["", "The MSS Collision Solver's default is `BoneContact = solid` (against every free "
              "particle not inside a bone at rest)."]
    lines += [
        "", "## Free particles inside bones at the most flexed pose", "",
        "Both demo scenes (full), the six filters at their defaults (N = 20, lattice-26, "
        "500 iterations cap), one time point. New in bone: free particles whose centre ends "
        "inside a bone that they were not inside of at rest (goal 0); all: every free particle "
        "inside a bone (particles embedded in their attachment bone at rest included); both "
        "deeper than 0.001 mm, by the bones' distance fields (the solver's field data, "
        "summary.csv's free_particle* columns). Sphere overlap: the deepest left between "
        "spheres of different muscles and of a muscle sphere with a bone as the solver sees it "
        "(summary.csv's sphere_overlap_mm). Seconds: the whole time point (pose, solve, MVC, "
        "statistics).", "",
        "| scene | t s | method | BoneContact | new in bone | deepest mm | all in bone | "
        "deepest mm | sphere overlap mm | volume error mean / max % | s | load |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for (region, t, method, contact, new, new_depth, every, depth, overlap, mean, worst,
         seconds, load) in users:
        lines.append(f"| {region} | {t:.2f} | {method} | {contact} | {new} | {new_depth:.2f} | "
                     f"{every} | {depth:.2f} | {overlap:.3f} | {mean:.2f} / {worst:.2f} | "
                     f"{seconds:.1f} | {load:.2f} |")
    write_result(lines, "bone_contact.md")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[20, 80])
    main(parser.parse_args())
