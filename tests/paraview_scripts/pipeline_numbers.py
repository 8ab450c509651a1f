"""pvpython: build the pipeline with the plugin's builder, update it at the given times, and save
the deformed surfaces' points and the posed bones' points per time, and the Fibre Resampler's and
Spring Builder's output arrays, to an .npz file.
Arguments: SCENE OUT.npz TIME [TIME ...]. Prints RESULT with the TimestepValues."""
import json
import sys

import numpy as np
from paraview import simple

from muscle_mss.filters import vtk_arrays as V
from muscle_mss.plugin.pipeline import build_pipeline

scene, out, times = sys.argv[1], sys.argv[2], [float(t) for t in sys.argv[3:]]
p = build_pipeline(scene, show=False, settings={"Iterations": 60})
arrays = {}
for k, t in enumerate(times):
    for key, proxy, port in (("surfaces", p["Volume-Error Probe"], 0),
                             ("bones", p["Rigid Pose Transform"], 1)):
        proxy.UpdatePipeline(t)
        data = proxy.GetClientSideObject().GetOutputDataObject(port)
        for name, block in V.blocks(data):
            arrays[f"{key}/{k}/{name}"] = V.points_of(block)
for key, proxy in (("particles", p["Fibre Resampler"]), ("model", p["Spring Builder"])):
    proxy.UpdatePipeline()
    for name, block in V.blocks(proxy.GetClientSideObject().GetOutputDataObject(0)):
        arrays[f"{key}/{name}/points"] = V.points_of(block)
        for array, values in V.point_arrays(block).items():
            arrays[f"{key}/{name}/point/{array}"] = values
        for array in ("rest_length", "stiffness"):
            values = V.cell_array(block, array, required=False)
            if values is not None:
                arrays[f"{key}/{name}/cell/{array}"] = values
np.savez(out, **arrays)
print("RESULT " + json.dumps({
    "timesteps": list(p["Rigid Pose Transform"].TimestepValues),
    "keeper": list(simple.GetTimeKeeper().TimestepValues),
    "filters": sorted(n for n in ("FibreResampler", "SpringBuilder", "RigidPoseTransform",
                                  "MSSCollisionSolver", "MVCSurfaceDeformer", "VolumeErrorProbe")
                      if hasattr(simple, n)),
}))
