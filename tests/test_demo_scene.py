"""The demo thigh scene (issue 2, DESIGN §4): closed outward surfaces, fibres inside their
muscles, packed muscles touching each other and the femur, a rigid anatomical walking cycle,
determinism, and a preview picture that is not blank.

Runs in the venv and in Debian's ParaView Python (vtkmodules only; the picture test needs
pyvista and is skipped without it).
"""
import importlib.util

import numpy as np
import pytest

from muscle_mss.core.demo import scene as demo
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.motion import rigid_problem
from muscle_mss.core.mesh_checks import surface_problems
from muscle_mss.core.volume import signed_volume
from surface_probes import (assert_closed_and_outward, assert_identical_scenes, gap as _gap,
                            inside as _inside, signed_distance as _signed_distance)

# Muscles that lie on the femur along their belly: the vasti, the short head of biceps and
# adductor magnus.
WRAPPING_FEMUR = ("vastus_lateralis", "vastus_intermedius", "vastus_medialis",
                  "biceps_femoris_short_head", "adductor_magnus")
INSERTING_ON_FEMUR = ("adductor_longus", "adductor_brevis", "adductor_magnus")
TOUCH_TOLERANCE = 1.0      # mm: neighbours touch or overlap
FEMUR_TOLERANCE = 3.0      # mm: muscles wrapping the femur lie against it
ATTACHMENT_TOLERANCE = 2.5  # mm: fibre ends on their bone (plus the bone mesh's chord error)


@pytest.fixture(scope="module")
def full():
    return demo.demo_scene("full")


@pytest.fixture(scope="module")
def small():
    return demo.demo_scene("small")


# ---- structure -----------------------------------------------------------------------------

def test_full_scene_has_the_anatomical_parts(full):
    assert list(full.bones) == ["pelvis", "femur", "tibia"]
    assert list(full.muscles) == list(demo.MUSCLE_NAMES)
    assert list(full.fibres) == list(demo.MUSCLE_NAMES)
    assert len(demo.MUSCLE_NAMES) == 13 and len(set(demo.MUSCLE_NAMES)) == 13
    for name, fibres in full.fibres.items():
        assert fibres.count == 64, name
        assert np.array_equal(np.diff(fibres.offsets), np.full(64, 30)), name
        grid = {tuple(g) for g in fibres.grid}
        assert grid == {(r, c) for r in range(8) for c in range(8)}, name
    assert full.motion.bones == ["pelvis", "femur", "tibia"]
    assert len(full.motion.times) == 21


def test_small_scene_is_a_smaller_full_grid_scene(full, small):
    assert list(small.bones) == list(full.bones)
    assert set(small.muscles) < set(full.muscles)
    assert len(small.muscles) == 4
    for name, fibres in small.fibres.items():
        g = int(round(np.sqrt(fibres.count)))
        assert g * g == fibres.count and g < 8, name
        assert {tuple(x) for x in fibres.grid} == {(r, c) for r in range(g) for c in range(g)}
        assert len(small.muscles[name].triangles) < len(full.muscles[name].triangles)
        assert len(fibres.points) < len(full.fibres[name].points)
    for bone in full.bones:
        assert len(small.bones[bone].triangles) < len(full.bones[bone].triangles)
    assert np.array_equal(small.motion.matrices, full.motion.matrices)


def test_unknown_size_is_refused():
    with pytest.raises(MuscleMSSError, match="size 'huge'"):
        demo.demo_scene("huge")


def test_demo_scene_is_deterministic(small):
    assert_identical_scenes(small, demo.demo_scene("small"))


# ---- surfaces ------------------------------------------------------------------------------

@pytest.mark.parametrize("size", ["full", "small"])
def test_every_surface_is_closed_manifold_and_outward(size, full, small):
    scene = full if size == "full" else small
    assert_closed_and_outward(scene)


def test_bones_are_shaped_like_bones(full):
    """Not cylinders: the femur's head, neck, shaft and condyles; the pelvis's wing and socket;
    the tibia's plateau wider than its shaft."""
    femur = full.bones["femur"].points
    head = np.linalg.norm(femur - demo.HIP_CENTRE, axis=1)
    assert abs(np.median(head[head < demo.FEMORAL_HEAD_RADIUS + 3.0]) - demo.FEMORAL_HEAD_RADIUS) < 1.0
    shaft = femur[np.abs(femur[:, 2] + 200.0) < 3.0]
    condyles = femur[np.abs(femur[:, 2] + 395.0) < 3.0]
    assert np.ptp(shaft[:, 0]) < 40.0 and np.ptp(condyles[:, 0]) > 70.0
    assert femur[:, 0].min() < -15.0 and femur[:, 0].max() > 55.0   # head medial, trochanter lateral
    pelvis = full.bones["pelvis"]
    socket = np.linalg.norm(pelvis.points - demo.HIP_CENTRE, axis=1)
    assert socket.min() > demo.FEMORAL_HEAD_RADIUS                  # the head fits in the socket
    assert (socket < demo.FEMORAL_HEAD_RADIUS + 3.0).sum() > 50     # ... which wraps it
    assert np.ptp(pelvis.points[:, 2]) > 180.0 and pelvis.points[:, 2].max() > 100.0  # the wing
    tibia = full.bones["tibia"].points
    plateau = tibia[np.abs(tibia[:, 2] + 433.0) < 3.0]
    tibial_shaft = tibia[np.abs(tibia[:, 2] + 600.0) < 3.0]
    assert np.ptp(plateau[:, 0]) > 2.5 * np.ptp(tibial_shaft[:, 0])


