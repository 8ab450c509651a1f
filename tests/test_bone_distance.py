"""Signed distance fields of bones and pushing points out of them (issues 12 and 14), and the
exact distances that correct them next to thin bones (issue 30)."""
import numpy as np
import pytest

from muscle_mss.core.bones.distance import (BRICK, COARSE, BoneFieldSet, push_out_of_bones,
                                           signed_distances)
from muscle_mss.core.bones.field_sampling import bone_distance_field, bone_field_set
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.bones.exact_distance import (EXACT_CLEARANCE, exact_signed_distances,
                                                 push_out_exactly)
from muscle_mss.core.bones.triangle_distance import (exact_signed_distance, inside_surface,
                                               prepared_surface)
from reference_distance import reference_push_out, reference_signed_distance


def box_mesh(lower, upper):
    """A closed, outward-oriented box of 12 triangles."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    corners = np.array([[(upper if (i >> k) & 1 else lower)[k] for k in range(3)]
                        for i in range(8)])
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2),
             (1, 3, 7, 5)]
    triangles = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return corners, np.array(triangles)


def sphere_mesh(radius, levels=4):
    """An icosphere of ``radius`` mm centred at the origin, subdivided ``levels`` times."""
    g = (1 + 5 ** 0.5) / 2
    points = [(-1, g, 0), (1, g, 0), (-1, -g, 0), (1, -g, 0), (0, -1, g), (0, 1, g),
              (0, -1, -g), (0, 1, -g), (g, 0, -1), (g, 0, 1), (-g, 0, -1), (-g, 0, 1)]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
             (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
             (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    points = [np.array(p, float) / np.linalg.norm(p) for p in points]
    for _ in range(levels):
        middle, new = {}, []

        def mid(a, b):
            key = (min(a, b), max(a, b))
            if key not in middle:
                m = points[a] + points[b]
                points.append(m / np.linalg.norm(m))
                middle[key] = len(points) - 1
            return middle[key]
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    return radius * np.array(points), np.array(faces)


def rigid(angle_deg, axis, translation):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.radians(angle_deg)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k
    return np.hstack([rotation, np.reshape(translation, (3, 1))])


BOX = box_mesh([-20.0, -15.0, -10.0], [20.0, 15.0, 10.0])


def test_exact_distance_matches_the_brute_force_reference_inside_and_out():
    rng = np.random.default_rng(1)
    for points, triangles in (BOX, sphere_mesh(10.0, levels=2)):
        queries = rng.uniform(-30, 30, (300, 3))
        queries[:8] = points[:8] * 0.999            # just inside, next to vertices
        fast = exact_signed_distance(points, triangles, queries)
        slow = reference_signed_distance(points, triangles, queries)
        np.testing.assert_allclose(fast, slow, atol=1e-9)


def test_a_surface_is_prepared_once_while_it_stays_bitwise_the_same():
    from muscle_mss.core.bones import triangle_distance
    triangle_distance.PREPARED_SURFACES.clear()
    points, triangles = sphere_mesh(10.0, levels=2)
    queries = np.random.default_rng(2).uniform(-15, 15, (50, 3))
    first = exact_signed_distance(points, triangles, queries)
    prepared = list(triangle_distance.PREPARED_SURFACES.values())
    np.testing.assert_array_equal(exact_signed_distance(points.copy(), triangles, queries), first)
    assert list(triangle_distance.PREPARED_SURFACES.values()) == prepared and len(prepared) == 1
    moved = points + [0.5, 0.0, 0.0]                     # another surface: prepared afresh
    np.testing.assert_allclose(exact_signed_distance(moved, triangles, queries + [0.5, 0, 0]),
                               first, atol=1e-12)
    assert len(triangle_distance.PREPARED_SURFACES) == 2
    open_surface = triangles[1:]                         # refused every time, never kept
    for _ in range(2):
        with pytest.raises(MuscleMSSError, match="open"):
            exact_signed_distance(points, open_surface, queries)
    assert len(triangle_distance.PREPARED_SURFACES) == 2


def test_sphere_field_matches_the_analytic_distance_within_half_a_cell():
    points, triangles = sphere_mesh(12.0)
    field = bone_field_set([(points, triangles)], spacing=1.0)
    rng = np.random.default_rng(2)
    queries = rng.uniform(-19, 19, (4000, 3))          # the sampled box: 12 + 8 mm padding
    distance, gradient = signed_distances(field, queries)
    analytic = np.linalg.norm(queries, axis=1) - 12.0
    near = np.abs(analytic) < 4.0                     # the narrow band: fine cells of 1 mm
    assert np.abs(distance[near, 0] - analytic[near]).max() < 0.5 * 0.1
    # Elsewhere coarse cells of COARSE mm; the worst is the kink at the centre.
    assert np.abs(distance[:, 0] - analytic).max() < 0.5 * COARSE
    outward = queries / np.linalg.norm(queries, axis=1, keepdims=True)
    band = np.abs(analytic) < 4.0
    cosine = np.einsum("ij,ij->i", gradient[band, 0], outward[band])
    assert cosine.min() > 0.9 and np.median(cosine) > 0.999   # outward, within ~25 degrees


def test_box_field_tells_inside_from_outside_and_its_gradient_points_outward():
    field = bone_field_set([BOX], spacing=1.0)
    rng = np.random.default_rng(3)
    queries = rng.uniform(-30, 30, (3000, 3))
    exact = reference_signed_distance(*BOX, queries[:300])
    distance, gradient = signed_distances(field, queries)
    inside = (np.abs(queries) < [20, 15, 10]).all(axis=1)
    assert (distance[inside, 0] < 0).all() and (distance[~inside, 0] > 0).all()
    band = np.abs(exact) < 4.0                        # within half a fine cell near the surface
    np.testing.assert_allclose(distance[:300, 0][band], exact[band], atol=0.5)
    # Gradient towards the nearest face, seen from points near the top face.
    top = np.column_stack([rng.uniform(-15, 15, 50), rng.uniform(-10, 10, 50),
                           rng.uniform(7.5, 13, 50)])
    _, g = signed_distances(field, top)
    np.testing.assert_allclose(g[:, 0], np.tile([0.0, 0.0, 1.0], (50, 1)), atol=1e-6)


def test_field_is_sparse_and_the_far_field_is_an_upper_bound():
    field = bone_distance_field(*sphere_mesh(30.0, levels=3), spacing=1.0, band=2.0)
    total = int(np.prod(field.dims))
    assert 0 < len(field.bricks) < total                # only bricks near the surface
    assert field.bricks.dtype == np.float32
    packed = BoneFieldSet.pack([field])
    far = np.array([[200.0, 0.0, 0.0]])
    d, g = signed_distances(packed, far)
    assert d[0, 0] >= 170.0 - 1e-6 and d[0, 0] <= 171.0
    np.testing.assert_allclose(g[0, 0], [1, 0, 0], atol=1e-12)
    assert BRICK % COARSE == 0


@pytest.mark.parametrize("mesh", ["box", "sphere"])
def test_the_fields_error_bound_holds_and_inside_is_measured_only_near_the_surface(mesh,
                                                                                 monkeypatch):
    points, triangles = BOX if mesh == "box" else sphere_mesh(12.0, levels=3)
    field = bone_distance_field(points, triangles, spacing=1.0, band=2.0)
    rng = np.random.default_rng(7)
    queries = np.concatenate([rng.uniform(-60, 60, (2000, 3)),        # far, near, in and out
                              points * rng.uniform(0.9, 1.1, (len(points), 1))])
    exact = exact_signed_distance(points, triangles, queries)
    sampled = signed_distances(BoneFieldSet.pack([field]), queries)[0][:, 0]
    upper = field.origin + field.dims * BRICK * field.spacing
    in_box = ((queries >= field.origin) & (queries <= upper)).all(axis=1)
    assert 0 < in_box.sum() < len(queries)
    assert np.abs(sampled - exact)[in_box].max() <= field.error_bound
    assert (sampled[~in_box] >= exact[~in_box] - 1e-9).all() and (exact[~in_box] > 0).all()
    measured = []
    import muscle_mss.core.bones.triangle_distance as T
    real = T.exact_signed_distance
    monkeypatch.setattr(T, "exact_signed_distance",
                        lambda p, t, q, where="": measured.append(len(q)) or real(p, t, q, where))
    inside = inside_surface(points, triangles, queries, sampled, field.error_bound)
    np.testing.assert_array_equal(inside, exact < 0.0)
    assert 0 < inside.sum() and 0 < measured[0] < len(queries) / 2


def test_posed_field_is_the_rest_field_moved_rigidly():
    field = bone_field_set([BOX])
    transform = rigid(35.0, [1, 2, 0.5], [30.0, -5.0, 12.0])[None]
    rng = np.random.default_rng(4)
    rest = rng.uniform(-25, 25, (500, 3))
    posed = rest @ transform[0, :, :3].T + transform[0, :, 3]
    d_rest, g_rest = signed_distances(field, rest)
    d_posed, g_posed = signed_distances(field, posed, transform)
    np.testing.assert_allclose(d_posed, d_rest, atol=1e-9)
    np.testing.assert_allclose(g_posed[:, 0], g_rest[:, 0] @ transform[0, :, :3].T, atol=1e-9)


def test_particles_inside_a_box_bone_end_outside_with_their_clearance():
    field = bone_field_set([BOX])
    transform = rigid(20.0, [0, 1, 1], [5.0, 2.0, -3.0])[None]
    rest = np.array([[0.0, 0.0, 5.0],       # 5 mm inside, below the top face
                     [0.0, 0.0, 0.0],       # the centre
                     [3.0, -4.0, -10.0],    # on the bottom face
                     [0.0, 0.0, 14.0]])     # outside, 4 mm above the top face
    radii = np.array([2.0, 2.5, 1.0, 3.0])
    posed = rest @ transform[0, :, :3].T + transform[0, :, 3]
    moved = posed + push_out_of_bones(field, posed, radii, transform)
    back = (moved - transform[0, :, 3]) @ transform[0, :, :3]
    exact = reference_signed_distance(*BOX, back)
    np.testing.assert_allclose(exact[:3], radii[:3], atol=1e-3)
    np.testing.assert_allclose(back[0], [0.0, 0.0, 12.0], atol=1e-3)   # out of the top face
    assert abs(back[1, 2]) == pytest.approx(12.5, abs=1e-3)            # nearest faces: z
    np.testing.assert_array_equal(moved[3], posed[3])                  # already clear: unmoved
    reference = reference_push_out(*BOX, rest[:1], radii[:1])
    np.testing.assert_allclose(back[:1], reference, atol=1e-3)


def test_a_lattice_pushed_halfway_into_a_bone_comes_out_on_the_near_side():
    field = bone_field_set([BOX])
    x, y, z = np.meshgrid(np.linspace(-8, 8, 5), np.linspace(-4, 4, 3),
                          np.linspace(0.5, 16.5, 9), indexing="ij")
    lattice = np.column_stack([x.ravel(), y.ravel(), z.ravel()])   # front layer at 0.45 depth
    radius = 1.5
    moved = lattice + push_out_of_bones(field, lattice, np.full(len(lattice), radius))
    exact = reference_signed_distance(*BOX, moved)
    assert exact.min() >= radius - 1e-3
    was_inside = lattice[:, 2] < 10.0
    assert was_inside.sum() == 5 * 3 * 5
    np.testing.assert_allclose(moved[was_inside, 2], 10.0 + radius, atol=1e-3)
    np.testing.assert_array_equal(moved[was_inside, :2], lattice[was_inside, :2])


def test_active_mask_exempts_points_and_point_bone_pairs():
    upper = box_mesh([-5.0, -5.0, 20.0], [5.0, 5.0, 30.0])
    field = bone_field_set([BOX, upper])
    points = np.array([[0.0, 0.0, 9.0], [0.0, 0.0, 29.0], [0.0, 0.0, 21.0]])
    shift = push_out_of_bones(field, points, active=[True, False, True])
    assert shift[0, 2] == pytest.approx(1.0, abs=1e-3) and not shift[1].any()
    pairs = np.array([[True, True], [True, True], [True, False]])
    shift = push_out_of_bones(field, points, active=pairs)
    assert shift[1, 2] == pytest.approx(1.0, abs=1e-3)
    assert not shift[2].any()                               # inside the exempt bone only


def test_bad_surfaces_and_arguments_are_refused_with_the_bone_named():
    points, triangles = BOX
    with pytest.raises(MuscleMSSError, match="femur.*open"):
        bone_distance_field(points, triangles[:-1], where="bones.vtm block 'femur'")
    with pytest.raises(MuscleMSSError, match="femur.*spacing"):
        bone_distance_field(points, triangles, spacing=0.0, where="bones.vtm block 'femur'")
    with pytest.raises(MuscleMSSError, match="femur.*spacing 0.01 mm would hold .* larger"):
        bone_distance_field(points, triangles, spacing=0.01, where="bones.vtm block 'femur'")
    field = bone_field_set([BOX])
    with pytest.raises(MuscleMSSError, match="transforms"):
        signed_distances(field, np.zeros((1, 3)), np.zeros((2, 3, 4)))
    with pytest.raises(MuscleMSSError, match="active"):
        push_out_of_bones(field, np.zeros((2, 3)), active=[True])


def test_exact_distances_and_push_correct_the_field_next_to_a_thin_bone():
    # a plate 1.2 mm thick, thinner than the field's 1 mm cells can resolve: the looked-up
    # distances inside it are off by a good part of a millimetre
    plate = box_mesh([-10.0, -10.0, -0.6], [10.0, 10.0, 0.6])
    transform = rigid(30.0, [1, 2, 0], [4.0, -1.0, 2.0])
    fields = bone_field_set([plate])
    with_surfaces = BoneFieldSet.pack([bone_distance_field(*plate)],
                                      surfaces=[prepared_surface(*plate, "plate")])
    rest = np.array([[0.3, 0.2, 0.05], [-2.0, 4.0, -0.5], [1.0, 1.0, 0.55], [0.0, 0.0, 3.0],
                     [0.0, 0.0, 30.0]])
    posed = rest @ transform[:, :3].T + transform[:, 3]
    exact = reference_signed_distance(*plate, rest)
    sampled = signed_distances(fields, posed, transform[None])[0][:, 0]
    assert np.abs(sampled[:3] - exact[:3]).max() > 0.1        # the field is not enough here
    measured = exact_signed_distances(with_surfaces, posed, transform[None])[:, 0]
    np.testing.assert_allclose(measured[:4], exact[:4], atol=1e-9)
    assert measured[4] == sampled[4]                           # far out: the field's value
    np.testing.assert_array_equal(exact_signed_distances(fields, posed, transform[None])[:, 0],
                                  sampled)                     # no surfaces: the fields only

    shift = push_out_exactly(with_surfaces, posed, transform[None])
    back = (posed + shift - transform[:, 3]) @ transform[:, :3]
    after = reference_signed_distance(*plate, back)
    np.testing.assert_allclose(after[:3], EXACT_CLEARANCE, atol=1e-9)   # on the near face
    np.testing.assert_allclose(np.abs(back[:3, 2]), 0.6 + EXACT_CLEARANCE, atol=1e-9)
    np.testing.assert_allclose(back[:3, :2], rest[:3, :2], atol=1e-9)
    assert np.sign(back[1, 2]) == -1 and np.sign(back[2, 2]) == 1
    assert not shift[3:].any()                                  # outside: exactly unmoved
    held = push_out_exactly(with_surfaces, posed, transform[None],
                            active=[[True], [False], [True], [True], [True]])
    assert not held[1].any() and held[0].any()
