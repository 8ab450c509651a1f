"""MSS Collision Solver: the posed mass-spring model's equilibrium with sphere collisions (DESIGN
§5–6, paper §3.1 and §3.3).

Inputs: ``PosedModel`` (the Rigid Pose Transform's model: points = posed particles; point data
``rest_position``, ``fibre_id``, ``fibre_index``, ``fixed``, ``boundary``, ``radius``, ``mass``,
optional ``in_bone_at_rest`` (the particles the solid bones leave where they are);
springs = two-point line cells with cell data ``rest_length``, ``stiffness``, ``damping``) and
``PosedBones`` (the posed bone surfaces: solids, each bone's signed distance field, by default;
or spheres sampled by :func:`muscle_mss.core.bones.spheres.bone_spheres`; both sampled once per
bone shape and moved with the bone, :mod:`~muscle_mss.filters.bone_sets`).

Outputs: ``SolvedModel`` — every input block and array kept, points = solved positions, plus
``velocity`` (mm/s), ``displacement`` (solved - posed, mm) and ``collided`` (uint8, in the last
iteration or the final collision passes), and per block (muscle) the field data
``free_particles_in_bone`` / ``free_particle_bone_depth_mm`` (free particles with their centre
inside a posed bone, by the bones' exact distance near their surfaces, and the deepest, mm) and
``free_particles_new_in_bone`` / ``free_particle_new_in_bone_depth_mm`` (those of them not inside
a bone at rest, ``in_bone_at_rest``: the goal is 0); ``Convergence`` — a table with one row per
iteration: ``iteration``, ``mean_displacement_<muscle>`` per muscle (mm; the paper's figures 5
and 6 in a line chart), ``colliding_pairs``, ``max_penetration`` (mm, before that iteration's
response, of the pairs it can resolve: not a fixed tendon sphere against its bone) and
``seconds`` (cumulative); its field data ``projection_passes`` and ``remaining_penetration``
(mm) tell how many collision passes ran after the last iteration and the deepest overlap left.

Two methods (property ``Method``): ``quasi-static`` (the default,
:mod:`muscle_mss.core.quasi_static`) solves for the static equilibrium of the model, its
connective tissue and contacts to ``Tolerance`` (mm, the largest particle move of a
quasi-Newton step; its table adds a ``residual`` column); ``paper relaxation``
(:mod:`muscle_mss.core.relaxation`) runs the paper's explicit iterations. Both tables carry
field data ``method`` and ``converged``; an unconverged solve prints a warning. Every solve
starts from the posed state, so a time point's answer does not depend on the times solved
before it (``WarmStart`` trades that for speed). The whole stage, fibre shortening and the bone
contact (``BoneContact``: solids by default, or the paper's sphere sets) included, is one call
of :func:`muscle_mss.core.solver.solve`; this filter converts VTK to arrays and back, and keeps
what a later pose of the same model can reuse.
"""
from __future__ import annotations

import dataclasses
import hashlib

import numpy as np

from vtkmodules.vtkCommonCore import vtkOutputWindow

from muscle_mss.core import quasi_static as Q
from muscle_mss.core.model import (BONE_CONTACT_SOLID, BONE_CONTACT_SPHERES, BONE_CONTACTS,
                                   Bones, MSSModel, PreparedModel, prepare, with_rest_state)
from muscle_mss.core.solver import solve
from muscle_mss.core.bones.spheres import DEFAULT_SPACING
from muscle_mss.core.errors import MuscleMSSError, PoseError
from muscle_mss.core.settings import (
    DEFAULT_BULK_MODULUS, DEFAULT_BVH_MAX_DEPTH, DEFAULT_CONNECTIVE_TISSUE,
    DEFAULT_BVH_MIN_PRIMITIVES, DEFAULT_DISPLACEMENT_THRESHOLD, DEFAULT_DRAG,
    DEFAULT_FIBRE_SHORTENING, DEFAULT_ITERATIONS,
    DEFAULT_METHOD, DEFAULT_PENETRATION_TOLERANCE, DEFAULT_PROJECTION_PASSES, DEFAULT_SPRINGS,
    DEFAULT_TIME_BUDGET, DEFAULT_TIME_STEP, DEFAULT_TISSUE_ALONG, DEFAULT_TOLERANCE, METHOD_QUASI_STATIC, METHODS, STRUCTURE_HASH,
    SPRING_ENERGIES, STRUCTURES, TERMINATION_ITERATIONS, TERMINATION_THRESHOLD, TERMINATIONS,
    SolverSettings)

