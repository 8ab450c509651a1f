"""The deterministic elbow demo scene (DESIGN §4): a right arm with the seven elbow
muscles and one flexion–extension of the elbow.

Axes: x lateral (to the right), y anterior, z superior; millimetres; the centre of the humeral head
(the shoulder's centre of rotation) is the origin. The arm hangs beside the trunk in the anatomical
position, forearm supinated (radius lateral, ulna medial), the elbow flexed
:data:`REST_FLEXION` degrees: the rest pose is the motion's first pose.

Bones (scapula, humerus, ulna, radius) are smooth unions of spheres, ellipsoids and round cones
at anatomical landmarks (glenoid, supra- and infraglenoid tubercles, coracoid, acromion, spine
and blade; humeral head, tubercles, shaft, supracondylar ridges, epicondyles, trochlea and
capitulum; olecranon, coronoid process, ulnar tuberosity, ulnar shaft and head; radial head,
neck, tuberosity, shaft and distal end with the styloid), meshed by marching tetrahedra
(:mod:`.demo.geometry`, shared with the thigh of :mod:`.demo.scene`). Joint spaces of 2 mm keep
the bones apart. Proportions are those of an adult arm: humerus about 320 mm from the head's top
to the trochlea, ulna about 270 mm, radius about 240 mm.

Muscles (paper §3: a closed surface and fibres from origin to insertion) are fusiform envelopes
around centrelines through anatomical way-points, packed against each other and the bones:

========================  =====================================  ==============================
muscle                    origin                                 insertion
========================  =====================================  ==============================
biceps long head          scapula, supraglenoid tubercle         radius, radial tuberosity
biceps short head         scapula, coracoid process tip          radius, radial tuberosity
brachialis                humerus, anterior distal shaft         ulna, ulnar tuberosity
brachioradialis           humerus, lateral supracondylar ridge   radius, above the styloid
triceps long head         scapula, infraglenoid tubercle         ulna, olecranon
triceps lateral head      humerus, posterior shaft (lateral)     ulna, olecranon
triceps medial head       humerus, posterior shaft (distal)      ulna, olecranon
========================  =====================================  ==============================

The motion flexes the elbow from 10 to 130 degrees and back (a cosine ramp over
:data:`TIME_POINTS` time points): ulna and radius rotate rigidly about the elbow's flexion axis
through the centres of the trochlea and the capitulum; scapula and humerus stay fixed.
"""
from __future__ import annotations

from functools import partial

import numpy as np

from .geometry import (MuscleSpec, Size, around, assemble_scene, ellipsoid, frame,
                            rotation_about, round_cone, size_named, smooth_union, sphere, v)
from .implicit_meshing import SampledField, project_to_surface
from ..scene import Motion, Scene

SHOULDER_CENTRE = v(0.0, 0.0, 0.0)
"""Centre of the humeral head (mm)."""
HUMERAL_HEAD_RADIUS = 22.0
ELBOW_CENTRE = v(2.0, 6.0, -308.0)
"""A point of the elbow's flexion axis (mm): between the centres of trochlea and capitulum."""
ELBOW_AXIS = v(1.0, 0.0, 0.0)
"""Elbow flexion axis; flexion is a positive rotation about it (right-hand rule), which swings the
forearm forward and up."""
REST_FLEXION = 10.0
"""Elbow flexion (degrees) of the rest pose, the first and last pose of the motion."""
MAX_FLEXION = 130.0
"""Elbow flexion (degrees) at the middle of the motion."""
DURATION = 2.0
"""Duration of the flexion–extension (s)."""
TIME_POINTS = 13
"""Time points of the motion, evenly spread over :data:`DURATION` including both ends."""

BONE_NAMES = ("scapula", "humerus", "ulna", "radius")
MUSCLE_NAMES = (
    "biceps_long_head", "biceps_short_head", "brachialis", "brachioradialis",
    "triceps_long_head", "triceps_lateral_head", "triceps_medial_head",
)

_SIZES = {
    "full": Size(bone_spacing=3.0, grid=8, fibre_vertices=30, refine=1, ring_vertices=32),
    "small": Size(bone_spacing=5.0, grid=4, fibre_vertices=12, refine=2, ring_vertices=16),
}


# ---- motion ----------------------------------------------------------------------------------

