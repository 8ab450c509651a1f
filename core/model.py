"""The muscles' mass-spring model as the solvers see it: the posed model, its preparation for
the kernels (particle order, spring layout, volume cages), the stability checks of the explicit
integration, and the solved state both methods return.

Arrays are concatenated muscle after muscle (``offsets``); the solvers work in their own particle
order (:func:`prepare`: lattice neighbours at constant index offsets, the spring kernel's fast
order) and return results in the input order.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .cage import muscle_cage
from .errors import MuscleMSSError
from .mss import VolumeCages, lattice_order, spring_layout
from .solver_properties import name_of
from .settings import (BONE_CONTACT_NONE, BONE_CONTACT_SOLID, BONE_CONTACT_SPHERES,
                       METHOD_RELAXATION, TERMINATION_ITERATIONS)
from .volume import signed_volume


REFERENCE_PARTICLES = 20
"""Particles per fibre at which the resolution-dependent stiffnesses (the connective tissue's,
the quasi-static contacts') take their nominal values (:meth:`MSSModel.resolution_scale`)."""


@dataclass
class MSSModel:
    """The posed mass-spring model of all muscles (arrays concatenated muscle after muscle).

    ``names`` the muscles; ``offsets`` (M+1,) their particle ranges; ``positions`` (n, 3) mm
    posed; ``fixed``, ``boundary`` (n,) bool; ``mass`` (n,) g; ``radius`` (n,) mm;
    ``fibre_id``, ``fibre_index`` (n,) int and optional ``fibre_grid`` (n, 2) (to order the
    particles for speed, and for the cages); ``springs`` (S, 2) int global particle indices;
    ``rest_length`` mm, ``stiffness`` g/s^2, ``damping`` g/s (S,); ``rest_positions`` (n, 3) mm,
    the rest pose whose cage volumes the volume force keeps (omitted: ``positions``);
    ``in_bone_at_rest`` (n,) bool, the particles inside a bone in the rest pose (the bones as
    solids leave them there; omitted: not known, and only the particles with a sphere are
    kept out of the solids); ``rest_vectors`` (S, 3) mm, each spring's vector from its first
    particle to its second in the springs' rest shape where that is not the rest pose
    (:mod:`~muscle_mss.core.fibre_shortening`'s shortened fibres; omitted:
    :meth:`spring_rest_vectors`); ``tissue_target`` (n, 3) mm, where the connective tissue
    holds each particle when that is not its posed position (the shortened muscles' targets of
    :mod:`~muscle_mss.core.fibre_shortening`; omitted: :meth:`tissue_target_positions`).
    """

    names: list
    offsets: np.ndarray
    positions: np.ndarray
    fixed: np.ndarray
    mass: np.ndarray
    boundary: np.ndarray
    radius: np.ndarray
    fibre_id: np.ndarray
    fibre_index: np.ndarray
    springs: np.ndarray
    rest_length: np.ndarray
    stiffness: np.ndarray
    damping: np.ndarray
    fibre_grid: np.ndarray | None = None
    rest_positions: np.ndarray | None = None
    in_bone_at_rest: np.ndarray | None = None
    rest_vectors: np.ndarray | None = None
    tissue_target: np.ndarray | None = None

    def tissue_target_positions(self) -> np.ndarray:
        """(n, 3) float64 mm: where the connective tissue holds each particle,
        ``tissue_target`` or the posed ``positions``."""
        target = self.positions if self.tissue_target is None else self.tissue_target
        return np.asarray(target, dtype=np.float64).reshape(-1, 3)

    def spring_rest_vectors(self) -> np.ndarray:
        """(S, 3) float64 mm: each spring's rest vector, ``rest_vectors``, or the rest pose's
        vector from its first particle to its second scaled to the rest length (a spring whose
        ends coincide at rest: zero). The co-rotational springs keep it in their particles'
        rotated frames."""
        if self.rest_vectors is not None:
            return np.asarray(self.rest_vectors, dtype=np.float64).reshape(-1, 3)
        rest = self.rest_pose()
        ends = np.asarray(self.springs, dtype=np.int64).reshape(-1, 2)
        vectors = rest[ends[:, 1]] - rest[ends[:, 0]]
        length = np.linalg.norm(vectors, axis=1)
        scale = np.divide(np.asarray(self.rest_length, dtype=np.float64), length,
                          out=np.zeros_like(length), where=length > 0.0)
        return vectors * scale[:, None]

    def rest_pose(self) -> np.ndarray:
        """(n, 3) float64 mm: ``rest_positions``, or ``positions`` where the rest pose is
        omitted."""
        rest = self.positions if self.rest_positions is None else self.rest_positions
        return np.asarray(rest, dtype=np.float64).reshape(-1, 3)

    def resolution_scale(self) -> np.ndarray:
        """(M,): ``(REFERENCE_PARTICLES - 1) / (N_m - 1)`` for each muscle of ``N_m``
        particles per fibre (1 at :data:`REFERENCE_PARTICLES`). A fibre's ``N_m - 1`` springs
        act in series, so its stiffness falls as ``1 / (N_m - 1)``, while a per-particle term
        acts ``N_m`` times along it: such a term times this scale keeps its force per length
        of fibre, and times its square its balance against the springs."""
        offsets = np.asarray(self.offsets, dtype=np.int64)
        index = np.asarray(self.fibre_index, dtype=np.int64).ravel()
        per_fibre = np.zeros(len(offsets) - 1, dtype=np.int64)
        np.maximum.at(per_fibre, np.repeat(np.arange(len(offsets) - 1), np.diff(offsets)),
                      index + 1)
        return (REFERENCE_PARTICLES - 1.0) / np.maximum(per_fibre - 1, 1)


@dataclass
class SolveResult:
    """Solved state (input particle order) and the per-iteration history.

    ``positions``, ``velocity`` (n, 3) mm, mm/s; ``collided`` (n,) bool (last iteration);
    ``mean_displacement`` (K, M) mm; ``muscle_pairs``, ``bone_pairs`` (K,) colliding pairs;
    ``max_penetration`` (K,) mm (deepest before the response, of a pair not fixed on both
    sides); ``seconds`` (K,) cumulative;
    ``phase_seconds`` MSS / muscle-muscle CD / muscle-bone CD (with the response) totals of the
    iterations, and the final projection's (against bones as solids the muscle-bone contacts
    run inside the MSS step's parallel region, so their time is in MSS, and muscle-bone CD is
    their tally only); ``stopped_by`` the termination that ended the loop;
    ``projection_passes`` the collision passes after the last iteration and
    ``remaining_penetration`` (mm) the deepest overlap the last of them found (0: none; at most
    the tolerance unless the passes ran out); ``method`` the method that solved it;
    ``tissue_share`` (M,) % the connective tissue's force over the springs' per muscle
    (:func:`~muscle_mss.core.connective_tissue.tissue_share`; None: not measured);
    ``bone_contact`` the :attr:`Bones.contact` solved against; ``converged`` whether the
    method met its own criterion (the relaxation's displacement threshold, the quasi-static
    tolerance); ``residual`` (K,) mm, for a method that measures one, the largest particle move
    of each iteration's step (None: not measured).
    """

    positions: np.ndarray
    velocity: np.ndarray
    collided: np.ndarray
    mean_displacement: np.ndarray
    muscle_pairs: np.ndarray
    bone_pairs: np.ndarray
    max_penetration: np.ndarray
    seconds: np.ndarray
    phase_seconds: dict = field(default_factory=dict)
    stopped_by: str = TERMINATION_ITERATIONS
    rebuilds: int = 0
    projection_passes: int = 0
    remaining_penetration: float = 0.0
    method: str = METHOD_RELAXATION
    tissue_share: np.ndarray | None = None
    bone_contact: str = "none"
    converged: bool = False
    residual: np.ndarray | None = None

    @property
    def iterations(self) -> int:
        return len(self.seconds)

    @property
    def colliding_pairs(self) -> np.ndarray:
        return self.muscle_pairs + self.bone_pairs


@dataclass(frozen=True)
class Bones:
    """The posed bones as the muscle-bone contacts read them: ``solids`` (a
    :class:`~muscle_mss.core.bones.distance.BoneSolids`) or ``spheres``, the paper's sphere sets
    ``(centres (b, 3) mm, radius (b,) mm, bone (b,) int)`` sorted by bone; neither: no bones."""

    spheres: tuple | None = None
    solids: object = None

    @property
    def contact(self) -> str:
        """Which bone contact these bones give: one of :data:`BONE_CONTACTS`, or ``"none"``."""
        if self.solids is not None:
            return BONE_CONTACT_SOLID
        return BONE_CONTACT_SPHERES if self.spheres is not None else BONE_CONTACT_NONE

    @property
    def sphere_arrays(self) -> tuple:
        """``spheres``, or three Nones."""
        return self.spheres if self.spheres is not None else (None, None, None)


NO_BONES = Bones()


@dataclass
class PreparedModel:
    """What depends only on the model's topology: particle order and spring layout, and what
    the quasi-static method builds of this model on first use: ``spring_table`` (its
    :class:`~muscle_mss.core.quasi_static.preconditioner.SpringTable`, which holds the rest
    lengths: :func:`with_rest_state` drops it) and ``factorisations`` (its
    :class:`~muscle_mss.core.quasi_static.preconditioner.Preconditioner` by connective tissue
    ratio, which depend on the springs' stiffnesses and the fixed particles but not on their
    rest lengths: :func:`with_rest_state` keeps them)."""

    order: np.ndarray
    offsets: np.ndarray
    layout: object
    cages: VolumeCages
    inv_mass: np.ndarray
    radius: np.ndarray
    muscle: np.ndarray
    fixed: np.ndarray
    boundary: np.ndarray
    in_bone_at_rest: np.ndarray | None = None   # (n,) bool, solver order, or None: not known
    stable_step: tuple | None = None            # stable_time_step(model) (springs, masses)
    spring_table: object = None
    factorisations: dict = field(default_factory=dict)


def prepare(model: MSSModel) -> PreparedModel:
    """Order the particles (lattice neighbours at constant offsets) and group the springs;
    reusable for every pose of the same model."""
    offsets = np.asarray(model.offsets, dtype=np.int64)
    n = int(offsets[-1])
    order = np.empty(n, dtype=np.int64)
    for m in range(len(offsets) - 1):
        lo, hi = offsets[m], offsets[m + 1]
        grid = None if model.fibre_grid is None else model.fibre_grid[lo:hi]
        order[lo:hi] = lo + lattice_order(model.fibre_id[lo:hi], model.fibre_index[lo:hi], grid)
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n)
    springs = rank[np.asarray(model.springs, dtype=np.int64).reshape(-1, 2)]
    layout = spring_layout(springs, model.rest_length, model.stiffness, model.damping, offsets)
    fixed = np.asarray(model.fixed, dtype=bool)[order]
    inv_mass = np.where(fixed, 0.0, 1.0 / np.asarray(model.mass, dtype=np.float64)[order])
    muscle = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    in_bone = (None if model.in_bone_at_rest is None
                else np.asarray(model.in_bone_at_rest, dtype=bool)[order])
    return PreparedModel(order, offsets, layout, volume_cages(model, rank), inv_mass,
                         np.asarray(model.radius, dtype=np.float64)[order], muscle, fixed,
                         np.asarray(model.boundary, dtype=bool)[order], in_bone,
                         stable_step=stable_time_step(model))