# ---- fibres ----------------------------------------------------------------------------------

@pytest.mark.parametrize("size", ["full", "small"])
def test_fibres_lie_inside_their_own_muscle(size, full, small):
    scene = full if size == "full" else small
    for name, fibres in scene.fibres.items():
        inside = _inside(scene.muscles[name], fibres.points)
        assert inside.mean() >= 0.99, (name, inside.mean())


def test_outer_fibres_lie_just_beneath_the_surface(full):
    for name, fibres in full.fibres.items():
        outer = np.isin(fibres.grid, [0, 7]).any(axis=1)
        middle = np.concatenate([fibres.fibre(f)[10:20] for f in np.flatnonzero(outer)])
        depth = -_signed_distance(full.muscles[name], middle)
        assert np.median(depth) < 4.0, name
        inner = np.concatenate([fibres.fibre(f)[10:20] for f in np.flatnonzero(~outer)])
        assert np.median(depth) < 0.5 * np.median(-_signed_distance(full.muscles[name], inner))


def test_fibres_run_from_origin_to_insertion_on_the_right_bones(full):
    bones = {b: full.bones[b] for b in full.bones}
    for name, fibres in full.fibres.items():
        origin_bone, origin, insertion_bone, insertion = demo.muscle_attachments(name)
        starts = fibres.points[fibres.offsets[:-1]]
        ends = fibres.points[fibres.offsets[1:] - 1]
        assert np.abs(_signed_distance(bones[origin_bone], starts)).max() < ATTACHMENT_TOLERANCE, name
        assert np.abs(_signed_distance(bones[insertion_bone], ends)).max() < ATTACHMENT_TOLERANCE, name
        assert np.linalg.norm(starts - origin, axis=1).max() < 3.0
        assert np.linalg.norm(ends - insertion, axis=1).max() < 3.0
        assert origin[2] > insertion[2]                        # origin is the proximal end
    expected = {"vastus_lateralis": ("femur", "tibia"), "adductor_longus": ("pelvis", "femur"),
                "biceps_femoris_short_head": ("femur", "tibia"), "sartorius": ("pelvis", "tibia"),
                "semimembranosus": ("pelvis", "tibia"), "adductor_magnus": ("pelvis", "femur")}
    for name, (o, i) in expected.items():
        attachments = demo.muscle_attachments(name)
        assert (attachments[0], attachments[2]) == (o, i), name


# ---- packing -------------------------------------------------------------------------------

def test_each_muscle_touches_a_neighbour(full):
    names = list(full.muscles)
    for a in names:
        gaps = {}
        for b in names:
            if b != a:
                gaps[b] = _gap(full.muscles[a], full.muscles[b])
                if gaps[b] < TOUCH_TOLERANCE:
                    break
        assert min(gaps.values()) < TOUCH_TOLERANCE, (a, gaps)


def test_small_scene_muscles_touch_each_other_and_the_femur(small):
    names = list(small.muscles)
    for a in names:
        assert min(_gap(small.muscles[a], small.muscles[b]) for b in names if b != a) < TOUCH_TOLERANCE
        if a in WRAPPING_FEMUR:
            assert _gap(small.muscles[a], small.bones["femur"]) < FEMUR_TOLERANCE, a


def test_muscles_wrapping_the_femur_lie_against_it(full):
    """Not only at an attachment: the belly, away from both ends, reaches the bone."""
    femur = full.bones["femur"]
    for name in WRAPPING_FEMUR:
        points = full.muscles[name].points
        _, origin, _, insertion = demo.muscle_attachments(name)
        away = ((np.linalg.norm(points - origin, axis=1) > 40.0)
                & (np.linalg.norm(points - insertion, axis=1) > 40.0))
        assert _signed_distance(femur, points[away]).min() < FEMUR_TOLERANCE, name
    for name in INSERTING_ON_FEMUR:
        assert _gap(full.muscles[name], femur) < FEMUR_TOLERANCE, name


def test_muscles_do_not_swallow_each_other(full):
    """Neighbours share faces: along them they overlap slightly, but hardly any of a muscle's
    belly (the middle 60 % of its height; the quadriceps share a tendon) lies deep inside
    another muscle."""
    for a, surface in full.muscles.items():
        z = surface.points[:, 2]
        lo, hi = np.percentile(z, [20.0, 80.0])
        belly = surface.points[(z > lo) & (z < hi)]
        for b, other in full.muscles.items():
            near = belly[((belly > other.points.min(axis=0)) & (belly < other.points.max(axis=0))).all(axis=1)]
            if a != b and len(near):
                assert (_signed_distance(other, near) < -2.0).sum() < 0.05 * len(belly), (a, b)