def flexion_angles(times):
    """Elbow flexion (degrees) of the demo motion at ``times`` (s): a cosine ramp from
    :data:`REST_FLEXION` at 0 to :data:`MAX_FLEXION` at half of :data:`DURATION` and back."""
    phase = np.clip(np.asarray(times, dtype=np.float64) / DURATION, 0.0, 1.0)
    return REST_FLEXION + (MAX_FLEXION - REST_FLEXION) * 0.5 * (1.0 - np.cos(2.0 * np.pi * phase))


def flexion_motion(time_points: int = TIME_POINTS) -> Motion:
    """Scapula and humerus fixed; ulna and radius rotated about the elbow axis from the rest
    flexion to the flexion of :func:`flexion_angles` at ``time_points`` times."""
    times = np.linspace(0.0, DURATION, time_points)
    matrices = np.empty((len(times), len(BONE_NAMES), 3, 4))
    identity = np.hstack([np.eye(3), np.zeros((3, 1))])
    for i, angle in enumerate(flexion_angles(times)):
        forearm = rotation_about(ELBOW_AXIS, ELBOW_CENTRE, angle - REST_FLEXION)
        matrices[i] = [identity, identity, forearm, forearm]
    return Motion(times, list(BONE_NAMES), matrices)


_TO_EXTENDED = rotation_about(ELBOW_AXIS, ELBOW_CENTRE, -REST_FLEXION)
_FROM_EXTENDED = rotation_about(ELBOW_AXIS, ELBOW_CENTRE, REST_FLEXION)


def _forearm(*xyz):
    """A forearm landmark given with the elbow straight, placed at the rest flexion (mm)."""
    return _FROM_EXTENDED[:, :3] @ v(*xyz) + _FROM_EXTENDED[:, 3]


# ---- bones -------------------------------------------------------------------------------------

GLENOID_CENTRE = v(-30.0, 0.0, 0.0)
SUPRAGLENOID_TUBERCLE = v(-27.0, 1.0, 24.0)
INFRAGLENOID_TUBERCLE = v(-30.0, -5.0, -26.0)
CORACOID_TIP = v(-16.0, 40.0, 20.0)
_BLADE_CENTRE = v(-82.0, -46.0, -36.0)
_BLADE_FRAME = frame(v(0.0, 0.0, 1.0), v(-0.8, -0.6, 0.0))
_BLADE_RADII = v(78.0, 46.0, 4.0)


def _scapula(p):
    glenoid = ellipsoid(p, GLENOID_CENTRE, v(9.0, 14.0, 21.0))
    neck = round_cone(p, v(-36.0, -2.0, 0.0), v(-50.0, -14.0, -4.0), 13.0, 11.0)
    supraglenoid = sphere(p, SUPRAGLENOID_TUBERCLE, 4.5)
    infraglenoid = ellipsoid(p, INFRAGLENOID_TUBERCLE, v(6.0, 6.0, 9.0))
    coracoid = [round_cone(p, v(-42.0, 6.0, 22.0), v(-34.0, 28.0, 32.0), 7.0, 6.5),
                round_cone(p, v(-34.0, 28.0, 32.0), CORACOID_TIP, 6.5, 5.5)]
    spine = round_cone(p, v(-118.0, -62.0, 38.0), v(-40.0, -34.0, 40.0), 5.0, 7.0)
    acromion = [round_cone(p, v(-40.0, -34.0, 40.0), v(-4.0, -20.0, 40.0), 7.0, 6.5),
                ellipsoid(p, v(6.0, -8.0, 38.0), v(14.0, 16.0, 5.0))]
    blade = ellipsoid(p, _BLADE_CENTRE, _BLADE_RADII, _BLADE_FRAME)
    lateral_border = round_cone(p, INFRAGLENOID_TUBERCLE + v(-4.0, -4.0, -6.0),
                                v(-72.0, -52.0, -108.0), 6.0, 5.0)
    solid = smooth_union(4.0, glenoid, neck, supraglenoid, infraglenoid, *coracoid, spine,
                         *acromion, blade, lateral_border)
    # The glenoid fossa: a socket 2 mm wider than the humeral head (cartilage space).
    return np.maximum(solid, -sphere(p, SHOULDER_CENTRE, HUMERAL_HEAD_RADIUS + 2.0))


TROCHLEA_CENTRE = v(-8.0, 6.0, -308.0)
CAPITULUM_CENTRE = v(14.0, 6.0, -308.0)
_TROCHLEA_RADIUS = 11.0
_CAPITULUM_RADIUS = 10.0


