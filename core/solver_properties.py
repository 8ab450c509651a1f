"""The MSS Collision Solver's properties: one row per setting, and what is said in their names.

Each :class:`~muscle_mss.core.properties.Property` row holds the ParaView name, default, range,
help, the :class:`~muscle_mss.core.settings.SolverSettings` field it sets and its command-line
:class:`~muscle_mss.core.properties.Option`. The filter's properties, its ``settings()``, the CLI
and batch options and the study's ignore list are derived from these rows; so are the checks
of a :class:`~muscle_mss.core.settings.SolverSettings` (:func:`check_settings`) and every
message that names a setting (:func:`name_of`), so that a new setting is one row plus its use.
"""
from __future__ import annotations

import math

from .errors import MuscleMSSError
from .properties import Option, Property
from .settings import (
    BONE_CONTACT_SOLID, BONE_CONTACT_SPHERES, BONE_CONTACTS, DEFAULT_BONE_CONTACT,
    DEFAULT_BONE_SPHERE_SPACING, DEFAULT_BULK_MODULUS, DEFAULT_BVH_MAX_DEPTH,
    DEFAULT_BVH_MIN_PRIMITIVES, DEFAULT_CONNECTIVE_TISSUE, DEFAULT_DISPLACEMENT_THRESHOLD,
    DEFAULT_DRAG, DEFAULT_FIBRE_SHORTENING, DEFAULT_ITERATIONS, DEFAULT_METHOD,
    DEFAULT_PENETRATION_TOLERANCE, DEFAULT_PROJECTION_PASSES, DEFAULT_SPRINGS,
    DEFAULT_TIME_BUDGET, DEFAULT_TIME_STEP, DEFAULT_TISSUE_ALONG, DEFAULT_TOLERANCE, METHODS,
    SPRING_ENERGIES, STRUCTURE_HASH, STRUCTURES, TERMINATION_ITERATIONS, TERMINATIONS,
    SolverSettings)

