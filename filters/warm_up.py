"""Compile every Numba kernel once per Python, saying so, before the first real solve.

A cold start compiles the core's kernels (1–2 minutes; README "The first run"). Numba caches
them (:mod:`muscle_mss.core.kernel_cache`) in a folder per Python, Numba and NumPy, so this
happens once per Python and version of the sources. :func:`ensure_compiled` is called by the
entry points, never by the filters themselves (the warm-up runs them): the CLI and the batch
before they solve, the ParaView proxies (``muscle_mss.plugin.paraview_proxies``) before a filter
executes, and ``muscle_mss.filters`` when a script takes a filter class from it. When the cache
is cold it reports :func:`~muscle_mss.core.kernel_cache.compile_notice`, compiles every kernel
by running tiny solves through the filter chain (the default settings first, then each other
method, collision structure and blending, so that a later choice compiles nothing either) and
records the cache as warm. ``./setup.sh`` runs it for the venv, then for Debian's Python::

    python -m muscle_mss.filters.warm_up [--quiet]
"""
from __future__ import annotations

import os
import shutil
import sys
import tempfile
import time

from vtkmodules.vtkCommonCore import vtkOutputWindow, vtkStringOutputWindow

from muscle_mss.core import kernel_cache
from muscle_mss.core.pose import LINEAR
from muscle_mss.core.settings import (METHOD_RELAXATION, METHODS, STRUCTURE_BVH, STRUCTURES,
                                      TERMINATION_THRESHOLD)

from . import motion_run
from .collision_solver import BONE_CONTACTS

DEFAULT_VARIANTS = ({"Iterations": 3}, {"Iterations": 30})
"""The default settings (the method :mod:`muscle_mss.core.settings` makes the default): the
kernels a first run uses, compiled before any other. Python calls some kernels only when the
data asks for them, so the tiny scene is solved twice: 3 iterations leave surface vertices
inside a bone (the MVC Surface Deformer's push), 30 move spheres far enough for their lists
to be patched in their grid (tests/test_compile_scope.py)."""
OTHER_VARIANTS = tuple(
    {"Iterations": 3, "Method": method, "CollisionStructure": structure, "BoneContact": contact,
     "ConnectiveTissue": 0.1}
    for method in METHODS for structure in STRUCTURES for contact in BONE_CONTACTS) + (
    {"Iterations": 3, "Method": METHOD_RELAXATION, "CollisionStructure": STRUCTURE_BVH,
     "Blending": LINEAR, "Termination": TERMINATION_THRESHOLD},
)
"""Every method with every collision structure and bone contact (with the connective tissue,
whose kernels the default ratio 0 does not reach; each solve calls only the kernels of its
choices), linear blending and the relaxation's threshold termination: compiled after the
defaults, so that a later choice compiles nothing either."""
VARIANTS = DEFAULT_VARIANTS + OTHER_VARIANTS
"""Filter settings whose tiny solves together call every kernel with the argument types of a
real run (property values select kernels, not argument types), the defaults first."""
_settled = {"done": False}
"""Whether this process has found the kernels compiled or tried to compile them: later calls
return at once (ParaView asks before every filter update; a failed warm-up is not retried)."""


def warm_up(variants=VARIANTS) -> float:
    """Run one time point of a two-muscle scene through the whole filter chain for each of
    ``variants``; return the seconds taken (mostly compiling, when the cache is cold)."""
    from muscle_mss.core.demo_scene import demo_scene
    from .scene_io import write_scene

    start = time.perf_counter()
    scene = demo_scene("small")
    for name in list(scene.muscles)[2:]:
        del scene.muscles[name]
        del scene.fibres[name]
    folder = tempfile.mkdtemp(prefix="muscle-mss-warm-up-")
    # the tiny solves' own warnings (a 3-iteration solve has not converged) are not the user's
    previous = vtkOutputWindow.GetInstance()
    vtkOutputWindow.SetInstance(vtkStringOutputWindow())
    try:
        write_scene(scene, folder)
        for settings in variants:
            pipeline = motion_run.build_pipeline(folder, settings)
            motion_run.solve_time_point(pipeline, len(pipeline.times) // 2)
    finally:
        vtkOutputWindow.SetInstance(previous)
        shutil.rmtree(folder, ignore_errors=True)
    return time.perf_counter() - start


def _compiled_files() -> dict:
    """Numba's machine-code files in this Python's cache folder, with their modification
    times."""
    found = {}
    for root, _, names in os.walk(kernel_cache.kernel_cache_dir()):
        for name in names:
            if name.endswith(".nbc"):
                path = os.path.join(root, name)
                found[path] = os.stat(path).st_mtime_ns
    return found


def ensure_compiled(report) -> bool:
    """When the kernel cache of this Python is cold, ``report(text)`` the compile notice,
    compile every kernel (:func:`warm_up`), record the cache as warm and report the seconds it
    took; at most once per process. Returns True when it compiled."""
    if _settled["done"] or kernel_cache.is_warm():
        _settled["done"] = True
        return False
    report(kernel_cache.compile_notice())
    before = _compiled_files()
    try:
        seconds = warm_up()
    except Exception as err:  # noqa: BLE001  the solve itself then compiles what it uses
        report(f"compiling ahead failed ({type(err).__name__}: {err}); the kernels compile as "
               "they are first used")
        return False
    finally:
        _settled["done"] = True
    # The marker's seconds are the next cold start's estimate: a warm-up that compiled nothing
    # (its kernels were cached, the marker was not) keeps the earlier estimate.
    kernel_cache.mark_warm(seconds if _compiled_files() != before
                           else kernel_cache.compile_estimate())
    report(f"compiled the numeric kernels in {seconds:.0f} s; later runs of this Python load "
           "them from the cache")
    return True


def stderr_notice(text: str) -> None:
    """Show a compile notice on stderr (the CLI, the batch)."""
    print(text, file=sys.stderr, flush=True)


def output_window_notice(text: str) -> None:
    """Show a compile notice among ParaView's output messages (VTK's output window: stderr
    outside ParaView)."""
    vtkOutputWindow.GetInstance().DisplayWarningText(f"Muscle MSS: {text}\n")


def main(argv=None) -> int:
    """``python -m muscle_mss.filters.warm_up [--quiet]``: compile (or find compiled) every
    kernel; ``--quiet`` says nothing when they are compiled already (``./setup.sh`` run again)."""
    quiet = "--quiet" in (sys.argv[1:] if argv is None else argv)
    if not ensure_compiled(stderr_notice) and not quiet:
        print(f"numeric kernels already compiled in {kernel_cache.kernel_cache_dir()}",
              file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
