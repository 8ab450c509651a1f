"""The MSS Collision Solver's settings: one type for both methods, every default and every option
value defined once.

:class:`SolverSettings` holds what both methods read (iteration cap, volume pressure, contacts,
final collision passes); its :attr:`~SolverSettings.relaxation` part is read only by the paper's
relaxation (:mod:`muscle_mss.core.relaxation`), its :attr:`~SolverSettings.quasi_static` part only
by the quasi-static method (:mod:`muscle_mss.core.quasi_static`). The filter's properties, the
CLI's and the batch's options take their defaults and choices from here.
"""
from __future__ import annotations

from dataclasses import MISSING, dataclass, field, fields

from .contacts.octree_bvh import MAX_DEPTH as DEFAULT_BVH_MAX_DEPTH
from .contacts.octree_bvh import MIN_PRIMITIVES as DEFAULT_BVH_MIN_PRIMITIVES

# ---- option values ---------------------------------------------------------------------------

METHOD_QUASI_STATIC = "quasi-static"
METHOD_RELAXATION = "paper relaxation"
METHOD_PARTS = {METHOD_QUASI_STATIC: "quasi_static", METHOD_RELAXATION: "relaxation"}
"""Each method's module under ``core/`` (imported when first used), which is also the name of
its part of :class:`SolverSettings`, the settings that method alone reads."""
METHODS = tuple(METHOD_PARTS)

TERMINATION_ITERATIONS = "iterations"
TERMINATION_THRESHOLD = "displacement threshold"
TERMINATION_BUDGET = "time budget"
TERMINATIONS = (TERMINATION_ITERATIONS, TERMINATION_THRESHOLD, TERMINATION_BUDGET)

STRUCTURE_HASH = "spatial hash"
STRUCTURE_BVH = "octree BVH"
STRUCTURES = (STRUCTURE_HASH, STRUCTURE_BVH)

BONE_CONTACT_SOLID, BONE_CONTACT_SPHERES, BONE_CONTACT_NONE = "solid", "sphere set", "none"
BONE_CONTACTS = (BONE_CONTACT_SOLID, BONE_CONTACT_SPHERES)

SPRINGS_HOOKE = "Hooke"
SPRINGS_COROTATIONAL = "co-rotational"
SPRING_ENERGIES = (SPRINGS_HOOKE, SPRINGS_COROTATIONAL)

# ---- defaults shared by both methods ---------------------------------------------------------

