"""Volume error and attachment error of a scene at chosen time points (issue 12).

    python benchmarks/anatomy_figures.py SCENE INDEX [INDEX ...] [Property=value ...]

Solves each time point with the default settings (or the given filter properties, e.g.
``BulkModulus=50``) (the six filters of ``muscle-mss run``) and
prints, per time point and muscle, the volume error (%) and the attachment error: the distance
(mm) of each solved fixed end particle from where its attachment bone's transform carries its
rest position (bones from the ``origin_bone`` / ``insertion_bone`` field data of fibres.vtm),
mean and max over the muscle's fibre ends, the largest fibre strain, the deepest surface vertex
newly inside a bone after the MVC Surface Deformer's push, and the solve's iterations and
convergence; then the mean and max over everything. It uses only
the pipeline's outputs, so it measures any version of the filters the same way.
"""
import sys
import time

import numpy as np

from muscle_mss.core.pose import pose_at
from muscle_mss.filters import array_names as A
from muscle_mss.app import motion_run
from muscle_mss.filters import vtk_arrays as V
from muscle_mss.filters.scene_io import load_scene, read_scene


def attachment_bones(folder):
    """``{muscle: (origin bone, insertion bone)}`` from the field data of fibres.vtm."""
    fibres = read_scene(folder)[1]
    return {name: (V.field(block, "origin_bone"), V.field(block, "insertion_bone"))
            for name, block in V.blocks(fibres)}


def attachment_errors(particles, ends, bones, matrices):
    """``{muscle: (mean, max) mm}`` of the fixed end particles' distance from their bone."""
    out = {}
    for name, block in V.blocks(particles):
        rest = V.point_array(block, A.REST_POSITION)
        index = V.point_array(block, A.FIBRE_INDEX)
        fixed = V.point_array(block, A.FIXED) == 1
        last = index == index.max()
        solved = V.points_of(block)
        errors = []
        for mask, bone in ((fixed & (index == 0), ends[name][0]), (fixed & last, ends[name][1])):
            m = matrices[bones.index(bone)]
            errors.append(np.linalg.norm(solved[mask] - (rest[mask] @ m[:, :3].T + m[:, 3]), axis=1))
        errors = np.concatenate(errors)
        out[name] = (errors.mean(), errors.max())
    return out


def _value(text):
    """A property value from the command line: a number when it reads as one, else text
    (``Method=quasi-static``)."""
    try:
        return float(text)
    except ValueError:
        return text


def main(folder, indices, settings):
    scene = load_scene(folder)
    ends = attachment_bones(folder)
    bones = list(scene.bones)
    pipeline = motion_run.build_pipeline(folder, settings)
    print(f"{'t s':>6s} {'muscle':28s} {'vol err %':>9s} {'max strain':>10s} "
          f"{'attach mean mm':>14s} {'max mm':>7s} {'in bone mm':>10s} {'iters':>5s} "
          f"{'conv':>4s} {'s':>6s}")
    volume, attach, depth = [], [], []
    for i in indices:
        start = time.perf_counter()
        result = motion_run.solve_time_point(pipeline, i)
        seconds = time.perf_counter() - start
        matrices, _ = pose_at(scene.motion, result.time)
        errors = attachment_errors(result.particles, ends, bones, matrices)
        for row in result.rows:
            name = row["muscle"]
            volume.append(float(row["volume_error_pct"]))
            attach.append(errors[name])
            depth.append(float(row[A.NEW_IN_BONE_DEPTH_AFTER_MM]))
            print(f"{result.time:6.3f} {name:28s} {volume[-1]:9.2f} "
                  f"{float(row['max_fibre_strain']):10.3f} {errors[name][0]:14.3f} "
                  f"{errors[name][1]:7.3f} {depth[-1]:10.3f} {int(row['iterations']):5d} "
                  f"{int(row['converged']):4d} {seconds:6.1f}", flush=True)
    attach = np.array(attach)
    print(f"volume error % mean {np.mean(volume):.2f} max {np.max(volume):.2f} "
          f"(rows over 6 %: {int(np.sum(np.array(volume) > 6.0))} of {len(volume)}); "
          f"attachment error mm mean {attach[:, 0].mean():.3f} max {attach[:, 1].max():.3f}; "
          f"surface newly inside a bone after the push, deepest {np.nanmax(depth):.3f} mm")


if __name__ == "__main__":
    pairs = [a.split("=", 1) for a in sys.argv[2:] if "=" in a]
    main(sys.argv[1], [int(a) for a in sys.argv[2:] if "=" not in a],
         {name: _value(value) for name, value in pairs})
