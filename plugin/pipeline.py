"""Build the whole Muscle MSS pipeline on a scene folder in ParaView (DESIGN §7).

In ParaView's Python shell, pvpython or a ``paraview --script``::

    from muscle_mss.plugin.pipeline import build_pipeline
    build_pipeline("demo_out/scene")

creates the scene's readers and the six filters wired together, shows bones in white, the deformed
muscles coloured by displacement and the fibres by strain, and the solver's convergence table in a
line chart (the paper's figures 5 and 6). File names are kept as given, so a relative scene path
makes a state file that opens from any checkout (``state_files/``). The plugin is loaded if needed.
Command line: ``pvpython -m muscle_mss.plugin.pipeline SCENE STATE.pvsm`` saves such a state.
"""
import os
import sys

from muscle_mss.core.attachment_areas import ATTACHMENTS_FILE
from muscle_mss.filters import array_names as A

PLUGIN_FILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "paraview_plugins",
                           "muscle_mss_plugin.py")
PIPELINE_NAMES = ("Fibre Resampler", "Spring Builder", "Rigid Pose Transform",
                  "MSS Collision Solver", "MVC Surface Deformer", "Volume-Error Probe")


def load_plugin():
    """Load the Muscle MSS plugin into this ParaView session unless it is loaded already."""
    from paraview import simple
    if not hasattr(simple, "FibreResampler"):
        simple.LoadPlugin(PLUGIN_FILE, ns=vars(simple))


def state_file_names(state_file) -> dict:
    """``{source name: [file names]}`` of the readers a state file creates, as it stores them
    (relative names stay relative)."""
    import xml.etree.ElementTree as ET
    root = ET.parse(state_file).getroot()
    names = {item.get("id"): item.get("name")
             for collection in root.iter("ProxyCollection") if collection.get("name") == "sources"
             for item in collection.iter("Item")}
    files = {}
    for proxy in root.iter("Proxy"):
        if proxy.get("group") != "sources" or proxy.get("id") not in names:
            continue
        for prop in proxy.findall("Property"):
            if prop.get("name") == "FileName":
                files[names[proxy.get("id")]] = [e.get("value") for e in prop.findall("Element")]
    return files


def load_state(state_file, data_directory=None, **options):
    """Load the plugin, then the state file ``state_file`` with its data files looked up under
    ``data_directory`` (``LoadState``'s, restricted to that folder when given; other ``options``
    go to ``LoadState``).

    Raise :class:`~muscle_mss.core.errors.MuscleMSSError` naming the first file of the state
    that its reader cannot read: ParaView's ``LoadState`` prints its readers' errors and
    carries on, so that a script would exit 0 with every filter's output empty."""
    from paraview import simple
    from muscle_mss.core.errors import MuscleMSSError
    saved = state_file_names(state_file)
    load_plugin()
    if data_directory is not None:
        options = {"data_directory": data_directory, "restrict_to_data_directory": True,
                   **options}
    simple.LoadState(state_file, **options)
    for (name, _), proxy in sorted(simple.GetSources().items()):
        if "FileName" not in proxy.ListProperties():
            continue
        files = proxy.FileName
        files = [files] if isinstance(files, str) else list(files)
        for k, path in enumerate(files):
            if path and os.path.isfile(path) and os.access(path, os.R_OK):
                continue
            stored = saved.get(name, files)[k] if k < len(saved.get(name, files)) else path
            if data_directory is not None:
                why = f"not found under the data folder {data_directory}"
            elif not os.path.exists(path):
                why = f"{os.path.abspath(path)} does not exist"
            else:
                why = f"{os.path.abspath(path)} cannot be read"
            raise MuscleMSSError(
                f"{state_file}: reader {name!r} reads {stored}: {why}; load the state with its "
                "data folder, load_state(STATE, data_directory=FOLDER) with FOLDER holding "
                f"{stored} (see state_files/README.md)")


