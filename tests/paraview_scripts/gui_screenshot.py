# paraview --script: runs inside the GUI (no __file__, no argv): paths come from the environment.
# Loads MUSCLE_MSS_STATE (the plugin is auto-loaded through PV_PLUGIN_PATH), renders, and saves
# the render view to MUSCLE_MSS_SCREENSHOT.
import os

from paraview import simple

simple.LoadState(os.environ["MUSCLE_MSS_STATE"],
                 data_directory=os.environ["MUSCLE_MSS_DATA"], restrict_to_data_directory=True)
views = [v for v in simple.GetViews() if v.GetXMLName() == "RenderView"]
simple.SetActiveView(views[0])
simple.Render(views[0])
simple.SaveScreenshot(os.environ["MUSCLE_MSS_SCREENSHOT"], views[0], ImageResolution=[800, 600])