def _humerus(p):
    head = sphere(p, SHOULDER_CENTRE, HUMERAL_HEAD_RADIUS)
    greater_tubercle = ellipsoid(p, v(18.0, 2.0, 0.0), v(10.0, 13.0, 15.0))
    lesser_tubercle = sphere(p, v(6.0, 17.0, -6.0), 7.0)
    neck = round_cone(p, v(0.0, 0.0, 0.0), v(8.0, 0.0, -40.0), 19.0, 13.0)
    shaft = smooth_union(8.0, round_cone(p, v(8.0, 0.0, -40.0), v(5.0, 0.0, -160.0), 13.0, 11.0),
                         round_cone(p, v(5.0, 0.0, -160.0), v(3.0, 1.0, -255.0), 11.0, 11.0))
    deltoid_tuberosity = ellipsoid(p, v(17.0, 3.0, -110.0), v(5.0, 6.0, 18.0))
    flare = ellipsoid(p, v(2.0, 1.0, -284.0), v(25.0, 8.0, 26.0))
    ridges = [round_cone(p, v(10.0, -1.0, -215.0), v(27.0, -1.0, -292.0), 3.5, 5.0),
              round_cone(p, v(-6.0, -1.0, -230.0), v(-27.0, -2.0, -296.0), 3.5, 6.0)]
    epicondyles = [sphere(p, v(-29.0, -3.0, -300.0), 8.0), sphere(p, v(27.0, -1.0, -300.0), 6.5)]
    trochlea = round_cone(p, TROCHLEA_CENTRE - v(8.0, 0.0, 0.0), TROCHLEA_CENTRE + v(6.0, 0.0, 0.0),
                          _TROCHLEA_RADIUS + 1.0, _TROCHLEA_RADIUS - 1.0)
    capitulum = sphere(p, CAPITULUM_CENTRE, _CAPITULUM_RADIUS)
    solid = smooth_union(5.0, head, greater_tubercle, lesser_tubercle, neck, shaft,
                         deltoid_tuberosity, flare, *ridges, *epicondyles, trochlea, capitulum)
    # The olecranon fossa: 2 mm of joint space around the ulna of the rest pose.
    return np.maximum(solid, -(_BONE_FIELDS["ulna"](p) - 2.0))


# Forearm landmarks with the elbow straight (the fields below are evaluated in that frame).
def _around_elbow(angle_deg, distance, x):
    """The point ``distance`` mm from the elbow axis at ``x``, ``angle_deg`` from straight down
    towards anterior (negative: towards posterior), elbow straight."""
    a = np.radians(angle_deg)
    return v(x, ELBOW_CENTRE[1] + distance * np.sin(a), ELBOW_CENTRE[2] - distance * np.cos(a))


OLECRANON = _around_elbow(-112.0, 22.0, -8.0)
CORONOID = _around_elbow(62.0, 18.0, -8.0)
ULNAR_TUBEROSITY = v(-7.0, 13.0, -340.0)
RADIAL_TUBEROSITY = v(8.0, 10.0, -352.0)
RADIAL_STYLOID = v(34.0, 6.0, -562.0)
# The trochlear notch's rim: from the coronoid process under the trochlea to the olecranon.
_NOTCH_RIM = [_around_elbow(a, 19.0, -8.0) for a in (62.0, 25.0, -15.0, -55.0, -95.0, -128.0)]


def _ulna_extended(p):
    rim = [round_cone(p, _NOTCH_RIM[i], _NOTCH_RIM[i + 1], 6.5, 6.5)
           for i in range(len(_NOTCH_RIM) - 1)]
    olecranon = ellipsoid(p, OLECRANON, v(9.0, 7.0, 11.0))
    coronoid = ellipsoid(p, CORONOID, v(8.0, 6.0, 5.0))
    tuberosity = ellipsoid(p, ULNAR_TUBEROSITY + v(0.0, -3.0, 0.0), v(5.0, 5.0, 8.0))
    shaft = smooth_union(8.0, round_cone(p, v(-9.0, 2.0, -330.0), v(-13.0, -1.0, -450.0), 9.0, 6.5),
                         round_cone(p, v(-13.0, -1.0, -450.0), v(-15.0, -2.0, -560.0), 6.5, 5.0))
    head = sphere(p, v(-15.0, -2.0, -566.0), 7.5)
    styloid = sphere(p, v(-19.0, -6.0, -576.0), 3.0)
    solid = smooth_union(4.0, *rim, olecranon, coronoid, tuberosity, shaft, head, styloid)
    # The trochlear notch: 2 mm of joint space around the trochlea (and the capitulum).
    notch = round_cone(p, TROCHLEA_CENTRE - v(14.0, 0.0, 0.0), CAPITULUM_CENTRE,
                       _TROCHLEA_RADIUS + 3.0, _CAPITULUM_RADIUS + 2.0)
    return np.maximum(solid, -notch)


