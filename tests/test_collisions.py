"""Collision detection and response (core/contacts/spatial_hash.py, core/contacts/octree_bvh.py,
core/bones/spheres.py and the response rule of core/mss.py)."""
import numpy as np
import pytest

from muscle_mss.core.contacts import (collision_spheres, octree_bvh, spatial_hash, sphere_lists,
                                      sphere_contacts as contacts)
from muscle_mss.core import solver
from muscle_mss.core.model import Bones, MSSModel
from muscle_mss.core.bones.spheres import SPHERES_PER_AREA, bone_spheres, surface_area
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.settings import DEFAULT_PENETRATION_TOLERANCE, STRUCTURES

from test_solver import paper


def loose_model(positions, radii, muscles, fixed=None, springs=None, rest=None):
    """Particles without springs (or with the given ones), every particle a boundary sphere."""
    positions = np.asarray(positions, float).reshape(-1, 3)
    n = len(positions)
    muscles = np.asarray(muscles)
    offsets = np.concatenate([[0], np.cumsum(np.bincount(muscles))])
    springs = np.zeros((0, 2), int) if springs is None else np.asarray(springs)
    rest = np.zeros(0) if rest is None else np.asarray(rest, float)
    return MSSModel(
        [f"m{m}" for m in range(len(offsets) - 1)], offsets, positions,
        np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool), np.ones(n),
        np.ones(n, bool), np.asarray(radii, float), np.arange(n), np.zeros(n, int), springs,
        rest, np.full(len(rest), 10.0), np.full(len(rest), 0.5))


def one_iteration(model, structure, bones=None, projection_passes=0):
    """One iteration: the paper's single response (no final projection unless asked)."""
    settings = paper(iterations=1, structure=structure,
                                     projection_passes=projection_passes)
    return solver.solve(model, Bones(bones), settings)


@pytest.mark.parametrize("structure", STRUCTURES)
def test_two_free_muscle_spheres_move_half_each(structure):
    model = loose_model([[0, 0, 0], [1.5, 0.4, -0.2]], [1.0, 0.8], [0, 1])
    result = one_iteration(model, structure)
    a, b = result.positions
    assert np.linalg.norm(a - b) == pytest.approx(1.8, abs=1e-12)
    np.testing.assert_allclose((a + b) / 2, [0.75, 0.2, -0.1], atol=1e-12)
    direction = np.array([1.5, 0.4, -0.2]) / np.linalg.norm([1.5, 0.4, -0.2])
    np.testing.assert_allclose(np.cross(b - a, direction), 0, atol=1e-12)
    assert result.collided.all() and result.muscle_pairs[0] == 1


@pytest.mark.parametrize("structure", STRUCTURES)
def test_free_sphere_moves_whole_penetration_when_the_other_is_fixed(structure):
    model = loose_model([[0, 0, 0], [0, 1.0, 0]], [1.0, 0.5], [0, 1], fixed=[True, False])
    result = one_iteration(model, structure)
    assert np.array_equal(result.positions[0], [0, 0, 0])
    np.testing.assert_allclose(result.positions[1], [0, 1.5, 0], atol=1e-12)


@pytest.mark.parametrize("structure", STRUCTURES)
def test_two_fixed_spheres_do_not_move(structure):
    model = loose_model([[0, 0, 0], [0, 1.0, 0]], [1.0, 0.5], [0, 1], fixed=[True, True])
    result = one_iteration(model, structure)
    assert np.array_equal(result.positions, model.positions)
    assert result.muscle_pairs[0] == 1


@pytest.mark.parametrize("structure", STRUCTURES)
def test_muscle_sphere_moves_whole_penetration_out_of_a_bone_sphere(structure):
    model = loose_model([[0, 0, 1.0]], [1.0], [0])
    bones = (np.array([[0.0, 0.0, 0.0]]), np.array([0.5]), np.array([0]))
    result = one_iteration(model, structure, bones)
    np.testing.assert_allclose(result.positions[0], [0, 0, 1.5], atol=1e-12)
    assert result.bone_pairs[0] == 1 and result.max_penetration[0] == pytest.approx(0.5)


