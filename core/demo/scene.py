"""The deterministic demo scene (DESIGN §4): a right thigh with 13 muscles and one walking cycle.

Axes: x lateral (to the right), y anterior, z superior; millimetres; the hip centre (the centre
of the femoral head) is the origin. The scene is the embedded default of the demo, the tests and
the benchmarks, so it is built from closed formulas only: no random numbers, no files.

Bones (pelvis, femur, tibia) are the zero level sets of implicit functions, smooth unions of
spheres, ellipsoids and round cones placed at anatomical landmarks (acetabulum, iliac wing and
crest, pubis, ischium with the obturator foramen; femoral head, neck, trochanters, shaft, linea
aspera, condyles; tibial plateau, tuberosity, shaft, malleolus), meshed by marching tetrahedra.
Muscles follow the paper's input (§3): a closed surface and fibres from origin to insertion, each
a fusiform envelope around a centreline through anatomical way-points, packed against its
neighbours and the bones (:mod:`.demo.geometry` holds the machinery shared with the elbow scene
of :mod:`.demo.arm`).

The walking cycle rotates the femur about the hip centre (flexion / extension about the x axis)
and the tibia additionally about the knee axis, after normative sagittal gait curves.
"""
from __future__ import annotations

from functools import partial

import numpy as np
from scipy.interpolate import CubicSpline

from .geometry import (MuscleSpec as _MuscleSpec, Size as _Size,  # noqa: F401
                            around, assemble_scene, compose as _compose,
                            ellipsoid as _ellipsoid, frame as _frame, rotation_about,
                            round_cone as _round_cone, size_named, smooth_union as _blend,
                            sphere as _sphere, v as _v)
from .implicit_meshing import (SampledField, mesh_implicit, mesh_sampled,  # noqa: F401
                               project_to_surface)
from ..scene import Motion, Scene, Surface

HIP_CENTRE = np.array([0.0, 0.0, 0.0])
"""Centre of the femoral head (mm): the hip's centre of rotation."""
HIP_AXIS = np.array([1.0, 0.0, 0.0])
"""Hip flexion axis: positive rotation about +x (right-hand rule) swings the knee forward."""
KNEE_CENTRE = np.array([7.0, -8.0, -395.0])
"""A point of the knee flexion axis (mm): midway between the centres of the femoral condyles."""
KNEE_AXIS = np.array([1.0, 0.0, 0.0])
"""Knee flexion axis (through the condyle centres); flexion is a negative rotation about it,
which swings the tibia backward."""
GAIT_CYCLE = 1.0
"""Duration of the walking cycle (s), heel strike to heel strike of the right foot."""
TIME_POINTS = 21
"""Time points of the demo motion, evenly spread over one cycle including both heel strikes."""

BONE_NAMES = ("pelvis", "femur", "tibia")
MUSCLE_NAMES = (
    "rectus_femoris", "vastus_lateralis", "vastus_intermedius", "vastus_medialis",
    "sartorius", "gracilis", "adductor_longus", "adductor_brevis", "adductor_magnus",
    "semitendinosus", "semimembranosus", "biceps_femoris_long_head",
    "biceps_femoris_short_head",
)
SMALL_MUSCLE_NAMES = ("rectus_femoris", "vastus_lateralis", "vastus_intermedius",
                      "vastus_medialis")
"""The muscles of ``demo_scene("small")``: the quadriceps, which touch each other and the femur."""

# Sagittal joint angles over one cycle (fraction of the cycle, degrees), read off normative adult
# gait curves (Perry & Burnfield, Gait Analysis; Winter, Biomechanics and Motor Control of Human
# Movement): hip 30 deg flexion at heel strike, -10 deg extension at terminal stance, ~35 deg
# in late swing; knee 5 deg at heel strike, ~18 deg loading response, ~3 deg mid/terminal stance,
# ~62 deg peak in initial swing. A periodic cubic spline joins them.
_HIP_CURVE = ((0.0, 30.0), (0.12, 25.0), (0.3, 8.0), (0.5, -10.0), (0.62, 0.0), (0.75, 22.0),
              (0.87, 34.0), (1.0, 30.0))
_KNEE_CURVE = ((0.0, 5.0), (0.15, 18.0), (0.3, 8.0), (0.42, 3.0), (0.52, 12.0), (0.62, 40.0),
               (0.72, 62.0), (0.82, 45.0), (0.92, 12.0), (1.0, 5.0))

_SIZES = {
    "full": _Size(bone_spacing=4.0, grid=8, fibre_vertices=30, refine=1, ring_vertices=32),
    "small": _Size(bone_spacing=7.0, grid=4, fibre_vertices=12, refine=2, ring_vertices=16),
}


