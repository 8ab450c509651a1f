"""The motion table (DESIGN §4): rows of (time, bone, 3x4 rigid transform) to a :class:`Motion`.

Used by the scene validator and by the Rigid Pose Transform filter, so that both apply the same
rules with the same messages. Rows are numbered from 1 = the first data row (file line 2). A row
naming a bone the scene lacks is reported first: the other rules then fail only as its
consequence.
"""
import numpy as np

from .errors import first_problem
from .scene import MOTION_COLUMNS, MOTION_FILE, Motion

ROTATION_TOLERANCE = 1e-5
"""Largest allowed deviation of ``R^T R`` from the identity and of ``det R`` from 1."""


def rigid_problem(matrix) -> str | None:
    """Why a 3x4 (or 3x3 + translation) transform is not rigid, or None when it is."""
    m = np.asarray(matrix, dtype=np.float64)
    r = m[:3, :3]
    deviation = float(np.abs(r.T @ r - np.eye(3)).max())
    if deviation > ROTATION_TOLERANCE:
        return (f"is not rigid: its 3x3 part is scaled or sheared (|R^T R - I| = {deviation:.3g}); "
                "each transform must be a rotation plus a translation")
    det = float(np.linalg.det(r))
    if det < 0.0:
        return f"is not rigid: its 3x3 part is a reflection (det = {det:.3g}); it must be a rotation"
    if abs(det - 1.0) > ROTATION_TOLERANCE:
        return (f"is not rigid: its 3x3 part scales volumes by det = {det:.8g} (|R^T R - I| = "
                f"{deviation:.3g}); a rotation has det 1 within {ROTATION_TOLERANCE:g}")
    return None


def motion_problems(times, bones, values, known_bones=None, source=MOTION_FILE):
    """Check motion rows; return ``(motion or None, problems)``.

    Parameters
    ----------
    times : (R,) float, s
    bones : sequence of R bone names
    values : (R, 12) float, the row-major 3x4 matrices
    known_bones : names of the bones of the scene (``bones.vtm`` block order), or None to take
        the bones in order of first appearance
    source : the file name used in messages
    """
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    values = np.asarray(values, dtype=np.float64).reshape(len(times), 12)
    bones = [str(b) for b in bones]
    problems = []
    if len(times) == 0:
        return None, [f"{source}: has no rows; the motion needs at least one time point"]
    order = list(known_bones) if known_bones is not None else list(dict.fromkeys(bones))
    index = {b: i for i, b in enumerate(order)}
    # a bone the scene lacks first: rows added for it break the other rules as a consequence
    for r, b in enumerate(bones):
        if b not in index:
            problems.append(f"{source} row {r + 1}: bone '{b}' is not a bone of the scene "
                            f"(bones: {', '.join(order)})")
    for r in np.flatnonzero(~np.isfinite(times)):
        problems.append(f"{source} row {r + 1}: time is not a finite number (an empty cell, "
                        "NaN or inf); every time must be a number")
    bad_rows, bad_cols = np.nonzero(~np.isfinite(values))
    for r, c in zip(bad_rows, bad_cols):
        problems.append(f"{source} row {r + 1} (bone '{bones[r]}'): {MOTION_COLUMNS[2 + c]} is "
                        "not a finite number (an empty cell, NaN or inf); every matrix entry "
                        "must be a number")
    finite_rows = np.isfinite(values).all(axis=1)
    for r in np.flatnonzero(finite_rows):
        why = rigid_problem(values[r].reshape(3, 4))
        if why:
            problems.append(f"{source} row {r + 1} (bone '{bones[r]}', time {times[r]:g}): "
                            f"the transform {why}")
    for r in np.flatnonzero(np.diff(times) < 0):
        problems.append(f"{source} row {r + 2}: time {times[r + 1]:g} comes after {times[r]:g}; "
                        "times must be ascending")

    unique_times = np.unique(times[np.isfinite(times)])
    matrices = np.full((len(unique_times), len(order), 3, 4), np.nan)
    seen = np.zeros((len(unique_times), len(order)), dtype=bool)
    for r, (t, b) in enumerate(zip(times, bones)):
        if b not in index or not np.isfinite(t):
            continue
        ti = int(np.searchsorted(unique_times, t))
        if seen[ti, index[b]]:
            problems.append(f"{source} row {r + 1}: a second row for bone '{b}' at time {t:g}; "
                            "one row per (time, bone)")
        seen[ti, index[b]] = True
        matrices[ti, index[b]] = values[r].reshape(3, 4)
    for bi, b in enumerate(order):
        if not seen[:, bi].any():
            problems.append(f"{source}: bone '{b}' has no rows; every bone needs a row at every time")
            continue
        for ti in np.flatnonzero(~seen[:, bi]):
            problems.append(f"{source}: no row for bone '{b}' at time {unique_times[ti]:g}; "
                            "every bone needs a row at every time")
    if problems:
        return None, problems
    return Motion(unique_times, order, matrices), []


def motion_from_rows(times, bones, values, known_bones=None, source=MOTION_FILE) -> Motion:
    """Like :func:`motion_problems` but raise :class:`MuscleMSSError` on the first problem."""
    motion, problems = motion_problems(times, bones, values, known_bones, source)
    if problems:
        raise first_problem(problems)
    return motion


def motion_rows(motion: Motion):
    """Inverse of :func:`motion_from_rows`: ``(times, bones, values (R, 12))`` time-major."""
    t_count, b_count = motion.matrices.shape[:2]
    times = np.repeat(motion.times, b_count)
    bones = list(motion.bones) * t_count
    values = motion.matrices.reshape(t_count * b_count, 12)
    return times, bones, values


def farthest_pose_index(motion: Motion) -> int:
    """Index of the time point at which the bones are rotated farthest from the rest pose in
    total (sum of rotation angles): the pose worth showing, mid-swing for a walking cycle."""
    traces = np.trace(motion.matrices[:, :, :, :3], axis1=2, axis2=3)
    angles = np.arccos(np.clip((traces - 1.0) / 2.0, -1.0, 1.0)).sum(axis=1)
    return int(np.argmax(angles))
