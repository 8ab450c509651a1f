"""pvpython, a fresh process: the plugin's pipeline on SCENE (muscle_mss.plugin.pipeline,
nothing shown) with the solver's Iterations ITERATIONS and FrameCache VALUE (a folder, "off",
or "-": left empty, the property's default), updated at its first COUNT time points (all: 0),
and print the solver's counts of frames loaded and solved, the volume errors and the seconds of
the solver's updates at each time (the upstream filters updated first), and Numba's threading
layer.
Arguments: SCENE ITERATIONS VALUE COUNT."""
import json
import sys
import time

from paraview import simple

from muscle_mss.filters import vtk_arrays as V
from muscle_mss.plugin.pipeline import build_pipeline

scene, iterations, value, count = sys.argv[1], int(sys.argv[2]), sys.argv[3], int(sys.argv[4])
settings = {"Iterations": iterations}
if value != "-":
    settings["FrameCache"] = value
p = build_pipeline(scene, show=False, settings=settings)
solver, pose, probe = p["MSS Collision Solver"], p["Rigid Pose Transform"], p["Volume-Error Probe"]
times = list(simple.GetAnimationScene().TimeKeeper.TimestepValues)
seconds, volume = [], []
for t in times[:count or len(times)]:
    pose.UpdatePipeline(t)
    start = time.perf_counter()
    solver.UpdatePipeline(t)
    seconds.append(time.perf_counter() - start)
    probe.UpdatePipeline(t)
    volume.append(list(V.table_columns(probe.GetClientSideObject().GetOutputDataObject(1))
                       ["volume_error_pct"]))
import numba  # noqa: E402
print("RESULT " + json.dumps({"counts": solver.GetClientSideObject().frame_counts,
                              "threading_layer": numba.threading_layer(),
                              "frame_cache": solver.FrameCache, "seconds": seconds,
                              "volume": volume}))