# The quasi-static equilibrium (with the tissue and the co-rotational springs below): every
# time point of both demo motions converges at N = 20, and what a user sees improves on the
# paper relaxation's 500 iterations (surface volume error over the thigh walk 0.27 / 2.02 %
# mean / max against 0.82 / 5.14 %, the elbow 0.32 / 1.28 % against 1.12 / 4.78 %, no sphere
# wedged at 130 degrees), at 2-3 times its seconds (docs/solver-notes.md, "The default").
DEFAULT_METHOD = METHOD_QUASI_STATIC
# The iteration cap, for both methods. The quasi-static solves of both demo motions stop at
# their tolerance well within it (at N = 20 at most 474 iterations at a tolerance of 0.001 mm,
# 423 at the default 0.1 mm; the elbow's 130 degrees at N = 80 593 and 452); the paper
# relaxation runs all of them unless its termination says otherwise (the paper ran 500).
DEFAULT_ITERATIONS = 2000
DEFAULT_TIME_BUDGET = 1.0               # s
# Without a volume force the converged lattices lose 9-22 % of their volume where the posed
# fibres are stretched ~10 % (lattice-26 cells 2.5 times longer than wide narrow several
# times faster than they stretch). Muscle is nearly incompressible, and the volume term's stiff
# mode is implicit (mss._implicit_volume_forces), so a stiff term does not shorten the stable
# time step; above 200 little is gained, the rest of the surface's error being the MVC map's and
# the bone push's (docs/accuracy.md, "The elbow at 130°").
DEFAULT_BULK_MODULUS = 200.0            # g/(mm s^2)
# The connective tissue (epimysium, septa, fascia) holding every free particle toward its posed
# rest position, as a ratio to the fibre springs' stiffness (core/connective_tissue.py); 0 is
# the paper's model, free-floating between the tendons. 0.1 is the ratio at which every time
# point of both demo motions converges with co-rotational springs (0.03 left a sphere wedged
# at the elbow's 130 degrees; 0.3 and 1.0 converge too but hold the muscles 2.5-5.7 mm mean
# nearer their posed place, benchmarks/results/quasi_static_corotational.md Table 2).
DEFAULT_CONNECTIVE_TISSUE = 0.1
# The tissue's stiffness along each particle's fibre as a fraction of it across (1: isotropic):
# below 1 a fibre lengthens and shortens, and a muscle slides along its neighbours, against a
# weaker tissue (core/connective_tissue.py). Over both demo motions 0.1 beats 1 in iterations,
# in how well the shortening fibres follow their ends and in volume error (docs/accuracy.md,
# "With the quasi-static method: a tissue weaker along the fibres").
DEFAULT_TISSUE_ALONG = 0.1
# Fibres shorten with their muscle (core/fibre_shortening.py): with it the elbow's flexors
# shorten and thicken instead of folding (fibres' arc / chord over the motion at most 1.18
# against 1.53 without), and both demo motions converge in fewer iterations.
DEFAULT_FIBRE_SHORTENING = True
# The final collision passes (:func:`muscle_mss.core.contacts.sphere_contacts.project`): a sphere pressed
# between two objects keeps half its overlap per pass (two passes halve it), so 100 passes leave
# any overlap below 1e-15 of itself; they stop as soon as the deepest penetration is below the
# tolerance.
DEFAULT_PROJECTION_PASSES = 100
DEFAULT_PENETRATION_TOLERANCE = 0.01    # mm
# The bones as solids (their signed distance) keep every free particle out and are the faster;
# the paper's sphere sets (core/bones/spheres.py) at this spacing give about 8,600 spheres on the
# demo pelvis, the paper's 8527.
DEFAULT_BONE_CONTACT = BONE_CONTACT_SOLID
DEFAULT_BONE_SPHERE_SPACING = 2.05      # mm

# ---- defaults of the paper relaxation --------------------------------------------------------

DEFAULT_DISPLACEMENT_THRESHOLD = 1e-3   # mm per iteration
# Stable with margin for the Spring Builder defaults (k = 10 g/s^2, c = 0.5 g/s, m = 1 g) and
# lattice-26: a particle's stiffest mode is below sqrt(2 * 26 * k / m) ~ 23 rad/s, and
# symplectic Euler needs omega * dt < 2; 0.05 s gives 1.1 in that worst case.
DEFAULT_TIME_STEP = 0.05                # s
# Measured on the small and full demo at the pose farthest from rest: without drag
# the lattices ring for the whole solve (damping ratio c / (2 sqrt(k m)) = 0.08 per spring) and
# fold; 5 1/s damps the slow modes of a 20-particle fibre within ~100 iterations.
DEFAULT_DRAG = 5.0                      # 1/s

# ---- defaults of the quasi-static method -----------------------------------------------------

