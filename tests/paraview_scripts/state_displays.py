"""pvpython (under xvfb-run), a fresh process: load the plugin, then STATE with its data files
under DATA_DIR, and print what the state shows: whether the fibres are visible, the chart's
series, and the displacement colour range against the data's range at two times (the
state's, then the first time point). Arguments: STATE DATA_DIR."""
import json
import sys

from paraview import simple

from muscle_mss.plugin.pipeline import load_plugin

state, data_dir = sys.argv[1], sys.argv[2]
load_plugin()
simple.LoadState(state, data_directory=data_dir, restrict_to_data_directory=True)
views = {v.GetXMLName(): v for v in simple.GetViews()}


def shown(view, label, port):
    """The representation in ``view`` of output ``port`` of the source labelled ``label``."""
    for rep in view.Representations:
        inputs = rep.GetProperty("Input")
        if inputs is not None and inputs.GetNumberOfProxies() \
                and inputs.GetProxy(0).GetXMLLabel() == label \
                and inputs.GetOutputPortForConnection(0) == port:
            return rep
    raise SystemExit(f"the state shows no output {port} of {label}")


def colour_and_data_range(t):
    scene = simple.GetAnimationScene()
    scene.AnimationTime = t
    simple.Render(views["RenderView"])
    points = simple.GetColorTransferFunction("displacement").RGBPoints
    probe = simple.FindSource("Volume-Error Probe")
    data = probe.GetDataInformation(0).GetPointDataInformation().GetArrayInformation(
        "displacement").GetComponentRange(-1)
    return [points[0], points[-4]], list(data)


times = list(simple.GetAnimationScene().TimeKeeper.TimestepValues)
state_time = simple.GetAnimationScene().AnimationTime
fibres = shown(views["RenderView"], "MVC Surface Deformer", 1)
chart = shown(views["XYChartView"], "MSS Collision Solver", 1)
ranges = [colour_and_data_range(t) for t in (state_time, times[0])]
print("RESULT " + json.dumps({"fibres_visible": bool(fibres.Visibility),
                              "chart_series": list(chart.SeriesVisibility),
                              "ranges": ranges, "times": [state_time, times[0]]}))
