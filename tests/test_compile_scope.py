"""A run with the default settings compiles only the kernels it uses (issue 27, "compile less,
and only what is used"): not the octree BVH's (the default structure is the spatial hash), not
the contact kernels of bones as sphere sets (the default bone contact is solid; the sphere
sampling itself runs, as the Spring Builder clears the rest radii of both forms of a bone), not
the other method's. Asserted on what Numba compiled, not on time: in a fresh process with an empty kernel
cache every kernel a run reaches is compiled through its dispatcher, callees included, and the
dispatcher lists the argument types it was compiled for (``signatures``); a kernel nothing
reached has none (``contacts.collide`` calls the kernels of the structures a run uses only:
``contacts.used_structures``).

One cold compile of the default path (minutes), in the venv only: which kernels a call reaches
is decided by the sources, the same in Debian's Python.
"""
import json
import os
import subprocess
import sys

import pytest

from muscle_mss.core.settings import DEFAULT_METHOD, METHOD_QUASI_STATIC, METHOD_RELAXATION

COMPILED = """
import json, sys
from numba.core.dispatcher import Dispatcher
import muscle_mss.core.contacts.octree_bvh, muscle_mss.core.quasi_static, muscle_mss.core.relaxation
from muscle_mss.app import warm_up
warm_up.warm_up(warm_up.DEFAULT_VARIANTS)
found = {}
for name, module in sorted(sys.modules.items()):
    if name.startswith("muscle_mss.core."):
        for attr, value in vars(module).items():
            if isinstance(value, Dispatcher) and value.py_func.__module__ == name:
                found[f"{name}.{attr}"] = len(value.signatures)
print("RESULT " + json.dumps(found))
from numba.core import event
from muscle_mss.core.demo.scene import demo_scene
from muscle_mss.app import motion_run
from muscle_mss.filters.scene_io import write_scene
later = []
class Compiles(event.Listener):
    def on_start(self, ev):
        later.append(getattr(ev.data["dispatcher"], "py_func", ev.data["dispatcher"]).__name__)
    def on_end(self, ev):
        pass
write_scene(demo_scene("small"), sys.argv[1])
with event.install_listener("numba:compile", Compiles()):
    pipeline = motion_run.build_pipeline(sys.argv[1], {})
    for k in (0, len(pipeline.times) // 2, len(pipeline.times) - 1):
        motion_run.solve_time_point(pipeline, k)
print("LATER " + json.dumps(later))
"""

BVH = "muscle_mss.core.contacts.octree_bvh."
SPHERE_SET_CONTACTS = ("muscle_mss.core.contacts.spatial_hash.own_list_contacts",
                       "muscle_mss.core.contacts.spatial_hash._own_list_contacts")
METHOD_MODULES = {METHOD_RELAXATION: "muscle_mss.core.relaxation.",
                  METHOD_QUASI_STATIC: "muscle_mss.core.quasi_static."}

pytestmark = pytest.mark.skipif(sys.prefix == sys.base_prefix,
                                reason="one cold compile, in the venv (see the module's note)")


@pytest.fixture(scope="module")
def compile_run(tmp_path_factory):
    """``(signatures, later)``: ``{module.kernel: number of signatures}`` of every core kernel
    after the warm-up's default solve of its two-muscle scene, compiled from an empty cache, and
    the kernels a full run of the small demo scene (three time points, the defaults) compiled
    after it."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path_factory.mktemp("empty_kernel_cache")))
    scene = str(tmp_path_factory.mktemp("scene"))
    proc = subprocess.run([sys.executable, "-c", COMPILED, scene], env=env, capture_output=True,
                          text=True, timeout=1800)
    assert proc.returncode == 0, proc.stderr[-4000:]
    lines = proc.stdout.splitlines()

    def result(tag):
        line = next(l for l in reversed(lines) if l.startswith(tag + " "))
        return json.loads(line[len(tag) + 1:])

    return result("RESULT"), result("LATER")


@pytest.fixture(scope="module")
def compiled(compile_run):
    return compile_run[0]


def _with_signatures(compiled, names):
    return sorted(k for k, n in compiled.items() if n and k.startswith(names))


def test_the_default_run_compiled_its_kernels(compiled):
    """The control: the run reached the kernels every default run uses (pose blending, the
    contacts, mean value coordinates), each once."""
    for kernel in ("muscle_mss.core.pose._blend_dual_quaternion",
                   "muscle_mss.core.contacts.solid_contacts.solid_contacts",
                   "muscle_mss.core.mvc._mean_value_coordinates"):
        assert compiled[kernel] == 1, kernel
    assert any(n for k, n in compiled.items() if k.startswith(METHOD_MODULES[DEFAULT_METHOD]))


def test_the_default_run_compiles_no_kernel_of_the_other_method(compiled):
    others = tuple(prefix for method, prefix in METHOD_MODULES.items()
                   if method != DEFAULT_METHOD)
    assert _with_signatures(compiled, others) == []


def test_the_default_run_compiles_no_octree_bvh_kernel(compiled):
    assert any(k.startswith(BVH) for k in compiled)
    assert _with_signatures(compiled,
                            (BVH, "muscle_mss.core.contacts.sphere_contacts._bvh_contacts")) == []


def test_the_default_run_compiles_no_bone_sphere_set_contact_kernel(compiled):
    assert _with_signatures(compiled, SPHERE_SET_CONTACTS) == []


def test_the_default_run_compiles_each_kernel_for_one_signature(compiled):
    """Issue 27's "one type signature per kernel": a kernel called with the index of a parallel
    loop compiled once for int64 (the loop as typed) and again for uint64 (the loop's body as
    run), a literal argument (``-1``, ``False``) once more for the literal; each compile of a
    large kernel costs seconds."""
    assert sorted(k for k, n in compiled.items() if n > 1) == []


def test_a_run_after_the_warm_up_compiles_nothing(compile_run):
    """The warm-up compiles what a default run calls, also what Python calls only in some
    iterations or passes: a run after it finds every kernel in the cache (a kernel compiled
    later would freeze the first real run, and in the tests eat a timeout)."""
    assert compile_run[1] == []
