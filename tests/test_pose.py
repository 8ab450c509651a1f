"""The rigid pose core (core/pose.py): interpolation of the motion, weights, blending.

Each kernel is compared with a slow, obviously correct NumPy reference, and the mathematics is
checked by its properties (identity exact, rigid stays rigid, slerp halves the angle).
"""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.bones.weights import bone_distances, bone_weights, weights_from_distances
from muscle_mss.core.pose import (blend, blend_dual_quaternion, blend_linear, pose_at,
                                  quaternion_to_rotation, rotation_to_quaternion, slerp,
                                  transform_rigid)
from muscle_mss.core.scene import Motion

CUBE_CORNERS = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                         [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=np.float64)
CUBE_TRIANGLES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                           [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


def cube(half, centre=(0.0, 0.0, 0.0)):
    return CUBE_CORNERS * half + np.asarray(centre), CUBE_TRIANGLES.copy()


def box_distance(points, half, centre):
    """Exact distance to the surface of an axis-aligned cube (inside and outside)."""
    p = np.abs(points - np.asarray(centre))
    inside = (p <= half).all(axis=1)
    outside = np.linalg.norm(np.maximum(p - half, 0.0), axis=1)
    return np.where(inside, half - p.max(axis=1), outside)


def rigid(rotvec, translation):
    m = np.zeros((3, 4))
    m[:, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    m[:, 3] = translation
    return m


def random_weights(rng, n, bone_count):
    w = rng.random((n, bone_count))
    return w / w.sum(axis=1, keepdims=True)


def naive_linear(points, weights, matrices):
    out = np.zeros_like(points)
    for b, m in enumerate(matrices):
        out += weights[:, [b]] * (points @ m[:, :3].T + m[:, 3])
    return out


def quat_mul(a, b):
    return np.array([a[0] * b[0] - a[1:] @ b[1:],
                     *(a[0] * b[1:] + b[0] * a[1:] + np.cross(a[1:], b[1:]))])


def naive_dual_quaternion(points, weights, matrices):
    """Kavan's DLB, one point at a time, with scipy's quaternions (x, y, z, w)."""
    real = [Rotation.from_matrix(m[:, :3]).as_quat()[[3, 0, 1, 2]] for m in matrices]
    dual = [0.5 * quat_mul(np.r_[0.0, m[:, 3]], q) for m, q in zip(matrices, real)]
    out = np.empty_like(points)
    for i, p in enumerate(points):
        pivot = real[int(np.argmax(weights[i]))]
        qr = sum(w * np.sign(q @ pivot or 1.0) * q for w, q in zip(weights[i], real))
        qd = sum(w * np.sign(q @ pivot or 1.0) * d for w, q, d in zip(weights[i], real, dual))
        norm = np.linalg.norm(qr)
        qr, qd = qr / norm, qd / norm
        t = 2.0 * quat_mul(qd, qr * [1, -1, -1, -1])[1:]
        out[i] = Rotation.from_quat(qr[[1, 2, 3, 0]]).apply(p) + t
    return out


# ---- quaternions ---------------------------------------------------------------------------

def test_quaternions_match_scipy_and_round_trip():
    rotations = Rotation.random(200, random_state=3)
    q = rotation_to_quaternion(rotations.as_matrix())
    ref = rotations.as_quat()[:, [3, 0, 1, 2]]
    ref *= np.where(ref[:, :1] < 0, -1.0, 1.0)
    np.testing.assert_allclose(q, ref, atol=1e-12)
    np.testing.assert_allclose(quaternion_to_rotation(q), rotations.as_matrix(), atol=1e-12)
    # The branches for half-turns, where the trace is -1 (w = 0).
    for axis in np.eye(3):
        r = Rotation.from_rotvec(math.pi * axis).as_matrix()
        np.testing.assert_allclose(quaternion_to_rotation(rotation_to_quaternion(r)), r,
                                   atol=1e-12)


def test_slerp_halves_the_angle_and_takes_the_short_arc():
    q0 = rotation_to_quaternion(np.eye(3))
    q1 = rotation_to_quaternion(Rotation.from_rotvec([0, 0, 1.2]).as_matrix())
    half = Rotation.from_quat(slerp(q0, q1, 0.5)[[1, 2, 3, 0]])
    np.testing.assert_allclose(half.as_rotvec(), [0, 0, 0.6], atol=1e-12)
    # -q1 is the same rotation: the result must not go the long way round.
    half_neg = Rotation.from_quat(slerp(q0, -q1, 0.5)[[1, 2, 3, 0]])
    np.testing.assert_allclose(half_neg.as_rotvec(), [0, 0, 0.6], atol=1e-12)
    np.testing.assert_allclose(slerp(q0, q1, 0.0), q0, atol=1e-15)


# ---- the bone transforms at a time -----------------------------------------------------------

def knee_motion():
    """Two bones; 'tibia' turns about the x axis by 0, 90, 90 degrees, 'femur' slides in z."""
    times = np.array([0.0, 0.5, 1.0])
    m = np.zeros((3, 2, 3, 4))
    m[:, 0] = [rigid([0, 0, 0], [0, 0, 10 * k]) for k in range(3)]
    m[:, 1] = [rigid([0, 0, 0], [0, 0, 0]), rigid([math.pi / 2, 0, 0], [4, 0, 0]),
               rigid([math.pi / 2, 0, 0], [4, 0, 0])]
    return Motion(times, ["femur", "tibia"], m)


def test_at_a_row_time_the_pose_is_that_row_exactly():
    motion = knee_motion()
    for t, row in zip(motion.times, motion.matrices):
        matrices, used = pose_at(motion, t)
        assert used == t
        assert np.array_equal(matrices, row)


def test_halfway_between_rows_the_rotation_is_at_half_the_angle():
    motion = knee_motion()
    matrices, used = pose_at(motion, 0.25)
    assert used == 0.25
    tibia = Rotation.from_matrix(matrices[1, :, :3])
    np.testing.assert_allclose(tibia.as_rotvec(), [math.pi / 4, 0, 0], atol=1e-12)
    np.testing.assert_allclose(matrices[1, :, 3], [2, 0, 0], atol=1e-12)  # linear translation
    np.testing.assert_allclose(matrices[0, :, 3], [0, 0, 5.0], atol=1e-12)
    quarter, _ = pose_at(motion, 0.125)
    np.testing.assert_allclose(Rotation.from_matrix(quarter[1, :, :3]).as_rotvec(),
                               [math.pi / 8, 0, 0], atol=1e-12)


def test_outside_the_range_the_time_is_clamped():
    motion = knee_motion()
    before, used_before = pose_at(motion, -3.0)
    after, used_after = pose_at(motion, 7.0)
    assert (used_before, used_after) == (0.0, 1.0)
    assert np.array_equal(before, motion.matrices[0])
    assert np.array_equal(after, motion.matrices[-1])
    with pytest.raises(MuscleMSSError, match="not a finite number"):
        pose_at(motion, float("nan"))


# ---- blending ------------------------------------------------------------------------------

@pytest.mark.parametrize("method", ["linear", "dual quaternion"])
def test_identity_leaves_every_point_exactly_where_it_was(method):
    rng = np.random.default_rng(1)
    points = rng.normal(scale=80.0, size=(500, 3)) + [13.1, -7.7, 250.3]
    weights = random_weights(rng, 500, 3)
    identity = np.repeat(rigid([0, 0, 0], [0, 0, 0])[None], 3, axis=0)
    assert np.array_equal(blend(points, weights, identity, method), points)
    assert np.array_equal(transform_rigid(points, identity[0]), points)


@pytest.mark.parametrize("method", ["linear", "dual quaternion"])
def test_the_same_transform_on_every_bone_moves_everything_rigidly(method):
    rng = np.random.default_rng(2)
    points = rng.normal(scale=60.0, size=(200, 3))
    weights = random_weights(rng, 200, 3)
    m = rigid([0.7, -1.9, 2.4], [15.0, -3.0, 40.0])
    posed = blend(points, weights, np.repeat(m[None], 3, axis=0), method)
    np.testing.assert_allclose(posed, points @ m[:, :3].T + m[:, 3], atol=1e-9)
    rest_d = np.linalg.norm(points[:, None] - points[None], axis=2)
    posed_d = np.linalg.norm(posed[:, None] - posed[None], axis=2)
    assert np.abs(posed_d - rest_d).max() < 1e-9


def test_dual_quaternion_keeps_lengths_where_linear_blending_shortens_them():
    # Two bones: one still, one turned by 120 degrees about z. Two nearby points halfway between.
    matrices = np.stack([rigid([0, 0, 0], [0, 0, 0]), rigid([0, 0, 2 * math.pi / 3], [0, 0, 0])])
    points = np.array([[30.0, 0.0, 0.0], [30.0, 5.0, 0.0]])
    weights = np.full((2, 2), 0.5)
    rest = np.linalg.norm(points[1] - points[0])
    dq = blend_dual_quaternion(points, weights, matrices)
    lin = blend_linear(points, weights, matrices)
    assert np.linalg.norm(dq[1] - dq[0]) == pytest.approx(rest, abs=1e-12)
    assert np.linalg.norm(lin[1] - lin[0]) == pytest.approx(rest * math.cos(math.pi / 3),
                                                            abs=1e-12)
    # The blended rotation is the half-way one.
    np.testing.assert_allclose(dq[0], [30 * math.cos(math.pi / 3), 30 * math.sin(math.pi / 3), 0],
                               atol=1e-12)


def test_blends_match_the_naive_references():
    rng = np.random.default_rng(4)
    points = rng.normal(scale=50.0, size=(300, 3))
    weights = random_weights(rng, 300, 3)
    weights[rng.random((300, 3)) < 0.3] = 0.0
    weights[weights.sum(axis=1) == 0, 0] = 1.0
    weights /= weights.sum(axis=1, keepdims=True)
    matrices = np.stack([rigid(rng.normal(size=3), rng.normal(scale=20, size=3))
                         for _ in range(3)])
    np.testing.assert_allclose(blend_linear(points, weights, matrices),
                               naive_linear(points, weights, matrices), atol=1e-10)
    np.testing.assert_allclose(blend_dual_quaternion(points, weights, matrices),
                               naive_dual_quaternion(points, weights, matrices), atol=1e-10)


def test_dual_quaternion_blend_across_a_half_turn_does_not_collapse():
    # Bones 179 degrees apart: without the hemisphere alignment the quaternions nearly cancel.
    matrices = np.stack([rigid([0, 0, 0], [0, 0, 0]), rigid([0, 0, math.radians(179)], [0, 0, 0])])
    points = np.array([[10.0, 0.0, 0.0]])
    posed = blend_dual_quaternion(points, np.array([[0.5, 0.5]]), matrices)
    assert np.linalg.norm(posed[0]) == pytest.approx(10.0, abs=1e-9)
    np.testing.assert_allclose(posed, naive_dual_quaternion(points, np.array([[0.5, 0.5]]),
                                                            matrices), atol=1e-9)


def test_blend_refuses_bad_weights():
    matrices = np.stack([rigid([0, 0, 0], [0, 0, 0])] * 2)
    points = np.zeros((2, 3))
    with pytest.raises(MuscleMSSError, match="point 1 sum to 0.5"):
        blend_linear(points, np.array([[0.5, 0.5], [0.5, 0.0]]), matrices)
    with pytest.raises(MuscleMSSError, match=r"\(2, 2\)"):
        blend_dual_quaternion(points, np.ones((2, 3)) / 3, matrices)
    with pytest.raises(MuscleMSSError, match="not one of"):
        blend(points, np.full((2, 2), 0.5), matrices, "cubic")


# ---- weights ------------------------------------------------------------------------------

def naive_distances(points, vertices, triangles):
    """Distance to a triangle set, every triangle measured (no pruning), in NumPy."""
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    best = np.full(len(points), np.inf)
    for i, p in enumerate(points):
        u, v, w = b - a, c - a, p - a
        n = np.cross(u, v)
        gram = np.stack([np.stack([(u * u).sum(1), (u * v).sum(1)], 1),
                         np.stack([(u * v).sum(1), (v * v).sum(1)], 1)], 1)
        rhs = np.stack([(w * u).sum(1), (w * v).sum(1)], 1)
        beta_gamma = np.linalg.solve(gram, rhs[..., None])[..., 0]
        inside = (beta_gamma >= 0).all(1) & (beta_gamma.sum(1) <= 1)
        plane = np.abs((w * n).sum(1)) / np.linalg.norm(n, axis=1)
        edges = []
        for s, e in ((a, b), (b, c), (c, a)):
            t = np.clip(((p - s) * (e - s)).sum(1) / ((e - s) ** 2).sum(1), 0, 1)
            edges.append(np.linalg.norm(p - (s + t[:, None] * (e - s)), axis=1))
        d = np.where(inside, plane, np.minimum.reduce(edges))
        best[i] = d.min()
    return best


def test_distances_to_cubes_are_exact_inside_and_outside():
    rng = np.random.default_rng(5)
    points = rng.uniform(-40, 40, size=(2000, 3))
    bones = [cube(10.0), cube(7.0, (0, 0, 25))]
    d = bone_distances(points, bones)
    np.testing.assert_allclose(d[:, 0], box_distance(points, 10.0, (0, 0, 0)), atol=1e-12)
    np.testing.assert_allclose(d[:, 1], box_distance(points, 7.0, (0, 0, 25)), atol=1e-12)


def subdivided_cube(half, n):
    """The surface of the cube [-half, half]^3, each face an n x n grid of squares split in two."""
    u = np.linspace(-half, half, n + 1)
    a, b = (g.ravel() for g in np.meshgrid(u, u, indexing="ij"))
    quad = np.array([[i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1,
                      i * (n + 1) + j + 1] for i in range(n) for j in range(n)])
    vertices, triangles = [], []
    for axis in range(3):
        for side in (-half, half):
            face = np.empty((len(a), 3))
            face[:, axis] = side
            face[:, (axis + 1) % 3] = a
            face[:, (axis + 2) % 3] = b
            offset = sum(len(v) for v in vertices)
            vertices.append(face)
            triangles.append(quad[:, [0, 1, 2]] + offset)
            triangles.append(quad[:, [0, 2, 3]] + offset)
    return np.concatenate(vertices), np.concatenate(triangles)


def test_distances_to_finely_meshed_cubes_are_exact_near_and_far():
    # 4800 and 1200 triangles: many cells and blocks of the search, all pruned by bounds.
    rng = np.random.default_rng(7)
    near = rng.uniform(-30, 30, size=(1500, 3))
    far = rng.normal(size=(200, 3))
    far = far / np.linalg.norm(far, axis=1, keepdims=True) * rng.uniform(100, 400, size=(200, 1))
    points = np.concatenate([near, far])
    big, small = subdivided_cube(20.0, 20), subdivided_cube(5.0, 10)
    d = bone_distances(points, [big, (small[0] + [0, 0, 40], small[1])])
    np.testing.assert_allclose(d[:, 0], box_distance(points, 20.0, (0, 0, 0)), atol=1e-10)
    np.testing.assert_allclose(d[:, 1], box_distance(points, 5.0, (0, 0, 40)), atol=1e-10)


def test_distances_match_the_unpruned_reference_on_a_triangle_soup():
    rng = np.random.default_rng(6)
    vertices = rng.normal(scale=20.0, size=(90, 3))
    triangles = rng.integers(0, 90, size=(60, 3))
    distinct = ((triangles[:, 0] != triangles[:, 1]) & (triangles[:, 1] != triangles[:, 2])
                & (triangles[:, 0] != triangles[:, 2]))
    triangles = triangles[distinct]
    points = rng.normal(scale=30.0, size=(150, 3))
    d = bone_distances(points, [(vertices, triangles)])
    np.testing.assert_allclose(d[:, 0], naive_distances(points, vertices, triangles), atol=1e-10)


def test_a_degenerate_triangle_is_measured_as_its_edges():
    vertices = np.array([[0.0, 0, 0], [10.0, 0, 0], [20.0, 0, 0]])
    d = bone_distances(np.array([[5.0, 3.0, 4.0], [-3.0, 4.0, 0.0]]), [(vertices, [[0, 1, 2]])])
    np.testing.assert_allclose(d[:, 0], [5.0, 5.0], atol=1e-12)


def test_weights_follow_the_documented_formula():
    d = np.array([[5.0, 50.0, 60.0],
                  [60.0, 5.0, 50.0],
                  [10.0, 10.0, 10.0],
                  [0.0, 100.0, 100.0]])
    w = weights_from_distances(d, 2, 20.0)
    e = np.exp(-np.array([5.0, 50.0, 60.0]) / 20.0)
    expected = np.array([e[0] - e[2], e[1] - e[2]]) / (e[0] + e[1] - 2 * e[2])
    np.testing.assert_allclose(w[0], [expected[0], expected[1], 0.0], atol=1e-15)
    np.testing.assert_allclose(w[1], [0.0, expected[0], expected[1]], atol=1e-15)
    np.testing.assert_allclose(w[2], [0.5, 0.5, 0.0])   # three-way tie: the first two share
    np.testing.assert_allclose(w[3], [1.0, 0.0, 0.0])   # the others equally far: all to the nearest
    np.testing.assert_allclose(weights_from_distances(d, 1, 20.0)[:2],
                               [[1, 0, 0], [0, 1, 0]])
    all_bones = weights_from_distances(d[:1], 3, 20.0)
    np.testing.assert_allclose(all_bones[0], e / e.sum(), atol=1e-15)


def test_weights_are_continuous_where_the_nearest_bones_change():
    # A point moving along a line past three bones: the second and third nearest swap at x = 0.
    x = np.linspace(-1.0, 1.0, 2001)
    d = np.stack([np.full_like(x, 5.0), 30.0 + x, 30.0 - x], axis=1)
    w = weights_from_distances(d, 2, 20.0)
    assert np.abs(np.diff(w, axis=0)).max() < 1e-3
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-15)


def test_bone_weights_refuse_bad_input():
    bones = [cube(10.0)]
    with pytest.raises(MuscleMSSError, match="fall-off"):
        bone_weights(np.zeros((1, 3)), bones, 2, 0.0)
    with pytest.raises(MuscleMSSError, match="at least 1"):
        bone_weights(np.zeros((1, 3)), bones, 0, 20.0)
    with pytest.raises(MuscleMSSError, match="femur'.*no triangles"):
        bone_weights(np.zeros((1, 3)), [(CUBE_CORNERS, np.zeros((0, 3)))], 2, 20.0,
                     labels=["bones.vtm block 'femur'"])
    with pytest.raises(MuscleMSSError, match="point 1 has a NaN"):
        bone_weights(np.array([[0, 0, 0], [np.nan, 0, 0]]), bones, 2, 20.0)