def with_rest_state(prep: PreparedModel, model: MSSModel) -> PreparedModel:
    """``prep``, prepared for a model with ``model``'s topology, rest pose, masses, spring
    stiffnesses and damping and fixed particles, made ready for ``model``, whose springs' rest
    lengths and rest vectors may differ (fibre shortening gives every pose its own): the spring
    layout built again, the particle order, cages, stable step and ``factorisations`` kept (the
    same arrays as :func:`prepare` would give; the quasi-static factorisation costs 0.05 s a
    pose of the demo thigh at N = 20, 0.3 s at N = 80)."""
    rank = np.empty(len(prep.order), dtype=np.int64)
    rank[prep.order] = np.arange(len(prep.order))
    springs = rank[np.asarray(model.springs, dtype=np.int64).reshape(-1, 2)]
    layout = spring_layout(springs, model.rest_length, model.stiffness, model.damping,
                           prep.offsets)
    return replace(prep, layout=layout, spring_table=None)


def volume_cages(model: MSSModel, rank) -> VolumeCages:
    """Each muscle's MVC cage (:func:`muscle_mss.core.cage.muscle_cage`) in the solver's particle
    order, with its rest volume. A muscle whose boundary particles span no solid (a sheet, a
    line: no volume to keep) gets no cage."""
    offsets = np.asarray(model.offsets, dtype=np.int64)
    rest = model.rest_pose()
    triangles, counts, volumes = [], [], []
    for m, name in enumerate(model.names):
        lo, hi = offsets[m], offsets[m + 1]
        grid = None if model.fibre_grid is None else model.fibre_grid[lo:hi]
        try:
            cage = muscle_cage(rest[lo:hi], model.boundary[lo:hi], model.fibre_id[lo:hi],
                               model.fibre_index[lo:hi], grid, where=f"muscle '{name}'")
        except MuscleMSSError:
            counts.append(0)
            volumes.append(1.0)
            continue
        corners = lo + cage.vertices
        triangles.append(rank[corners[cage.triangles]])
        counts.append(len(cage.triangles))
        volumes.append(signed_volume(rest[corners], cage.triangles))
    ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return VolumeCages(ptr, np.concatenate(triangles).astype(np.int64) if triangles
                       else np.zeros((0, 3), np.int64), np.asarray(volumes, dtype=np.float64))


