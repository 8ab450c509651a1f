"""Motion rows -> Motion (core.motion): rigid transforms only, every bone at every time."""
import numpy as np
import pytest

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.motion import motion_from_rows, motion_rows, rigid_problem


def rotation_z(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def rows(times=(0.0, 0.5, 1.0), bones=("femur", "tibia")):
    t, b, v = [], [], []
    for ti in times:
        for j, name in enumerate(bones):
            m = np.hstack([rotation_z(30 * ti + 10 * j), [[1.0], [2.0], [3.0 * ti]]])
            t.append(ti), b.append(name), v.append(m.reshape(12))
    return np.array(t), b, np.array(v)


def test_rows_round_trip():
    t, b, v = rows()
    motion = motion_from_rows(t, b, v)
    assert motion.matrices.shape == (3, 2, 3, 4)
    t2, b2, v2 = motion_rows(motion)
    np.testing.assert_array_equal(t, t2)
    assert b == b2
    np.testing.assert_array_equal(v, v2)


@pytest.mark.parametrize("matrix, words", [
    (np.hstack([np.diag([1.0, 1.0, 1.1]), np.zeros((3, 1))]), "scaled or sheared"),
    (np.hstack([np.array([[1, 0.2, 0], [0, 1, 0], [0, 0, 1.0]]), np.zeros((3, 1))]), "scaled or sheared"),
    (np.hstack([np.diag([1.0, 1.0, -1.0]), np.zeros((3, 1))]), "reflection"),
])
def test_non_rigid_matrices_are_named(matrix, words):
    assert words in rigid_problem(matrix)
    assert rigid_problem(np.hstack([rotation_z(33), np.ones((3, 1))])) is None


def test_errors_name_the_row():
    t, b, v = rows()
    v[3, 0] *= 2
    with pytest.raises(MuscleMSSError, match=r"motion.csv row 4 \(bone 'tibia', time 0.5\)"):
        motion_from_rows(t, b, v)
    t, b, v = rows()
    v[2, 5] = np.nan
    with pytest.raises(MuscleMSSError, match="row 3 .*m11 is not a finite number"):
        motion_from_rows(t, b, v)
    t, b, v = rows()
    with pytest.raises(MuscleMSSError, match="bone 'pelvis' has no rows"):
        motion_from_rows(t, b, v, known_bones=["pelvis", "femur", "tibia"])
    with pytest.raises(MuscleMSSError, match="row 2: bone 'tibia' is not a bone of the scene"):
        motion_from_rows(t, b, v, known_bones=["femur"])