SOLVER_PROPERTIES = (
    Property("Method", "enum", DEFAULT_METHOD,
             "quasi-static (the default): solve for the static equilibrium of the springs, "
             "volume pressure, connective tissue, fixed tendon particles and contacts to "
             "Tolerance (energy minimisation by L-BFGS on a spring matrix factorised once "
             "per model, contacts as penalties, then the final collision passes); "
             "TimeStep, Drag and DisplacementThreshold do not apply. With the defaults "
             "every time point of both demo motions converges (a few hundred iterations); "
             "without ConnectiveTissue the slack, slender muscles' shape is not determined "
             "(thousands of iterations). paper relaxation: the paper's explicit iterations "
             "(mass-spring step, collision response) with the terminations below; its "
             "shape depends on the iteration cap.",
             choices=METHODS, group="Method",
             field="method",
             option=Option("--method", "solver: paper, the paper's relaxation, or "
                           "quasi-static, the quasi-static equilibrium (default "
                           "{default})",
                           values=tuple((method.split()[0], method) for method in METHODS))),
    Property("Tolerance", "double", DEFAULT_TOLERANCE,
             "Quasi-static: the solve has converged when no particle moves more than this "
             "(mm) in one quasi-Newton step, nor (estimated from how fast the steps "
             "shrink) in all the steps still to come, and no two objects overlap by more than "
             "PenetrationTolerance. Iterations caps the steps; with Termination 'time "
             "budget' so does TimeBudget. An unconverged solve prints a warning.",
             minimum=0.0, group="Method",
             field="quasi_static.tolerance",
             option=Option("--tolerance", "quasi-static tolerance: largest particle move "
                           "of a step, mm (default {default:g})",
                           what="the largest particle move of its last step")),
    Property("Springs", "enum", DEFAULT_SPRINGS,
             "Quasi-static: the springs' energy. Hooke: the paper's springs, "
             "k (|d| - rest length)^2 / 2, as soft across themselves as their stretch "
             "(negatively stiff when compressed), so a flexed pose's compressed slender "
             "muscles take hundreds of iterations more. co-rotational (the default): each "
             "spring costs "
             "k (|d - R_a D|^2 + |d - R_b D|^2) / 4, D its rest vector, R_a and R_b the "
             "rotations that best fit its two particles' springs: the same as Hooke for a "
             "stretch along the spring, stiff across it as well (the lattice resists "
             "shear), with contacts 1.0 instead of 0.3 times as stiff; with "
             "ConnectiveTissue 0.1 every time point of both demo motions converges at 20 "
             "particles per fibre, in 2-4 times fewer iterations, the answer a few mm from "
             "Hooke's (docs/solver-notes.md).",
             choices=SPRING_ENERGIES, group="Method",
             field="quasi_static.springs",
             option=Option("--springs", "quasi-static spring energy: the paper's Hooke "
                           "springs or co-rotational springs, stiff across themselves "
                           "as well (default {default})", what="its spring energy")),
    Property("WarmStart", "bool", False,
             "Quasi-static: start from the last solution of this filter (its displacement "
             "from its posed particles added to the new posed particles) when the model "
             "and the properties are the same and only the pose changed (the next time "
             "step). Off (the default): always start from the posed particles, so that the "
             "answer at a time does not depend on which times were solved before (contacts "
             "make the equilibrium not unique: a warm start can land in a neighbouring "
             "minimum); on is faster along a motion but its results depend on the order.",
             group="Method"),
    Property("Termination", "enum", TERMINATION_ITERATIONS,
             "When to stop. iterations: after Iterations iterations. displacement threshold: "
             "when every muscle's mean particle displacement of an iteration is below "
             "DisplacementThreshold and no longer rising. time budget: when TimeBudget "
             "seconds have passed. Iterations caps all three.",
             choices=TERMINATIONS, group="Termination",
             field="termination"),
    Property("Iterations", "int", DEFAULT_ITERATIONS,
             "Number of iterations (the cap for every termination).",
             minimum=1, group="Termination",
             field="iterations",
             option=Option("--iterations", "solver iterations per time point (default "
                           "{default})")),
    Property("DisplacementThreshold", "double", DEFAULT_DISPLACEMENT_THRESHOLD,
             "Mean particle displacement of one iteration (mm) below which a muscle counts "
             "as at rest (termination 'displacement threshold').",
             minimum=0.0, group="Termination",
             field="relaxation.displacement_threshold"),
    Property("TimeBudget", "double", DEFAULT_TIME_BUDGET,
             "Wall-clock seconds for the solve (termination 'time budget').",
             minimum=0.0, group="Termination",
             field="time_budget"),
    Property("TimeStep", "double", DEFAULT_TIME_STEP,
             "Time step of the semi-implicit Euler integration (s). The default is stable "
             "with margin for the Spring Builder's defaults (stiffness 10 g/s^2, damping "
             "0.5 g/s, mass 1 g) and lattice-26 springs; lower it for stiffer springs or "
             "lighter particles (stability needs about dt < 2 sqrt(m / (2 n k)) for n "
             "springs per particle).",
             minimum=1e-9, group="Integration",
             field="relaxation.time_step"),
    Property("Drag", "double", DEFAULT_DRAG,
             "Viscous drag on every particle's velocity (1/s): the force -Drag m v, taken "
             "implicitly so that it is stable at any strength. It makes the relaxation settle "
             "(the springs' own damping is explicit and must stay small to be stable); 0 "
             "turns it off (the paper's plain mass-spring system).",
             minimum=0.0, group="Integration",
             field="relaxation.drag"),
    Property("BulkModulus", "double", DEFAULT_BULK_MODULUS,
             "Resistance of each muscle to a change of its volume (g/(mm s^2), a pressure): "
             "the boundary particles' cage (the one that carries the surface) is pushed "
             "outwards by -BulkModulus (V / V_rest - 1) per unit of its area. Muscle is "
             "nearly incompressible, a spring lattice is not: without it a stretched lattice "
             "narrows and loses volume. 0 turns it off (the paper's springs only).",
             minimum=0.0, group="Integration",
             field="bulk_modulus"),
    Property("ConnectiveTissue", "double", DEFAULT_CONNECTIVE_TISSUE,
             "The connective tissue (epimysium, septa, fascia) that ties every muscle to "
             "the tissue around it, which moves with the skeleton: each free particle is "
             "held toward its posed rest position by a spring of this ratio to its muscle's "
             "mean spring stiffness (energy k |x - x_posed|^2 / 2; the ratio is the one at "
             "20 particles per fibre, scaled by ((20 - 1) / (N - 1))^2 at N so that the "
             "shape does not depend on the resolution). It makes the equilibrium of slack, "
             "slender muscles well-defined, so that the quasi-static method converges and "
             "the shape does not depend on the iteration cap. Both methods; 0 is the "
             "paper's model (muscles free between their tendons). The default 0.1 is the "
             "ratio at which both demo motions converge everywhere.",
             minimum=0.0, group="Integration",
             field="connective_tissue",
             option=Option("--connective-tissue", "connective tissue holding each free "
                           "particle toward its posed position, as a ratio to the "
                           "springs' stiffness; 0: the paper's model (default "
                           "{default:g})")),
    Property("TissueAlongFibres", "double", DEFAULT_TISSUE_ALONG,
             "The connective tissue's stiffness along each particle's fibre (its direction "
             "at the posed particles) as a fraction of its stiffness across: below 1 a "
             "fibre lengthens and shortens, and a muscle slides along its neighbours, "
             "against a weaker tissue (energy k (|d|^2 - (1 - fraction) (d . f)^2) / 2, d "
             "the particle's displacement from its posed position, f its fibre direction). "
             "1: the same in every direction. The default 0.1 lets the flexors of the "
             "elbow demo follow their muscles' shortening (with FibreShortening).",
             minimum=0.0, maximum=1.0, group="Integration",
             field="tissue_along",
             option=Option("--tissue-along", "the connective tissue's stiffness along the "
                           "fibres as a fraction of that across, 0 to 1; 1: isotropic "
                           "(default {default:g})")),
    Property("FibreShortening", "bool", DEFAULT_FIBRE_SHORTENING,
             "Fibres that shorten with their muscle: when a fibre's ends come closer than "
             "at rest (by the factor s), the springs' rest lengths along it follow (times "
             "s along the fibres, 1 / sqrt(s) across, the rest volume kept), so a "
             "shortening muscle shortens and thickens instead of keeping its fibre length "
             "and folding; the connective tissue then holds such a muscle toward its rest "
             "shape shortened so, not toward its bent posed pose. Lengthening fibres "
             "stretch as before. Both methods. On by default; off: the paper's springs "
             "(core/fibre_shortening.py).",
             group="Integration", field="fibre_shortening",
             option=Option("--fibre-shortening", "fibres shorten with their muscle "
                           "instead of folding (the solver's FibreShortening; "
                           "default {default})")),
    Property("CollisionStructure", "enum", STRUCTURE_HASH,
             "How colliding spheres are found. spatial hash: a uniform grid with candidate "
             "lists, parallel (the fast default). octree BVH: the paper's per-object octree "
             "of bounding boxes, refitted and lazily subdivided, on one thread. Both find "
             "the same pairs.",
             choices=STRUCTURES, group="Collisions",
             field="contacts.structure"),
    Property("BVHMaxDepth", "int", DEFAULT_BVH_MAX_DEPTH,
             "Octree BVH: deepest subdivision level (the paper's 8).",
             minimum=1, maximum=20, group="Collisions",
             field="contacts.bvh_max_depth"),
    Property("BVHMinPrimitives", "int", DEFAULT_BVH_MIN_PRIMITIVES,
             "Octree BVH: a node with this many spheres or fewer is not subdivided (the "
             "paper's 10).", minimum=1, group="Collisions",
             field="contacts.bvh_min_primitives"),
    Property("MuscleMuscle", "bool", True,
             "Handle collisions between spheres of different muscles.", group="Collisions",
             field="contacts.muscle_muscle"),
    Property("MuscleBone", "bool", True,
             "Handle collisions between muscle spheres and bone spheres.",
             group="Collisions",
             field="contacts.muscle_bone"),
    Property("ProjectionPasses", "int", DEFAULT_PROJECTION_PASSES,
             "Collision passes (detection and response, no spring update) after the last "
             "iteration, until no two spheres of different objects overlap by more than "
             "PenetrationTolerance. A sphere pressed between two objects keeps half its "
             "overlap after one response, and the springs push it back in every iteration; "
             "these passes remove what is left. 0 turns them off (the paper's loop).",
             minimum=0, group="Collisions",
             field="contacts.projection_passes"),
    Property("PenetrationTolerance", "double", DEFAULT_PENETRATION_TOLERANCE,
             "Deepest overlap (mm) of two spheres of different objects at which the final "
             "collision passes stop.", minimum=0.0, group="Collisions",
             field="contacts.penetration_tolerance"),
    Property("BoneContact", "enum", DEFAULT_BONE_CONTACT,
             "How the bones push muscle spheres (both methods, iterations and final "
             "collision passes). solid (the default, and the faster): each bone is a solid "
             "(its signed distance, sampled once per bone shape, about 10 s for the demo "
             "thigh, and moved with the bone); a sphere is pushed out along the distance "
             "gradient from any depth until it touches the surface. sphere set: the "
             "paper's spheres on the bone surface (BoneSphereSpacing; a sphere carried past "
             "that shell is pushed on through it by its inner spheres).",
             choices=BONE_CONTACTS, group="Collisions",
             field="contacts.bone_contact"),
    Property("BoneSphereSpacing", "double", DEFAULT_BONE_SPHERE_SPACING,
             "BoneContact 'sphere set': least distance between bone sphere centres, and "
             "their radius (mm). The bones "
             "are sampled into about 0.62 * area / spacing^2 spheres (Poisson-disc): the "
             "default gives about 8,600 on the demo pelvis (58,000 mm^2), the paper's "
             "density (8527 spheres for a pelvis).",
             minimum=1e-3, group="Collisions",
             field="contacts.bone_sphere_spacing"),
)

