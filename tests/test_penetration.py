"""Remaining overlap per object after a solve (core.contacts.penetration)."""
import numpy as np

from muscle_mss.core.contacts.penetration import max_penetration_per_object


def brute_force(centres, radii, owner, n, bone_centres, bone_radii, fixed):
    deepest = np.zeros(n)
    all_c = np.concatenate([centres, bone_centres])
    all_r = np.concatenate([radii, bone_radii])
    all_o = np.concatenate([owner, np.full(len(bone_centres), -1)])
    all_fixed = np.concatenate([fixed, np.ones(len(bone_centres), bool)])
    for a in range(len(centres)):
        for b in range(len(all_c)):
            if all_o[b] != owner[a] and not (fixed[a] and all_fixed[b]):
                depth = radii[a] + all_r[b] - np.linalg.norm(centres[a] - all_c[b])
                deepest[owner[a]] = max(deepest[owner[a]], depth)
    return deepest


def test_two_spheres_overlapping_by_a_known_depth():
    centres = np.array([[0.0, 0, 0], [3.0, 0, 0]])
    got = max_penetration_per_object(centres, [2.0, 1.5], [0, 1], 2)
    np.testing.assert_allclose(got, [0.5, 0.5])
    got = max_penetration_per_object(centres, [1.0, 1.5], [0, 1], 2)  # apart: 0.5 mm gap
    np.testing.assert_array_equal(got, [0.0, 0.0])
    got = max_penetration_per_object(centres, [2.0, 1.5], [0, 0], 1)  # same object: no overlap
    np.testing.assert_array_equal(got, [0.0])


def test_random_clouds_match_brute_force():
    rng = np.random.default_rng(7)
    centres = rng.uniform(0, 20, (150, 3))
    radii = rng.uniform(0.2, 2.5, 150)
    owner = rng.integers(0, 4, 150)
    bone_c = rng.uniform(0, 20, (40, 3))
    bone_r = rng.uniform(0.5, 1.5, 40)
    fixed = rng.random(150) < 0.3
    got = max_penetration_per_object(centres, radii, owner, 4, bone_c, bone_r, fixed)
    np.testing.assert_allclose(got, brute_force(centres, radii, owner, 4, bone_c, bone_r, fixed))
    assert got.max() > 0


def test_pairs_no_solver_can_resolve_are_left_out():
    centres = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    bone = np.array([[0.5, 0, 0]])
    # a fixed tendon sphere inside its bone sphere: nothing can move, nothing to report
    got = max_penetration_per_object(centres[:1], [1.0], [0], 1, bone, [1.0], fixed=[True])
    np.testing.assert_array_equal(got, [0.0])
    got = max_penetration_per_object(centres[:1], [1.0], [0], 1, bone, [1.0], fixed=[False])
    np.testing.assert_allclose(got, [1.5])