# ---- joint angles and motion -------------------------------------------------------------

def _periodic_spline(curve):
    u, angle = np.array(curve).T
    return CubicSpline(u * GAIT_CYCLE, angle, bc_type="periodic")


def gait_angles(times):
    """Hip and knee flexion (degrees) of the demo walking cycle at ``times`` (s).

    The cycle repeats every :data:`GAIT_CYCLE` seconds. Hip flexion is positive when the thigh
    swings forward, knee flexion is positive when the shank swings back.

    Returns
    -------
    (hip_flexion_deg, knee_flexion_deg) : two (T,) float64 arrays
    """
    t = np.mod(np.asarray(times, dtype=np.float64), GAIT_CYCLE)
    return _periodic_spline(_HIP_CURVE)(t), _periodic_spline(_KNEE_CURVE)(t)



def gait_motion(time_points: int = TIME_POINTS) -> Motion:
    """One walking cycle: pelvis fixed, femur rotated about the hip centre by the hip flexion,
    tibia = femur transform composed with the knee flexion about the knee axis.

    ``time_points`` evenly spaced times (s) from 0 to :data:`GAIT_CYCLE` inclusive.
    """
    times = np.linspace(0.0, GAIT_CYCLE, time_points)
    hip, knee = gait_angles(times)
    matrices = np.empty((len(times), len(BONE_NAMES), 3, 4))
    for i, (h, k) in enumerate(zip(hip, knee)):
        femur = rotation_about(HIP_AXIS, HIP_CENTRE, h)
        matrices[i, 0] = np.hstack([np.eye(3), np.zeros((3, 1))])
        matrices[i, 1] = femur
        matrices[i, 2] = _compose(femur, rotation_about(KNEE_AXIS, KNEE_CENTRE, -k))
    return Motion(times, list(BONE_NAMES), matrices)



# ---- bones ---------------------------------------------------------------------------------

ASIS = _v(34.0, 52.0, 68.0)            # anterior superior iliac spine
AIIS = _v(28.0, 40.0, 32.0)            # anterior inferior iliac spine
PSIS = _v(-45.0, -88.0, 62.0)          # posterior superior iliac spine
PUBIC_BODY = _v(-74.0, 36.0, -34.0)
ISCHIAL_TUBEROSITY = _v(-32.0, -44.0, -70.0)
_ACETABULUM_OPENING = _v(0.72, 0.3, -0.62) / np.linalg.norm(_v(0.72, 0.3, -0.62))
_WING_CENTRE = _v(-8.0, -16.0, 72.0)
_WING_FRAME = _frame(ASIS - PSIS, _v(0.25, 0.1, 1.0))
_WING_RADII = _v(86.0, 52.0, 6.0)


def _pelvis(p):
    body = _sphere(p, -14.0 * _ACETABULUM_OPENING, 29.5)
    wing = _ellipsoid(p, _WING_CENTRE, _WING_RADII, _WING_FRAME)
    # The iliac crest: a thick rim along the upper half of the wing.
    angles = np.linspace(0.0, np.pi, 7)
    rim = [_WING_CENTRE + 0.93 * (_WING_RADII[0] * np.cos(a) * _WING_FRAME[0]
                                  + _WING_RADII[1] * np.sin(a) * _WING_FRAME[1]) for a in angles]
    crest = [_round_cone(p, rim[i], rim[i + 1], 6.5, 6.5) for i in range(len(rim) - 1)]
    ilium = _round_cone(p, _v(-4.0, -6.0, 18.0), _v(-10.0, -18.0, 58.0), 19.0, 14.0)
    spines = [_sphere(p, ASIS, 8.0), _sphere(p, AIIS, 7.0)]
    # The anterior border of the ilium: ASIS down to AIIS and on to the acetabular rim.
    anterior_border = [_round_cone(p, ASIS, AIIS, 7.0, 7.0),
                       _round_cone(p, AIIS, _v(8.0, 18.0, 14.0), 7.0, 12.0)]
    superior_ramus = _round_cone(p, _v(-14.0, 24.0, -6.0), PUBIC_BODY + _v(6.0, 0.0, 6.0), 10.0, 8.5)
    pubis = _ellipsoid(p, PUBIC_BODY + _v(-6.0, -2.0, -4.0), _v(10.0, 12.0, 24.0))
    inferior_ramus = _round_cone(p, PUBIC_BODY + _v(-2.0, -8.0, -22.0),
                                 ISCHIAL_TUBEROSITY + _v(-8.0, 6.0, -2.0), 7.5, 8.5)
    ischium = _round_cone(p, _v(-10.0, -24.0, -18.0), ISCHIAL_TUBEROSITY, 13.0, 12.0)
    tuberosity = _ellipsoid(p, ISCHIAL_TUBEROSITY, _v(12.0, 14.0, 18.0))
    solid = _blend(5.0, body, wing, *crest, ilium, *spines, *anterior_border, superior_ramus, pubis,
                   inferior_ramus, ischium, tuberosity)
    # The acetabulum: a socket 2 mm wider than the femoral head (cartilage space).
    return np.maximum(solid, -_sphere(p, HIP_CENTRE, 24.0))