# The Gershgorin bounds of stable_time_step overestimate the stiffest mode (a checkerboard
# mode of lattice-26 reaches 0.67 of the bound's omega^2), and the implicit drag and the
# collision response (collided particles stop) widen the stable range: the 3x3x8 lattices of
# the solver tests still settle at 2.2 times the bound's step and diverge from 2.5 times (in 65
# iterations; 7 at 3 times). Steps up to this many times the bound's run (a divergence then
# stops the solve with an error); longer ones are refused before the solve.
STABILITY_MARGIN = 3.0

# The per-iteration history (mean displacement of each muscle and four columns) is refused above
# this size: the iteration cap caps a time budget's solve, and 1e9 would ask for tens of GiB.
MAX_HISTORY_BYTES = 2 * 1024 ** 3


def stable_time_step(model: MSSModel):
    """``(dt s, muscle index, particle, kind)``: the longest semi-implicit Euler step that the
    stiffest particle of the model takes without growing (``kind`` "stiffness" or
    "damping"), from a Gershgorin bound on the mass-scaled spring stiffness matrix
    ``M^-1/2 K M^-1/2`` (row i: ``sum_j k_ij (1/m_i + 1/sqrt(m_i m_j))``, fixed particles do
    not move) and the same bound on the springs' (explicit) damping: ``dt = 2 / omega_max``
    and ``dt = 2 / gamma_max``. ``inf`` when no free particle has a spring."""
    springs = np.asarray(model.springs, dtype=np.int64).reshape(-1, 2)
    mass = np.asarray(model.mass, dtype=np.float64)
    free = ~np.asarray(model.fixed, dtype=bool)
    if len(springs) == 0 or not free.any():
        return np.inf, 0, 0, "stiffness"
    with np.errstate(divide="ignore"):
        inv = np.where(free, 1.0 / mass, 0.0)
    root = np.sqrt(inv)
    a, b = springs[:, 0], springs[:, 1]
    best = (np.inf, 0, 0, "stiffness")
    for kind, coefficient, scale in (("stiffness", model.stiffness, np.sqrt),
                                     ("damping", model.damping, lambda r: r)):
        c = np.asarray(coefficient, dtype=np.float64)
        cross = c * root[a] * root[b]
        row = (np.bincount(a, c * inv[a] + cross, minlength=len(mass))
               + np.bincount(b, c * inv[b] + cross, minlength=len(mass)))
        p = int(np.argmax(row))
        if row[p] > 0.0:
            dt = 2.0 / float(scale(row[p]))
            if dt < best[0]:
                muscle = int(np.searchsorted(model.offsets, p, side="right") - 1)
                best = (dt, muscle, p - int(model.offsets[muscle]), kind)
    return best


