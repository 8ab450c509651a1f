"""The Muscle MSS ParaView plugin: the six filters of muscle-mss in a "Muscle MSS" menu.

Load it with Tools > Manage Plugins > Load New…, ``LoadPlugin(path)`` in pvpython, or by putting
this folder on ``PV_PLUGIN_PATH`` (keep the folder free of other ``.py`` files: ParaView loads
every one as a plugin). With Debian's ParaView 5.11 on Python 3.11, ``plugin/shim`` must be on
``PYTHONPATH`` (see the README). The filters themselves live in ``muscle_mss.filters``; the
proxies are generated from their property tables in ``muscle_mss.plugin.paraview_proxies``.
"""
import os
import runpy

try:
    import muscle_mss.plugin.paraview_proxies  # noqa: F401  (installed, or the shim ran)
except ImportError:
    # Loaded straight from a checkout without the shim: let the shim map muscle_mss to it.
    runpy.run_path(os.path.join(os.path.dirname(os.path.abspath(__file__)), os.pardir,
                                "shim", "sitecustomize.py"))

from muscle_mss.plugin.paraview_proxies import *  # noqa: E402,F401,F403

paraview_plugin_name = "Muscle MSS"
paraview_plugin_version = "0.1.0"
