"""The collision spheres of a solve and the paper's response rule (§3.3).

The collision spheres are the boundary particles with a positive radius (:class:`Spheres`).
The response shared by both collision structures (:func:`sphere_push`, :func:`push_share`,
:func:`deeper`) is the paper's §3.3 rule — a colliding pair moves apart by its penetration
along the centre line, half each, or all of it for the free sphere when the other is fixed or a
bone sphere; pushes are accumulated and applied after all tests — with one refinement: a sphere
takes one push per *other object*, that of its deepest pair with that object. The paper sums
every pair; when a muscle sphere overlaps many small spheres of one bone (the demo's posed
muscles: up to 53 bone spheres of 2 mm under one 7 mm muscle sphere) that sum throws it by
tens of times its penetration (over 100 mm at N = 80), whereas the deepest pair's push lifts it
exactly onto the surface of the sphere set. With one pair per object (two muscles in contact:
1.02 pairs per colliding sphere on the demo) the two rules coincide.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit


@dataclass
class Spheres:
    """The collision spheres of a solve (paper §3.3).

    Muscle spheres: ``particle`` (m,) int64 the particle each one sits on, ``radius`` (m,)
    float64 mm, ``muscle`` (m,) int64, ``fixed`` (m,) bool. Bone spheres: ``bone_centres``
    (3, b) float64 mm, ``bone_radius`` (b,) mm, ``bone`` (b,) int64. Bones do not move during a
    solve; muscle sphere centres are the current particle positions.
    """

    particle: np.ndarray
    radius: np.ndarray
    muscle: np.ndarray
    fixed: np.ndarray
    bone_centres: np.ndarray
    bone_radius: np.ndarray
    bone: np.ndarray

    @property
    def count(self) -> int:
        return len(self.particle)

    @property
    def n_muscles(self) -> int:
        return int(self.muscle.max()) + 1 if len(self.muscle) else 0

    @property
    def n_bones(self) -> int:
        return int(self.bone.max()) + 1 if len(self.bone) else 0


def make_spheres(radius, muscle, fixed, boundary, bone_centres=None, bone_radius=None,
                 bone=None) -> Spheres:
    """The :class:`Spheres` of boundary particles with a positive radius plus the bone spheres.

    radius (n,) mm, muscle (n,) int, fixed (n,) bool, boundary (n,) bool per particle;
    bone_centres (b, 3) mm, bone_radius (b,) mm, bone (b,) int (omit for no bones).
    """
    radius = np.asarray(radius, dtype=np.float64).ravel()
    particle = np.flatnonzero(np.asarray(boundary, dtype=bool).ravel() & (radius > 0.0))
    if bone_centres is None:
        bone_centres, bone_radius, bone = np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64)
    return Spheres(particle.astype(np.int64), radius[particle].copy(),
                   np.asarray(muscle, dtype=np.int64).ravel()[particle].copy(),
                   np.asarray(fixed, dtype=bool).ravel()[particle].copy(),
                   np.ascontiguousarray(np.asarray(bone_centres, np.float64).reshape(-1, 3).T),
                   np.asarray(bone_radius, dtype=np.float64).ravel().copy(),
                   np.asarray(bone, dtype=np.int64).ravel().copy())


@njit(cache=True, inline="always")
def sphere_push(xi, yi, zi, ri, xj, yj, zj, rj, i_before_j):
    """Penetration (mm, > 0 when the spheres overlap) and the unit direction from sphere j to
    sphere i. Coincident centres get a fixed axis, signed by which sphere comes first, so that
    the two spheres still move apart."""
    dx = xi - xj
    dy = yi - yj
    dz = zi - zj
    dist = np.sqrt(dx * dx + dy * dy + dz * dz)
    pen = ri + rj - dist
    if pen <= 0.0:
        return pen, 0.0, 0.0, 0.0
    if dist > 0.0:
        return pen, dx / dist, dy / dist, dz / dist
    return pen, (-1.0 if i_before_j else 1.0), 0.0, 0.0


@njit(cache=True, inline="always")
def push_share(fixed_self, other_moves):
    """The paper's rule: the part of the penetration a sphere moves — half when both are free,
    the whole when the other is fixed or a bone sphere, nothing when it is fixed itself."""
    if fixed_self:
        return 0.0
    return 0.5 if other_moves else 1.0


@njit(cache=True, inline="always")
def deeper(pen, partner, best_pen, best_partner):
    """Whether a pair of penetration ``pen`` with sphere ``partner`` replaces the deepest pair
    found so far with the same object (ties: the lower partner index, so that the order in
    which a structure finds the pairs does not matter)."""
    return pen > best_pen or (pen == best_pen and partner < best_partner)