@pytest.mark.parametrize("structure", STRUCTURES)
def test_sphere_on_a_dense_bone_sheet_is_lifted_onto_it_not_thrown(structure):
    # one push per other object: that of the deepest pair (the paper's sum would add ~40 pushes)
    g = np.arange(-6, 6.5, 0.5)
    sheet = np.stack(np.meshgrid(g, g, [0.0], indexing="ij"), -1).reshape(-1, 3)
    model = loose_model([[0.0, 0.0, 1.2]], [2.0], [0])
    result = one_iteration(model, structure, (sheet, np.full(len(sheet), 0.5),
                                              np.zeros(len(sheet), int)))
    assert result.bone_pairs[0] > 30
    np.testing.assert_allclose(result.positions[0], [0, 0, 2.5], atol=1e-12)


@pytest.mark.parametrize("structure", STRUCTURES)
def test_collided_particles_lose_their_velocity(structure):
    # particle 1 is pulled by a stretched spring; particle 2 (same pull) ends in a bone sphere
    positions = [[0, 0, 0], [0, 0, 3.0], [10, 0, 0], [10, 0, 3.0]]
    model = loose_model(positions, [0.1, 0.1, 0.1, 0.1], [0, 0, 1, 1],
                        fixed=[True, False, True, False], springs=[[0, 1], [2, 3]],
                        rest=[1.0, 1.0])
    bones = (np.array([[10.0, 0.0, 2.9]]), np.array([0.2]), np.array([0]))
    result = one_iteration(model, structure, bones)
    assert result.collided.tolist() == [False, False, False, True]
    assert np.abs(result.velocity[1]).max() > 0.1
    assert np.array_equal(result.velocity[3], [0, 0, 0])


@pytest.mark.parametrize("structure", STRUCTURES)
def test_final_passes_free_a_sphere_pressed_between_a_bone_and_another_muscle(structure):
    # A (r 1) sits 0.2 mm in a bone sphere (r 1) and 0.4 mm under B (r 1) of another muscle
    model = loose_model([[0, 0, 1.8], [0, 0, 3.4]], [1.0, 1.0], [0, 1])
    bones = (np.array([[0.0, 0.0, 0.0]]), np.array([1.0]), np.array([0]))
    once = one_iteration(model, structure, bones)
    # the paper's response: A out of the bone by 0.2 and back by half of 0.4; B up by 0.2
    np.testing.assert_allclose(once.positions[:, 2], [1.8, 3.6], atol=1e-12)
    assert once.projection_passes == 0
    tolerance = DEFAULT_PENETRATION_TOLERANCE
    result = one_iteration(model, structure, bones, projection_passes=100)
    a, b = result.positions[:, 2]
    assert 2.0 - tolerance <= a <= 2.0 + 1e-12        # on the bone, not thrown off it
    assert b - a >= 2.0 - tolerance                     # B rests on A
    # each pass: A's bone overlap becomes half the A-B overlap, the A-B overlap becomes A's
    # old bone overlap; the passes stop at the first one that finds nothing above tolerance
    bone_overlap, pair_overlap, passes = 0.2, 0.2, 0
    while True:
        passes += 1
        if max(bone_overlap, pair_overlap) <= tolerance:
            break
        bone_overlap, pair_overlap = pair_overlap / 2, bone_overlap
    assert result.projection_passes == passes == 11
    assert result.remaining_penetration <= tolerance
    assert result.collided.all() and np.array_equal(result.velocity, np.zeros((2, 3)))


def box_solid(lower, upper, clearance):
    """One box bone as a solid (rest pose) and its mesh."""
    from muscle_mss.core.bones.distance import BoneSolids
    from muscle_mss.core.bones.field_sampling import bone_field_set
    from test_bone_distance import box_mesh
    box = box_mesh(lower, upper)
    return BoneSolids(bone_field_set([box]), np.eye(3, 4)[None], np.array([clearance])), box


