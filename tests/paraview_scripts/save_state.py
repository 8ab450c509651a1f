"""pvpython (under xvfb-run): build the pipeline on SCENE (path kept as given), go to TIME, save
STATE and print the volume table. Arguments: SCENE STATE TIME."""
import json
import sys

from paraview import simple

from muscle_mss.filters import vtk_arrays as V
from muscle_mss.plugin.pipeline import build_pipeline

scene, state, t = sys.argv[1], sys.argv[2], float(sys.argv[3])
p = build_pipeline(scene, settings={"Iterations": 60})
simple.GetAnimationScene().AnimationTime = t
simple.Render()
probe = p["Volume-Error Probe"]
probe.UpdatePipeline(t)
table = V.table_columns(probe.GetClientSideObject().GetOutputDataObject(1))
simple.SaveState(state)
print("RESULT " + json.dumps({"volume": [float(v) for v in table["volume"]],
                              "muscle": list(table["muscle"])}))