def _radius_extended(p):
    head = round_cone(p, CAPITULUM_CENTRE + v(0.0, 0.0, -16.0), CAPITULUM_CENTRE + v(0.0, 0.0, -24.0),
                      10.0, 10.0)
    neck = round_cone(p, CAPITULUM_CENTRE + v(0.0, 0.0, -24.0), v(12.0, 7.0, -346.0), 7.0, 6.5)
    tuberosity = ellipsoid(p, RADIAL_TUBEROSITY + v(2.0, -3.0, 0.0), v(5.0, 5.0, 9.0))
    shaft = smooth_union(8.0, round_cone(p, v(12.0, 7.0, -346.0), v(19.0, 6.0, -450.0), 7.0, 7.0),
                         round_cone(p, v(19.0, 6.0, -450.0), v(22.0, 4.0, -540.0), 7.0, 9.5))
    distal = ellipsoid(p, v(21.0, 4.0, -553.0), v(16.0, 11.0, 10.0))
    styloid = sphere(p, RADIAL_STYLOID, 5.0)
    solid = smooth_union(4.0, head, neck, tuberosity, shaft, distal, styloid)
    # Joint spaces: 2 mm below the capitulum and beside the ulna's radial notch.
    return np.maximum(solid, -sphere(p, CAPITULUM_CENTRE, _CAPITULUM_RADIUS + 2.0))


def _at_rest_flexion(field):
    """A forearm field of the straight elbow, moved to the rest flexion."""
    def moved(p):
        return field(p @ _TO_EXTENDED[:, :3].T + _TO_EXTENDED[:, 3])
    return moved


_BONE_FIELDS = {"scapula": _scapula, "humerus": _humerus,
                "ulna": _at_rest_flexion(_ulna_extended),
                "radius": _at_rest_flexion(_radius_extended)}
_BONE_BOXES = {  # (lower, upper) corners enclosing each bone at rest (mm)
    "scapula": (v(-135.0, -85.0, -125.0), v(30.0, 55.0, 55.0)),
    "humerus": (v(-45.0, -25.0, -330.0), v(40.0, 30.0, 30.0)),
    "ulna": (v(-35.0, -30.0, -590.0), v(10.0, 115.0, -270.0)),
    "radius": (v(-10.0, -20.0, -580.0), v(50.0, 120.0, -305.0)),
}


def bone_field(name: str, points) -> np.ndarray:
    """Implicit function of a demo arm bone at ``points`` (n, 3) mm in the rest pose: negative
    inside, zero on the surface, roughly the signed distance (mm) near it."""
    return _BONE_FIELDS[name](np.asarray(points, dtype=np.float64).reshape(-1, 3))


def project_to_bone(name: str, point, steps: int = 8) -> np.ndarray:
    """The point of the bone's implicit surface (rest pose) reached from ``point`` (mm)."""
    return project_to_surface(_BONE_FIELDS[name], point, steps)


def sampled_bone(name: str, spacing: float = 3.0) -> SampledField:
    """A demo arm bone's implicit function sampled on a grid of step ``spacing`` (mm)."""
    lower, upper = _BONE_BOXES[name]
    return SampledField.sample(_BONE_FIELDS[name], lower, upper, spacing)


# ---- muscles -------------------------------------------------------------------------------

def _arm_axis(z):
    """Point (n, 3) of the limb axis at heights ``z`` (mm): the humeral shaft's axis, extended."""
    z = np.asarray(z, dtype=np.float64)
    s = np.clip(z / -300.0, -0.2, 2.0)
    return np.column_stack([8.0 - 6.0 * s, np.zeros_like(z), z])


_around = partial(around, _arm_axis)
"""``_around(z, theta_deg, rho)``: :func:`.demo.geometry.around` the arm's axis."""