FEMORAL_HEAD_RADIUS = 22.0
_SHAFT_TOP = _v(42.0, -4.0, -50.0)
_SHAFT_MID = _v(26.0, 3.0, -200.0)
_SHAFT_BOTTOM = _v(10.0, 0.0, -340.0)
_CONDYLE_RADII = _v(16.0, 27.0, 24.0)
MEDIAL_CONDYLE = _v(-14.0, -8.0, -395.0)
LATERAL_CONDYLE = _v(28.0, -8.0, -395.0)


def _femur(p):
    head = _sphere(p, HIP_CENTRE, FEMORAL_HEAD_RADIUS)
    neck = _round_cone(p, HIP_CENTRE, _v(40.0, -6.0, -42.0), 14.5, 17.0)
    greater_trochanter = _ellipsoid(p, _v(50.0, -9.0, -30.0), _v(13.0, 19.0, 24.0))
    lesser_trochanter = _sphere(p, _v(28.0, -17.0, -74.0), 8.0)
    shaft = _blend(8.0, _round_cone(p, _SHAFT_TOP, _SHAFT_MID, 16.0, 14.0),
                   _round_cone(p, _SHAFT_MID, _SHAFT_BOTTOM, 14.0, 15.0))
    linea_aspera = _round_cone(p, _v(34.0, -14.0, -110.0), _v(18.0, -12.0, -290.0), 5.0, 5.0)
    metaphysis = _ellipsoid(p, _v(8.0, -2.0, -345.0), _v(28.0, 20.0, 40.0))
    condyles = [_ellipsoid(p, MEDIAL_CONDYLE, _CONDYLE_RADII),
                _ellipsoid(p, LATERAL_CONDYLE, _CONDYLE_RADII)]
    trochlea = _ellipsoid(p, _v(7.0, 10.0, -378.0), _v(30.0, 14.0, 22.0))
    epicondyles = [_sphere(p, _v(-27.0, -5.0, -386.0), 9.0), _sphere(p, _v(41.0, -5.0, -386.0), 8.0)]
    return _blend(6.0, head, neck, greater_trochanter, lesser_trochanter, shaft, linea_aspera,
                  metaphysis, *condyles, trochlea, *epicondyles)


TIBIAL_TUBEROSITY = _v(8.0, 24.0, -468.0)
FIBULAR_HEAD = _v(44.0, -18.0, -460.0)


def _tibia(p):
    plateau = _ellipsoid(p, _v(7.0, -4.0, -433.0), _v(40.0, 28.0, 11.0))
    condyles = _ellipsoid(p, _v(7.0, -4.0, -448.0), _v(35.0, 25.0, 20.0))
    tuberosity = _ellipsoid(p, TIBIAL_TUBEROSITY + _v(0.0, -4.0, 0.0), _v(9.0, 8.0, 15.0))
    # The head of the fibula, fused to the tibia in this demo, carries the biceps insertion.
    fibular_head = _sphere(p, FIBULAR_HEAD, 10.0)
    shaft = _round_cone(p, _v(7.0, 0.0, -455.0), _v(3.0, 3.0, -760.0), 17.0, 11.0)
    distal = _ellipsoid(p, _v(2.0, 3.0, -770.0), _v(22.0, 20.0, 17.0))
    malleolus = _sphere(p, _v(-16.0, 5.0, -785.0), 9.0)
    return _blend(6.0, plateau, condyles, tuberosity, fibular_head, shaft, distal, malleolus)


_BONE_FIELDS = {"pelvis": _pelvis, "femur": _femur, "tibia": _tibia}
_BONE_BOXES = {  # (lower, upper) corners enclosing each bone (mm)
    "pelvis": (_v(-100.0, -110.0, -100.0), _v(60.0, 75.0, 135.0)),
    "femur": (_v(-50.0, -45.0, -430.0), _v(75.0, 40.0, 30.0)),
    "tibia": (_v(-45.0, -40.0, -800.0), _v(60.0, 40.0, -415.0)),
}