ROW_OF_FIELD = {prop.field: prop for prop in SOLVER_PROPERTIES if prop.field}
"""Each :class:`~muscle_mss.core.settings.SolverSettings` field (``relaxation.time_step``) and
its row."""


ROW_OF_KEYWORD = {prop.field.rpartition(".")[2]: prop for prop in ROW_OF_FIELD.values()}
"""Each flat settings keyword (``time_step``, as :meth:`SolverSettings.build` takes them) and its
row."""


def by_name(**values) -> dict:
    """``{property name: value}`` of solver settings given as :meth:`SolverSettings.build`'s
    flat keywords (``by_name(iterations=3, method=METHOD_RELAXATION)``), for a pipeline set up
    by property names; an unknown keyword is a TypeError. Enums take their choice's text."""
    unknown = set(values) - set(ROW_OF_KEYWORD)
    if unknown:
        raise TypeError(f"no solver property sets {', '.join(sorted(unknown))}")
    return {ROW_OF_KEYWORD[key].name: value for key, value in values.items()}


def name_of(field: str) -> str:
    """The property name of a settings field (``name_of("relaxation.time_step")`` is
    ``TimeStep``): what a message calls the setting, in ParaView and in state files."""
    return ROW_OF_FIELD[field].name


def field_value(settings: SolverSettings, field: str):
    """The value of ``settings`` at a dotted ``field`` (``contacts.structure``)."""
    value = settings
    for part in field.split("."):
        value = getattr(value, part)
    return value


