"""MVC Surface Deformer with bones: surfaces kept out of the bones they were outside at rest
(issue 12), and what reaches the Volume-Error Probe."""
import numpy as np
import pytest

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.filters import MVCSurfaceDeformer
from muscle_mss.filters import array_names as A
from muscle_mss.filters import vtk_arrays as V
from test_bone_distance import box_mesh, rigid
from test_filter_mvc_volume import moved, probe, scene

DROP = 3.0   # mm the solved muscles move down (-y) into the box


def box_bone(model_surfaces):
    """A wide box under 'vastus' whose top face cuts 1.5 mm into its rest surface."""
    low = V.points_of(dict(V.blocks(model_surfaces))["vastus"])[:, 1].min()
    top = low + 1.5
    points, triangles = box_mesh([-20.0, top - 30.0, -30.0], [25.0, top, 60.0])
    return top, V.make_multiblock([("femur", V.make_polydata(points, triangles=triangles))])


def posed(bones, transform):
    return V.make_multiblock([(name, V.with_points(block, V.points_of(block) @ transform[:, :3].T
                                                   + transform[:, 3]))
                              for name, block in V.blocks(bones)])


def run(solved, surfaces, model, rest_bones=None, posed_bones=None, deformer=None, **props):
    deformer = deformer or MVCSurfaceDeformer()
    for name, value in props.items():
        getattr(deformer, "Set" + name)(value)
    for port, data in enumerate((solved, surfaces, model, rest_bones, posed_bones)):
        deformer.SetInputDataObject(port, data)
    deformer.Update()
    return deformer


def test_vertices_pushed_into_a_box_bone_come_out_onto_it_and_those_inside_at_rest_stay():
    model, surfaces = scene()
    top, bones = box_bone(surfaces)
    transform = rigid(30.0, [1, 1, 0], [10.0, -4.0, 7.0])
    drop = rigid(0.0, [0, 0, 1], [0.0, -DROP, 0.0])

    def pose(p):                       # the muscle dropped into the bone, then all moved rigidly
        return (p + drop[:, 3]) @ transform[:, :3].T + transform[:, 3]
    f = run(moved(model, pose), surfaces, model, bones, posed(bones, transform))
    out = dict(V.blocks(f.GetOutputDataObject(0)))["vastus"]
    rest = V.points_of(dict(V.blocks(surfaces))["vastus"])
    back = (V.points_of(out) - transform[:, 3]) @ transform[:, :3]     # in the bone's rest frame
    inside_at_rest = rest[:, 1] < top
    new = ~inside_at_rest & (rest[:, 1] - DROP < top)
    assert inside_at_rest.sum() > 3 and new.sum() > 10
    np.testing.assert_allclose(back[new, 1], top, atol=2e-3)            # onto the top face
    np.testing.assert_allclose(back[new][:, [0, 2]], rest[new][:, [0, 2]], atol=1e-6)
    np.testing.assert_allclose(back[inside_at_rest], rest[inside_at_rest] - [0, DROP, 0],
                               atol=1e-6)                               # left where MVC put them
    np.testing.assert_allclose(back[~new & ~inside_at_rest],
                               rest[~new & ~inside_at_rest] - [0, DROP, 0], atol=1e-6)
    assert V.field(out, A.NEW_IN_BONE_VERTICES) == new.sum()
    assert V.field(out, A.NEW_IN_BONE_DEPTH_MM) == pytest.approx(
        (top - (rest[new, 1] - DROP)).max(), abs=1e-3)
    assert V.field(out, A.NEW_IN_BONE_VERTICES_AFTER) == 0
    assert V.field(out, A.NEW_IN_BONE_DEPTH_AFTER_MM) == 0.0
    depth = V.point_array(out, A.NEW_IN_BONE_DEPTH)
    np.testing.assert_allclose(depth[new], top - (rest[new, 1] - DROP), atol=1e-3)
    assert not depth[~new].any()
    np.testing.assert_allclose(V.point_array(out, A.DISPLACEMENT), V.points_of(out) - rest,
                               atol=1e-9)
    gracilis = dict(V.blocks(f.GetOutputDataObject(0)))["gracilis"]
    assert V.field(gracilis, A.NEW_IN_BONE_VERTICES) == 0

    table = V.table_columns(probe(f.GetOutputDataObject(0), surfaces).GetOutputDataObject(1))
    assert list(table[A.MUSCLE]) == ["vastus", "gracilis", "mean"]
    assert table[A.NEW_IN_BONE_VERTICES][0] == new.sum()
    assert table[A.NEW_IN_BONE_DEPTH_MM][0] > 1.0
    assert table[A.NEW_IN_BONE_VERTICES_AFTER][0] == 0
    assert table[A.NEW_IN_BONE_DEPTH_AFTER_MM][0] == 0


