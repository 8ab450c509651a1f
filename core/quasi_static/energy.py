"""The quasi-static solve's energy as a function of the free particles: springs and volume
pressure (:func:`elastic_energy`), the connective tissue
(:func:`~muscle_mss.core.connective_tissue.add_tissue_energy`) and the contact penalties of overlapping spheres
(:func:`sphere_contact_energy`) and of particles in a bone as a solid
(:func:`solid_contact_energy`), found through candidate lists rebuilt when a sphere has moved
half their skin (:class:`ContactEnergy`)."""
from __future__ import annotations

import time

import numpy as np
from numba import njit, prange

from ..contacts import spatial_hash
from ..bones.distance import sample, to_rest
from ..connective_tissue import add_tissue_energy
from ..mss import add_cage_gradient, cage_volume
from ..bones.smooth_distance import smooth_sample
from ..settings import SPRINGS_COROTATIONAL
from ..contacts.solid_contacts import solid_points
from .contact_preconditioner import muscle_contact_columns
from .corotational import add_corotational_energy, corotational_state
from .preconditioner import Preconditioner, model_springs, spring_order

# Contact list skin, times the mean muscle sphere radius (the spatial hash's own lists use
# spatial_hash.SKIN_FRACTION).
CONTACT_SKIN_FRACTION = 1.0


@njit(cache=True, parallel=True)
def elastic_energy(x, gradient, volume_gradient, energy, ends, rest, stiffness, spring_ptr,
             bulk_modulus, cage_ptr, cage_triangles, rest_volume, offsets):
    """The spring and volume energy of every muscle into ``energy`` (M,), its gradient into
    ``gradient`` (3, n) (overwritten), each muscle's cage volume gradient ``dV/dx`` into
    ``volume_gradient`` (3, n) (zero off the cages and when ``bulk_modulus`` is 0), at ``x``
    (3, n) mm. One parallel region over the muscles (a spring never joins two)."""
    for m in prange(offsets.shape[0] - 1):
        for axis in range(3):
            for p in range(offsets[m], offsets[m + 1]):
                gradient[axis, p] = 0.0
                volume_gradient[axis, p] = 0.0
        e = 0.0
        for s in range(spring_ptr[m], spring_ptr[m + 1]):
            a, b = ends[s, 0], ends[s, 1]
            dx = x[0, b] - x[0, a]
            dy = x[1, b] - x[1, a]
            dz = x[2, b] - x[2, a]
            length = np.sqrt(dx * dx + dy * dy + dz * dz)
            stretch = length - rest[s]
            e += 0.5 * stiffness[s] * stretch * stretch
            if length > 0.0:
                f = stiffness[s] * stretch / length
                gradient[0, b] += f * dx
                gradient[1, b] += f * dy
                gradient[2, b] += f * dz
                gradient[0, a] -= f * dx
                gradient[1, a] -= f * dy
                gradient[2, a] -= f * dz
        if bulk_modulus > 0.0 and cage_ptr[m + 1] > cage_ptr[m]:
            volume = cage_volume(np.int64(m), x, cage_ptr, cage_triangles)
            strain = volume / (6.0 * rest_volume[m]) - 1.0
            e += 0.5 * bulk_modulus * rest_volume[m] * strain * strain
            add_cage_gradient(np.int64(m), x, gradient, bulk_modulus * strain / 6.0, cage_ptr,
                               cage_triangles)
            add_cage_gradient(np.int64(m), x, volume_gradient, 1.0 / 6.0, cage_ptr, cage_triangles)
        energy[m] = e