def bone_field(name: str, points) -> np.ndarray:
    """Implicit function of a demo bone at ``points`` (n, 3) mm: negative inside, zero on the
    surface, roughly the signed distance (mm) near it. ``name``: pelvis, femur or tibia."""
    return _BONE_FIELDS[name](np.asarray(points, dtype=np.float64).reshape(-1, 3))


def project_to_bone(name: str, point, steps: int = 8) -> np.ndarray:
    """The point of the bone's implicit surface reached from ``point`` (mm) by Newton steps
    along the field's gradient (for landmarks within a few mm of the surface)."""
    return project_to_surface(_BONE_FIELDS[name], point, steps)


def sampled_bone(name: str, spacing: float = 3.0) -> SampledField:
    """A demo bone's implicit function sampled on a grid of step ``spacing`` (mm)."""
    lower, upper = _BONE_BOXES[name]
    return SampledField.sample(_BONE_FIELDS[name], lower, upper, spacing)


def bone_surface(name: str, spacing: float = 3.0) -> Surface:
    """The closed surface of a demo bone meshed with grid step ``spacing`` (mm)."""
    return mesh_sampled(sampled_bone(name, spacing))


# ---- muscles -------------------------------------------------------------------------------

def _thigh_axis(z):
    """Point (n, 3) of the femoral shaft axis, extended, at heights ``z`` (mm)."""
    s = (np.asarray(z, dtype=np.float64) - _SHAFT_TOP[2]) / (_SHAFT_BOTTOM[2] - _SHAFT_TOP[2])
    return _SHAFT_TOP + s[:, None] * (_SHAFT_BOTTOM - _SHAFT_TOP)


_around = partial(around, _thigh_axis)
"""``_around(z, theta_deg, rho)``: :func:`.demo.geometry.around` the thigh axis."""