def test_keep_out_of_bones_off_only_counts_and_fields_are_built_once():
    model, surfaces = scene()
    top, bones = box_bone(surfaces)
    f = MVCSurfaceDeformer()
    f = run(moved(model, lambda p: p - [0, DROP, 0]), surfaces, model, bones, bones, f,
            KeepOutOfBones=False)
    out = dict(V.blocks(f.GetOutputDataObject(0)))["vastus"]
    rest = V.points_of(dict(V.blocks(surfaces))["vastus"])
    np.testing.assert_allclose(V.points_of(out), rest - [0, DROP, 0], atol=1e-6)
    assert V.field(out, A.NEW_IN_BONE_VERTICES) > 10
    assert V.field(out, A.NEW_IN_BONE_VERTICES_AFTER) == V.field(out, A.NEW_IN_BONE_VERTICES)
    run(moved(model, lambda p: p - [0, 1.0, 0]), surfaces, model, bones, bones, f,
        KeepOutOfBones=True)
    assert f.field_computations == 1


def test_fields_come_from_the_shared_bone_cache_whatever_frame_it_sampled_them_in():
    """At the default BoneFieldSpacing the deformer takes the fields the pose filter and the
    solver sample (one sampling per bone shape), also when the cache sampled a moved copy of
    the bone first: the deformer then composes that frame with the pose."""
    from muscle_mss.filters import bone_sets
    model, surfaces = scene()
    _, bones = box_bone(surfaces)
    transform = rigid(30.0, [1, 1, 0], [10.0, -4.0, 7.0])
    solved = moved(model, lambda p: (p - [0, DROP, 0]) @ transform[:, :3].T + transform[:, 3])
    outputs = []
    for first_seen in (bones, posed(bones, rigid(70.0, [0, 1, 1], [40.0, 5.0, -9.0]))):
        bone_sets.clear_bone_cache()
        block = first_seen.GetBlock(0)
        bone_sets.cached_bone_field(V.points_of(block), V.triangles_of(block))
        f = run(solved, surfaces, model, bones, posed(bones, transform))
        assert bone_sets.field_counts["sampled"] == 1            # the deformer sampled none
        outputs.append(dict(V.blocks(f.GetOutputDataObject(0)))["vastus"])
    bone_sets.clear_bone_cache()
    at_rest, moved_frame = outputs
    assert V.field(at_rest, A.NEW_IN_BONE_VERTICES) > 10
    for name in (A.NEW_IN_BONE_VERTICES, A.NEW_IN_BONE_VERTICES_AFTER):
        assert V.field(moved_frame, name) == V.field(at_rest, name)
    np.testing.assert_allclose(V.points_of(moved_frame), V.points_of(at_rest), atol=2e-3)


def test_without_bones_nothing_is_reported_and_one_bone_input_alone_is_refused():
    model, surfaces = scene()
    _, bones = box_bone(surfaces)
    f = run(moved(model, lambda p: p - [0, DROP, 0]), surfaces, model)
    out = dict(V.blocks(f.GetOutputDataObject(0)))["vastus"]
    assert V.field(out, A.NEW_IN_BONE_VERTICES) is None
    table = V.table_columns(probe(f.GetOutputDataObject(0), surfaces).GetOutputDataObject(1))
    assert np.isnan(table[A.NEW_IN_BONE_VERTICES]).all()
    with pytest.raises(MuscleMSSError, match="both RestBones"):
        run(moved(model, lambda p: p), surfaces, model, bones, None)
    moved_off = posed(bones, rigid(0.0, [0, 0, 1], [0, 0, 0]))
    squashed = V.make_multiblock([(n, V.with_points(b, V.points_of(b) * [1, 1, 1.1]))
                                  for n, b in V.blocks(moved_off)])
    with pytest.raises(MuscleMSSError, match="PosedBones block 'femur'.*not a rigid motion"):
        run(moved(model, lambda p: p), surfaces, model, bones, squashed)


def test_small_demo_at_its_most_flexed_pose_has_no_surface_vertex_newly_in_a_bone(
        small_scene_dir):
    from muscle_mss.core.bones.triangle_distance import exact_signed_distance
    from muscle_mss.app.motion_run import build_pipeline, solve_time_point, update_at
    p = build_pipeline(small_scene_dir)
    index = int(np.argmin(np.abs(np.asarray(p.times) - 0.75)))
    result = solve_time_point(p, index)
    assert sum(r[A.NEW_IN_BONE_VERTICES] for r in result.rows) > 0     # the push had work
    for row in result.rows:
        assert row[A.NEW_IN_BONE_VERTICES_AFTER] == 0, row
        assert row[A.NEW_IN_BONE_DEPTH_AFTER_MM] == 0.0, row
        assert 0 <= row["free_particles_new_in_bone"] <= row["free_particles_in_bone"]
        assert (row["free_particle_bone_depth_mm"] > 0) == (row["free_particles_in_bone"] > 0)
    # Checked against the exact distance to the posed bone surfaces: the pushed vertices are
    # out of every bone up to the field's interpolation error (well under 0.1 mm here).
    bones = [(V.points_of(b), V.triangles_of(b))
             for _, b in V.blocks(update_at(p.pose, 1, p.times[index]))]
    for name, surface in V.blocks(result.surfaces):
        pushed = V.points_of(surface)[V.point_array(surface, A.NEW_IN_BONE_DEPTH) > 0]
        for points, triangles in bones:
            if len(pushed):
                assert exact_signed_distance(points, triangles, pushed).min() > -0.1, name