def build_pipeline(scene_folder, show=True, settings=None):
    """Create readers and filters for ``scene_folder``; return them by name.

    ``settings`` maps property names to values (as ``paraview.simple`` names them), set on
    every filter having that property. With ``show`` the results are shown in the active render
    view and a line chart of the convergence table is added beside it.
    """
    from paraview import simple
    from muscle_mss.filters.scene_io import load_scene
    # the checks ParaView's readers do not make (a block whose .vtp is missing or cut, an empty
    # motion.csv cell read as 0), as muscle-mss validate makes them: refused before building
    load_plugin()       # first: it chooses how the kernels run their threads in ParaView
    scene = load_scene(scene_folder)
    path = lambda name: os.path.join(scene_folder, name)  # noqa: E731  (kept relative if given so)
    p = {}
    p["muscles"] = simple.XMLMultiBlockDataReader(registrationName="muscles.vtm",
                                                  FileName=[path("muscles.vtm")])
    p["fibres"] = simple.XMLMultiBlockDataReader(registrationName="fibres.vtm",
                                                 FileName=[path("fibres.vtm")])
    p["bones"] = simple.XMLMultiBlockDataReader(registrationName="bones.vtm",
                                                FileName=[path("bones.vtm")])
    p["motion"] = simple.CSVReader(registrationName="motion.csv", FileName=[path("motion.csv")])
    p["Fibre Resampler"] = simple.FibreResampler(registrationName="Fibre Resampler",
                                                 Fibres=p["fibres"], Bones=p["bones"])
    if os.path.isfile(path(ATTACHMENTS_FILE)):
        p["attachments"] = simple.CSVReader(registrationName=ATTACHMENTS_FILE,
                                            FileName=[path(ATTACHMENTS_FILE)],
                                            DetectNumericColumns=0)
        p["Fibre Resampler"].Attachments = p["attachments"]
    p["Spring Builder"] = simple.SpringBuilder(registrationName="Spring Builder",
                                               Particles=p["Fibre Resampler"],
                                               Surfaces=p["muscles"], Bones=p["bones"])
    p["Rigid Pose Transform"] = simple.RigidPoseTransform(
        registrationName="Rigid Pose Transform", Model=p["Spring Builder"], Bones=p["bones"],
        Motion=p["motion"], Surfaces=p["muscles"])
    pose = p["Rigid Pose Transform"]
    p["MSS Collision Solver"] = simple.MSSCollisionSolver(
        registrationName="MSS Collision Solver", PosedModel=simple.OutputPort(pose, 0),
        PosedBones=simple.OutputPort(pose, 1))
    solver = p["MSS Collision Solver"]
    p["MVC Surface Deformer"] = simple.MVCSurfaceDeformer(
        registrationName="MVC Surface Deformer", SolvedModel=simple.OutputPort(solver, 0),
        RestSurfaces=p["muscles"], RestModel=p["Spring Builder"], RestBones=p["bones"],
        PosedBones=simple.OutputPort(pose, 1))
    p["Volume-Error Probe"] = simple.VolumeErrorProbe(
        registrationName="Volume-Error Probe",
        DeformedSurfaces=simple.OutputPort(p["MVC Surface Deformer"], 0),
        RestSurfaces=p["muscles"])
    for name, value in (settings or {}).items():
        owners = [p[n] for n in PIPELINE_NAMES if name in p[n].ListProperties()]
        if not owners:
            raise KeyError(f"no Muscle MSS filter has a property {name!r}")
        for proxy in owners:
            setattr(proxy, name, value)
    simple.GetAnimationScene().UpdateAnimationUsingDataTimeSteps()
    if show:
        show_pipeline(p)
        fibre_strain_chart(p, list(scene.muscles))
    return p


def show_pipeline(p):
    """Displays: posed bones white, deformed muscles by displacement, fibres by strain, and the
    convergence table in a line chart."""
    from paraview import simple
    view = simple.GetActiveViewOrCreate("RenderView")
    bones = simple.Show(simple.OutputPort(p["Rigid Pose Transform"], 1), view)
    bones.ColorArrayName = ["POINTS", ""]  # solid colour (ColorBy(rep, None) fails in 5.11)
    bones.AmbientColor = bones.DiffuseColor = [1.0, 1.0, 1.0]
    muscles = simple.Show(simple.OutputPort(p["Volume-Error Probe"], 0), view)
    simple.ColorBy(muscles, ("POINTS", "displacement", "Magnitude"))
    _rescale_every_time(muscles, "displacement")
    muscles.SetScalarBarVisibility(view, True)
    fibre_port = simple.OutputPort(p["MVC Surface Deformer"], 1)
    fibres = simple.Show(fibre_port, view)
    simple.ColorBy(fibres, ("CELLS", "fibre_strain"))
    _rescale_every_time(fibres, "fibre_strain")
    fibres.LineWidth = 2.0
    simple.Hide(fibre_port, view)  # inside the muscles; switch on with the eye in the browser
    frame_muscles(p, view)

    layout = simple.GetLayout(view)
    chart = simple.CreateView("XYChartView")
    simple.AssignViewToLayout(view=chart, layout=layout, hint=0)
    table = simple.Show(simple.OutputPort(p["MSS Collision Solver"], 1), chart)
    table.UseIndexForXAxis = 0
    table.XArrayName = A.ITERATION
    series = convergence_series(p["MSS Collision Solver"])
    table.SeriesVisibility = series
    # the muscle's name alone: a narrower legend beside the plot
    table.SeriesLabel = [text for name in series
                         for text in (name, name[len(A.MEAN_DISPLACEMENT):])]
    chart.LeftAxisTitle = "mean displacement (mm)"
    chart.BottomAxisTitle = A.ITERATION
    # linear: a quasi-static solve's last rows reach 0 mm, which a log axis cannot show
    # (ParaView covers the chart with "One or more plot series crosses or contains an axis
    # origin")
    chart.LeftAxisLogScale = 0
    chart.LegendLocation = LEGEND_LOCATION
    simple.SetActiveView(view)
    return view, chart