_MUSCLES = {
    "rectus_femoris": _MuscleSpec(
        "pelvis", AIIS + _v(0.0, 2.0, -6.0), "tibia", TIBIAL_TUBEROSITY + _v(0.0, 6.0, 4.0),
        (_around(-60.0, 80.0, 44.0), _around(-200.0, 90.0, 47.0), _around(-320.0, 92.0, 44.0),
         _v(8.0, 44.0, -392.0)),
        radial=15.0, tangential=21.0, peak=0.45),
    "vastus_lateralis": _MuscleSpec(
        "femur", _v(62.0, -2.0, -56.0), "tibia", TIBIAL_TUBEROSITY + _v(6.0, 6.0, 8.0),
        (_around(-120.0, 8.0, 38.0), _around(-230.0, 10.0, 38.0), _around(-330.0, 30.0, 36.0),
         _v(22.0, 40.0, -395.0)),
        radial=17.0, tangential=30.0, peak=0.42, fullness=0.5),
    "vastus_intermedius": _MuscleSpec(
        "femur", _v(50.0, 14.0, -85.0), "tibia", TIBIAL_TUBEROSITY + _v(0.0, 4.0, 12.0),
        (_around(-150.0, 60.0, 25.0), _around(-250.0, 75.0, 25.0), _around(-330.0, 90.0, 28.0),
         _v(7.0, 38.0, -390.0)),
        radial=11.0, tangential=26.0, peak=0.45, fullness=0.5),
    "vastus_medialis": _MuscleSpec(
        "femur", _v(20.0, -8.0, -95.0), "tibia", TIBIAL_TUBEROSITY + _v(-6.0, 6.0, 8.0),
        (_around(-160.0, 175.0, 30.0), _around(-280.0, 150.0, 34.0), _around(-350.0, 125.0, 36.0),
         _v(-8.0, 40.0, -396.0)),
        radial=17.0, tangential=26.0, peak=0.68, fullness=0.7),
    "sartorius": _MuscleSpec(
        "pelvis", ASIS + _v(0.0, 0.0, -6.0), "tibia", _v(-24.0, 14.0, -482.0),
        (_around(0.0, 75.0, 58.0), _around(-100.0, 112.0, 63.0), _around(-200.0, 145.0, 64.0),
         _around(-300.0, 175.0, 60.0), _around(-385.0, 200.0, 50.0), _v(-38.0, -6.0, -440.0)),
        radial=6.0, tangential=15.0, fullness=0.3),
    "gracilis": _MuscleSpec(
        "pelvis", PUBIC_BODY + _v(-4.0, -6.0, -26.0), "tibia", _v(-26.0, 10.0, -488.0),
        (_around(-130.0, 190.0, 62.0), _around(-250.0, 198.0, 57.0), _around(-360.0, 210.0, 48.0),
         _v(-42.0, -12.0, -440.0)),
        radial=7.0, tangential=13.0, peak=0.4, fullness=0.4),
    "adductor_longus": _MuscleSpec(
        "pelvis", PUBIC_BODY + _v(4.0, 2.0, -4.0), "femur", _v(22.0, -17.0, -230.0),
        (_around(-100.0, 165.0, 48.0), _around(-160.0, 195.0, 36.0), _around(-205.0, 235.0, 24.0)),
        radial=11.0, tangential=20.0, peak=0.4),
    "adductor_brevis": _MuscleSpec(
        "pelvis", PUBIC_BODY + _v(2.0, -10.0, -18.0), "femur", _v(32.0, -17.0, -140.0),
        (_around(-85.0, 200.0, 38.0), _around(-120.0, 235.0, 24.0)),
        radial=10.0, tangential=15.0, peak=0.4),
    "adductor_magnus": _MuscleSpec(
        "pelvis", ISCHIAL_TUBEROSITY + _v(-10.0, 6.0, -8.0), "femur", _v(-24.0, -6.0, -362.0),
        (_around(-140.0, 220.0, 42.0), _around(-240.0, 215.0, 32.0), _around(-320.0, 195.0, 28.0)),
        radial=19.0, tangential=28.0, peak=0.4, fullness=0.5),
    "semitendinosus": _MuscleSpec(
        "pelvis", ISCHIAL_TUBEROSITY + _v(-4.0, -6.0, -6.0), "tibia", _v(-28.0, 6.0, -494.0),
        (_around(-150.0, 248.0, 58.0), _around(-280.0, 238.0, 56.0), _around(-380.0, 220.0, 46.0),
         _v(-40.0, -18.0, -440.0)),
        radial=12.0, tangential=14.0, peak=0.4),
    "semimembranosus": _MuscleSpec(
        "pelvis", ISCHIAL_TUBEROSITY + _v(6.0, -4.0, -10.0), "tibia", _v(-22.0, -20.0, -446.0),
        (_around(-170.0, 245.0, 38.0), _around(-300.0, 232.0, 40.0), _around(-380.0, 222.0, 36.0)),
        radial=14.0, tangential=20.0, peak=0.6),
    "biceps_femoris_long_head": _MuscleSpec(
        "pelvis", ISCHIAL_TUBEROSITY + _v(2.0, -8.0, -4.0), "tibia", FIBULAR_HEAD + _v(0.0, -4.0, 6.0),
        (_around(-150.0, 272.0, 50.0), _around(-280.0, 295.0, 48.0), _around(-370.0, 320.0, 44.0)),
        radial=14.0, tangential=18.0, peak=0.45),
    "biceps_femoris_short_head": _MuscleSpec(
        "femur", _v(28.0, -16.0, -210.0), "tibia", FIBULAR_HEAD + _v(-2.0, -2.0, 8.0),
        (_around(-280.0, 295.0, 26.0), _around(-360.0, 318.0, 30.0)),
        radial=9.0, tangential=14.0, peak=0.5),
}

def muscle_attachments(name: str):
    """``(origin bone, origin point, insertion bone, insertion point)`` of a demo muscle; the
    points (mm) lie on the bones' implicit surfaces."""
    spec = _MUSCLES[name]
    return (spec.origin_bone, project_to_bone(spec.origin_bone, spec.origin),
            spec.insertion_bone, project_to_bone(spec.insertion_bone, spec.insertion))


def demo_scene(size: str = "full") -> Scene:
    """The demo thigh scene (DESIGN §4).

    ``"full"``: pelvis, femur and tibia, the 13 muscles of :data:`MUSCLE_NAMES` with an 8x8
    ``fibre_grid`` of 30-vertex fibres each, and a walking cycle of :data:`TIME_POINTS` time
    points. ``"small"``: the same bones and motion, meshed coarser, with the four muscles of
    :data:`SMALL_MUSCLE_NAMES` and a 4x4 grid of 12-vertex fibres, for fast tests.
    Every call returns an identical, newly built scene.
    """
    sizes = size_named(size, _SIZES)
    names = MUSCLE_NAMES if size == "full" else SMALL_MUSCLE_NAMES
    bones = {bone: sampled_bone(bone, sizes.bone_spacing) for bone in BONE_NAMES}
    return assemble_scene(gait_motion(), bones, _MUSCLES, names, project_to_bone,
                          _thigh_axis, sizes)