@njit(cache=True, parallel=True)
def sphere_contact_energy(x, gradient, weight, particle, radius, fixed, mm_begin, mm_end, mm_idx,
              mb_begin, mb_end, mb_idx, bone_centres, bone_radius, sphere_energy, overlaps,
              deepest):
    """The contact penalty of every muscle sphere against the spheres in its candidate lists
    (``mm_*`` other muscles' spheres, ``mb_*`` bone spheres, CSR as
    :func:`~muscle_mss.core.contacts.spatial_hash.candidate_lists`), ``weight`` (n,) g/s^2 the contact
    stiffness of each particle (a pair's the mean of its two): its gradient added to ``gradient``
    (3, n) at the sphere's particle (a free sphere only), per sphere the energy of its pairs
    (a muscle pair counted by its lower sphere) into ``sphere_energy`` (s,), the overlapping
    pairs into ``overlaps`` (s, 2) (muscle, bone; a muscle pair by its lower sphere) and the
    deepest overlap of its pairs into ``deepest`` (s,) (0: it touches nothing). Sphere ``i``
    writes only its own entries."""
    for i in prange(particle.shape[0]):
        p = particle[i]
        xi, yi, zi = x[0, p], x[1, p], x[2, p]
        gx, gy, gz = 0.0, 0.0, 0.0
        e = 0.0
        n_mm, n_mb = 0, 0
        worst = 0.0
        for k in range(mm_begin[i], mm_end[i]):
            j = mm_idx[k]
            q = particle[j]
            dx, dy, dz = xi - x[0, q], yi - x[1, q], zi - x[2, q]
            d = np.sqrt(dx * dx + dy * dy + dz * dz)
            pen = radius[i] + radius[j] - d
            if pen > 0.0 and not (fixed[i] and fixed[j]):
                worst = max(worst, pen)
                w = 0.5 * (weight[p] + weight[q])
                if j > i:
                    e += 0.5 * w * pen * pen
                    n_mm += 1
                if d > 0.0:
                    gx -= w * pen * dx / d
                    gy -= w * pen * dy / d
                    gz -= w * pen * dz / d
        if not fixed[i]:
            for k in range(mb_begin[i], mb_end[i]):
                j = mb_idx[k]
                dx = xi - bone_centres[0, j]
                dy = yi - bone_centres[1, j]
                dz = zi - bone_centres[2, j]
                d = np.sqrt(dx * dx + dy * dy + dz * dz)
                pen = radius[i] + bone_radius[j] - d
                if pen > 0.0:
                    e += 0.5 * weight[p] * pen * pen
                    n_mb += 1
                    worst = max(worst, pen)
                    if d > 0.0:
                        gx -= weight[p] * pen * dx / d
                        gy -= weight[p] * pen * dy / d
                        gz -= weight[p] * pen * dz / d
        if not fixed[i]:
            gradient[0, p] += gx
            gradient[1, p] += gy
            gradient[2, p] += gz
        sphere_energy[i] = e
        overlaps[i, 0] = n_mm
        overlaps[i, 1] = n_mb
        deepest[i] = worst


@njit(cache=True, parallel=True)
def solid_contact_energy(x, gradient, weight, particle, radius, near_bones, clearance,
                         transforms, grid, sphere_energy, overlaps, deepest):
    """The contact penalty of free muscle spheres against the bones as solids: ``w_i / 2
    max(0, r_i + clearance_b - d_b(c_i))^2`` (``w`` = ``weight`` (n,) g/s^2 at the sphere's
    particle) per bone ``b`` that ``near_bones[i, b]`` marks
    (the others are out of reach, :func:`near_solids`), ``d_b`` its signed distance
    (continuously differentiable, :mod:`muscle_mss.core.bones.smooth_distance`, so that no particle
    rests on a kink of the energy; ``grid`` the fields sampled in the bones' rest
    frames, ``transforms`` (b, 3, 4) rest to posed), pushing along the distance gradient from
    whatever depth. Added to ``gradient``; per sphere its energy, overlapping bones and deepest
    overlap written to ``sphere_energy``, ``overlaps[:, 1]`` and ``deepest``."""
    for i in prange(particle.shape[0]):
        p = particle[i]
        gx, gy, gz = 0.0, 0.0, 0.0
        e = 0.0
        count = 0
        worst = 0.0
        for b in range(transforms.shape[0]):
            if not near_bones[i, b]:
                continue
            qx, qy, qz = to_rest(transforms, b, x[0, p], x[1, p], x[2, p])
            value, hx, hy, hz = smooth_sample(b, qx, qy, qz, grid)
            pen = radius[i] + clearance[b] - value
            if pen > 0.0:
                e += 0.5 * weight[p] * pen * pen
                count += 1
                worst = max(worst, pen)
                m = transforms[b]
                gx -= weight[p] * pen * (m[0, 0] * hx + m[0, 1] * hy + m[0, 2] * hz)
                gy -= weight[p] * pen * (m[1, 0] * hx + m[1, 1] * hy + m[1, 2] * hz)
                gz -= weight[p] * pen * (m[2, 0] * hx + m[2, 1] * hy + m[2, 2] * hz)
        gradient[0, p] += gx
        gradient[1, p] += gy
        gradient[2, p] += gz
        sphere_energy[i] = e
        overlaps[i, 0] = 0
        overlaps[i, 1] = count
        deepest[i] = worst


