"""Start-up shim for Debian's ParaView 5.11 (Python 3.11); put this folder on PYTHONPATH.

1. ParaView 5.11's Python-plugin loader imports ``inspect.getargspec``, which Python 3.11
   removed; alias it to ``getfullargspec`` (the loader only reads ``.args``). A no-op on
   ParaView >= 5.12 and older Pythons.
2. When ``muscle_mss`` is not installed in ParaView's Python, make it importable from this
   checkout: the repository maps ``muscle_mss.core`` / ``.filters`` / ``.app`` / ``.plugin`` to
   its top-level ``core/``, ``filters/``, ``app/``, ``plugin/`` folders (pyproject's package-dir).

Python imports ``sitecustomize`` at start-up in pvpython, pvbatch and the GUI, so both are in
place before ParaView or a batch script imports anything.
"""
import importlib.util
import inspect
import os
import sys
import types

if not hasattr(inspect, "getargspec"):
    inspect.getargspec = inspect.getfullargspec

if "muscle_mss" not in sys.modules and importlib.util.find_spec("muscle_mss") is None:
    _checkout = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    if os.path.isfile(os.path.join(_checkout, "core", "__init__.py")):
        _package = types.ModuleType("muscle_mss")
        _package.__path__ = [_checkout]
        _package.__file__ = None
        sys.modules["muscle_mss"] = _package