def stability_problem(model: MSSModel, time_step: float, stable_step=None) -> str | None:
    """Why ``time_step`` cannot give a meaningful solve of ``model`` (the explicit integration
    grows without bound: particles jump ~1e8 mm in the first iteration), or None. Refused
    above :data:`STABILITY_MARGIN` times :func:`stable_time_step` (``stable_step``: its result
    for this model when known, e.g. :attr:`PreparedModel.stable_step`)."""
    dt, m, p, kind = stable_step if stable_step is not None else stable_time_step(model)
    if not time_step > STABILITY_MARGIN * dt:
        return None
    lo = int(model.offsets[m])
    springs = np.asarray(model.springs, dtype=np.int64).reshape(-1, 2)
    mine = (springs == lo + p).any(axis=1)
    total = float(np.asarray(model.stiffness if kind == "stiffness" else model.damping,
                             dtype=np.float64)[mine].sum())
    unit = "g/s^2" if kind == "stiffness" else "g/s"
    fix = ("raise the Spring Builder's Mass or lower its Stiffness" if kind == "stiffness"
           else "raise the Spring Builder's Mass or lower its Damping")
    step = name_of("relaxation.time_step")
    return (f"the model cannot be solved with {step} {time_step:g} s: particle {p} of "
            f"muscle '{model.names[m]}' (mass {float(model.mass[lo + p]):.3g} g, springs of "
            f"total {kind} {total:.3g} {unit}) is stable only below {dt:.3g} s, and explicit "
            f"integration would blow up ({time_step / dt:.3g} times too long); lower the "
            f"MSS Collision Solver's {step} below {dt:.3g} s, or {fix}")


def check_history_size(iterations, muscles: int) -> None:
    """Refuse an iteration cap whose per-iteration history would not fit
    :data:`MAX_HISTORY_BYTES` (it is allocated before the solve starts)."""
    size = float(iterations) * (muscles + 4) * 8
    if size > MAX_HISTORY_BYTES:
        most = int(MAX_HISTORY_BYTES // ((muscles + 4) * 8))
        raise MuscleMSSError(
            f"{name_of('iterations')} {int(iterations)} would need a {size / 1024 ** 3:.3g} GiB history "
            f"({muscles} muscles + 4 values per iteration); at most "
            f"{MAX_HISTORY_BYTES / 1024 ** 3:.3g} GiB ({most} iterations) are allowed; lower "
            f"{name_of('iterations')} (it caps every termination)")