def check_settings(settings: SolverSettings) -> None:
    """Raise :class:`MuscleMSSError` naming the first setting outside its row's choices or
    range (a whole number for a count, finite), or an L-BFGS ``history``, ``contact_weight``,
    ``soft_start`` or ``contact_preconditioner`` (settings with no property) out of
    theirs."""
    for prop in ROW_OF_FIELD.values():
        value = field_value(settings, prop.field)
        problem = None
        if prop.kind == "enum" and value not in prop.choices:
            problem = (f"property {prop.name} is {value!r}; it must be one of "
                       f"{', '.join(prop.choices)}")
        elif prop.kind in ("int", "double"):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                problem = f"property {prop.name} is {value!r}; it must be a number"
            elif prop.kind == "int" and not (math.isfinite(value) and value == int(value)):
                problem = f"property {prop.name} is {value}; it must be a whole number"
            else:
                problem = prop.range_problem(value)
        if problem:
            raise MuscleMSSError(problem)
    history = settings.quasi_static.history
    if not (isinstance(history, int) and history >= 0):
        raise MuscleMSSError(f"quasi-static history is {history!r}; it must be a whole number, "
                             "0 or more")
    if not isinstance(settings.quasi_static.contact_preconditioner, bool):
        raise MuscleMSSError("quasi-static contact_preconditioner is "
                             f"{settings.quasi_static.contact_preconditioner!r}; it must be "
                             "True or False")
    soft = settings.quasi_static.soft_start
    if isinstance(soft, bool) or not isinstance(soft, (int, float)) or not 0.0 < soft <= 1.0:
        raise MuscleMSSError(f"quasi-static soft_start is {soft!r}; it must be a number above "
                             "0 and at most 1 (the first stage's contact stiffness as a "
                             "fraction of the full; 1 for one stage)")
    weight = settings.quasi_static.weight
    if not (weight > 0.0 and math.isfinite(weight)):
        raise MuscleMSSError(f"quasi-static contact weight is {weight}; it must be finite and "
                             "positive")


