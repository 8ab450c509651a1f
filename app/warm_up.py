"""Compile every Numba kernel once per Python, saying so, before the first real solve.

A cold start compiles the core's kernels (1–2 minutes; README "The first run"). Numba caches
them (:mod:`muscle_mss.core.kernel_cache`) in a folder per Python, Numba and NumPy, so this
happens once per Python and version of the sources. :func:`ensure_compiled` is called by the
entry points, never by the filters themselves (the warm-up runs them): the CLI and the batch
before they solve (the CLI, for a run with the default settings, while it prepares the run:
:func:`compiling_beside`) and the ParaView proxies (``muscle_mss.plugin.paraview_proxies``)
before a filter executes; importing a filter starts nothing. When the cache is cold it reports :func:`~muscle_mss.core.kernel_cache.compile_notice`, compiles
every kernel by running tiny solves through the filter chain (the default settings first, then
each other method, collision structure and blending, so that a later choice compiles nothing
either) and records the cache as warm. Numba compiles on one core: for every kernel, where the
Python can start itself again (not in ParaView, pvpython or pvbatch), a second process compiles
the surfaces' kernels and the quasi-static method's meanwhile (:func:`compile_ahead`).
``./setup.sh`` runs it for the venv, then for Debian's Python::

    python -m muscle_mss.app.warm_up [--quiet] [--defaults | --after-defaults]

``--defaults`` compiles only the kernels of a run with the default settings (what the demo
needs; the CLI asks for no more when a run sets nothing else, :func:`scope_for`);
``--after-defaults`` every kernel once those are compiled (``./demo.sh``'s background compile,
after the demo's own).
"""
from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
import time

from vtkmodules.vtkCommonCore import vtkOutputWindow, vtkStringOutputWindow

from muscle_mss.core import kernel_cache
from muscle_mss.core.pose import LINEAR
from muscle_mss.core.settings import (METHOD_QUASI_STATIC, METHOD_RELAXATION, METHODS,
                                      SPRINGS_HOOKE, STRUCTURE_BVH, STRUCTURES,
                                      TERMINATION_THRESHOLD)

from muscle_mss.core.settings import BONE_CONTACTS
from muscle_mss.core.solver_properties import by_name, name_of
from . import motion_run

DEFAULT_VARIANTS = (by_name(iterations=3), by_name(iterations=30))
"""The default settings (the method :mod:`muscle_mss.core.settings` makes the default): the
kernels a first run uses, compiled before any other. Python calls some kernels only when the
data asks for them, so the tiny scene is solved twice: 3 iterations leave surface vertices
inside a bone (the MVC Surface Deformer's push), 30 move spheres far enough for their lists
to be patched in their grid (tests/test_compile_scope.py)."""
OTHER_VARIANTS = tuple(
    by_name(iterations=3, method=method, structure=structure, bone_contact=contact,
            connective_tissue=0.0, fibre_shortening=False)
    for method in METHODS for structure in STRUCTURES for contact in BONE_CONTACTS) + (
    {**by_name(iterations=3, method=METHOD_RELAXATION, structure=STRUCTURE_BVH,
               termination=TERMINATION_THRESHOLD), "Blending": LINEAR},
    by_name(iterations=3, method=METHOD_QUASI_STATIC, springs=SPRINGS_HOOKE),
)
"""Every method with every collision structure and bone contact (without the connective tissue
and fibre shortening, whose kernels the defaults reach and whose absence calls others; each
solve calls only the kernels of its choices), linear blending, the relaxation's threshold
termination and the quasi-static method's Hooke springs: compiled after the defaults, so that
a later choice compiles nothing either."""
VARIANTS = DEFAULT_VARIANTS + OTHER_VARIANTS
"""Filter settings whose tiny solves together call every kernel with the argument types of a
real run (property values select kernels, not argument types), the defaults first."""
KERNEL_NEUTRAL_SETTINGS = frozenset({"ParticlesPerFibre", name_of("iterations")})
"""Filter properties whose values do not change which kernels a run calls: a run that sets no
other needs only the default settings' kernels (:func:`scope_for`)."""
_settled = {kernel_cache.EVERY_KERNEL: False, kernel_cache.DEFAULT_KERNELS: False}
"""Per scope, whether this process has found its kernels compiled or tried to compile them:
later calls return at once (ParaView asks before every filter update; a failed warm-up is not
retried). Every kernel settled settles the default settings' too."""