@pytest.mark.parametrize("structure", STRUCTURES)
def test_solid_bone_takes_spheres_out_from_any_depth_in_one_response(structure):
    """Issue 14: a sphere 5 mm inside a box bone and one at its very centre (where the distance
    gradient vanishes) both end their radius plus the clearance outside it after one paper
    response; a fixed (tendon) sphere inside stays; the one 5 mm deep leaves by the near face."""
    from reference_distance import reference_signed_distance
    clearance, radii = 0.5, np.array([1.0, 1.5, 1.0])
    solids, box = box_solid([-10.0, -10.0, -10.0], [10.0, 10.0, 10.0], clearance)
    model = loose_model([[1.0, 2.0, 5.0], [0.0, 0.0, 0.0], [0.0, 0.0, -8.0]], radii,
                        [0, 1, 2], fixed=[False, False, True])
    settings = paper(iterations=1, structure=structure, projection_passes=0)
    result = solver.solve(model, Bones(solids=solids), settings)
    depth = reference_signed_distance(*box, result.positions)
    assert depth[0] == pytest.approx(radii[0] + clearance, abs=1e-3)
    np.testing.assert_allclose(result.positions[0], [1.0, 2.0, 10.0 + radii[0] + clearance],
                               atol=1e-3)
    # from the cube's centre the interpolated gradient leads to a corner, where the field
    # overstates the distance by up to half its 1 mm spacing (bone_distance's docstring);
    # measured 1.981 mm for the 2.0 wanted
    assert depth[1] == pytest.approx(radii[1] + clearance, abs=0.05)
    assert np.array_equal(result.positions[2], model.positions[2])
    assert result.collided.tolist() == [True, True, False]
    assert result.bone_pairs[0] == 2
    assert result.max_penetration[0] == pytest.approx(10.0 + 1.5 + 0.5, abs=1e-3)


def test_solid_bone_keeps_out_particles_without_a_sphere_unless_inside_at_rest():
    """With ``in_bone_at_rest`` known, every free particle is kept out of the solids, a sphere
    to its radius, one without a sphere (interior, radius 0) to the surface; a particle inside
    the bone at rest (embedded next to its tendon) stays where it is, and so does a fixed one.
    Without it, only the spheres are kept out."""
    from reference_distance import reference_signed_distance
    solids, box = box_solid([-10.0, -10.0, -10.0], [10.0, 10.0, 10.0], 0.0)
    positions = [[1.0, 2.0, 8.0], [2.0, -1.0, 7.0], [-3.0, 0.0, 6.0], [0.0, 3.0, -9.0]]
    model = loose_model(positions, [1.0, 0.0, 0.0, 0.0], [0, 0, 0, 0],
                        fixed=[False, False, False, True])
    model.boundary[:] = [True, False, True, False]
    model.in_bone_at_rest = np.array([False, False, True, True])
    settings = paper(iterations=1, projection_passes=0)
    result = solver.solve(model, Bones(solids=solids), settings)
    depth = reference_signed_distance(*box, result.positions)
    assert depth[0] == pytest.approx(1.0, abs=1e-3) and depth[1] == pytest.approx(0.0, abs=1e-3)
    np.testing.assert_allclose(result.positions[1], [2.0, -1.0, 10.0], atol=1e-3)
    assert np.array_equal(result.positions[2:], model.positions[2:])
    assert result.collided.tolist() == [True, True, False, False]
    model.in_bone_at_rest = None
    spheres_only = solver.solve(model, Bones(solids=solids), settings)
    assert np.array_equal(spheres_only.positions[0], result.positions[0])
    assert np.array_equal(spheres_only.positions[1:], model.positions[1:])


def test_solid_bones_replace_the_sphere_sets_and_can_be_switched_off():
    """With solids the bone spheres are not tested (a sphere set given beside them is ignored);
    MuscleBone off turns the solids off too."""
    solids, _ = box_solid([-10.0, -10.0, -10.0], [10.0, 10.0, 10.0], 0.0)
    model = loose_model([[0.0, 0.0, 20.0]], [1.0], [0])
    far_sphere = (np.array([[0.0, 0.0, 20.5]]), np.array([0.5]), np.array([0]))
    result = solver.solve(model, Bones(far_sphere, solids), paper(iterations=1))
    assert np.array_equal(result.positions, model.positions) and result.bone_pairs[0] == 0
    inside = loose_model([[0.0, 0.0, 5.0]], [1.0], [0])
    off = solver.solve(inside, Bones(solids=solids), paper(iterations=1, muscle_bone=False))
    assert np.array_equal(off.positions, inside.positions)
    with pytest.raises(MuscleMSSError, match="one finite 3x4 transform per bone"):
        solver.solve(inside, Bones(solids=type(solids)(solids.fields, np.eye(3, 4), np.zeros(1))))


