"""MSS Collision Solver filter (filters/collision_solver.py) on the small demo scene."""
import numpy as np
import pytest

from muscle_mss.core.contacts import collision_spheres, octree_bvh, spatial_hash
from muscle_mss.core.bones.spheres import bone_spheres
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.motion import farthest_pose_index
from muscle_mss.filters import (FibreResampler, MSSCollisionSolver, RigidPoseTransform,
                                SpringBuilder)
from muscle_mss.filters import array_names as A
from muscle_mss.filters import vtk_arrays as V
from muscle_mss.filters.scene_io import scene_to_vtk


def posed_at(scene, time, builder_bones=True):
    """The scene's posed model and bones at ``time`` (8 particles per fibre), the bones wired
    to the Spring Builder too unless ``builder_bones`` is False."""
    muscles, fibres, bones, motion = scene_to_vtk(scene)
    resampler = FibreResampler()
    resampler.SetInputDataObject(0, fibres)
    resampler.SetParticlesPerFibre(8)
    builder = SpringBuilder()
    builder.SetInputConnection(0, resampler.GetOutputPort())
    builder.SetInputDataObject(1, muscles)
    if builder_bones:
        builder.SetInputDataObject(2, bones)
    pose = RigidPoseTransform()
    pose.SetInputConnection(0, builder.GetOutputPort())
    pose.SetInputDataObject(1, bones)
    pose.SetInputDataObject(2, motion)
    pose.UpdateTimeStep(float(time))
    model = pose.GetOutputDataObject(0).NewInstance()
    model.DeepCopy(pose.GetOutputDataObject(0))
    posed_bones = pose.GetOutputDataObject(1).NewInstance()
    posed_bones.DeepCopy(pose.GetOutputDataObject(1))
    return model, posed_bones