_MUSCLES = {
    "biceps_long_head": MuscleSpec(
        "scapula", SUPRAGLENOID_TUBERCLE + v(0.0, 2.0, 4.0), "radius",
        _forearm(*(RADIAL_TUBEROSITY + v(2.0, 4.0, 0.0))),
        (v(-8.0, 27.0, 12.0), v(14.0, 24.0, -30.0), _around(-110.0, 72.0, 30.0),
         _around(-190.0, 78.0, 36.0), _around(-255.0, 82.0, 30.0), v(10.0, 28.0, -300.0)),
        radial=12.0, tangential=13.0, peak=0.55, fullness=0.5),
    "biceps_short_head": MuscleSpec(
        "scapula", CORACOID_TIP + v(0.0, 2.0, -4.0), "radius",
        _forearm(*(RADIAL_TUBEROSITY + v(0.0, 4.0, 2.0))),
        (v(-14.0, 36.0, -20.0), _around(-110.0, 108.0, 30.0), _around(-190.0, 102.0, 36.0),
         _around(-255.0, 96.0, 30.0), v(6.0, 28.0, -302.0)),
        radial=11.0, tangential=12.0, peak=0.55, fullness=0.5),
    "brachialis": MuscleSpec(
        "humerus", _around(-150.0, 90.0, 11.0),
        "ulna", _forearm(*(ULNAR_TUBEROSITY + v(0.0, 2.0, 4.0))),
        (_around(-200.0, 90.0, 19.0), _around(-255.0, 90.0, 22.0), v(-2.0, 31.0, -306.0)),
        radial=9.0, tangential=22.0, peak=0.55, fullness=0.6),
    "brachioradialis": MuscleSpec(
        "humerus", v(24.0, 2.0, -245.0), "radius", _forearm(*(RADIAL_STYLOID + v(0.0, 6.0, 12.0))),
        (v(27.0, 17.0, -290.0), _forearm(29.0, 22.0, -350.0), _forearm(32.0, 18.0, -430.0),
         _forearm(32.0, 12.0, -500.0)),
        radial=9.0, tangential=12.0, peak=0.35, fullness=0.6),
    "triceps_long_head": MuscleSpec(
        "scapula", INFRAGLENOID_TUBERCLE + v(0.0, -4.0, 0.0),
        "ulna", _forearm(*(OLECRANON + v(-2.0, -6.0, 10.0))),
        (v(-24.0, -22.0, -60.0), _around(-120.0, 225.0, 32.0), _around(-200.0, 240.0, 34.0),
         _around(-260.0, 258.0, 24.0)),
        radial=13.0, tangential=15.0, peak=0.5, fullness=0.5),
    "triceps_lateral_head": MuscleSpec(
        "humerus", _around(-70.0, 320.0, 12.0),
        "ulna", _forearm(*(OLECRANON + v(2.0, -6.0, 10.0))),
        (_around(-125.0, 300.0, 26.0), _around(-200.0, 288.0, 30.0), _around(-260.0, 278.0, 22.0)),
        radial=11.0, tangential=18.0, peak=0.5, fullness=0.5),
    "triceps_medial_head": MuscleSpec(
        "humerus", _around(-140.0, 255.0, 11.0), "ulna", _forearm(*(OLECRANON + v(-2.0, -4.0, 8.0))),
        (_around(-190.0, 262.0, 17.0), _around(-245.0, 268.0, 15.0)),
        radial=8.0, tangential=20.0, peak=0.55, fullness=0.6),
}


def muscle_attachments(name: str):
    """``(origin bone, origin point, insertion bone, insertion point)`` of a demo arm muscle; the
    points (mm, rest pose) lie on the bones' implicit surfaces."""
    spec = _MUSCLES[name]
    return (spec.origin_bone, project_to_bone(spec.origin_bone, spec.origin),
            spec.insertion_bone, project_to_bone(spec.insertion_bone, spec.insertion))


def demo_arm_scene(size: str = "full") -> Scene:
    """The demo elbow scene (DESIGN §4).

    ``"full"``: scapula, humerus, ulna and radius, the seven muscles of :data:`MUSCLE_NAMES`
    with an 8x8 ``fibre_grid`` of 30-vertex fibres each, and the flexion 10 -> 130 -> 10 degrees
    at :data:`TIME_POINTS` time points. ``"small"``: the same bones, muscles and motion, meshed
    coarser, with a 4x4 grid of 12-vertex fibres, for fast tests.
    Every call returns an identical, newly built scene.
    """
    sizes = size_named(size, _SIZES)
    bones = {bone: sampled_bone(bone, sizes.bone_spacing) for bone in BONE_NAMES}
    return assemble_scene(flexion_motion(), bones, _MUSCLES, MUSCLE_NAMES, project_to_bone,
                          _arm_axis, sizes)
