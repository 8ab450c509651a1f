"""pvpython: build the pipeline with the plugin's builder and the given property settings, update
the Volume-Error Probe at a time; the filters' messages go to stderr (ParaView's output messages).
Arguments: SCENE SETTINGS_JSON TIME. Prints RESULT with the probe's number of output blocks."""
import json
import sys

from muscle_mss.plugin.pipeline import build_pipeline

scene, settings, time = sys.argv[1], json.loads(sys.argv[2]), float(sys.argv[3])
p = build_pipeline(scene, show=False, settings=settings)
probe = p["Volume-Error Probe"]
probe.UpdatePipeline(time)
data = probe.GetClientSideObject().GetOutputDataObject(0)
print("RESULT " + json.dumps({"probe_blocks": data.GetNumberOfBlocks()}))