# mm: the largest particle move of a quasi-Newton step, and of the steps still to come as their
# decay estimates them. The iterations from 0.1 mm down to 0.001 mm moved no particle further
# than 0.36 mm (0.002-0.009 mm mean, each time point of both demo motions at N = 20 and the
# elbow's 70 and 130 degrees at N = 80) and changed no volume error, overlap, bone figure or
# 'follows' of the motions, yet were 31-34 % of the motions' iterations (the walking thigh's
# pose: 72 of 127); the accuracy asked of a pose is 0.1 mm mean, 1 mm max to a 10 times
# tighter solve (docs/solver-notes.md, "The tolerance").
DEFAULT_TOLERANCE = 0.1
DEFAULT_HISTORY = 8             # L-BFGS pairs kept
# The contact stiffness w as a multiple of the largest diagonal entry of L (the sum of the
# stiffnesses of one particle's springs, 260 g/s^2 for a lattice-26 particle at the Spring
# Builder's 10 g/s^2), per spring energy. Stiffer contacts leave less overlap for the final
# passes but are stiff modes the Laplacian preconditioner does not know; each value is the one at
# which the demo poses converge (docs/solver-notes.md, "The elbow's wedge and the contact
# weight"; with co-rotational springs 0.3 left a sphere wedged at the elbow's 130 degrees).
DEFAULT_CONTACT_WEIGHTS = {SPRINGS_HOOKE: 0.3, SPRINGS_COROTATIONAL: 1.0}
# The quasi-static method's spring energy: the paper's Hooke springs, or co-rotational springs
# (core/quasi_static/corotational.py), which keep their stiffness across themselves when
# compressed and so converge the flexed poses in a fraction of the iterations.
DEFAULT_SPRINGS = SPRINGS_COROTATIONAL
# The contacts' stiffness in the quasi-static solve's first stage, a fraction of the full
# (1: one stage, the default). Against contacts at 0.3 the muscles pressed on each other slide
# into place sooner (N = 20: the demo thigh's most flexed pose 471 iterations in one stage, 289
# in two), but at N = 80 the path ends in other equilibria, two of them of more energy (the
# elbow +0.5 %): docs/solver-notes.md, "Soft contacts first".
DEFAULT_SOFT_START = 1.0


@dataclass(slots=True)
class ContactSettings:
    """What both methods read of the contacts: the ``structure`` that finds them (one of
    :data:`STRUCTURES`; the octree BVH's ``bvh_max_depth`` and ``bvh_min_primitives``), which
    count (``muscle_muscle``, ``muscle_bone``), the final collision passes, run up to
    ``projection_passes`` times until no overlap exceeds ``penetration_tolerance`` mm, and how
    the bones are given to the solve (``bone_contact``, one of :data:`BONE_CONTACTS`; sphere
    sets at ``bone_sphere_spacing`` mm): the caller builds the
    :class:`~muscle_mss.core.model.Bones` from these two."""

    structure: str = STRUCTURE_HASH
    bvh_max_depth: int = DEFAULT_BVH_MAX_DEPTH
    bvh_min_primitives: int = DEFAULT_BVH_MIN_PRIMITIVES
    muscle_muscle: bool = True
    muscle_bone: bool = True
    projection_passes: int = DEFAULT_PROJECTION_PASSES
    penetration_tolerance: float = DEFAULT_PENETRATION_TOLERANCE
    bone_contact: str = DEFAULT_BONE_CONTACT
    bone_sphere_spacing: float = DEFAULT_BONE_SPHERE_SPACING


@dataclass(slots=True)
class RelaxationSettings:
    """What only the paper relaxation reads: its termination threshold (mm per iteration), the
    time step (s) of its semi-implicit Euler integration and the viscous drag (1/s)."""

    displacement_threshold: float = DEFAULT_DISPLACEMENT_THRESHOLD
    time_step: float = DEFAULT_TIME_STEP
    drag: float = DEFAULT_DRAG