def warm_up(variants=VARIANTS, surfaces_alone=False) -> float:
    """Run one time point of a two-muscle scene through the whole filter chain for each of
    ``variants``; return the seconds taken (mostly compiling, when the cache is cold).
    ``surfaces_alone``: first the chain with the MVC Surface Deformer fed by the posed model,
    no solve (the surface kernels, for a second process to compile while the first compiles
    the solver's: :func:`compile_ahead`)."""
    from muscle_mss.core.demo.scene import demo_scene
    from muscle_mss.filters.scene_io import write_scene

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
        if surfaces_alone:
            pipeline = motion_run.build_pipeline(folder, DEFAULT_VARIANTS[0])
            t = pipeline.times[len(pipeline.times) // 2]
            motion_run.surfaces_of_posed_model(pipeline, t)
        for settings in variants:
            pipeline = motion_run.build_pipeline(folder, settings)
            motion_run.solve_time_point(pipeline, len(pipeline.times) // 2)
    finally:
        vtkOutputWindow.SetInstance(previous)
        shutil.rmtree(folder, ignore_errors=True)
    return time.perf_counter() - start


def shares(scope: str):
    """``(first, second)``: the variants of ``scope`` split between two processes
    (:func:`compile_ahead`). Every kernel: the first solves the default settings (the solver's
    kernels) and the paper relaxation's other variants; the second compiles the surfaces'
    kernels meanwhile (``surfaces_alone``), then the quasi-static method's and the rest. The
    default settings' kernels alone: one process (two took 99 s against 86 s on the 2-core
    development machine, both compiling the pipeline's first stages; every kernel 96 against
    125 s)."""
    if scope == kernel_cache.DEFAULT_KERNELS:
        return DEFAULT_VARIANTS, ()
    first = tuple(v for v in OTHER_VARIANTS if v.get(name_of("method")) == METHOD_RELAXATION
                  and "Blending" not in v)
    return DEFAULT_VARIANTS + first, tuple(v for v in OTHER_VARIANTS if v not in first)


def _can_start_itself() -> bool:
    """Whether this process can start another of its Python with ``-m`` (not inside ParaView,
    pvpython or pvbatch, whose executables are not a Python) and there is a core for it."""
    return (os.path.basename(sys.executable).startswith("python")
            and (os.cpu_count() or 1) >= 2)


def compile_ahead(scope: str = kernel_cache.EVERY_KERNEL) -> float:
    """Compile the kernels of ``scope`` by :func:`warm_up`, in two processes when this one can
    start a second (:func:`_can_start_itself`): Numba compiles on one core, and the two shares
    (:func:`shares`) call mostly different kernels; a kernel both reach is compiled twice, the
    result being the same. Returns the wall seconds. A second process that fails leaves its
    share to this one."""
    first, second = shares(scope)
    if not second or not _can_start_itself():
        return warm_up(first + second)
    start = time.perf_counter()
    helper = subprocess.Popen([sys.executable, "-m", __name__, "--second-share"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        warm_up(first)
    finally:
        helper.wait()
    if helper.returncode != 0:
        warm_up(second, surfaces_alone=True)
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


def scope_for(settings: dict) -> str:
    """The kernels a run with the filter ``settings`` (property: value) needs compiled:
    ``kernel_cache.DEFAULT_KERNELS`` when it sets nothing but :data:`KERNEL_NEUTRAL_SETTINGS`,
    else ``kernel_cache.EVERY_KERNEL``."""
    return (kernel_cache.DEFAULT_KERNELS if set(settings) <= KERNEL_NEUTRAL_SETTINGS
            else kernel_cache.EVERY_KERNEL)


def ensure_compiled(report, scope: str = kernel_cache.EVERY_KERNEL) -> bool:
    """When this Python's kernels of ``scope`` (every kernel, or the default settings' only:
    :func:`scope_for`) are not in its cache, ``report(text)`` the compile notice, compile them
    (:func:`warm_up`), record the cache as warm for them and report the seconds it took; at
    most once per process and scope. Returns True when it compiled."""
    every = scope == kernel_cache.EVERY_KERNEL
    if _settled[kernel_cache.EVERY_KERNEL] or _settled[scope] or kernel_cache.is_warm(
            scope=scope):
        _settled[scope] = True
        return False
    report(kernel_cache.compile_notice(scope=scope))
    # every kernel after the default settings' ones: the record is the sum of the two compiles
    earlier = kernel_cache.recorded_seconds(scope=kernel_cache.DEFAULT_KERNELS) if every else 0.0
    before = _compiled_files()
    try:
        seconds = compile_ahead(scope)
    except Exception as err:  # noqa: BLE001  the solve itself then compiles what it uses
        report(f"compiling ahead failed ({type(err).__name__}: {err}); the kernels compile as "
               "they are first used")
        return False
    finally:
        _settled[scope] = True
    # The marker's seconds are the next cold start's estimate: a warm-up that compiled nothing
    # (its kernels were cached, the marker was not) keeps the earlier estimate.
    kernel_cache.mark_warm(earlier + seconds if _compiled_files() != before
                           else kernel_cache.compile_estimate(scope=scope), scope=scope)
    report(f"compiled the numeric kernels in {seconds:.0f} s; later runs of this Python load "
           "them from the cache")
    return True


@contextlib.contextmanager
def compiling_beside(report, scope: str = kernel_cache.EVERY_KERNEL):
    """Leave the body with the kernels of ``scope`` compiled, as :func:`ensure_compiled` does; the
    default settings' kernels, when this Python has not compiled them and can start itself
    (:func:`_can_start_itself`), compile in a second process while the body runs (reporting on
    this process's stderr; ``report`` is then used only when it fails and this one compiles).
    Gives the body True in that case, else False (compiled before it). The body should prepare
    what needs no solver kernel: a scene to write, a time point's stages before the solver
    (``motion_run.prepare_time_point``), on the other core, Numba's parallel loops here kept to
    one thread meanwhile. Every kernel compiles here first (its warm-up takes both cores
    already: :func:`compile_ahead`)."""
    if (scope != kernel_cache.DEFAULT_KERNELS or _settled[kernel_cache.EVERY_KERNEL]
            or _settled[scope] or kernel_cache.is_warm(scope=scope)
            or not _can_start_itself()):
        ensure_compiled(report, scope)
        yield False
        return
    import numba
    helper = subprocess.Popen([sys.executable, "-m", __name__, "--defaults", "--quiet"])
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        yield True
    except BaseException:
        helper.terminate()
        raise
    finally:
        numba.set_num_threads(threads)
        helper.wait()
    if helper.returncode != 0:
        ensure_compiled(report, scope)
    _settled[scope] = True


def stderr_notice(text: str) -> None:
    """Show a compile notice on stderr (the CLI, the batch)."""
    print(text, file=sys.stderr, flush=True)


def output_window_notice(text: str) -> None:
    """Show a compile notice among ParaView's output messages (VTK's output window: stderr
    outside ParaView)."""
    vtkOutputWindow.GetInstance().DisplayWarningText(f"Muscle MSS: {text}\n")


AFTER_DEFAULTS_WAIT = 300.0
"""Seconds ``--after-defaults`` waits at most for the default settings' kernels (a demo
compiling them: about a minute) before it compiles them itself."""


def wait_for_defaults(limit: float = AFTER_DEFAULTS_WAIT, poll: float = 2.0) -> bool:
    """Wait until the default settings' kernels are compiled (True) or ``limit`` seconds have
    passed (False)."""
    end = time.monotonic() + limit
    while not kernel_cache.is_warm(scope=kernel_cache.DEFAULT_KERNELS):
        if time.monotonic() >= end:
            return False
        time.sleep(poll)
    return True


def main(argv=None) -> int:
    """``python -m muscle_mss.app.warm_up [--quiet] [--defaults | --after-defaults]``:
    compile (or find compiled) every kernel, or with ``--defaults`` those a run with the
    default settings calls (the demo's, :func:`compiling_beside`); ``--after-defaults``: every
    kernel once the default settings' are compiled (``./demo.sh``'s background compile:
    :func:`wait_for_defaults`); ``--quiet`` says nothing when they are compiled already
    (``./setup.sh`` run again)."""
    argv = sys.argv[1:] if argv is None else argv
    if "--second-share" in argv:        # compile_ahead's second process
        warm_up(shares(kernel_cache.EVERY_KERNEL)[1], surfaces_alone=True)
        return 0
    scope = kernel_cache.DEFAULT_KERNELS if "--defaults" in argv else kernel_cache.EVERY_KERNEL
    if "--after-defaults" in argv:
        wait_for_defaults()
    if not ensure_compiled(stderr_notice, scope) and "--quiet" not in argv:
        print(f"numeric kernels already compiled in {kernel_cache.kernel_cache_dir()}",
              file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