@pytest.fixture(scope="module")
def posed(small_scene):
    """The small demo's posed model and bones at a walking pose a third into the motion."""
    return posed_at(small_scene, small_scene.motion.times[len(small_scene.motion.times) // 3])


@pytest.fixture(scope="module")
def flexed(small_scene):
    """The small demo at the pose farthest from rest (the knee most flexed)."""
    return posed_at(small_scene, small_scene.motion.times[farthest_pose_index(small_scene.motion)])


def solve(model, bones, **properties):
    """Solve with the paper relaxation unless ``Method`` is given (these are its tests; the
    quasi-static method's are in test_quasi_static.py)."""
    properties.setdefault("Method", "paper relaxation")   # the default, pinned
    solver = MSSCollisionSolver()
    solver.SetInputDataObject(0, model)
    solver.SetInputDataObject(1, bones)
    for name, value in properties.items():
        getattr(solver, "Set" + name)(value)
    solver.Update()
    return solver.GetOutputDataObject(0), solver.GetOutputDataObject(1)


@pytest.fixture(scope="module")
def solved(posed):
    return solve(*posed, Iterations=300)


def snapshot(multiblock):
    return {name: (V.points_of(b), V.point_arrays(b)) for name, b in V.blocks(multiblock)}


def spheres_of(multiblock, bones, spacing):
    blocks = V.blocks(multiblock)
    cat = lambda key: np.concatenate([V.point_array(b, key) for _, b in blocks])  # noqa: E731
    muscle = np.concatenate([np.full(b.GetNumberOfPoints(), m) for m, (_, b) in enumerate(blocks)])
    centres, radii, ids = [], [], []
    for k, (name, bone) in enumerate(V.blocks(bones)):
        c, r = bone_spheres(V.points_of(bone), V.triangles_of(bone), spacing)
        centres.append(c), radii.append(r), ids.append(np.full(len(c), k))
    spheres = collision_spheres.make_spheres(cat(A.RADIUS), muscle, cat(A.FIXED) > 0, cat(A.BOUNDARY) > 0,
                               np.concatenate(centres), np.concatenate(radii),
                               np.concatenate(ids))
    points = np.concatenate([V.points_of(b) for _, b in blocks])
    return points[spheres.particle], spheres


def test_solved_model_keeps_every_array_and_adds_the_solver_arrays(posed, solved):
    model, _ = posed
    out, table = solved
    before = dict(snapshot(model))
    for name, block in V.blocks(out):
        points, arrays = before[name]
        got = V.point_arrays(block)
        for key, values in arrays.items():
            assert np.array_equal(got[key], values)
        solved_points = V.points_of(block)
        assert np.isfinite(solved_points).all()
        np.testing.assert_allclose(got[A.DISPLACEMENT], solved_points - points, atol=1e-12)
        assert got[A.VELOCITY].shape == points.shape
        assert got[A.COLLIDED].dtype == np.uint8
        fixed = arrays[A.FIXED] > 0
        assert np.array_equal(solved_points[fixed], points[fixed])
        assert block.GetNumberOfLines() == dict(V.blocks(model))[name].GetNumberOfLines()


def test_convergence_table_has_a_row_per_iteration_and_a_column_per_muscle(posed, solved):
    columns = V.table_columns(solved[1])
    names = [name for name, _ in V.blocks(posed[0])]
    assert list(columns) == (["iteration"] + ["mean_displacement_" + n for n in names]
                             + ["colliding_pairs", "max_penetration", "seconds"])
    assert np.array_equal(columns["iteration"], np.arange(1, 301))


def deepest_penetration(out, bones):
    """Deepest overlap (mm) of spheres of different muscles and of a muscle sphere with a bone
    as a solid (the default BoneContact: its distance field, as the solver sees it) that a solve
    can resolve (not both fixed; tendon spheres sit in their bone), and the mean sphere
    radius."""
    from muscle_mss.core.bones.distance import signed_distances
    from muscle_mss.filters.bone_sets import bone_solids
    centres, spheres = spheres_of(out, bones, 2.05)
    muscle_pairs, _ = spatial_hash.colliding_pairs(centres, spheres)
    depth = (spheres.radius[muscle_pairs[:, 0]] + spheres.radius[muscle_pairs[:, 1]]
             - np.linalg.norm(centres[muscle_pairs[:, 0]] - centres[muscle_pairs[:, 1]], axis=1))
    movable = ~(spheres.fixed[muscle_pairs[:, 0]] & spheres.fixed[muscle_pairs[:, 1]])
    fields, transforms = bone_solids(bones)
    in_bone = spheres.radius[:, None] - signed_distances(fields, centres, transforms)[0]
    return (max(depth[movable].max(initial=0.0), in_bone[~spheres.fixed].max(initial=0.0)),
            spheres.radius.mean())


def test_walking_pose_solves_without_nan_or_penetration_and_settles(posed, solved):
    out, table = solved
    columns = V.table_columns(table)
    deepest, mean_radius = deepest_penetration(out, posed[1])
    assert deepest <= 0.01 * mean_radius
    assert V.field(table, A.REMAINING_PENETRATION) <= 0.01
    history = np.stack([v for k, v in columns.items() if k.startswith("mean_displacement_")], 1)
    assert np.isfinite(history).all()
    assert history[-30:].mean() < 0.5 * history[:30].mean()


def test_most_flexed_pose_ends_without_penetration_thanks_to_the_final_passes(flexed):
    # the muscles are pressed between each other and the femur: the iterations alone leave
    # ~9 % of the mean radius overlapped, the final collision passes remove it
    out, table = solve(*flexed, Iterations=300)
    deepest, mean_radius = deepest_penetration(out, flexed[1])
    assert deepest <= 0.01 * mean_radius
    passes = int(V.field(table, A.PROJECTION_PASSES))
    assert V.field(table, A.REMAINING_PENETRATION) <= 0.01
    # they stop at the first pass that finds nothing above the tolerance: one fewer is not enough
    _, fewer = solve(*flexed, Iterations=300, ProjectionPasses=passes - 1)
    assert V.field(fewer, A.REMAINING_PENETRATION) > 0.01
    assert np.isfinite(V.table_columns(table)["max_penetration"]).all()
    out, table = solve(*flexed, Iterations=300, ProjectionPasses=0)
    assert deepest_penetration(out, flexed[1])[0] > 0.05 * mean_radius
    assert V.field(table, A.PROJECTION_PASSES) == 0


def test_solved_blocks_count_free_particles_in_bones_and_solids_leave_none_new(flexed):
    """Issue 14: each solved block reports its free particles inside a posed bone (all, and
    those not inside a bone at rest) and the deepest; at the most flexed pose the solid bones
    (the default) leave no free particle newly inside one, while the sphere sets let some
    through their shell."""
    new = {}
    for contact in ("solid", "sphere set"):
        out, _ = solve(*flexed, Iterations=300, BoneContact=contact)
        figures = np.array([[V.field(b, key) for key in A.FREE_IN_BONE_FIELDS]
                            for _, b in V.blocks(out)])
        count, deepest, new_count, new_deepest = figures.T
        assert (new_count <= count).all() and ((deepest > 0) == (count > 0)).all()
        assert ((new_deepest > 0) == (new_count > 0)).all()
        new[contact] = (int(new_count.sum()), float(new_deepest.max()))
    assert new["solid"] == (0, 0.0)
    assert new["sphere set"][0] > 0 and new["sphere set"][1] > 0.1


def test_skipping_particles_clear_of_the_solid_bones_changes_nothing(flexed, monkeypatch):
    """The solid contacts skip a particle that has moved little since it was found clear of
    every bone by a margin (core/contacts/solid_contacts.py, SOLID_LIPSCHITZ); testing every particle in
    every iteration gives bitwise the same solve at the most flexed pose."""
    from muscle_mss.core.contacts import solid_contacts
    skipping = snapshot(solve(*flexed, Iterations=150)[0])
    monkeypatch.setattr(solid_contacts, "SOLID_SLACK_CELLS", np.inf)
    every = snapshot(solve(*flexed, Iterations=150)[0])
    for name, (points, arrays) in every.items():
        assert np.array_equal(skipping[name][0], points), name
        assert np.array_equal(skipping[name][1][A.COLLIDED], arrays[A.COLLIDED]), name
    assert sum(int(a[A.COLLIDED].sum()) for _, a in every.values()) > 0


def test_both_structures_find_the_same_pairs_on_the_demo(posed):
    centres, spheres = spheres_of(posed[0], posed[1], 2.05)
    hashed = spatial_hash.colliding_pairs(centres, spheres)
    bvh = octree_bvh.colliding_pairs(centres, octree_bvh.octree_bvh(spheres))
    assert len(hashed[0]) > 0 and len(hashed[1]) > 0
    assert np.array_equal(hashed[0], bvh[0]) and np.array_equal(hashed[1], bvh[1])


def test_same_inputs_same_result_and_inputs_unchanged(posed, solved):
    before = snapshot(posed[0])
    again, _ = solve(*posed, Iterations=300)
    for (name, a), (_, b) in zip(V.blocks(solved[0]), V.blocks(again)):
        assert np.array_equal(V.points_of(a), V.points_of(b))
    after = snapshot(posed[0])
    for name in before:
        assert np.array_equal(before[name][0], after[name][0])
        for key in before[name][1]:
            assert np.array_equal(before[name][1][key], after[name][1][key])
        assert A.VELOCITY not in after[name][1]


def test_terminations_by_name(posed):
    _, table = solve(*posed, Iterations=50, Termination="time budget", TimeBudget=0.05)
    seconds = V.table_columns(table)["seconds"]
    assert seconds[-1] >= 0.05 or len(seconds) == 50
    _, table = solve(*posed, Iterations=7, CollisionStructure="octree BVH")
    assert len(V.table_columns(table)["iteration"]) == 7


def damaged(model, change):
    copy = model.NewInstance()
    copy.DeepCopy(model)
    change(V.blocks(copy)[0][1])
    return copy


def test_missing_array_is_refused_with_the_block_named(posed):
    model = damaged(posed[0], lambda b: b.GetPointData().RemoveArray(A.RADIUS))
    with pytest.raises(MuscleMSSError, match="PosedModel block .*'radius' is missing"):
        solve(model, posed[1], Iterations=2)
    model = damaged(posed[0], lambda b: b.GetCellData().RemoveArray(A.DAMPING))
    with pytest.raises(MuscleMSSError, match="'damping' is missing"):
        solve(model, posed[1], Iterations=2)


def test_nan_position_is_refused(posed):
    model = damaged(posed[0], lambda b: b.GetPoints().SetPoint(3, float("nan"), 0.0, 0.0))
    with pytest.raises(MuscleMSSError, match="particle 3 has a NaN"):
        solve(model, posed[1], Iterations=2)


def test_rest_pose_stays_at_rest_once_the_spheres_are_clear_of_the_bones(small_scene):
    muscles, fibres, bones, _ = scene_to_vtk(small_scene)
    resampler = FibreResampler()
    resampler.SetInputDataObject(0, fibres)
    resampler.SetParticlesPerFibre(8)
    moved = []
    for with_bones in (False, True):
        builder = SpringBuilder()
        builder.SetInputConnection(0, resampler.GetOutputPort())
        builder.SetInputDataObject(1, muscles)
        if with_bones:
            builder.SetInputDataObject(2, bones)
        builder.Update()
        out, _ = solve(builder.GetOutputDataObject(0), bones, Iterations=100)
        moved.append(max(np.abs(V.point_array(b, A.DISPLACEMENT)).max() for _, b in V.blocks(out)))
    assert moved[0] > 1.0 and moved[1] < 1e-9


@pytest.fixture(scope="module")
def small_arm():
    from muscle_mss.core.demo.arm import demo_arm_scene
    return demo_arm_scene("small")


def rest_motion(scene):
    """The scene's motion replaced by the rest pose (identity transforms) at two times."""
    from muscle_mss.core.scene import Motion
    bones = list(scene.bones)
    return Motion(np.array([0.0, 1.0]), bones, np.tile(np.eye(3, 4), (2, len(bones), 1, 1)))


@pytest.mark.parametrize("region", ("thigh", "arm"))
def test_rest_pose_stays_at_rest_without_the_spring_builders_bones_input(region, small_scene,
                                                                          small_arm):
    """Issue 14: the chain as a GUI user adds it filter by filter (nothing asks for the Spring
    Builder's optional Bones) solves the rest pose of both demo scenes to the rest pose, with
    either bone contact and either method: the Rigid Pose Transform clears the radii of the
    bones, exactly as the Spring Builder does with its Bones. The Spring Builder's own output,
    fed straight to the solver, still moves (its radius array is not cleared; the test
    above)."""
    from dataclasses import replace
    scene = replace(small_scene if region == "thigh" else small_arm)
    scene.motion = rest_motion(scene)
    posed_model, posed_bones = posed_at(scene, 0.0, builder_bones=False)
    for contact in ("solid", "sphere set"):
        for method in ("paper relaxation", "quasi-static"):
            out, _ = solve(posed_model, posed_bones, Method=method, BoneContact=contact,
                           Iterations=100)
            moved = max(np.abs(V.point_array(b, A.DISPLACEMENT)).max() for _, b in V.blocks(out))
            assert moved < 1e-9, (contact, method, moved)
    # the radii and the particles inside a bone at rest the solver saw: those of the pipeline
    # with the Spring Builder's Bones wired
    wired = posed_at(scene, 0.0)[0]
    for (name, block), (_, other) in zip(V.blocks(posed_model), V.blocks(wired)):
        for key in (A.RADIUS, A.IN_BONE_AT_REST):
            assert np.array_equal(V.point_array(block, key), V.point_array(other, key)), name
    assert sum(int(V.point_array(b, A.IN_BONE_AT_REST).sum()) for _, b in V.blocks(wired)) > 0

