"""A run with the default settings compiles only the kernels it uses (issue 27, "compile less,
and only what is used"): not the octree BVH's (the default structure is the spatial hash), not
the contact kernels of bones as sphere sets (the default bone contact is solid; the sphere
sampling itself runs, as the Spring Builder clears the rest radii of both forms of a bone), not
the other method's. Asserted on what Numba compiled, not on time: in a fresh process with an empty kernel
cache every kernel a run reaches is compiled through its dispatcher, callees included, and the
dispatcher lists the argument types it was compiled for (``signatures``); a kernel nothing
reached has none (the contact code hands the structures a run does not use to its kernels as
None, whose branches Numba prunes: ``contacts.used_structures``).

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
import muscle_mss.core.octree_bvh, muscle_mss.core.quasi_static, muscle_mss.core.relaxation
from muscle_mss.filters import warm_up
warm_up.warm_up(warm_up.DEFAULT_VARIANTS)
found = {}
for name, module in sorted(sys.modules.items()):
    if name.startswith("muscle_mss.core."):
        for attr, value in vars(module).items():
            if isinstance(value, Dispatcher) and value.py_func.__module__ == name:
                found[f"{name}.{attr}"] = len(value.signatures)
print("RESULT " + json.dumps(found))
"""

BVH = "muscle_mss.core.octree_bvh."
SPHERE_SET_CONTACTS = ("muscle_mss.core.contacts._bone_list_contacts",
                       "muscle_mss.core.spatial_hash.own_list_contacts",
                       "muscle_mss.core.spatial_hash._own_list_contacts")
METHOD_MODULES = {METHOD_RELAXATION: "muscle_mss.core.relaxation.",
                  METHOD_QUASI_STATIC: "muscle_mss.core.quasi_static."}

pytestmark = pytest.mark.skipif(sys.prefix == sys.base_prefix,
                                reason="one cold compile, in the venv (see the module's note)")


@pytest.fixture(scope="module")
def compiled(tmp_path_factory):
    """``{module.kernel: number of signatures}`` of every core kernel after one time point of
    the two-muscle warm-up scene with the default settings, compiled from an empty cache."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path_factory.mktemp("empty_kernel_cache")))
    proc = subprocess.run([sys.executable, "-c", COMPILED], env=env, capture_output=True,
                          text=True, timeout=1800)
    assert proc.returncode == 0, proc.stderr[-4000:]
    line = next(l for l in reversed(proc.stdout.splitlines()) if l.startswith("RESULT "))
    return json.loads(line[len("RESULT "):])


def _with_signatures(compiled, names):
    return sorted(k for k, n in compiled.items() if n and k.startswith(names))


def test_the_default_run_compiled_its_kernels(compiled):
    """The control: the run reached the kernels every default run uses (pose blending, the
    contacts, mean value coordinates), each once."""
    for kernel in ("muscle_mss.core.pose._blend_dual_quaternion",
                   "muscle_mss.core.solid_contacts.solid_contacts",
                   "muscle_mss.core.mvc._mean_value_coordinates"):
        assert compiled[kernel] == 1, kernel
    assert any(n for k, n in compiled.items() if k.startswith(METHOD_MODULES[DEFAULT_METHOD]))


def test_the_default_run_compiles_no_kernel_of_the_other_method(compiled):
    others = tuple(prefix for method, prefix in METHOD_MODULES.items()
                   if method != DEFAULT_METHOD)
    assert _with_signatures(compiled, others) == []


def test_the_default_run_compiles_no_octree_bvh_kernel(compiled):
    assert any(k.startswith(BVH) for k in compiled)
    assert _with_signatures(compiled, (BVH, "muscle_mss.core.contacts._bvh_contacts")) == []


def test_the_default_run_compiles_no_bone_sphere_set_contact_kernel(compiled):
    assert _with_signatures(compiled, SPHERE_SET_CONTACTS) == []