@njit(cache=True, parallel=True)
def near_solids(x, particle, radius, reach, transforms, grid, near):
    """``near[i, b]``: whether particle ``particle[i]`` lies within its ``radius[i]`` plus
    ``reach[b]`` (mm) of bone ``b`` as a solid (its signed distance in ``grid``, posed by
    ``transforms``)."""
    for i in prange(particle.shape[0]):
        p = particle[i]
        for b in range(transforms.shape[0]):
            qx, qy, qz = to_rest(transforms, b, x[0, p], x[1, p], x[2, p])
            near[i, b] = sample(b, qx, qy, qz, grid)[0] < radius[i] + reach[b]


@njit(cache=True)
def set_free(x, free, positions):
    """``x[:, free] = positions.T``: the free particles' positions (f, 3) into ``x`` (3, n)."""
    for i in range(free.shape[0]):
        for axis in range(3):
            x[axis, free[i]] = positions[i, axis]


@njit(cache=True)
def free_rows(field, free):
    """``field[:, free].T`` as a new (f, 3) array, from ``field`` (3, n)."""
    out = np.empty((free.shape[0], 3))
    for i in range(free.shape[0]):
        for axis in range(3):
            out[i, axis] = field[axis, free[i]]
    return out


@njit(cache=True, parallel=True)
def moved_flags(x, particle, built, limit, moved):
    """``moved[i]``: whether sphere ``i``'s particle ``particle[i]`` is farther than ``limit``
    mm from ``built[:, i]`` (3, s) (a NaN there: yes)."""
    for i in prange(particle.shape[0]):
        p = particle[i]
        d2 = 0.0
        for axis in range(3):
            d2 += (x[axis, p] - built[axis, i]) ** 2
        moved[i] = not d2 <= limit * limit


@njit(cache=True)
def moved_more(x, particle, built, limit):
    """Whether a sphere's particle is farther than ``limit`` mm from ``built`` (3, s)."""
    for i in range(particle.shape[0]):
        p = particle[i]
        d2 = 0.0
        for axis in range(3):
            d2 += (x[axis, p] - built[axis, i]) ** 2
        if not d2 <= limit * limit:
            return True
    return False