# ---- motion --------------------------------------------------------------------------------

def test_every_motion_transform_is_rigid(full):
    for t in range(len(full.motion.times)):
        for b in range(len(full.motion.bones)):
            assert rigid_problem(full.motion.matrices[t, b]) is None


def test_pelvis_fixed_femur_about_the_hip_tibia_about_the_knee(full):
    m = full.motion.matrices
    identity = np.hstack([np.eye(3), np.zeros((3, 1))])
    assert np.allclose(m[:, 0], identity)
    hip = np.append(demo.HIP_CENTRE, 1.0)
    knee = np.append(demo.KNEE_CENTRE, 1.0)
    assert np.allclose(m[:, 1] @ hip, demo.HIP_CENTRE)          # the femoral head stays put
    assert np.allclose(m[:, 2] @ knee, m[:, 1] @ knee)          # the knee axis moves with the femur
    hip_deg, knee_deg = demo.gait_angles(full.motion.times)
    femur_angle = np.degrees(np.arctan2(m[:, 1, 2, 1], m[:, 1, 1, 1]))
    assert np.allclose(femur_angle, hip_deg)
    relative = np.einsum("tij,tjk->tik", np.transpose(m[:, 1, :, :3], (0, 2, 1)), m[:, 2, :, :3])
    assert np.allclose(np.degrees(np.arctan2(-relative[:, 2, 1], relative[:, 1, 1])), knee_deg)
    # Flexing the hip swings the knee forward; flexing the knee swings the ankle back.
    t = int(np.argmax(hip_deg))
    assert (m[t, 1] @ knee)[1] > 100.0
    ankle = np.array([3.0, 3.0, -770.0, 1.0])
    t = int(np.argmax(knee_deg))
    assert (m[t, 2] @ ankle)[1] < (m[t, 1] @ ankle)[1] - 200.0


def test_walking_cycle_follows_normative_gait():
    times = np.linspace(0.0, demo.GAIT_CYCLE, 201)
    hip, knee = demo.gait_angles(times)
    assert 25.0 <= hip[0] <= 35.0                       # heel strike
    assert -15.0 <= hip.min() <= -5.0 and 0.4 <= times[np.argmin(hip)] <= 0.6
    assert 28.0 <= hip.max() <= 40.0
    assert 0.0 <= knee[0] <= 8.0                        # heel strike
    loading = knee[(times > 0.05) & (times < 0.25)]
    assert 12.0 <= loading.max() <= 25.0                # loading response
    stance = knee[(times > 0.35) & (times < 0.48)]
    assert stance.min() <= 6.0                          # near extension in mid/terminal stance
    assert 55.0 <= knee.max() <= 70.0 and 0.65 <= times[np.argmax(knee)] <= 0.8  # swing peak
    assert knee.min() >= -2.0
    assert np.allclose(demo.gait_angles(times + demo.GAIT_CYCLE), (hip, knee))   # periodic


def test_marching_tetrahedra_meshes_a_sphere_and_a_torus():
    sphere = demo.mesh_implicit(lambda p: np.linalg.norm(p, axis=1) - 10.0, [-13] * 3, [13] * 3, 1.5)
    assert surface_problems(sphere.points, sphere.triangles) == []
    assert np.allclose(np.linalg.norm(sphere.points, axis=1), 10.0, atol=1e-3)
    assert abs(signed_volume(sphere.points, sphere.triangles) / (4.0 / 3.0 * np.pi * 1000.0) - 1) < 0.03

    def torus(p):
        return np.hypot(np.hypot(p[:, 0], p[:, 1]) - 10.0, p[:, 2]) - 4.0
    ring = demo.mesh_implicit(torus, [-16, -16, -6], [16, 16, 6], 1.0)
    assert surface_problems(ring.points, ring.triangles) == []
    euler = len(ring.points) - len(ring.triangles) * 3 // 2 + len(ring.triangles)
    assert euler == 0                                   # genus 1 kept: the obturator foramen works


# ---- picture -------------------------------------------------------------------------------

@pytest.mark.skipif(importlib.util.find_spec("pyvista") is None, reason="needs pyvista")
def test_preview_is_written_and_not_blank(small, tmp_path):
    from muscle_mss.app.pictures import pose_time, scene_preview
    path = scene_preview(small, tmp_path / "preview.png", window_size=(640, 400))
    import pyvista
    image = pyvista.read(path)
    pixels = np.asarray(image.point_data[image.point_data.keys()[0]], dtype=np.float64)
    assert len(pixels) == 640 * 400
    assert pixels[:, :3].std() > 10.0
    assert 0.65 <= pose_time(small.motion) <= 0.8              # mid-swing by default
