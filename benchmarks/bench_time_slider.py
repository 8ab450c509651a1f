"""Benchmark of ParaView's time slider on the Muscle MSS pipeline (issue 15), in pvpython.

The plugin's pipeline (:func:`muscle_mss.plugin.pipeline.build_pipeline`, shown in a render view
as the GUI shows it) is built on the full demo thigh and elbow at N = 20 and 80 particles per
fibre, and
the animation time is stepped through time points as a user drags the time slider. Each step
updates the filters in pipeline order and then renders; per step it records the seconds of the
Rigid Pose Transform, the MSS Collision Solver (split into its iterations, from its convergence
table's ``seconds`` column, and the rest), the MVC Surface Deformer, the Volume-Error Probe and
the render, and how much of the four filters' updates ParaView spent outside the filters (its
executives, data information and the displays' bookkeeping). The first step (scene checks,
MVC weights, bone fields, kernel loads) is listed apart from the steady state (mean of the
later steps). Writes benchmarks/results/time_slider.md.

    PYTHONPATH=$PWD/plugin/shim xvfb-run -a pvpython benchmarks/bench_time_slider.py \
        [N ...] [--points K] [--scenes thigh arm]     (default: 20 80, K = 4, both scenes)
"""
import os
import sys
import tempfile
import time

import numpy as np
from paraview import simple

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_solver import machine, write_result  # noqa: E402
from bench_time_point import SCENE_LABELS, sizes_and_points, spread  # noqa: E402

from muscle_mss.filters import base, bone_sets  # noqa: E402
from muscle_mss.app.demo_folder import demo_region_scene  # noqa: E402
from muscle_mss.filters import vtk_arrays as V  # noqa: E402
from muscle_mss.filters.scene_io import write_scene  # noqa: E402
from muscle_mss.plugin.pipeline import build_pipeline, show_pipeline  # noqa: E402

STAGES = ("Rigid Pose Transform", "MSS Collision Solver", "MVC Surface Deformer",
          "Volume-Error Probe")
COLUMNS = ("pose", "solver setup", "iterations", "MVC", "probe", "render")


class FilterClock:
    """Seconds spent inside the muscle-mss filters' RequestData (wraps
    ``MuscleFilter.RequestData``): the rest of a stage's UpdatePipeline is ParaView's own work
    (its executives, data information, the displays' bookkeeping)."""

    def __init__(self):
        self.seconds = 0.0
        self.inner = base.MuscleFilter.RequestData
        clock = self

        def timed(algorithm, *args):
            start = time.perf_counter()
            try:
                return clock.inner(algorithm, *args)
            finally:
                clock.seconds += time.perf_counter() - start

        base.MuscleFilter.RequestData = timed


def slider_step(p, t, clock, first=False) -> dict:
    """Seconds of each of :data:`COLUMNS` for moving the time slider to ``t`` (``first``: the
    pipeline is shown after this update, as Apply does in the GUI), and ``ParaView``: the part
    of the four stages' updates spent outside the filters (``clock``, a :class:`FilterClock`)."""
    seconds = {}
    clock.seconds = 0.0
    for name, column in zip(STAGES, ("pose", "solver", "MVC", "probe")):
        start = time.perf_counter()
        p[name].UpdatePipeline(t)
        seconds[column] = time.perf_counter() - start
    table = p["MSS Collision Solver"].GetClientSideObject().GetOutputDataObject(1)
    seconds["iterations"] = float(V.table_columns(table)["seconds"][-1])
    seconds["solver setup"] = seconds.pop("solver") - seconds["iterations"]
    seconds["ParaView"] = (sum(seconds[k] for k in ("pose", "solver setup", "iterations", "MVC",
                                                    "probe")) - clock.seconds)
    start = time.perf_counter()
    simple.GetAnimationScene().AnimationTime = t    # before the displays exist: they ask for t
    if first:
        show_pipeline(p)
    simple.Render()
    seconds["render"] = time.perf_counter() - start
    return seconds


def main(argv=None):
    args = sizes_and_points(argv, __doc__.splitlines()[0])
    rows = []
    clock = FilterClock()
    with tempfile.TemporaryDirectory() as folder:
        for region in args.scenes:
            scene = os.path.join(folder, region)
            write_scene(demo_region_scene(region, "full"), scene)
            for n in args.sizes:
                # a fresh session for each N: the last pipeline, views and layouts removed
                for source in list(simple.GetSources().values()):
                    simple.Delete(source)
                for view in list(simple.GetViews()):
                    simple.Delete(view)
                for layout in list(simple.GetLayouts().values()):
                    simple.RemoveLayout(layout)
                bone_sets.clear_bone_cache()        # each N's first step samples the bones
                p = build_pipeline(scene, show=False, settings={"ParticlesPerFibre": n})
                times = list(p["Rigid Pose Transform"].TimestepValues)
                steps = []
                for t in [times[i] for i in spread(len(times), args.points)]:
                    steps.append(slider_step(p, t, clock, first=not steps))
                    print(f"{region} N={n} t={t:.3f}: " + ", ".join(
                        f"{k} {v:.3f}" for k, v in steps[-1].items()), flush=True)
                steady = {k: float(np.mean([s[k] for s in steps[1:]])) for k in steps[0]}
                rows.append((SCENE_LABELS[region], n, steps[0], steady, len(steps) - 1,
                             os.getloadavg()[0]))
    lines = [
        "# ParaView's time slider on the Muscle MSS pipeline (issue 15)", "",
        f"Machine: {machine()}; pvpython. Load average "
        "(1 min) after each N is given.", "",
        "Full demo thigh (13 muscles x 64 fibres, 3 bones) and elbow (7 muscles, 4 bones), "
        "lattice-26, filter defaults, the plugin's pipeline shown in a render view; "
        "`PYTHONPATH=$PWD/plugin/shim xvfb-run -a pvpython benchmarks/bench_time_slider.py`. "
        "One row per scene and N: the first step of the time slider, then the mean of the "
        "later steps (steady state); the first step's render creates the displays and the "
        "chart view as Apply does and renders once. 'around' = all but the "
        "iterations; 'of which ParaView' = the part of the four filters' updates spent outside "
        "their RequestData (ParaView's executives, data information and displays).",
        "",
        "| scene | N | step | " + " s | ".join(COLUMNS) + " s | around s | of which ParaView s "
        "| total s | load |",
        "|---|---|---|" + "---|" * (len(COLUMNS) + 4),
    ]
    for scene, n, first, steady, count, load in rows:
        for label, s in (("first", first), (f"steady ({count})", steady)):
            total = sum(s[k] for k in COLUMNS)
            lines.append(f"| {scene} | {n} | {label} | "
                         + " | ".join(f"{s[k]:.3f}" for k in COLUMNS)
                         + f" | {total - s['iterations']:.3f} | {s['ParaView']:.3f} "
                         f"| {total:.3f} | {load:.2f} |")
    write_result(lines, "time_slider.md")


if __name__ == "__main__":
    main()
