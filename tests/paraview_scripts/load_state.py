"""pvpython (under xvfb-run), a fresh process: load the plugin, then STATE with its data files
looked up under DATA_DIR (muscle_mss.plugin.pipeline.load_state, which state_files/README.md
gives), and print the volume table at the state's time.
Arguments: STATE DATA_DIR."""
import json
import sys

from paraview import simple

from muscle_mss.filters import vtk_arrays as V
from muscle_mss.plugin.pipeline import load_state

state, data_dir = sys.argv[1], sys.argv[2]
load_state(state, data_directory=data_dir)
probe = simple.FindSource("Volume-Error Probe")
if probe is None:
    raise SystemExit("the state did not recreate the Volume-Error Probe")
t = simple.GetAnimationScene().AnimationTime
probe.UpdatePipeline(t)
table = V.table_columns(probe.GetClientSideObject().GetOutputDataObject(1))
print("RESULT " + json.dumps({"volume": [float(v) for v in table["volume"]],
                              "muscle": list(table["muscle"]), "time": t,
                              "iterations": simple.FindSource("MSS Collision Solver").Iterations}))