def test_projection_passes_are_capped():
    model = loose_model([[0, 0, 1.8], [0, 0, 3.4]], [1.0, 1.0], [0, 1])
    bones = (np.array([[0.0, 0.0, 0.0]]), np.array([1.0]), np.array([0]))
    result = one_iteration(model, "spatial hash", bones, projection_passes=2)
    assert result.projection_passes == 2 and result.remaining_penetration > 0.01


def test_final_passes_give_up_on_a_sphere_wedged_between_two_bones():
    # a 1 mm sphere in a 0.5 mm gap between two bones: each pass pushes it out of both
    model = loose_model([[0.0, 0.0, 1.25]], [1.0], [0])
    bones = (np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.5]]), np.array([1.0, 1.0]),
             np.array([0, 1]))
    result = one_iteration(model, "spatial hash", bones, projection_passes=100)
    assert result.projection_passes == 1 + contacts.STALLED_PASSES
    assert result.remaining_penetration == pytest.approx(0.75)
    np.testing.assert_allclose(result.positions[0], [0.0, 0.0, 1.25], atol=1e-12)


def random_cloud(seed, n=1500, muscles=5, bones=3):
    rng = np.random.default_rng(seed)
    muscle = np.sort(rng.integers(0, muscles, n))
    spheres = collision_spheres.make_spheres(rng.random(n) * 2 + 0.1, muscle, rng.random(n) < 0.1,
                               rng.random(n) < 0.85, rng.random((500, 3)) * 40,
                               rng.random(500) + 0.5, np.sort(rng.integers(0, bones, 500)))
    return rng.random((n, 3))[spheres.particle] * 40, spheres