class ContactEnergy:
    """The energy of one posed model as a function of the free particles' positions, with the
    contact candidate lists it keeps up to date (see the module docstring)."""

    def __init__(self, model, prep, pre: Preconditioner, spheres, settings, x, weight,
                 solids=None, target=None):
        self.prep, self.pre = prep, pre
        self.full_weight = weight                   # (n,) g/s^2 the contacts' stiffness
        self.weight = weight.copy()                 # the one in use (:meth:`soften`)
        self.x = x                                  # (3, n) mm, fixed particles posed
        # the connective tissue's targets (3 or 6, n): the posed particles (None: no tissue)
        self.target = target if pre.tissue.any() else None
        self.free = pre.free
        n = x.shape[1]
        self.gradient = np.zeros((3, n))
        self.volume_gradient = np.zeros((3, n))
        self.muscle_energy = np.zeros(len(prep.offsets) - 1)
        self.springs = model_springs(model, prep)
        # co-rotational springs: their own term, the Hooke term's springs left out
        self.corotational = None
        if settings.quasi_static.springs == SPRINGS_COROTATIONAL:
            self.corotational = corotational_state(
                model.spring_rest_vectors()[spring_order(model, prep)], n)
            self.hooke_ptr = np.zeros_like(self.springs[3])
        else:
            self.hooke_ptr = self.springs[3]
        self.bulk_modulus = float(settings.bulk_modulus)
        self.spheres = spheres
        ns = spheres.count
        self.muscle_muscle = bool(settings.contacts.muscle_muscle)
        self.solids = solids if settings.contacts.muscle_bone else None
        self.muscle_bone = (bool(settings.contacts.muscle_bone) and self.solids is None
                            and len(spheres.bone_radius) > 0)
        self.skin = CONTACT_SKIN_FRACTION * float(spheres.radius.mean()) if ns else 0.0
        self.sphere_energy = np.zeros(ns)
        self.overlaps = np.zeros((ns, 2), dtype=np.int64)
        self.deepest = np.zeros(ns)
        # the solids' penalty over every free particle not inside a bone at rest
        self.solid_points = solid_points(prep) if self.solids is not None \
            else np.zeros(0, dtype=np.int64)
        k = len(self.solid_points)
        self.solid_radius = prep.radius[self.solid_points].copy()
        self.solid_energy = np.zeros(k)
        self.solid_overlaps = np.zeros((k, 2), dtype=np.int64)
        self.solid_deepest = np.zeros(k)
        # each solid point's bones within its radius plus clearance plus the skin when its
        # entry was made (at its place in solid_built; NaN: not yet): it cannot touch another
        # before it moves half the skin (a sampled distance changes by at most sqrt(3) times a
        # move; the bones hold still), so the penalty skips those bones until then
        self.solid_built = np.full((3, k), np.nan)
        self.solid_moved = np.zeros(k, dtype=np.bool_)
        self.solid_near = np.zeros((k, len(solids.clearance) if solids is not None else 0),
                                   dtype=np.bool_)
        self.near = None                 # (indices into solid_points, their particles, ...)
        self.built = np.zeros((3, ns))
        self.bone_table = None
        if self.muscle_bone:
            self.bone_table = spatial_hash.grid_table(
                spheres.bone_centres, spheres.bone_radius,
                spatial_hash.bone_cell(spheres, self.skin), spheres.bone + spheres.n_muscles)
        none = np.zeros(ns, dtype=np.int64)
        self.mm = self.mb = (none, none, np.zeros(0, dtype=np.int32))
        self.lists_built = False
        self.rebuilds = 0
        self.seconds = np.zeros(3)       # elastic, muscle contacts, bone contacts

    def soften(self, fraction: float) -> None:
        """Every contact's stiffness to ``fraction`` of the full (1: the full, bit for bit);
        the next :meth:`evaluate` uses it."""
        np.multiply(self.full_weight, fraction, out=self.weight)

    def has_contacts(self) -> bool:
        """Whether the settings leave any contact penalty in the energy."""
        return bool(self.spheres.count and (self.muscle_muscle or self.muscle_bone)
                    or self.solids is not None and len(self.solid_points))

    def _refresh_lists(self):
        """Rebuild the contact candidate lists when a sphere moved half the skin."""
        sp = self.spheres
        if not sp.count or not (self.muscle_muscle or self.muscle_bone):
            return
        if self.lists_built and not moved_more(self.x, sp.particle, self.built,
                                                0.5 * self.skin):
            return
        self.built[:] = self.x[:, sp.particle]
        tick = time.perf_counter()
        if self.muscle_muscle:
            table = spatial_hash.grid_table(self.built, sp.radius,
                                            spatial_hash.muscle_cell(sp, self.skin), sp.muscle)
            self.mm = spatial_hash.candidate_lists(self.built, sp.radius, sp.muscle, table,
                                                   self.skin)
        tock = time.perf_counter()
        if self.muscle_bone:
            self.mb = spatial_hash.candidate_lists(self.built, sp.radius, sp.muscle,
                                                   self.bone_table, self.skin)
        self.seconds[1] += tock - tick
        self.seconds[2] += time.perf_counter() - tock
        self.lists_built = True
        self.rebuilds += 1

    def _refresh_near_solids(self):
        """Remake the entries of the solid points that moved half the skin since theirs were
        made (see ``solid_built``), and the list of those near a bone if an entry changed."""
        solids = self.solids
        moved_flags(self.x, self.solid_points, self.solid_built, 0.5 * self.skin,
                    self.solid_moved)
        moved = np.flatnonzero(self.solid_moved)
        if not len(moved):
            return
        points = self.solid_points[moved]
        self.solid_built[:, moved] = self.x[:, points]
        near = np.zeros((len(moved), self.solid_near.shape[1]), dtype=np.bool_)
        near_solids(self.x, points, self.solid_radius[moved], solids.clearance + self.skin,
                    solids.transforms, solids.fields.grid(), near)
        if self.near is not None and np.array_equal(near, self.solid_near[moved]):
            return
        self.solid_near[moved] = near
        index = np.flatnonzero(self.solid_near.any(axis=1))
        k = len(index)
        self.near = (index, self.solid_points[index], self.solid_radius[index],
                     np.ascontiguousarray(self.solid_near[index]), np.zeros(k),
                     np.zeros((k, 2), dtype=np.int64), np.zeros(k))

    def evaluate(self, free_positions):
        """Set the free particles to ``free_positions`` (f, 3) and return ``(energy, gradient
        (f, 3), volume gradient (f, 3))``; the contact statistics stay on the object."""
        set_free(self.x, self.free, np.ascontiguousarray(free_positions, dtype=np.float64))
        tick = time.perf_counter()
        springs = self.springs
        cages = self.prep.cages
        elastic_energy(self.x, self.gradient, self.volume_gradient, self.muscle_energy, springs[0],
                 springs[1], springs[2], self.hooke_ptr, self.bulk_modulus, cages.ptr,
                 cages.triangles, cages.rest_volume, self.prep.offsets)
        if self.corotational is not None:
            add_corotational_energy(self.x, self.gradient, self.muscle_energy, springs[0],
                                    springs[2], springs[3], self.prep.offsets, self.corotational)
        if self.target is not None:
            add_tissue_energy(self.x, self.target, self.pre.tissue, self.prep.offsets,
                              self.gradient, self.muscle_energy)
        self.seconds[0] += time.perf_counter() - tick
        self._refresh_lists()
        tick = time.perf_counter()
        sp = self.spheres
        if sp.count:
            sphere_contact_energy(self.x, self.gradient, self.weight, sp.particle, sp.radius, sp.fixed,
                      *self.mm, *self.mb, sp.bone_centres, sp.bone_radius, self.sphere_energy,
                      self.overlaps, self.deepest)
        if self.solids is not None and len(self.solid_points):
            solids = self.solids
            self._refresh_near_solids()
            index, points, radius, near_bones, energy, overlaps, deepest = self.near
            for array in (self.solid_energy, self.solid_overlaps, self.solid_deepest):
                array[:] = 0
            solid_contact_energy(self.x, self.gradient, self.weight, points, radius,
                                 near_bones, solids.clearance, solids.transforms,
                                 solids.fields.grid(), energy, overlaps, deepest)
            self.solid_energy[index] = energy
            self.solid_overlaps[index] = overlaps
            self.solid_deepest[index] = deepest
        self.seconds[1] += time.perf_counter() - tick
        energy = float(self.muscle_energy.sum() + self.sphere_energy.sum()
                       + self.solid_energy.sum())
        return (energy, free_rows(self.gradient, self.free),
                free_rows(self.volume_gradient, self.free))

    def contact_columns(self):
        """The overlapping pairs of muscle spheres at the last evaluation as the columns of
        :class:`~.contact_preconditioner.ContactInverseHessian`: ``(free particles (k,),
        sqrt(w) n (k, 3))``, one per pair and free side."""
        sp = self.spheres
        if not (sp.count and self.muscle_muscle):
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        at, column = muscle_contact_columns(self.x, self.weight, sp, self.mm)
        return np.searchsorted(self.free, at), column

    def contact_figures(self):
        """``(muscle pairs, bone pairs, deepest overlap mm)`` at the last evaluation."""
        totals = self.overlaps.sum(axis=0)
        return (int(totals[0]), int(totals[1] + self.solid_overlaps[:, 1].sum()),
                float(max(self.deepest.max(initial=0.0), self.solid_deepest.max(initial=0.0))))
