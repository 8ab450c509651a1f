"""Rigid Pose Transform: the skeleton at the requested time and the muscles carried along
(paper §3.1, DESIGN §5 and §6 "Pose").

The motion table sets the filter's time steps, so the ParaView time slider, pvpython's
``UpdatePipeline(t)`` and an animation drive it. The blend weights depend only on the rest
inputs and the weight properties; they are computed once and reused for every time, as are
the model's collision radii cleared of the rest bones (the same clearing as the Spring
Builder's with its Bones input, so that a pipeline built without that input does not push
muscle spheres out of the bones at rest and solves the same).
"""
from __future__ import annotations

import os

import numpy as np
from vtkmodules.vtkCommonCore import vtkOutputWindow
from vtkmodules.vtkCommonDataModel import vtkDataObject

from muscle_mss.core.attachments import (INSERTION, ORIGIN, fixed_particle_bones, nearest_bone,
                                         unknown_bone_problem)
from muscle_mss.core.bones.weights import bone_weights
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.motion import motion_from_rows
from muscle_mss.core.pose import BLENDINGS, DUAL_QUATERNION, blend, pose_at, transform_rigid
from muscle_mss.core.scene import BONES_FILE

from . import array_names as A
from . import vtk_arrays as V
from .base import SDDP, MuscleFilter, Port
from .bone_sets import clear_of_bones
from muscle_mss.core.properties import Property
from .scene_io import check_motion_cells, motion_rows_from_table

MOTION_PORT = 2  # index of the Motion input in INPUTS


def _finite(rest, where: str) -> np.ndarray:
    bad = ~np.isfinite(rest).all(axis=1)
    if bad.any():
        raise MuscleMSSError(f"{where}: point {int(np.flatnonzero(bad)[0])} has a NaN or infinite "
                             "rest coordinate; every coordinate must be finite")
    return rest


def _bone_clearance(model_items, model_rest, bones) -> list:
    """Per model block ``(radius cleared of the rest bones or None, inside a bone at rest
    (n,) bool)`` (:func:`~muscle_mss.filters.bone_sets.clear_of_bones`); the radius is None
    for every block when a block has no ``radius`` (a model not from the Spring Builder)."""
    if not model_items:
        return []
    radii = [V.point_array(block, A.RADIUS, f"Model block '{name}'", required=False,
                           dtype=np.float64) for name, block in model_items]
    given = all(r is not None and r.size == len(rest) for r, rest in zip(radii, model_rest))
    rest = np.concatenate(model_rest)
    cleared, inside = clear_of_bones(
        rest, np.concatenate(radii).ravel() if given else np.zeros(len(rest)), bones, BONES_FILE)
    ends = np.cumsum([len(r) for r in model_rest])[:-1]
    return [(r if given else None, i) for r, i in zip(np.split(cleared, ends),
                                                      np.split(inside, ends))]


def _attached_bones(block, rest, bone_names, bone_surfaces, labels, where: str):
    """``(bone index of every particle (n,) int64, {field name: bone name})`` of a model block:
    -1 for free particles; the fixed
    particles at fibre index 0 follow the block's ``origin_bone``, those at the fibres' last
    index its ``insertion_bone`` (field data carried from fibres.vtm); a bone not named there is
    the one nearest on average to that end's rest positions. The dict gives the bone of each
    end (``origin_bone``, ``insertion_bone``) that has fixed particles."""
    ends = fixed_particle_bones(V.point_array(block, A.FIBRE_ID, where=where),
                                V.point_array(block, A.FIBRE_INDEX, where=where),
                                V.point_array(block, A.FIXED, where=where), 0, 1)
    out = np.full(len(ends), -1, dtype=np.int64)
    names = {}
    for code, end, array in ((0, ORIGIN, A.ORIGIN_BONE), (1, INSERTION, A.INSERTION_BONE)):
        if not (ends == code).any():
            continue
        given = V.field(block, array)
        if given is not None:
            problem = unknown_bone_problem(where, end, str(given), bone_names)
            if problem:
                raise MuscleMSSError(problem)
            bone = bone_names.index(given)
        else:
            bone = nearest_bone(rest[ends == code], bone_surfaces, labels)[0]
        out[ends == code] = bone
        names[array] = bone_names[bone]
    return out, names