from . import array_names as A
from .bone_sets import POSED_BONES as BONES, bone_depths, contact_bones, particles_in_bones
from . import vtk_arrays as V
from .base import MuscleFilter, Port
from .model_blocks import MODEL, MODEL_BLOCK, muscle_block
from .properties import Option, Property



class MSSCollisionSolver(MuscleFilter):
    """The mass-spring model's equilibrium with sphere collisions; see the module docstring."""

    LABEL = "MSS Collision Solver"
    HELP = ("Solves the posed mass-spring model of every muscle (springs, each muscle's "
            "resistance to a change of its volume, the connective tissue around it, fixed "
            "tendon particles) for its static equilibrium, or relaxes it by the paper's "
            "explicit iterations (Method), while pushing the particles' spheres out of other "
            "muscles' spheres and out of the bones (solids by "
            "default, keeping every free particle out, or spheres on their surface). Outputs "
            "the solved model (velocity, displacement, collided added, and per muscle the free "
            "particles inside a bone as field data) and a table of the mean displacement of each muscle, the colliding "
            "pairs, the deepest penetration and the elapsed seconds per iteration: plot it with "
            "a Line Chart View to see the convergence.")
    INPUTS = (Port(MODEL, "vtkMultiBlockDataSet",
                   "The posed mass-spring model, one block per muscle (Rigid Pose Transform)."),
              Port(BONES, "vtkMultiBlockDataSet",
                   "The posed bone surfaces, one closed triangle surface per bone."))
    OUTPUTS = (Port("SolvedModel", "vtkMultiBlockDataSet",
                    "The model at the solved positions with velocity, displacement, collided."),
               Port("Convergence", "vtkTable",
                    "One row per iteration: mean displacement per muscle, colliding pairs, "
                    "max penetration, seconds."))
    PROPERTIES = (
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
        Property("BoneContact", "enum", BONE_CONTACT_SOLID,
                 "How the bones push muscle spheres (both methods, iterations and final "
                 "collision passes). solid (the default, and the faster): each bone is a solid "
                 "(its signed distance, sampled once per bone shape, about 10 s for the demo "
                 "thigh, and moved with the bone); a sphere is pushed out along the distance "
                 "gradient from any depth until it touches the surface. sphere set: the "
                 "paper's spheres on the bone surface (BoneSphereSpacing; a sphere carried past "
                 "that shell is pushed on through it by its inner spheres).",
                 choices=BONE_CONTACTS, group="Collisions"),
        Property("BoneSphereSpacing", "double", DEFAULT_SPACING,
                 "BoneContact 'sphere set': least distance between bone sphere centres, and "
                 "their radius (mm). The bones "
                 "are sampled into about 0.62 * area / spacing^2 spheres (Poisson-disc): the "
                 "default gives about 8,600 on the demo pelvis (58,000 mm^2), the paper's "
                 "density (8527 spheres for a pelvis).",
                 minimum=1e-3, group="Collisions"),
    )

    def __init__(self):
        super().__init__()
        self._prepared_key = None
        self._prepared_shape = None
        self._prepared = None
        self._prepared_identity = None
        self._last = None       # (key, posed, solved) of the last quasi-static solve
        self.solved_bones = None    # the core Bones the last solve used (its bone contact)
        # per model block name: (arrays_identity, checked arrays) of the last update, and the
        # model's arrays other than the coordinates (identities, MSSModel): every time point
        # of a motion brings the same arrays with new coordinates (the Rigid Pose Transform
        # shares them), so they are checked, concatenated and hashed once
        self._blocks = {}
        self._static = (None, None)
        self._ignored_warned = ()     # the ignored settings last warned about
        self.setup_counts = {"checked": 0, "remembered": 0, "prepared": 0, "rest state": 0}

    def settings(self) -> SolverSettings:
        """The properties as the core's :class:`~muscle_mss.core.settings.SolverSettings`: each
        row with a ``field`` gives that field its value (an enum its choice's text)."""
        return SolverSettings.build(**{
            prop.field.rpartition(".")[2]:
                self.choice(prop.name) if prop.kind == "enum" else self.value(prop.name)
            for prop in self.PROPERTIES if prop.field})

    def ignored_settings(self) -> list:
        """Warnings for properties set away from their default that the other properties make
        ineffective: TissueAlongFibres with no connective tissue, BoneSphereSpacing with the
        bones as solids. Not refused: in ParaView properties are set one at a time."""
        ignored = []
        along = self.value("TissueAlongFibres")
        if self.value("ConnectiveTissue") == 0.0 and along != DEFAULT_TISSUE_ALONG:
            ignored.append(f"TissueAlongFibres {along:g} has no effect with ConnectiveTissue 0: "
                           "it is the connective tissue's stiffness along the fibres, and the "
                           "tissue is off; raise ConnectiveTissue above 0 for it to apply, or "
                           f"leave TissueAlongFibres at its default {DEFAULT_TISSUE_ALONG:g}")
        spacing = self.value("BoneSphereSpacing")
        if self.choice("BoneContact") == BONE_CONTACT_SOLID and spacing != DEFAULT_SPACING:
            ignored.append(f"BoneSphereSpacing {spacing:g} mm has no effect with BoneContact "
                           f"'{BONE_CONTACT_SOLID}': the bones are solids, not spheres; set "
                           f"BoneContact to '{BONE_CONTACT_SPHERES}' for it to apply, or leave "
                           f"BoneSphereSpacing at its default {DEFAULT_SPACING:g} mm")
        return ignored

    def _warn_ignored_settings(self):
        """Print :meth:`ignored_settings` (ParaView's output messages) when they change, not
        at every time point."""
        ignored = tuple(self.ignored_settings())
        for text in ignored:
            if text not in self._ignored_warned:
                vtkOutputWindow.GetInstance().DisplayWarningText(f"{self.LABEL}: {text}\n")
        self._ignored_warned = ignored

    def execute(self, inputs, outputs):
        self._warn_ignored_settings()
        blocks = V.blocks(inputs[0], where=MODEL)
        if not blocks:
            raise MuscleMSSError(f"the {MODEL} input has no blocks; it needs one block per "
                                 "muscle")
        identities, parts = zip(*(self._checked_block(name, block) for name, block in blocks))
        model = self._posed_model([name for name, _ in blocks], parts, identities)
        try:
            self._solve_pose(inputs, outputs, blocks, parts, identities, model)
        except PoseError as err:
            raise err.at(self.requested_time()) from None

    def _solve_pose(self, inputs, outputs, blocks, parts, identities, model):
        """:meth:`execute` from the posed ``model`` of the checked ``blocks`` on."""
        bones = contact_bones(inputs[1], self.choice("BoneContact"),
                              self.value("BoneSphereSpacing"), self.value("MuscleBone"))
        result = self._solve(model, bones, self._prepare(model, identities))
        self.solved_bones = bones
        positions, collided = result.positions, result.collided
        items = []
        depth = bone_depths(positions, inputs[1], BONES)
        for m, ((name, block), part) in enumerate(zip(blocks, parts)):
            lo, hi = model.offsets[m], model.offsets[m + 1]
            out = V.with_points(block, positions[lo:hi])
            V.set_point_array(out, A.VELOCITY, result.velocity[lo:hi])
            V.set_point_array(out, A.DISPLACEMENT, positions[lo:hi] - part["points"])
            V.set_point_array(out, A.COLLIDED, collided[lo:hi].astype(np.uint8))
            in_bone = (None if model.in_bone_at_rest is None
                       else model.in_bone_at_rest[lo:hi])
            for key, value in zip(A.FREE_IN_BONE_FIELDS, particles_in_bones(
                    depth[lo:hi], ~model.fixed[lo:hi], in_bone)):
                V.set_field(out, key, value)
            V.set_field(out, A.TISSUE_SHARE_PCT, float(result.tissue_share[m]))
            items.append((name, out))
        V.fill_multiblock(outputs[0], items)
        columns = {A.ITERATION: np.arange(1, result.iterations + 1)}
        for m, (name, _) in enumerate(blocks):
            columns[A.MEAN_DISPLACEMENT + name] = result.mean_displacement[:, m]
        columns[A.COLLIDING_PAIRS] = result.colliding_pairs
        columns[A.MAX_PENETRATION] = result.max_penetration
        columns[A.SECONDS] = result.seconds
        quasi_static = result.method == METHOD_QUASI_STATIC
        if quasi_static:
            columns[A.RESIDUAL] = result.residual
        V.fill_table(outputs[1], columns)
        V.set_field(outputs[1], A.PROJECTION_PASSES, result.projection_passes)
        V.set_field(outputs[1], A.REMAINING_PENETRATION, result.remaining_penetration)
        converged = (result.converged if quasi_static
                     else result.stopped_by == TERMINATION_THRESHOLD)
        V.set_field(outputs[1], A.CONVERGED, int(converged))
        V.set_field(outputs[1], A.METHOD, self.choice("Method"))
        for part, name in A.PHASE_SECONDS.items():
            V.set_field(outputs[1], name, float(result.phase_seconds.get(part, 0.0)))
        if quasi_static and not converged:
            to_go = Q.distance_to_go(result.residual)
            still = (f"the steps still to come would move one about {to_go:.3g} mm more"
                     if np.isfinite(to_go) else "the steps are not shrinking yet")
            vtkOutputWindow.GetInstance().DisplayWarningText(
                f"{self.LABEL}: the quasi-static solve did not converge in "
                f"{result.iterations} iterations ({result.stopped_by}): the last step moved a "
                f"particle {result.residual[-1]:.3g} mm and {still} (Tolerance "
                f"{self.value('Tolerance')} mm), deepest overlap left "
                f"{result.remaining_penetration:.3g} mm (PenetrationTolerance "
                f"{self.value('PenetrationTolerance')} mm); raise Iterations or the "
                "Tolerance\n")
        self.progress(1.0)

    def _solve(self, model: MSSModel, bones: Bones, prepared: PreparedModel):
        """:func:`~muscle_mss.core.solver.solve`; the quasi-static method warm started from the
        last solution when the model (topology, rest pose, stiffnesses) and the properties are
        unchanged."""
        progress = lambda f: self.progress(0.05 + 0.9 * f)  # noqa: E731
        settings = self.settings()
        if settings.method != METHOD_QUASI_STATIC:
            return solve(model, bones, settings, prepared=prepared, progress=progress)
        key = (self._prepared_shape, repr(settings), self.value("BoneSphereSpacing"),
               self.choice("BoneContact"))
        start = None
        if self.value("WarmStart") and self._last is not None and self._last[0] == key:
            start = model.positions + (self._last[2] - self._last[1])
        result = solve(model, bones, settings, prepared=prepared, start=start,
                       progress=progress)
        self._last = (key, np.array(model.positions, dtype=np.float64), result.positions)
        return result

    @staticmethod
    def _model(names, parts) -> MSSModel:
        sizes = [len(p["points"]) for p in parts]
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)

        def cat(key, dtype=None):
            return np.concatenate([np.asarray(p[key], dtype=dtype) for p in parts])

        grid = None
        if all(p["grid"] is not None for p in parts):
            grid = np.concatenate([p["grid"].reshape(len(p["points"]), -1) for p in parts])
        springs = np.concatenate([p["springs"] + offsets[m] for m, p in enumerate(parts)])
        in_bone = None
        if all(p["in_bone"] is not None for p in parts):
            in_bone = np.concatenate([p["in_bone"].reshape(-1) != 0 for p in parts])
        return MSSModel(names, offsets, cat("points"), cat(A.FIXED) != 0,
                          cat(A.MASS, np.float64), cat(A.BOUNDARY) != 0,
                          cat(A.RADIUS, np.float64), cat(A.FIBRE_ID, np.int64),
                          cat(A.FIBRE_INDEX, np.int64), springs, cat(A.REST_LENGTH, np.float64),
                          cat(A.STIFFNESS, np.float64), cat(A.DAMPING, np.float64), grid,
                          np.concatenate([p[A.REST_POSITION].reshape(-1, 3) for p in parts]),
                          in_bone)

    def _checked_block(self, name, block):
        """``(arrays identity, checked arrays)`` of one model block
        (:func:`~muscle_mss.filters.model_blocks.muscle_block`),
        its arrays other than the coordinates taken from the last update when it had the same
        identity."""
        V.require_polydata(block, f"{MODEL} block '{name}'", MODEL_BLOCK)
        identity = V.arrays_identity(block)
        known = self._blocks.get(name)
        if known is not None and known[0] == identity:
            self.setup_counts["remembered"] += 1
            return identity, muscle_block(name, block, known[1])
        part = muscle_block(name, block)
        self._blocks[name] = (identity, {k: v for k, v in part.items() if k != "points"})
        self.setup_counts["checked"] += 1
        return identity, part

    def _posed_model(self, names, parts, identities) -> MSSModel:
        """:meth:`_model`, its arrays other than the coordinates reused while the blocks'
        identities are those of the last update."""
        key = (tuple(names), tuple(identities))
        for name in set(self._blocks) - set(names):
            del self._blocks[name]
        if self._static[0] == key:
            return dataclasses.replace(self._static[1], positions=np.concatenate(
                [p["points"] for p in parts]))
        model = self._model(names, parts)
        self._static = (key, model)
        return model

    def _prepare(self, model: MSSModel, identities=None) -> PreparedModel:
        """The particle order and spring layout, reused while the model's topology and spring
        parameters stay the same (every time point of a motion): while the blocks' array
        identities stay the same, else while the arrays' contents do."""
        if identities is not None and identities == self._prepared_identity:
            return self._prepared
        self._prepared_identity = None      # until this model is prepared (it may be refused)
        digest = hashlib.sha1()
        for array in (model.offsets, model.springs, model.stiffness, model.damping,
                      model.fixed, model.mass, model.boundary, model.radius, model.fibre_id,
                      model.fibre_index, model.rest_positions):
            digest.update(np.ascontiguousarray(array).tobytes())
        for label, optional in ((b"grid", model.fibre_grid),
                                (b"in bone", model.in_bone_at_rest)):
            if optional is not None:
                digest.update(label + np.ascontiguousarray(optional).tobytes())
        shape = digest.hexdigest()
        digest.update(np.ascontiguousarray(model.rest_length).tobytes())
        if model.rest_vectors is not None:
            digest.update(b"rest vectors" + np.ascontiguousarray(model.rest_vectors).tobytes())
        key = digest.hexdigest()
        if key != self._prepared_key:
            if self._prepared is not None and shape == self._prepared_shape:
                # only the rest lengths changed: keep the factorisation
                self._prepared = with_rest_state(self._prepared, model)
                self.setup_counts["rest state"] += 1
            else:
                self._prepared = prepare(model)
                self.setup_counts["prepared"] += 1
            self._prepared_key, self._prepared_shape = key, shape
        self._prepared_identity = identities
        return self._prepared
