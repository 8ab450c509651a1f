"""pvpython (under xvfb-run), a fresh process in a folder without the state's data: load the
plugin and STATE as a user would, then update the Volume-Error Probe at 0.5 s.
Arguments: STATE HOW, HOW one of ``LoadState`` (ParaView's own, which prints its readers' errors
and carries on), ``LoadState-empty`` (the same with ``data_directory`` an empty folder, which
leaves the readers without file names) and ``load_state``
(:func:`muscle_mss.plugin.pipeline.load_state`, which raises).
Prints RESULT with the probe's number of output blocks."""
import json
import os
import sys

from paraview import simple

from muscle_mss.plugin.pipeline import load_plugin, load_state

state, how = sys.argv[1], sys.argv[2]
if how == "load_state":
    load_state(state)
else:
    load_plugin()
    if how == "LoadState-empty":
        os.makedirs("empty", exist_ok=True)
        simple.LoadState(state, data_directory="empty", restrict_to_data_directory=True)
    else:
        simple.LoadState(state)
probe = simple.FindSource("Volume-Error Probe")
probe.UpdatePipeline(0.5)
data = probe.GetClientSideObject().GetOutputDataObject(0)
print("RESULT " + json.dumps({"probe_blocks": data.GetNumberOfBlocks()}))
