"""Checks of inputs that do not change between time points, run once per input content.

The Volume-Error Probe checks every rest surface it measures against (closed, manifold,
outward) at every time point, although the rest surfaces are the scene's and never change:
:func:`rest_surface_problems` remembers the answer per surface content (a digest of its points
and triangles), so a time slider or a motion run checks each rest surface once.
"""
import hashlib
from collections import OrderedDict

import numpy as np

from muscle_mss.core.mesh_checks import surface_problems

CACHE_ENTRIES = 256         # surfaces remembered (least recently used dropped)

#: Since :func:`clear_check_cache`: ``checked`` (surfaces checked), ``reused`` (answers reused).
check_counts = {"checked": 0, "reused": 0}
_answers = OrderedDict()    # digest of (points, triangles) -> list of problem sentences


def clear_check_cache():
    """Forget every remembered answer and zero :data:`check_counts`."""
    _answers.clear()
    for name in check_counts:
        check_counts[name] = 0


def rest_surface_problems(points, triangles) -> list:
    """:func:`muscle_mss.core.mesh_checks.surface_problems` of ``points`` (n, 3) mm and
    ``triangles`` (m, 3), remembered per content: the same arrays (bitwise) get the same list
    without being checked again."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    digest = hashlib.blake2b(digest_size=16)
    for array in (points, triangles):
        digest.update(np.asarray(array.shape, dtype=np.int64).tobytes())
        digest.update(array.tobytes())
    key = digest.digest()
    if key in _answers:
        _answers.move_to_end(key)
        check_counts["reused"] += 1
        return list(_answers[key])
    problems = surface_problems(points, triangles)
    check_counts["checked"] += 1
    _answers[key] = list(problems)
    while len(_answers) > CACHE_ENTRIES:
        _answers.popitem(last=False)
    return problems
