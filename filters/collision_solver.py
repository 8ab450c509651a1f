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

Frame cache (property ``FrameCache``, :mod:`~muscle_mss.filters.frame_cache`): a frame solved
before, by this filter or by ``muscle-mss run``, with the same scene files, the same properties
of this filter and of the three before it, and the same time, is loaded instead of solved; the
outputs are then computed from it as from a solve. ``frame_counts`` counts the frames loaded
and solved.
"""
from __future__ import annotations

import dataclasses
import hashlib

import numpy as np

from vtkmodules.vtkCommonCore import vtkOutputWindow

from muscle_mss.core import quasi_static as Q
from muscle_mss.core.model import Bones, MSSModel, PreparedModel, prepare, with_rest_state
from muscle_mss.core.solver import solve
from muscle_mss.core.errors import MuscleMSSError, PoseError
from muscle_mss.core.settings import METHOD_QUASI_STATIC, SolverSettings
from muscle_mss.core.solver_properties import (SOLVER_PROPERTIES, ignored_settings,
                                               unconverged_warning)

from . import array_names as A
from .bone_sets import POSED_BONES as BONES, bone_depths, contact_bones, particles_in_bones
from . import vtk_arrays as V
from .base import MuscleFilter, Port
from .frame_cache import FRAME_CACHE_PROPERTY, KEYED_FILTERS, chosen_folder
from .pipeline_frames import SolverFrames, pipeline_frames
from .model_blocks import MODEL, MODEL_BLOCK, muscle_block



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
    PROPERTIES = SOLVER_PROPERTIES + (FRAME_CACHE_PROPERTY,)

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
        self.frame_counts = {"loaded": 0, "solved": 0}
        self._frames = (None, None)     # (what they were made for, SolverFrames or None)
        self._scene = (None, None)      # (the readers' files and outputs, their digest)
        self._frames_note = None

    @staticmethod
    def default_frame_cache():
        """The folder an empty ``FrameCache`` means: none in a plain VTK pipeline (an
        application chooses its own: ``muscle-mss run`` its ``--cache``); the ParaView proxy's
        is the user's frame cache."""
        return None

    def settings(self) -> SolverSettings:
        """The properties as the core's :class:`~muscle_mss.core.settings.SolverSettings`: each
        row with a ``field`` gives that field its value (an enum its choice's text)."""
        return SolverSettings.build(**{
            prop.field.rpartition(".")[2]:
                self.choice(prop.name) if prop.kind == "enum" else self.value(prop.name)
            for prop in self.PROPERTIES if prop.field})

    def history_dependence(self) -> str | None:
        """Why a frame of this solver depends on more than its inputs, its properties and its
        time (None: it does not): WarmStart starts it from the frame solved before it, the
        termination 'time budget' stops it on the clock. The frame cache and the parallel
        runs read it (such frames are neither stored nor spread over processes)."""
        if self.value("WarmStart"):
            return "WarmStart makes a frame depend on the frame solved before it"
        if self.settings().budget is not None:
            return "termination 'time budget' stops a solve on the clock"
        return None

    def _warn_ignored_settings(self):
        """Print :func:`~muscle_mss.core.solver_properties.ignored_settings` (ParaView's output
        messages) when they change, not at every time point."""
        ignored = tuple(ignored_settings(self.settings()))
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
        contacts = self.settings().contacts
        bones = contact_bones(inputs[1], contacts.bone_contact, contacts.bone_sphere_spacing,
                              contacts.muscle_bone)
        frames, time = self._pipeline_frames(), self.requested_time()
        result = frames.load(time) if frames is not None and time is not None else None
        if result is None:
            result = self._solve(model, bones, self._prepare(model, identities))
            self.frame_counts["solved"] += 1
            if frames is not None and time is not None:
                frames.save(time, result)
        else:
            self.frame_counts["loaded"] += 1
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
        if result.residual is not None:
            columns[A.RESIDUAL] = result.residual
        V.fill_table(outputs[1], columns)
        V.set_field(outputs[1], A.PROJECTION_PASSES, result.projection_passes)
        V.set_field(outputs[1], A.REMAINING_PENETRATION, result.remaining_penetration)
        V.set_field(outputs[1], A.CONVERGED, int(result.converged))
        V.set_field(outputs[1], A.METHOD, result.method)
        for part, name in A.PHASE_SECONDS.items():
            V.set_field(outputs[1], name, float(result.phase_seconds.get(part, 0.0)))
        if result.residual is not None and not result.converged:
            vtkOutputWindow.GetInstance().DisplayWarningText(
                f"{self.LABEL}: " + unconverged_warning(
                    self.settings(), result.iterations, result.stopped_by, result.residual[-1],
                    Q.distance_to_go(result.residual), result.remaining_penetration) + "\n")
        self.progress(1.0)

    def frame_folder(self) -> str | None:
        """The frame cache's folder ``FrameCache`` chooses (None: off); the MVC Surface
        Deformer after this solver keeps its surfaces there too."""
        text = self.value("FrameCache").strip()
        return chosen_folder(text) if text else self.default_frame_cache()

    def _pipeline_frames(self):
        """The :class:`~muscle_mss.filters.pipeline_frames.SolverFrames` of the folder
        ``FrameCache`` chooses for this pipeline, or None: off, or a pipeline whose frames the
        key does not determine (said once among the messages)."""
        return pipeline_frames(self, KEYED_FILTERS[:-1], SolverFrames)

    def _solve(self, model: MSSModel, bones: Bones, prepared: PreparedModel):
        """:func:`~muscle_mss.core.solver.solve`; the quasi-static method warm started from the
        last solution when the model (topology, rest pose, stiffnesses) and the properties are
        unchanged."""
        progress = lambda f: self.progress(0.05 + 0.9 * f)  # noqa: E731
        settings = self.settings()
        if settings.method != METHOD_QUASI_STATIC:
            return solve(model, bones, settings, prepared=prepared, progress=progress)
        key = (self._prepared_shape, repr(settings))
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