def ignored_settings(settings: SolverSettings) -> list:
    """Warnings for settings away from their default that the others make ineffective: the
    tissue's along-fibre fraction with no connective tissue, the bone sphere spacing with the
    bones as solids. Not refused: in ParaView properties are set one at a time."""
    ignored = []
    along, tissue = name_of("tissue_along"), name_of("connective_tissue")
    if settings.connective_tissue == 0.0 and settings.tissue_along != DEFAULT_TISSUE_ALONG:
        ignored.append(f"{along} {settings.tissue_along:g} has no effect with {tissue} 0: it "
                       "is the connective tissue's stiffness along the fibres, and the tissue "
                       f"is off; raise {tissue} above 0 for it to apply, or leave {along} at "
                       f"its default {DEFAULT_TISSUE_ALONG:g}")
    spacing, contact = name_of("contacts.bone_sphere_spacing"), name_of("contacts.bone_contact")
    value = settings.contacts.bone_sphere_spacing
    if (settings.contacts.bone_contact == BONE_CONTACT_SOLID
            and value != DEFAULT_BONE_SPHERE_SPACING):
        ignored.append(f"{spacing} {value:g} mm has no effect with {contact} "
                       f"'{BONE_CONTACT_SOLID}': the bones are solids, not spheres; set "
                       f"{contact} to '{BONE_CONTACT_SPHERES}' for it to apply, or leave "
                       f"{spacing} at its default {DEFAULT_BONE_SPHERE_SPACING:g} mm")
    return ignored


def unconverged_warning(settings: SolverSettings, iterations: int, stopped_by: str,
                        last_step: float, to_go: float, remaining_penetration: float) -> str:
    """What a solve that stopped short of its tolerance says: the ``iterations``
    it ran, why it stopped, its ``last_step`` (mm, the largest particle move), the estimated
    distance ``to_go`` (mm, inf when the steps are not shrinking) and the deepest overlap
    left (mm)."""
    still = (f"the steps still to come would move one about {to_go:.3g} mm more"
             if math.isfinite(to_go) else "the steps are not shrinking yet")
    tolerance, overlap = name_of("quasi_static.tolerance"), name_of("contacts.penetration_tolerance")
    return (f"the {settings.method} solve did not converge in {iterations} iterations "
            f"({stopped_by}): "
            f"the last step moved a particle {last_step:.3g} mm and {still} ({tolerance} "
            f"{settings.quasi_static.tolerance} mm), deepest overlap left "
            f"{remaining_penetration:.3g} mm ({overlap} "
            f"{settings.contacts.penetration_tolerance} mm); raise {name_of('iterations')} or "
            f"the {tolerance}")
