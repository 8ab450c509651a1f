"""Benchmark of the bones' signed distance fields (core/bones/distance.py) on the full demo thigh.

For each bone of ``demo_scene(size="full")`` (pelvis, femur, tibia): triangles, the sampled box,
fine bricks kept, build seconds, memory of the sampled values and the memory a dense grid of the
same fine spacing over the same box would take (the ratio is what the narrow band saves); then
the lookup and the push-out of 1,000,000 points scattered within 10 mm of the bones' surfaces.
Kernels are compiled on a small sphere first, so the seconds are the work, not the compilation.
Prints a table with the machine and the load and writes it to benchmarks/results/bone_distance.md.

    python benchmarks/bench_bone_distance.py [SPACING_MM]        (default: the module default)
"""
from __future__ import annotations

import os
import platform
import sys
import time
from pathlib import Path

import numba
import numpy as np

from muscle_mss.core.bones import distance as D
from muscle_mss.core.bones import field_sampling as S
from muscle_mss.core.demo.scene import demo_scene

from bench_solver import cpu_model

QUERIES = 1_000_000


def warm_up():
    """Compile every kernel on an octahedron (a closed surface of 8 triangles)."""
    points = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
                      dtype=float) * 5.0
    triangles = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5],
                          [3, 1, 5], [0, 3, 5]])
    fields = S.bone_field_set([(points, triangles)])
    D.signed_distances(fields, points)
    D.push_out_of_bones(fields, points, np.ones(len(points)))


def main(spacing):
    warm_up()
    scene = demo_scene("full")
    rows, fields = [], []
    for name, bone in scene.bones.items():
        start = time.perf_counter()
        field = S.bone_distance_field(bone.points, bone.triangles, spacing=spacing,
                                      where=f"bone '{name}'")
        seconds = time.perf_counter() - start
        fields.append(field)
        dense = int(np.prod(field.dims * D.BRICK + 1)) * 4
        rows.append((name, len(bone.triangles), field.dims * D.BRICK * field.spacing,
                     len(field.bricks), int(np.prod(field.dims)), seconds, field.nbytes, dense,
                     os.getloadavg()[0]))
        print(f"{name}: {seconds:.2f} s, {field.nbytes / 2**20:.1f} MiB", flush=True)
    packed = D.BoneFieldSet.pack(fields, list(scene.bones))
    rng = np.random.default_rng(0)
    surfaces = [bone.points for bone in scene.bones.values()]
    every = np.concatenate(surfaces)
    queries = every[rng.integers(0, len(every), QUERIES)] + rng.uniform(-10, 10, (QUERIES, 3))
    start = time.perf_counter()
    distance, _ = D.signed_distances(packed, queries)
    lookup = time.perf_counter() - start
    start = time.perf_counter()
    D.push_out_of_bones(packed, queries, np.full(QUERIES, 2.0))
    push = time.perf_counter() - start
    inside = int((distance < 0).any(axis=1).sum())

    lines = [
        "# Bone signed distance fields (full demo thigh)", "",
        f"Machine: {cpu_model()}, {os.cpu_count()} cores, numba {numba.__version__} "
        f"({numba.get_num_threads()} threads), numpy {np.__version__}, Python "
        f"{platform.python_version()}. Fine spacing {spacing:g} mm, bricks of {D.BRICK}^3 cells, "
        f"coarse nodes every {D.COARSE * spacing:g} mm, band {S.DEFAULT_BAND:g} mm, padding "
        f"{S.DEFAULT_PADDING:g} mm, float32 values. Load average (1 min) after each build.", "",
        "| bone | triangles | box (mm) | fine bricks | bricks in box | build s | memory MiB | "
        "dense grid MiB | dense / sparse | load |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, tris, box, kept, total, seconds, memory, dense, load in rows:
        lines.append(f"| {name} | {tris} | {' x '.join(f'{v:.0f}' for v in box)} | {kept} | "
                     f"{total} | {seconds:.2f} | {memory / 2**20:.1f} | {dense / 2**20:.1f} | "
                     f"{dense / memory:.1f}x | {load:.2f} |")
    lines += [
        "",
        f"Lookup (value + gradient) of {QUERIES:,} points within 10 mm of the bones, against "
        f"all {len(fields)} bones: {lookup:.3f} s ({lookup / QUERIES / len(fields) * 1e9:.0f} ns "
        f"per point and bone); push out with a 2 mm radius ({inside:,} of them inside a bone): "
        f"{push:.3f} s. Load {os.getloadavg()[0]:.2f}.",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    out = Path(__file__).parent / "results" / "bone_distance.md"
    out.write_text(text)


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else S.DEFAULT_SPACING)