LEGEND_LOCATION = "Right"
"""Where the charts' legends go: beside the plot, right of it, not over the curves."""


def frame_muscles(p, view):
    """Point the camera from the front-right at the deformed muscles at the time shown and
    zoom to them (the bones reach far beyond them)."""
    from paraview import simple
    probe = p["Volume-Error Probe"]
    probe.UpdatePipeline(simple.GetAnimationScene().AnimationTime)
    bounds = probe.GetDataInformation(0).GetBounds()
    # the view's representations updated, as ResetCamera() without bounds does: the colour
    # ranges that follow the time rescale from them (without, a state saved after moving the
    # time kept the first time's range)
    view.Update()
    view.CameraPosition = [900.0, -1400.0, 300.0]
    view.CameraFocalPoint = [0.0, 0.0, -250.0]
    view.CameraViewUp = [0.0, 0.0, 1.0]
    if bounds[0] <= bounds[1]:
        view.ResetCamera(*bounds)
    else:
        view.ResetCamera()


FIBRE_STRAIN_OVER_TIME = "Mean fibre strain over time"


def fibre_strain_series(muscles) -> list:
    """The series of :data:`FIBRE_STRAIN_OVER_TIME`'s chart: each muscle's mean fibre strain,
    as ParaView names it (Plot Data Over Time on the fibres, one table per block, flat index
    1, 2, ... in muscle order)."""
    return [f"avg({A.FIBRE_STRAIN}) ( block={k})" for k in range(1, len(muscles) + 1)]


def fibre_strain_chart(p, muscles):
    """A line chart of each muscle's mean fibre strain over the whole motion (Plot Data Over
    Time on the MVC Surface Deformer's fibres, statistics per block), a line per muscle
    labelled by its name: the fibre-length study of ``muscle-mss study`` in ParaView. It
    solves every time point when first shown."""
    from paraview import simple
    view = simple.GetActiveView()
    layout = simple.GetLayout(view)
    # only the strain: statistics of every array make ~700 series, 1.4 MB of state
    strain = simple.PassArrays(registrationName="Fibre strain",
                               Input=simple.OutputPort(p["MVC Surface Deformer"], 1),
                               PointDataArrays=[], CellDataArrays=[A.FIBRE_STRAIN],
                               FieldDataArrays=[])
    plot = simple.PlotDataOverTime(registrationName=FIBRE_STRAIN_OVER_TIME, Input=strain)
    plot.OnlyReportSelectionStatistics = 1
    plot.FieldAssociation = "Cells"
    chart = simple.CreateView("XYChartView")
    simple.AssignViewToLayout(view=chart, layout=layout, hint=0)
    lines = simple.Show(plot, chart)
    lines.CompositeDataSetIndex = list(range(1, len(muscles) + 1))
    series = fibre_strain_series(muscles)
    lines.SeriesVisibility = series
    lines.SeriesLabel = [text for pair in zip(series, muscles) for text in pair]
    chart.LeftAxisTitle = f"mean {A.FIBRE_STRAIN} (length / rest length - 1)"
    chart.BottomAxisTitle = "time (s)"
    chart.LegendLocation = LEGEND_LOCATION
    p[FIBRE_STRAIN_OVER_TIME] = plot
    simple.SetActiveView(view)
    return chart


def _rescale_every_time(display, array):
    """Colour ``display`` by a range that follows the data at every time shown (a range fixed
    at the first time shown hides larger values later in the motion, e.g. 0-42 mm of 433)."""
    from paraview import simple
    display.RescaleTransferFunctionToDataRange(True, False)
    simple.GetColorTransferFunction(array).AutomaticRescaleRangeMode = \
        "Clamp and update every timestep"


def convergence_series(solver):
    """The convergence table's columns to plot: every muscle's mean displacement."""
    from paraview import simple
    solver.UpdatePipeline(simple.GetAnimationScene().AnimationTime)
    names = solver.GetDataInformation(1).GetRowDataInformation()
    return [names.GetArrayInformation(i).GetName() for i in range(names.GetNumberOfArrays())
            if names.GetArrayInformation(i).GetName().startswith(A.MEAN_DISPLACEMENT)]


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2:
        print("usage: pvpython -m muscle_mss.plugin.pipeline SCENE STATE.pvsm", file=sys.stderr)
        return 2
    from paraview import simple
    from muscle_mss.core.motion import farthest_pose_index
    from muscle_mss.filters.scene_io import load_scene
    scene, state = argv
    motion = load_scene(scene).motion
    p = build_pipeline(scene)
    simple.GetAnimationScene().AnimationTime = motion.times[farthest_pose_index(motion)]
    simple.Render()     # pvpython's first render resets the camera to every object shown
    frame_muscles(p, simple.GetActiveView())
    simple.Render()
    simple.SaveState(state)
    print(f"saved {state}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