@dataclass(slots=True)
class QuasiStaticSettings:
    """What only the quasi-static method reads: its tolerance (mm, the largest particle move of
    a quasi-Newton step), the contact stiffness (a multiple of the stiffest particle's spring
    sum; None: the spring energy's, :data:`DEFAULT_CONTACT_WEIGHTS`), the number of L-BFGS
    pairs kept, the spring energy (one of :data:`SPRING_ENERGIES`), the contacts' stiffness
    in a first stage as a fraction of the full (``soft_start``, in (0, 1]; 1: no such stage;
    :data:`DEFAULT_SOFT_START`) and whether the contacts between muscles enter the
    preconditioner
    (:mod:`~muscle_mss.core.quasi_static.contact_preconditioner`: up to half the iterations,
    but no fewer seconds over the demo motions on two cores, so off by default;
    docs/solver-notes.md, "Contacts in the preconditioner")."""

    tolerance: float = DEFAULT_TOLERANCE
    contact_weight: float | None = None
    history: int = DEFAULT_HISTORY
    springs: str = DEFAULT_SPRINGS
    soft_start: float = DEFAULT_SOFT_START
    contact_preconditioner: bool = False

    @property
    def weight(self) -> float:
        """The contact stiffness in use: ``contact_weight``, or the spring energy's default."""
        if self.contact_weight is None:
            return DEFAULT_CONTACT_WEIGHTS[self.springs]
        return self.contact_weight


@dataclass(slots=True)
class SolverSettings:
    """The MSS Collision Solver's parameters (the filter's properties). Slotted, as its parts:
    setting a field that does not exist (``settings.tolerance`` for
    ``settings.quasi_static.tolerance``) is an AttributeError, not a silent no-op.

    ``method`` one of :data:`METHODS`; ``termination`` one of :data:`TERMINATIONS` (the
    quasi-static method honours only ``time budget``, besides its tolerance); ``iterations``
    caps every termination; ``time_budget`` s; ``bulk_modulus`` g/(mm s^2);
    ``connective_tissue`` the dimensionless ratio of
    :func:`muscle_mss.core.connective_tissue.tissue_stiffness` (0: none); ``tissue_along`` its
    stiffness along the fibres as a fraction of that across (1: isotropic);
    ``fibre_shortening`` the springs' rest lengths follow fibres that shorten
    (:func:`muscle_mss.core.fibre_shortening.shortened_springs`; off here, the paper's springs,
    on in the filter: :data:`DEFAULT_FIBRE_SHORTENING`); ``contacts`` the
    :class:`ContactSettings` both methods read. The method-specific parts sit beside them.
    """

    method: str = DEFAULT_METHOD
    termination: str = TERMINATION_ITERATIONS
    iterations: int = DEFAULT_ITERATIONS
    time_budget: float = DEFAULT_TIME_BUDGET
    bulk_modulus: float = DEFAULT_BULK_MODULUS
    connective_tissue: float = DEFAULT_CONNECTIVE_TISSUE
    tissue_along: float = DEFAULT_TISSUE_ALONG
    fibre_shortening: bool = False
    contacts: ContactSettings = field(default_factory=ContactSettings)
    relaxation: RelaxationSettings = field(default_factory=RelaxationSettings)
    quasi_static: QuasiStaticSettings = field(default_factory=QuasiStaticSettings)

    @property
    def budget(self) -> float | None:
        """The wall-clock budget in s when the termination is ``time budget``, else None."""
        return self.time_budget if self.termination == TERMINATION_BUDGET else None

    @classmethod
    def build(cls, **values) -> "SolverSettings":
        """Settings from flat keywords, each given to the part that has a field of its name
        (``SolverSettings.build(method=METHOD_QUASI_STATIC, iterations=300, tolerance=1e-4)``);
        an unknown name is a TypeError, as for the constructor."""
        parts = {f.name: f.default_factory for f in fields(cls) if f.default_factory is not MISSING}
        own = {f.name for f in fields(cls)} - set(parts)
        unknown = set(values) - own - {f.name for part in parts.values() for f in fields(part)}
        if unknown:
            raise TypeError(f"SolverSettings has no field {', '.join(sorted(unknown))}")
        nested = {name: part(**{f.name: values[f.name] for f in fields(part) if f.name in values})
                  for name, part in parts.items()}
        return cls(**{k: v for k, v in values.items() if k in own}, **nested)
