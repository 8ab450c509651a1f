"""How deep the collision spheres of each object still overlap others after a solve.

A check of the result (DESIGN §7's ``max_penetration_mm`` per muscle), run once per time point,
not in the solver's loop: the paper's §3.3 response aims at spheres of different objects that
just touch, so the remaining overlap measures how far a solve is from that.
"""
import numpy as np
from scipy.spatial import cKDTree


def max_penetration_per_object(centres, radii, owner, n_objects, bone_centres=None,
                               bone_radii=None, fixed=None) -> np.ndarray:
    """Deepest overlap (mm; 0 when none) of each object's spheres with spheres of other objects,
    over the pairs a solver can resolve: at least one sphere free to move (bone spheres and
    ``fixed`` muscle spheres — tendon attachments, which sit inside their bone — cannot).

    Parameters
    ----------
    centres : (n, 3) float64 mm, radii : (n,) float64 mm
        The muscles' collision spheres (boundary particles).
    owner : (n,) int, the muscle of each sphere, in ``0 .. n_objects - 1``
    bone_centres : (k, 3) float64 mm, bone_radii : (k,) float64 mm, optional
        Bone spheres; they count as objects of their own for every muscle.
    fixed : (n,) bool, optional, muscle spheres that never move
    """
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    radii = np.asarray(radii, dtype=np.float64).reshape(-1)
    owner = np.asarray(owner, dtype=np.int64).reshape(-1)
    free = np.ones(len(centres), bool) if fixed is None else ~np.asarray(fixed, bool).reshape(-1)
    if bone_centres is not None and len(bone_centres):
        centres_all = np.concatenate([centres, np.asarray(bone_centres, dtype=np.float64)])
        radii_all = np.concatenate([radii, np.asarray(bone_radii, dtype=np.float64)])
        owner_all = np.concatenate([owner, np.full(len(bone_centres), -1)])
        free_all = np.concatenate([free, np.zeros(len(bone_centres), bool)])
    else:
        centres_all, radii_all, owner_all, free_all = centres, radii, owner, free
    deepest = np.zeros(n_objects)
    if len(centres) == 0:
        return deepest
    reach = radii + radii_all.max()
    neighbours = cKDTree(centres_all).query_ball_point(centres, reach)
    counts = np.fromiter((len(n) for n in neighbours), dtype=np.int64, count=len(neighbours))
    i = np.repeat(np.arange(len(centres)), counts)
    j = np.fromiter((k for n in neighbours for k in n), dtype=np.int64, count=int(counts.sum()))
    other = (owner_all[j] != owner[i]) & (free[i] | free_all[j])
    i, j = i[other], j[other]
    depth = radii[i] + radii_all[j] - np.linalg.norm(centres[i] - centres_all[j], axis=1)
    np.maximum.at(deepest, owner[i], np.maximum(depth, 0.0))
    return deepest


def max_penetration_pairs(centres, radii, owner, n_objects, bone_centres=None,
                          bone_radii=None, fixed=None) -> np.ndarray:
    """:func:`max_penetration_per_object` with every pair found and measured in arrays (one
    KD-tree pair query returning an index array, then NumPy over the pairs) instead of Python
    lists per sphere: issue 15 measured the generator over ~0.4 M pairs per time point at
    0.2 s. Same arguments and the same result, bitwise: every overlapping pair of the
    reference is found and measured by the same formula;
    :func:`max_penetration_per_object` stays as its slow reference."""
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    radii = np.asarray(radii, dtype=np.float64).reshape(-1)
    owner = np.asarray(owner, dtype=np.int64).reshape(-1)
    free = np.ones(len(centres), bool) if fixed is None else ~np.asarray(fixed, bool).reshape(-1)
    if bone_centres is not None and len(bone_centres):
        centres_all = np.concatenate([centres, np.asarray(bone_centres, dtype=np.float64)])
        radii_all = np.concatenate([radii, np.asarray(bone_radii, dtype=np.float64)])
        owner_all = np.concatenate([owner, np.full(len(bone_centres), -1)])
        free_all = np.concatenate([free, np.zeros(len(bone_centres), bool)])
    else:
        centres_all, radii_all, owner_all, free_all = centres, radii, owner, free
    deepest = np.zeros(n_objects)
    if len(centres) == 0:
        return deepest
    largest = radii_all.max()
    pairs = cKDTree(centres).sparse_distance_matrix(
        cKDTree(centres_all), radii.max() + largest, output_type="ndarray")
    i, j = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    # a superset of the reference's pairs (its reach is radii[i] + largest); the extra pairs
    # are farther apart than their radii and add depth 0
    near = (owner_all[j] != owner[i]) & (free[i] | free_all[j])
    i, j = i[near], j[near]
    depth = radii[i] + radii_all[j] - np.linalg.norm(centres[i] - centres_all[j], axis=1)
    np.maximum.at(deepest, owner[i], np.maximum(depth, 0.0))
    return deepest