def brute_force_pairs(centres, spheres):
    d = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    reach = spheres.radius[:, None] + spheres.radius[None]
    i, j = np.nonzero((d < reach) & (spheres.muscle[:, None] != spheres.muscle[None])
                      & np.triu(np.ones_like(d, bool), 1))
    db = np.linalg.norm(centres[:, None] - spheres.bone_centres.T[None], axis=2)
    k, b = np.nonzero(db < spheres.radius[:, None] + spheres.bone_radius[None])
    return np.stack([i, j], 1), np.stack([k, b], 1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_hash_and_bvh_find_the_same_pairs_as_brute_force_on_random_clouds(seed):
    centres, spheres = random_cloud(seed)
    want = brute_force_pairs(centres, spheres)
    assert len(want[0]) > 50 and len(want[1]) > 50
    hashed = spatial_hash.colliding_pairs(centres, spheres)
    bvh = octree_bvh.colliding_pairs(centres, octree_bvh.octree_bvh(spheres))
    for got in (hashed, bvh):
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


def test_hash_and_bvh_find_the_same_pairs_on_packed_lattices():
    # three lattices of touching spheres pressed 0.3 mm into each other, a bone sheet below
    g = np.arange(0, 10, 1.0)
    block = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    centres = np.concatenate([block, block + [9.7, 0, 0], block + [0, 9.7, 0]])
    muscle = np.repeat([0, 1, 2], len(block))
    sheet = np.stack(np.meshgrid(np.arange(-2, 22, 0.7), np.arange(-2, 22, 0.7), [-0.8],
                                 indexing="ij"), -1).reshape(-1, 3)
    spheres = collision_spheres.make_spheres(np.full(len(centres), 0.5), muscle, np.zeros(len(centres), bool),
                               np.ones(len(centres), bool), sheet, np.full(len(sheet), 0.6),
                               np.zeros(len(sheet), int))
    hashed = spatial_hash.colliding_pairs(centres, spheres)
    bvh = octree_bvh.colliding_pairs(centres, octree_bvh.octree_bvh(spheres, 8, 10))
    assert len(hashed[0]) > 100 and len(hashed[1]) > 100
    assert np.array_equal(hashed[0], bvh[0]) and np.array_equal(hashed[1], bvh[1])


def test_bvh_refits_after_motion_and_keeps_finding_the_same_pairs():
    centres, spheres = random_cloud(5)
    tree = octree_bvh.octree_bvh(spheres, 8, 10)
    octree_bvh.colliding_pairs(centres, tree)
    nodes = tree.state[0]
    moved = centres + np.random.default_rng(9).normal(scale=1.5, size=centres.shape)
    got = octree_bvh.colliding_pairs(moved, tree)
    want = brute_force_pairs(moved, spheres)
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    assert tree.state[0] >= nodes


def icosphere_like(radius=20.0, n=40):
    """A closed UV sphere surface (points, triangles)."""
    theta = np.linspace(0, np.pi, n)[1:-1]
    phi = np.linspace(0, 2 * np.pi, 2 * n, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    pts = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    pts = np.concatenate([pts, [[0, 0, 1], [0, 0, -1]]]) * radius
    rings, per = len(theta), len(phi)
    tris = []
    for r in range(rings - 1):
        for k in range(per):
            a, b = r * per + k, r * per + (k + 1) % per
            c, d = a + per, b + per
            tris += [[a, c, b], [b, c, d]]
    top, bottom = len(pts) - 2, len(pts) - 1
    for k in range(per):
        tris.append([top, k, (k + 1) % per])
        last = (rings - 1) * per
        tris.append([bottom, last + (k + 1) % per, last + k])
    return pts, np.array(tris)


def test_bone_spheres_are_spaced_cover_the_surface_and_are_deterministic():
    pts, tris = icosphere_like()
    spacing = 2.0
    centres, radii = bone_spheres(pts, tris, spacing)
    again, _ = bone_spheres(pts, tris, spacing)
    assert np.array_equal(centres, again)
    assert np.all(radii == spacing)
    d = np.linalg.norm(centres[:, None] - centres[None], axis=2) + np.eye(len(centres)) * 1e9
    assert d.min() >= spacing
    # every surface vertex and edge midpoint lies inside a sphere
    probes = np.concatenate([pts, (pts[tris[:, 0]] + pts[tris[:, 1]]) / 2])
    nearest = np.linalg.norm(probes[:, None] - centres[None], axis=2).min(axis=1)
    assert nearest.max() < spacing
    expected = SPHERES_PER_AREA * surface_area(pts, tris) / spacing ** 2
    assert abs(len(centres) / expected - 1) < 0.15


def test_bone_spheres_by_count_give_exactly_that_count():
    pts, tris = icosphere_like()
    centres, radii = bone_spheres(pts, tris, count=700)
    assert len(centres) == 700 and len(radii) == 700


def test_bone_spheres_refuse_bad_surfaces():
    pts, tris = icosphere_like()
    bad = pts.copy()
    bad[3] = np.nan
    with pytest.raises(MuscleMSSError, match="femur.*NaN"):
        bone_spheres(bad, tris, 2.0, where="femur")
    with pytest.raises(MuscleMSSError, match="positive"):
        bone_spheres(pts, tris, 0.0)
    with pytest.raises(MuscleMSSError, match="missing points"):
        bone_spheres(pts, tris + len(pts), 2.0)


def response_of_lists(x, spheres, begin, end, idx):
    """The response list_contacts gives from candidate lists (muscle-muscle)."""
    n = spheres.count
    out = (np.zeros((3, n)), np.zeros(n, np.uint8), np.zeros(n, np.int64), np.zeros(n))
    spatial_hash.list_contacts(x, spheres.radius, spheres.fixed, begin, end, idx, x,
                               spheres.radius, spheres.muscle, ~spheres.fixed, True, *out)
    return out


def incremental_step(x, spheres, skin, lists):
    n = spheres.count
    out = (np.zeros((3, n)), np.zeros(n, np.uint8), np.zeros(n, np.int64), np.zeros(n))
    refreshed, lists = sphere_lists.muscle_contacts(
        x, spheres.radius, spheres.muscle, spheres.fixed, ~spheres.fixed, skin,
        spatial_hash.muscle_cell(spheres, skin), lists, *out)
    return refreshed, lists, out


@pytest.mark.parametrize("room", [64, 1])
def test_lists_refreshed_sphere_by_sphere_find_the_brute_force_pairs_while_spheres_move(room):
    # jitter below the skin, a few far jumps, fixed spheres, a step without motion; room 1
    # makes every list outgrow its room (relaid pool); the response is list_contacts' bit for bit
    centres, spheres = random_cloud(3)
    n = spheres.count
    skin = 0.8
    rng = np.random.default_rng(4)
    x = np.ascontiguousarray(centres.T)
    lists = sphere_lists.muscle_lists(spheres.radius, room)
    refreshed_counts = []
    for step in range(8):
        refreshed, lists, got = incremental_step(x, spheres, skin, lists)
        refreshed_counts.append(refreshed)
        want_pairs = brute_force_pairs(x.T, spheres)[0]
        table = spatial_hash.grid_table(x, spheres.radius, 3.0, spheres.muscle)
        begin, end, idx = spatial_hash.candidate_lists(x, spheres.radius, spheres.muscle,
                                                       table, 0.0)
        want = response_of_lists(x, spheres, begin, end, idx)
        assert got[2].sum() == len(want_pairs) > 50
        for a, b in zip(got, want):
            assert np.array_equal(a, b)
        first, last, partner = lists[-3:]
        pairs = [(i, j) for i in range(n) for j in partner[first[i]:last[i]] if i < j]
        assert pairs == [tuple(p) for p in want_pairs.tolist()]
        move = rng.normal(scale=0.15, size=x.shape)
        move[:, rng.choice(n, 20, replace=False)] += rng.normal(scale=4.0, size=(3, 20))
        if step == 4:
            move[:] = 0.0
        move[:, spheres.fixed] = 0.0
        x = np.ascontiguousarray(x + move)
    assert refreshed_counts[0] == n and refreshed_counts[5] == 0
    assert 0 < min(refreshed_counts[1:5]) and max(refreshed_counts[1:]) < n


def test_a_pair_approached_by_exactly_half_the_skin_each_is_found():
    # two spheres start exactly r_i + r_j + skin apart (as rounded) and each moves exactly
    # skin / 2 towards the other: neither list is refreshed, and rounding leaves them
    # overlapping by 2e-16 mm; the list reach must not lose that pair
    skin = 1.0
    a = 0.4097352393619469
    spheres = collision_spheres.make_spheres([1.0, 1.0], [0, 1], [False, False], [True, True])
    x = np.array([[a, a + 3.0], [0.0, 0.0], [0.0, 0.0]])
    lists = sphere_lists.muscle_lists(spheres.radius)
    _, lists, out = incremental_step(x, spheres, skin, lists)
    assert out[2].sum() == 0
    x = np.array([[a + 0.5, a + 3.0 - 0.5], [0.0, 0.0], [0.0, 0.0]])
    refreshed, lists, out = incremental_step(x, spheres, skin, lists)
    assert refreshed == 0 and out[2].sum() == 1 and out[1].all()


def test_no_muscle_spheres_and_one_lone_sphere():
    for radius in ([], [1.0]):
        spheres = collision_spheres.make_spheres(radius, np.zeros(len(radius), int),
                                   np.zeros(len(radius), bool), np.ones(len(radius), bool))
        lists = sphere_lists.muscle_lists(spheres.radius)
        refreshed, lists, out = incremental_step(np.zeros((3, len(radius))), spheres, 0.5,
                                                 lists)
        assert refreshed == len(radius) and out[2].sum() == 0


def test_non_finite_centres_collide_with_nothing_and_do_not_spoil_the_grid():
    centres, spheres = random_cloud(6)
    centres = centres.copy()
    centres[0] = np.nan
    centres[1] = [np.inf, 0.0, 0.0]
    centres[2] = [-np.inf, np.inf, 5.0]
    with np.errstate(invalid="ignore"):
        want = brute_force_pairs(centres, spheres)
    got = spatial_hash.colliding_pairs(centres, spheres)
    assert len(want[0]) > 50
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


def test_size_levels_split_wide_radius_ranges():
    radius = np.concatenate([np.full(60, 1.0), np.full(35, 3.0), np.full(5, 10.0)])
    assert np.array_equal(spatial_hash.size_levels(radius), [1.0, 3.0, 10.0])
    assert np.array_equal(spatial_hash.size_levels(np.full(5, 2.0)), [2.0])
    assert np.array_equal(spatial_hash.size_levels(np.zeros(0)), [0.0])
