"""The shipped state opened right after ``./demo.sh``: seconds from pvpython's ``LoadState`` to
the first rendered view and to every view rendered (both charts filled: the convergence chart
and each muscle's mean fibre strain over the whole motion, 21 frames), the MSS Collision
Solver's frames loaded from the frame cache and solved (and the MVC Surface Deformer's deformed
surfaces loaded and computed), and one cached frame through the solver's update alone (its
inputs updated first, nothing rendered).

Run from the checkout root after ``./demo.sh`` (which fills the user's frame cache):

    PYTHONPATH=$PWD/plugin/shim PV_PLUGIN_PATH=$PWD/plugin/paraview_plugins \\
        xvfb-run -a pvpython benchmarks/bench_state_open.py [STATE [DATA_DIR]]

Prints one line ``RESULT <json>``; the figures are recorded by hand in
benchmarks/results/review.md with the machine and its load (a shared machine's seconds vary).
"""
import json
import os
import sys
import time

STARTED = time.perf_counter()

from paraview import simple  # noqa: E402

from muscle_mss.plugin.pipeline import FIBRE_STRAIN_OVER_TIME, load_state  # noqa: E402


def main() -> None:
    state = sys.argv[1] if len(sys.argv) > 1 else "state_files/demo_walk.pvsm"
    data = sys.argv[2] if len(sys.argv) > 2 else "demo_out"
    load = os.getloadavg()[0]
    imported = time.perf_counter()
    load_state(state, data_directory=data)
    loaded = time.perf_counter()
    views = {v.GetXMLName(): v for v in simple.GetViews()}
    simple.Render(views["RenderView"])
    first = time.perf_counter()
    for view in simple.GetViews():
        simple.Render(view)
    every = time.perf_counter()
    solver = simple.FindSource("MSS Collision Solver")
    counts = dict(solver.GetClientSideObject().frame_counts)
    surfaces = dict(simple.FindSource("MVC Surface Deformer").GetClientSideObject().frame_counts)
    strain = simple.FindSource(FIBRE_STRAIN_OVER_TIME)
    rows = strain.GetDataInformation(0).GetNumberOfRows() if strain is not None else 0
    # one cached frame through the solver alone: a time the state has not shown yet
    times = list(simple.GetAnimationScene().TimeKeeper.TimestepValues)
    t = times[3]
    simple.FindSource("Rigid Pose Transform").UpdatePipeline(t)
    start = time.perf_counter()
    solver.UpdatePipeline(t)
    cached_frame = time.perf_counter() - start
    after = dict(solver.GetClientSideObject().frame_counts)
    print("RESULT " + json.dumps({
        "import_s": round(imported - STARTED, 2), "load_state_s": round(loaded - imported, 2),
        "first_render_s": round(first - imported, 2), "every_view_s": round(every - imported, 2),
        "frames": counts, "surfaces": surfaces, "strain_rows": rows, "cached_frame_s": round(cached_frame, 3),
        "cached_frame_loaded": after["loaded"] - counts["loaded"], "load_average": load,
        "frame_cache": solver.FrameCache or "(empty: the user's frame cache)"}))


main()
