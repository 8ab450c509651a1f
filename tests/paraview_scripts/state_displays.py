"""pvpython (under xvfb-run), a fresh process: load the plugin, then STATE with its data files
under DATA_DIR, and print what the state shows: whether the fibres are visible, the chart's
series, the fibre strain chart's series, labels and values, the displacement colour range
against the data's range at two times (the state's, then the first time point), and per chart
axis whether it is logarithmic and the least value it carries. Arguments: STATE
DATA_DIR."""
import json
import sys

from paraview import simple

from muscle_mss.filters import vtk_arrays as V
from muscle_mss.plugin.pipeline import FIBRE_STRAIN_OVER_TIME, load_plugin

state, data_dir = sys.argv[1], sys.argv[2]
load_plugin()
simple.LoadState(state, data_directory=data_dir, restrict_to_data_directory=True)
views = {v.GetXMLName(): v for v in simple.GetViews()}


def shown(kind, label, port):
    """The representation in a view of ``kind`` of output ``port`` of the source registered
    as ``label``."""
    source = simple.FindSource(label)
    for view in simple.GetViews():
        if view.GetXMLName() != kind:
            continue
        for rep in view.Representations:
            inputs = rep.GetProperty("Input")
            if inputs is not None and inputs.GetNumberOfProxies() \
                    and source is not None and inputs.GetProxy(0) == source.SMProxy \
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
fibres = shown("RenderView", "MVC Surface Deformer", 1)
chart = shown("XYChartView", "MSS Collision Solver", 1)
strain = shown("XYChartView", FIBRE_STRAIN_OVER_TIME, 0)
over_time = simple.FindSource(FIBRE_STRAIN_OVER_TIME)
over_time.UpdatePipeline()
tables = [block for _, block in V.blocks(over_time.GetClientSideObject().GetOutputDataObject(0))]
strain_values = [list(V.table_columns(t)["avg(fibre_strain)"]) for t in tables]
solver = simple.FindSource("MSS Collision Solver")
solver.UpdatePipeline(state_time)
convergence = V.table_columns(solver.GetClientSideObject().GetOutputDataObject(1))


def axes(chart_rep, columns, x_name):
    """Per axis of the chart showing ``chart_rep``: whether it is logarithmic and the least
    value it carries (left: every visible series; bottom: the x column)."""
    view = next(v for v in simple.GetViews() if chart_rep in v.Representations)
    left = [float(min(columns[n])) for n in chart_rep.SeriesVisibility if n in columns]
    return {"left": [bool(view.LeftAxisLogScale), min(left)],
            "bottom": [bool(view.BottomAxisLogScale), float(min(columns[x_name]))],
            "legend": view.GetProperty("LegendLocation")[0]}


strain_columns = {name: [v for t in strain_values for v in t] for name in strain.SeriesVisibility}
strain_columns["Time"] = times
x_name = chart.XArrayName if isinstance(chart.XArrayName, str) else chart.XArrayName[0]
chart_axes = {"convergence": axes(chart, convergence, x_name),
              "strain": axes(strain, strain_columns, "Time")}
ranges = [colour_and_data_range(t) for t in (state_time, times[0])]
print("RESULT " + json.dumps({"fibres_visible": bool(fibres.Visibility),
                              "chart_series": list(chart.SeriesVisibility),
                              "strain_series": list(strain.SeriesVisibility),
                              "strain_labels": list(strain.SeriesLabel),
                              "strain_values": [[float(v) for v in t] for t in strain_values],
                              "ranges": ranges, "times": [state_time, times[0]],
                              "axes": chart_axes}))