def _tree_stamp(data):
    """What identifies one version of an input: the object and the newest MTime in its tree."""
    if data is None:
        return None
    stamp = data.GetMTime()
    it = data.NewIterator()
    it.InitTraversal()
    while not it.IsDoneWithTraversal():
        stamp = max(stamp, it.GetCurrentDataObject().GetMTime())
        it.GoToNextItem()
    return data.GetAddressAsString("vtkObjectBase"), stamp


class RigidPoseTransform(MuscleFilter):
    """Bones moved rigidly, muscle particles and surfaces by a blend of their nearest bones."""

    LABEL = "Rigid Pose Transform"
    HELP = ("Moves the bones rigidly to their pose at the current time of the motion table "
            "(interpolated between rows: rotation by quaternion slerp, translation linearly; "
            "clamped with a warning outside the table's range) and moves every particle of the "
            "mass-spring model and every vertex of the rest muscle surfaces by a blend of the "
            "transforms of its nearest bones, weighted by the rest-pose distance to the bone "
            "surfaces. The fixed end particles of each fibre follow their attachment bone "
            "rigidly instead: the origin_bone / insertion_bone field data of the fibres.vtm block "
            "(carried by Fibre Resampler and Spring Builder) or, where absent, the bone nearest "
            "on average to that end of the muscle. Advertises the motion's times as the "
            "pipeline's time steps. Adds the point array bone_weights (one column per bone, in "
            "bones.vtm order; one-hot for attached particles) and the field data bone_names, "
            "origin_bone and insertion_bone. The model's radius array is cleared of the rest "
            "bones as the Spring Builder clears it with its Bones input (a particle inside a "
            "bone at rest gets no sphere; no sphere reaches into a bone at rest), so the "
            "rest pose stays at rest whether or not the Spring Builder's Bones is connected; "
            "the point array in_bone_at_rest marks the particles inside a bone at rest (the "
            "solver keeps every other free particle out of the bones as solids).")
    INPUTS = (
        Port("Model", "vtkMultiBlockDataSet",
             "The mass-spring model in the rest pose, one block per muscle (Spring Builder)."),
        Port("Bones", "vtkMultiBlockDataSet",
             "bones.vtm: one closed triangle surface per bone in the rest pose, named after it."),
        Port("Motion", "vtkTable",
             "motion.csv as read by ParaView's CSV reader: columns time, bone, m00 … m23."),
        Port("Surfaces", "vtkMultiBlockDataSet",
             "Optional: the rest muscle surfaces (muscles.vtm), to show the rigid-only pose.",
             optional=True),
    )
    OUTPUTS = (
        Port("PosedModel", "vtkMultiBlockDataSet",
             "The model with posed particle positions; every input array kept, "
             "bone_weights added."),
        Port("PosedBones", "vtkMultiBlockDataSet", "The bones at the current time."),
        Port("PosedSurfaces", "vtkMultiBlockDataSet",
             "The muscle surfaces carried rigidly by their bones (empty without Surfaces)."),
    )
    PROPERTIES = (
        Property("Blending", "enum", DUAL_QUATERNION,
                 "How the transforms of a point's bones are combined. 'dual quaternion' "
                 "(Kavan et al. 2008) blends rigid transforms into a rigid transform and keeps "
                 "the muscle's volume at large joint angles; 'linear' averages the matrices, "
                 "which shrinks the muscle between bones turned far apart.",
                 choices=BLENDINGS, group="Blending"),
        Property("BonesPerPoint", "int", 2,
                 "How many of its nearest bones (by distance to the bone surfaces in the rest "
                 "pose) move each particle and surface vertex. 1 = the nearest bone only.",
                 minimum=1, group="Blending"),
        Property("FallOff", "double", 20.0,
                 "Distance scale F of the weights, mm. With d_1 <= d_2 <= ... a point's "
                 "distances to the bone surfaces and K = BonesPerPoint, bone k <= K gets "
                 "exp(-d_k/F) - exp(-d_(K+1)/F), the others 0, normalised to sum 1: a bone "
                 "F mm farther than another has about 1/e of its influence.",
                 minimum=1e-3, group="Blending"),
    )

    def __init__(self):
        super().__init__()
        # the motion read from the table and the rest pose, each kept with the key of the
        # inputs (and properties) it was computed from: reused while the key stays the same
        self._motion_key = self._motion = None
        self._rest_key = self._rest = None

    # ---- time -------------------------------------------------------------------------------
    def _motion_times(self) -> list:
        """The motion table's distinct finite times (s), read by updating its producer: input
        data does not exist yet in RequestInformation. Empty when there is no usable table;
        RequestData then reports why."""
        if self.GetNumberOfInputConnections(MOTION_PORT) == 0:
            return []
        conn = self.GetInputConnection(MOTION_PORT, 0)
        producer = conn.GetProducer()
        try:
            producer.Update(conn.GetIndex())
            table = producer.GetOutputDataObject(conn.GetIndex())
            if table is None:
                return []
            times = motion_rows_from_table(table)[0]
        except MuscleMSSError:
            return []
        return np.unique(times[np.isfinite(times)]).tolist()

    def RequestInformation(self, request, inInfo, outInfo):
        times = self._motion_times()
        for port in range(self.GetNumberOfOutputPorts()):
            info = outInfo.GetInformationObject(port)
            info.Remove(SDDP.TIME_STEPS())
            info.Remove(SDDP.TIME_RANGE())
            if times:
                info.Set(SDDP.TIME_STEPS(), times, len(times))
                info.Set(SDDP.TIME_RANGE(), [times[0], times[-1]], 2)
        return 1

    def _motion_file(self):
        """The file the motion table was read from, when its producer is a file reader
        (ParaView's CSV reader in a pipeline built by hand), else None."""
        if self.GetNumberOfInputConnections(MOTION_PORT) == 0:
            return None
        producer = self.GetInputConnection(MOTION_PORT, 0).GetProducer()
        name = producer.GetFileName() if hasattr(producer, "GetFileName") else None
        return name if isinstance(name, str) and os.path.isfile(name) else None

    def _read_motion(self, table, bone_names):
        key = (table.GetAddressAsString("vtkObjectBase"), table.GetMTime(), tuple(bone_names))
        if key != self._motion_key:
            path = self._motion_file()
            if path is not None:
                # a CSV reader reads an empty cell as 0 (a bone moved by tens of mm): name it
                check_motion_cells(path)
            times, bones, values = motion_rows_from_table(table)
            self._motion = motion_from_rows(times, bones, values, known_bones=bone_names)
            self._motion_key = key
        return self._motion

    # ---- rest pose: positions and weights, once per rest input --------------------------------
    def _rest_pose(self, model, bones, surfaces, model_items, bone_items, surface_items):
        """Rest positions (N, 3) and blend weights (N, B) of the model's and the surfaces' points,
        every block's ``(start, stop)`` in them, and the bones' rest vertices; recomputed only
        when an input or a weight property changes."""
        key = (_tree_stamp(model), _tree_stamp(bones), _tree_stamp(surfaces),
               self.value("BonesPerPoint"), self.value("FallOff"))
        if key == self._rest_key:
            return self._rest
        self._rest_key = self._rest = None
        bone_surfaces, labels = [], []
        for name, block in bone_items:
            labels.append(f"{BONES_FILE} block '{name}'")
            bone_surfaces.append((V.points_of(block), V.triangles_of(block, where=labels[-1])))
        model_rest = []
        for name, block in model_items:
            where = f"Model block '{name}'"
            rest = V.point_array(block, A.REST_POSITION, where=where, dtype=np.float64)
            if rest.ndim != 2 or rest.shape[1] != 3 or len(rest) != block.GetNumberOfPoints():
                raise MuscleMSSError(f"{where}: array '{A.REST_POSITION}' must have 3 components "
                                     "and one tuple per particle")
            model_rest.append(_finite(rest, where))
        clearance = _bone_clearance(model_items, model_rest, bones)
        surface_rest = [_finite(V.points_of(block), f"Surfaces block '{name}'")
                        for name, block in surface_items]
        every = model_rest + surface_rest
        points = np.concatenate(every) if every else np.zeros((0, 3))
        self.progress(0.1)
        ends = np.cumsum([len(r) for r in every], dtype=np.int64)
        ranges = list(zip(np.concatenate([[0], ends[:-1]]), ends))
        bone_names = [name for name, _ in bone_items]
        attached, ends = [], []
        for (name, block), rest in zip(model_items, model_rest):
            bones_of, names = _attached_bones(block, rest, bone_names, bone_surfaces, labels,
                                              f"Model block '{name}'")
            attached.append(bones_of)
            ends.append(names)
        # Surface vertices are never attached: they follow the blend.
        attached = np.concatenate(attached + [np.full(sum(map(len, surface_rest)), -1)])
        # All blocks in one array: one parallel kernel launch for the weights and, per time,
        # for the blend (a launch per block costs more than the blend of a block).
        weights = bone_weights(points, bone_surfaces, self.value("BonesPerPoint"),
                               self.value("FallOff"), labels)
        rows = np.flatnonzero(attached >= 0)
        weights[rows] = 0.0
        weights[rows, attached[rows]] = 1.0
        self._rest = {
            "bones": [v for v, _ in bone_surfaces],
            "points": points,
            "weights": weights,
            "attached": {b: np.flatnonzero(attached == b) for b in np.unique(attached[rows])},
            "ends": ends,
            "clearance": clearance,
            "model": ranges[:len(model_rest)],
            "surfaces": ranges[len(model_rest):],
        }
        # the point arrays every posed block gets, made once: the same VTK arrays at every
        # time point let the solver know its model's arrays unchanged (V.arrays_identity)
        self._rest["model arrays"] = [
            [V.shared_array(A.BONE_WEIGHTS, weights[start:stop])]
            + ([] if radii is None else [V.shared_array(A.RADIUS, radii)])
            + [V.shared_array(A.IN_BONE_AT_REST, inside.astype(np.uint8))]
            for (start, stop), (radii, inside) in zip(self._rest["model"], clearance)]
        self._rest["surface arrays"] = [
            [V.shared_array(A.BONE_WEIGHTS, weights[start:stop])]
            for start, stop in self._rest["surfaces"]]
        self._rest_key = key
        return self._rest

    # ---- execution ----------------------------------------------------------------------------
    def execute(self, inputs, outputs):
        model, bones, table, surfaces = inputs
        bone_items = V.polydata_blocks(bones, BONES_FILE)
        if not bone_items:
            raise MuscleMSSError(f"{BONES_FILE}: has no blocks; the pose needs at least one bone")
        bone_names = [name for name, _ in bone_items]
        motion = self._read_motion(table, bone_names)
        model_items = V.polydata_blocks(model, "Model")
        surface_items = V.polydata_blocks(surfaces, "Surfaces") if surfaces is not None else []

        time = self.requested_time(default=float(motion.times[0]))
        matrices, used = pose_at(motion, time)
        if used != time:
            vtkOutputWindow.GetInstance().DisplayWarningText(
                f"{self.LABEL}: time {time:g} is outside the motion's time range "
                f"[{motion.times[0]:g}, {motion.times[-1]:g}]; showing the pose at {used:g}\n")

        rest = self._rest_pose(model, bones, surfaces, model_items, bone_items, surface_items)
        self.progress(0.6)
        posed_points = blend(rest["points"], rest["weights"], matrices, self.choice("Blending"))
        # Attached particles sit exactly where their bone's transform puts them.
        for b, rows in rest["attached"].items():
            posed_points[rows] = transform_rigid(rest["points"][rows], matrices[b])

        def posed(items, ranges, arrays):
            out = []
            for (name, block), (start, stop), shared in zip(items, ranges, arrays):
                moved = V.with_points(block, posed_points[start:stop])
                V.add_point_arrays(moved, shared)
                V.set_field(moved, A.BONE_NAMES, bone_names)
                out.append((name, moved))
            return out

        model_out = posed(model_items, rest["model"], rest["model arrays"])
        for (_, moved), ends in zip(model_out, rest["ends"]):
            for array, bone in ends.items():
                V.set_field(moved, array, bone)
        V.fill_multiblock(outputs[0], model_out)
        V.fill_multiblock(outputs[1], [
            (name, V.with_points(block, transform_rigid(points, matrices[b])))
            for b, ((name, block), points) in enumerate(zip(bone_items, rest["bones"]))])
        V.fill_multiblock(outputs[2], posed(surface_items, rest["surfaces"],
                                            rest["surface arrays"]))
        for out in outputs:
            out.GetInformation().Set(vtkDataObject.DATA_TIME_STEP(), time)
        self.progress(1.0)
