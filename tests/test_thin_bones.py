"""Thin bones, checked by VTK's exact geometry (issue 30): at the small elbow demo's most flexed
pose (130 degrees, the six filters' defaults) no deformed surface vertex and no free particle
centre that was outside a bone at rest is inside it by more than 0.1 mm, by
vtkSelectEnclosedPoints and vtkImplicitPolyDataDistance on the posed bone meshes; and what the
filters report (free particles newly in a bone, each vertex's depth before the push) is what
that test finds. The sampled distance fields alone left a brachialis particle 0.13 mm inside
the ulna with nothing reported, and on another elbow scene surfaces 2.6 mm inside the humerus.

Runs in the venv and in Debian's ParaView Python (about 30 s)."""
import numpy as np
import pytest

from muscle_mss.core.demo import arm as demo_arm
from muscle_mss.filters import array_names as A
from muscle_mss.filters import vtk_arrays as V
from muscle_mss.filters.bone_sets import INSIDE_TOLERANCE
from muscle_mss.app.motion_run import build_pipeline, solve_time_point, update_at
from muscle_mss.core.scene import Surface
from arm_scenes import written_arm_at_full_flexion
from surface_probes import inside, signed_distance

EXACT_LIMIT = 0.1     # mm: the bound on anything newly inside a bone
AGREEMENT = 1e-6      # mm: reported depths against VTK's distance to the same triangles


@pytest.fixture(scope="module")
def arm_scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("small_elbow")
    scene, index = written_arm_at_full_flexion("small", folder)
    return scene, folder, index


def _solve(arm_scene, settings=None):
    scene, folder, index = arm_scene
    p = build_pipeline(folder, settings)
    result = solve_time_point(p, index)
    posed = {name: Surface(V.points_of(b), V.triangles_of(b))
             for name, b in V.blocks(update_at(p.pose, 1, p.times[index]))}
    return result, posed


@pytest.fixture(scope="module")
def solved(arm_scene):
    return _solve(arm_scene)


def _new_depths(scene, posed, rest_points, points):
    """(n,) mm: how deep each of ``points`` is, by VTK, inside a posed bone that its
    ``rest_points`` counterpart was outside at rest (0 when in none)."""
    depth = np.zeros(len(points))
    for name, bone in posed.items():
        new = inside(bone, points) & ~inside(scene.bones[name], rest_points)
        depth[new] = np.maximum(depth[new], -signed_distance(bone, points[new]))
    return depth


def test_no_surface_vertex_ends_newly_inside_a_thin_bone(arm_scene, solved):
    scene, _, index = arm_scene
    result, posed = solved
    assert demo_arm.flexion_angles(result.time) == pytest.approx(demo_arm.MAX_FLEXION)
    rows = {row["muscle"]: row for row in result.rows}
    assert sum(row[A.NEW_IN_BONE_VERTICES] for row in rows.values()) > 0   # the push had work
    for name, surface in V.blocks(result.surfaces):
        depth = _new_depths(scene, posed, scene.muscles[name].points, V.points_of(surface))
        assert depth.max() <= EXACT_LIMIT, (name, depth.max())
        assert rows[name][A.NEW_IN_BONE_VERTICES_AFTER] == (depth > INSIDE_TOLERANCE).sum()


def test_no_free_particle_centre_ends_newly_inside_a_thin_bone_and_the_report_says_so(solved,
                                                                                     arm_scene):
    scene = arm_scene[0]
    result, posed = solved
    rows = {row["muscle"]: row for row in result.rows}
    for name, block in V.blocks(result.particles):
        free = V.point_array(block, A.FIXED) == 0
        points = V.points_of(block)[free]
        rest = V.point_array(block, A.REST_POSITION)[free]
        at_rest = V.point_array(block, A.IN_BONE_AT_REST)[free] == 1
        depth = np.where(at_rest, 0.0, _new_depths(scene, posed, rest, points))
        assert depth.max() <= EXACT_LIMIT, (name, depth.max())
        assert rows[name][A.FREE_NEW_IN_BONE] == (depth > INSIDE_TOLERANCE).sum(), name
        assert rows[name][A.FREE_NEW_IN_BONE_DEPTH_MM] == pytest.approx(depth.max(),
                                                                        abs=AGREEMENT)


def test_reported_depths_before_the_push_are_the_exact_ones(arm_scene):
    """With KeepOutOfBones off the surfaces come out as deformed, so each vertex's reported
    depth (point data new_in_bone_depth) can be checked against VTK at the same point."""
    scene = arm_scene[0]
    result, posed = _solve(arm_scene, {"KeepOutOfBones": 0})
    deepest = 0.0
    for name, surface in V.blocks(result.surfaces):
        exact = _new_depths(scene, posed, scene.muscles[name].points, V.points_of(surface))
        reported = V.point_array(surface, A.NEW_IN_BONE_DEPTH)
        counted = exact > INSIDE_TOLERANCE
        np.testing.assert_allclose(np.where(counted, reported, 0.0),
                                   np.where(counted, exact, 0.0), atol=AGREEMENT, err_msg=name)
        assert (reported > 0).sum() == counted.sum(), name
        deepest = max(deepest, exact.max())
    assert deepest > 1.0                 # the pose does press surfaces into the bones
