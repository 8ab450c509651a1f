"""MVC Surface Deformer: the muscle surfaces and fibres follow the solved particles (paper §3.2).

Each muscle's cage (:mod:`muscle_mss.core.cage`) is built from the rest model's boundary
particles, and the mean value coordinates (:mod:`muscle_mss.core.mvc`) of every rest surface
vertex are computed once. They are kept while the rest inputs (RestSurfaces, RestModel) are
unchanged: a new time point changes only SolvedModel, and each deformed vertex is then one
weighted sum of the current cage positions.

Memory: the weights are computed in float64 one muscle at a time (8 x surface vertices x cage
vertices bytes) and kept dense as float32, applied to the cage's displacement from rest (see
:class:`MuscleBinding`). The full demo at N = 80 (about 1100 surface vertices, 2312 cage
vertices per muscle) keeps about 10 MB per muscle, 130 MB for its 13 muscles.

Surfaces kept out of bones. The cage follows the collision spheres, and between
them the surface can sink into a bone. With the optional RestBones and PosedBones inputs, each
bone gets a signed distance field (:mod:`muscle_mss.core.bones.distance`, sampled once in the
rest frame, rebuilt only when RestBones or BoneFieldSpacing change) and every deformed vertex
that is inside a posed bone but was outside that bone at rest is pushed out onto its surface
along the distance gradient (``KeepOutOfBones``); vertices inside a bone at rest (a muscle
pressed against its bone) are left alone; the push ends on the bone's triangles
(:mod:`muscle_mss.core.bones.exact_distance`: the fields are millimetres off next to thin
forearm bones), and inside and outside are decided by the exact distance near each surface.
Each bone's posed transform is fitted from its rest and posed vertices. Reported per muscle:
the point array ``new_in_bone_depth`` and the field data ``new_in_bone_vertices`` / ``new_in_bone_depth_mm`` (before the push) and
``new_in_bone_vertices_after_push`` / ``new_in_bone_depth_after_push_mm``; a vertex counts as
inside when deeper than :data:`INSIDE_TOLERANCE`. Every surface also reports the field data
``in_other_muscle_vertices`` / ``in_other_muscle_depth_mm``: its vertices (as written) inside
another muscle's deformed surface, and the deepest (:mod:`muscle_mss.core.contacts.muscle_overlap`).
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from muscle_mss.core import mvc
from muscle_mss.core.bones.distance import BoneFieldSet
from muscle_mss.core.fibre_shortening import kept_shape_lengths
from muscle_mss.core.bones.exact_distance import exact_signed_distances
from muscle_mss.core.bones.field_sampling import DEFAULT_SPACING, bone_distance_field
from muscle_mss.core.cage import (Cage, fibre_polylines, muscle_cage, polyline_chords,
                                  polyline_lengths)
from muscle_mss.core.cage_drift import CAGE_DRIFT_LIMIT, cage_distances, cage_drift
from muscle_mss.core.disk_store import DiskStore, array_digest
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.contacts.muscle_overlap import vertices_in_other_muscles
from muscle_mss.core.mvc import bounded_coordinates, mvc_deform
from muscle_mss.core.surface_normals import point_normals
from muscle_mss.core.bones.triangle_distance import prepared_surface

from . import array_names as A
from . import vtk_arrays as V
from .base import MuscleFilter, Port
from .bone_sets import (INSIDE_TOLERANCE, cached_bone_field, composed_transforms,
                        field_surface, keep_out_of_bones, posed_bone_transforms)
from .frame_cache import KEYED_FILTERS
from .pipeline_frames import SurfaceFrames, pipeline_frames
from muscle_mss.core.properties import Property

# Share of the progress bar taken by the weights when they are (re)computed.
_WEIGHTS_PROGRESS = 0.9

#: Each muscle's weights kept on disk between runs and sessions, keyed by its rest cage and rest
#: surface bitwise (``MUSCLE_MSS_MVC_WEIGHTS``: another folder, or ``off``): computing them is
#: most of the deformer's first time point (0.44 s for the demo thigh at N = 20, 1.45 s at
#: N = 80), reading them back a few milliseconds. At N = 80 a demo muscle's file is 10 MB.
WEIGHTS_STORE = DiskStore("mvc-weights", "MUSCLE_MSS_MVC_WEIGHTS",
                          (os.path.abspath(mvc.__file__),), max_files=128)
#: How each muscle's weights were obtained, over this process: "computed" or "loaded" (read from
#: :data:`WEIGHTS_STORE`).
weight_counts = {"computed": 0, "loaded": 0}


def stored_weights(cage_points, cage_triangles, points, where) -> np.ndarray:
    """The float32 mean value coordinates (v, m) of ``points`` (v, 3) w.r.t. the cage, read from
    :data:`WEIGHTS_STORE` when an earlier run computed them, else computed and stored."""
    key = array_digest(cage_points, cage_triangles, points)
    stored = WEIGHTS_STORE.load(key, ("weights",))
    if stored is not None:
        weights = stored["weights"]
        if weights.dtype == np.float32 and weights.shape == (len(points), len(cage_points)):
            weight_counts["loaded"] += 1
            return weights
    weights = bounded_coordinates(cage_points, cage_triangles, points,
                                  where=where).astype(np.float32)
    weight_counts["computed"] += 1
    WEIGHTS_STORE.save(key, {"weights": weights})
    return weights


@dataclass(frozen=True)
class MuscleBinding:
    """What one muscle's deformation needs from the rest inputs, computed once.

    ``weights`` (v, m) float32: MVC of the v rest surface vertices w.r.t. the m cage vertices
    (``4 v m`` bytes), applied to the cage's displacement from ``rest_cage`` (m, 3) mm (exact at
    rest; rounding about 1e-7 of the displacement, where float64 weights would double the
    memory read every time point: 5 of the deformer's 30 ms at N = 20); ``order``,
    ``offsets``, ``fibre_ids``: the fibres as from
    :func:`~muscle_mss.core.cage.fibre_polylines`; ``fibre_grid``: each fibre's grid cell, a
    VTK cell array shared by every time point's fibres (None when the model has none);
    ``rest_lengths``, ``rest_chords`` (F,) mm: the fibres' lengths and the distances between
    their ends at rest; ``triangles`` (t, 3) int64: the surface's; ``fibres``: the fibre
    polylines at rest with what does not change over time (cells, fibre_id, fibre_index,
    muscle_name), which each time point copies shallowly and moves; ``cage_distance`` (v,) mm:
    each rest vertex's distance to the rest cage (:mod:`muscle_mss.core.cage_drift`).
    """

    surface: object
    rest_points: np.ndarray
    rest_positions: np.ndarray
    cage: Cage
    rest_cage: np.ndarray
    weights: np.ndarray
    order: np.ndarray
    offsets: np.ndarray
    fibre_ids: np.ndarray
    fibre_grid: object
    rest_lengths: np.ndarray
    rest_chords: np.ndarray
    triangles: np.ndarray
    fibres: object
    cage_distance: np.ndarray


class MVCSurfaceDeformer(MuscleFilter):
    """Deformed muscle surfaces (by mean value coordinates) and fibres from the solved model.

    ``weight_computations`` counts how many times the weights were computed: once, and again
    only after a change of RestSurfaces or RestModel.

    Frame cache: fed by the scene's readers through the Muscle MSS filters, the deformed
    surface points and their reports (the push out of the bones, the drift, the vertices in
    other muscles: most of a frame's cost) are kept in the MSS Collision Solver's frame cache
    folder (its ``FrameCache``) under the solver's key and this filter's properties
    (:class:`~muscle_mss.filters.pipeline_frames.SurfaceFrames`), or in ``frames`` where an
    application sets one (``muscle-mss run``: its ``--cache``). ``frame_counts`` counts the
    frames loaded and computed.
    """

    frames = None

    LABEL = "MVC Surface Deformer"
    HELP = ("Moves each rest muscle surface with its particles: every surface vertex keeps its "
            "mean value coordinates (Ju, Schaefer and Warren 2005) with respect to a cage "
            "through the muscle's boundary particles (the lattice surface when the fibres have "
            "a fibre_grid, else the convex hull of the boundary particles). The coordinates are "
            "computed once from the rest surfaces and the rest model and reused at every time "
            "point. Outputs the deformed surfaces with recomputed normals and point data "
            "displacement (mm), and each muscle's fibres as polylines through its particles "
            "with cell data fibre_length (mm) and fibre_strain (length / rest length - 1). "
            "With RestBones (bones.vtm) and PosedBones (the Rigid Pose Transform's second "
            "output) connected, vertices that end inside a posed bone but were outside it at "
            "rest are pushed out onto the bone's surface (KeepOutOfBones; a signed distance "
            "field per bone, built once), and each surface reports them: point data "
            "new_in_bone_depth, field data new_in_bone_vertices and new_in_bone_depth_mm "
            "(before the push), new_in_bone_vertices_after_push and "
            "new_in_bone_depth_after_push_mm. Every surface also reports how far each vertex "
            "left its cage (point data cage_drift, mm: its distance to the cage through the "
            "boundary particles now minus at rest; field data cage_drift_mm, the largest, and "
            f"cage_drift_vertices, how many drifted more than {CAGE_DRIFT_LIMIT:g} mm: there "
            "the surface does not follow the particles around it).")
    INPUTS = (
        Port("SolvedModel", "vtkMultiBlockDataSet",
             "the MSS Collision Solver's model: one block per muscle, points = current "
             "particle positions, point data rest_position, fibre_id, fibre_index"),
        Port("RestSurfaces", "vtkMultiBlockDataSet",
             "muscles.vtm: the closed rest surface of each muscle"),
        Port("RestModel", "vtkMultiBlockDataSet",
             "the Spring Builder's model (rest pose): point data rest_position, fibre_id, "
             "fibre_index, boundary, optional fibre_grid; unchanged over time, so the "
             "coordinates computed from it are kept"),
        Port("RestBones", "vtkMultiBlockDataSet",
             "Optional, with PosedBones: bones.vtm, the rest bone surfaces; deformed vertices "
             "are then kept out of the bones they were outside at rest", optional=True),
        Port("PosedBones", "vtkMultiBlockDataSet",
             "Optional, with RestBones: the Rigid Pose Transform's PosedBones (the same bones "
             "at the current time)", optional=True),
    )
    OUTPUTS = (
        Port("DeformedSurfaces", "vtkMultiBlockDataSet",
             "the rest surfaces' triangles at the deformed positions, with normals and point "
             "data displacement (deformed - rest, mm)"),
        Port("DeformedFibres", "vtkMultiBlockDataSet",
             "one polyline per fibre through its particles, cell data fibre_id, fibre_length "
             "(mm), fibre_strain, fibre_grid when present"),
    )
    PROPERTIES = (
        Property("KeepOutOfBones", "bool", True,
                 "Push deformed surface vertices that end inside a posed bone, but were outside "
                 "it at rest, out onto the bone's surface (needs RestBones and PosedBones). Off: "
                 "they are only counted.", group="Bones"),
        Property("BoneFieldSpacing", "double", DEFAULT_SPACING,
                 "Grid step (mm) of each bone's signed distance field near its surface; the "
                 "field is exact on flat bone and off by about spacing^2 / (8 R) where the bone "
                 "curves with radius R. Memory and time grow as 1 / spacing^3 (1 mm: 6-9 MiB "
                 "and seconds per bone of the demo thigh).", minimum=0.25, group="Bones"),
    )

    def __init__(self):
        super().__init__()
        self._rest_key = None
        self._bindings = None
        self.weight_computations = 0
        self._bone_key = None
        self._bones = None
        self.field_computations = 0
        self._outside_key = None
        self._outside = None
        self.frame_counts = {"loaded": 0, "computed": 0}
        self._frames = (None, None)     # (what they were made for, SurfaceFrames or None)
        self._scene = (None, None)      # (the readers' files and outputs, their digest)
        self._frames_note = None

    # ---- the cached bone side ------------------------------------------------------------------
    def bone_fields(self, rest_bones):
        """``(BoneFieldSet, {bone name: rest vertices (n, 3) mm}, frames (b, 3, 4))`` of the rest
        bones, built only when they (or BoneFieldSpacing) changed since the last call; a frame
        takes its field's points to the rest bone. At the default spacing the fields come from
        the rigid-bone cache (:func:`~muscle_mss.filters.bone_sets.cached_bone_field`) that
        the Rigid Pose Transform and the MSS Collision Solver sample them into, so a pipeline
        samples each bone once (6-8 s for the demo thigh's three bones), not twice."""
        key = (_modification_key(rest_bones, "RestBones"), self.value("BoneFieldSpacing"))
        if key != self._bone_key:
            items = V.polydata_blocks(rest_bones, "RestBones", "a bone's triangle surface")
            if not items:
                raise MuscleMSSError("RestBones: has no blocks; connect bones.vtm")
            spacing = self.value("BoneFieldSpacing")
            fields, rest_points, frames, surfaces = [], {}, [], []
            for i, (name, block) in enumerate(items):
                where = f"RestBones block '{name}'"
                rest_points[name] = V.points_of(block)
                triangles = V.triangles_of(block, where)
                if spacing == DEFAULT_SPACING:
                    field, frame = cached_bone_field(rest_points[name], triangles, where)
                    surfaces.append(field_surface(field))
                else:
                    field = bone_distance_field(rest_points[name], triangles, spacing=spacing,
                                                where=where)
                    frame = np.eye(3, 4)
                    surfaces.append(prepared_surface(rest_points[name], triangles, where))
                fields.append(field)
                frames.append(frame)
                if self.progress((i + 1) / len(items)):
                    raise MuscleMSSError("aborted while sampling the bones' distance fields")
            self._bones = (BoneFieldSet.pack(fields, list(rest_points), surfaces), rest_points,
                           np.array(frames).reshape(-1, 3, 4))
            self._bone_key = key
            self.field_computations += 1
        return self._bones

    def _outside_at_rest(self, bindings, fields, frames):
        """``{muscle: (v, b) bool}``: which rest surface vertices are outside which bone."""
        key = (self._rest_key, self._bone_key)
        if key != self._outside_key:
            self._outside = {name: exact_signed_distances(fields, b.rest_points, frames)
                             >= -INSIDE_TOLERANCE for name, b in bindings.items()}
            self._outside_key = key
        return self._outside

    # ---- the cached rest-pose side -----------------------------------------------------------
    def bindings(self, rest_surfaces, rest_model) -> dict:
        """``{muscle name: MuscleBinding}`` for the rest inputs, computed only when they changed
        since the last call (key: their modification times)."""
        key = (_modification_key(rest_surfaces, "RestSurfaces"),
               _modification_key(rest_model, "RestModel"))
        if key != self._rest_key:
            self._bindings = self._bind(rest_surfaces, rest_model)
            self._rest_key = key
            self.weight_computations += 1
        return self._bindings

    def _bind(self, rest_surfaces, rest_model) -> dict:
        surfaces = dict(V.blocks(rest_surfaces, where="RestSurfaces"))
        models = V.blocks(rest_model, where="RestModel")
        if not models:
            raise MuscleMSSError("RestModel: has no muscle blocks; connect the Spring Builder")
        bindings = {}
        for i, (name, model) in enumerate(models):
            if name not in surfaces:
                raise MuscleMSSError(f"RestSurfaces: has no block '{name}'; every muscle of "
                                     "RestModel needs its rest surface (block names must match)")
            bindings[name] = _bind_muscle(name, surfaces[name], model)
            if self.progress(_WEIGHTS_PROGRESS * (i + 1) / len(models)):
                raise MuscleMSSError("aborted while computing the mean value coordinates")
        extra = [n for n in surfaces if n not in bindings]
        if extra:
            raise MuscleMSSError(f"RestSurfaces block '{extra[0]}': RestModel has no muscle of "
                                 "that name; block names must match")
        return bindings

    # ---- every time point ----------------------------------------------------------------------
    def _surface_frames(self):
        """Where this frame's surfaces are kept: ``frames``, else the solver's frame cache
        folder when the pipeline's frames are keyed, else None."""
        if self.frames is not None:
            return self.frames
        return pipeline_frames(self, KEYED_FILTERS, SurfaceFrames)

    def execute(self, inputs, outputs):
        solved, rest_surfaces, rest_model, rest_bones, posed_bones = inputs
        bindings = self.bindings(rest_surfaces, rest_model)
        if (rest_bones is None) != (posed_bones is None):
            raise MuscleMSSError("connect both RestBones (bones.vtm) and PosedBones (the Rigid "
                                 "Pose Transform's PosedBones), or neither")
        blocks = V.blocks(solved, where="SolvedModel")
        names = [n for n, _ in blocks]
        for name in bindings:
            if name not in names:
                raise MuscleMSSError(f"SolvedModel: has no block '{name}'; it must have the "
                                     "same muscles as RestModel")
        for name in names:
            if name not in bindings:
                raise MuscleMSSError(f"SolvedModel block '{name}': RestModel has no muscle of "
                                     "that name; block names must match")
        points = [_deformed_points(name, block, bindings[name]) for name, block in blocks]
        frames, time = self._surface_frames(), self.requested_time()
        stored = frames.load(time) if frames is not None and time is not None else None
        if stored is not None and [len(d) for d in stored[0]] == [len(p) for _, p in points]:
            deformed, reports = stored
            self.frame_counts["loaded"] += 1
        else:
            deformed, reports = self._deformed(names, points, bindings, rest_bones,
                                               posed_bones)
            self.frame_counts["computed"] += 1
            if frames is not None and time is not None:
                frames.save(time, (deformed, reports))
        surfaces, fibres = [], []
        for name, (current, _), surface_points, report in zip(names, points, deformed, reports):
            surface, polylines = _muscle_outputs(name, bindings[name], current, surface_points,
                                                 report)
            surfaces.append((name, surface))
            fibres.append((name, polylines))
        V.fill_multiblock(outputs[0], surfaces)
        V.fill_multiblock(outputs[1], fibres)
        self.progress(1.0)

    def _deformed(self, names, points, bindings, rest_bones, posed_bones) -> tuple:
        """``(surface points, reports)`` per muscle: the deformed surfaces ``points`` gives
        (``(particles, surface vertices)`` per muscle) pushed out of the bones they newly
        entered, and what each reports (the push, the cage drift, the vertices inside other
        muscles)."""
        deformed = [d for _, d in points]
        reports = [{} for _ in names]
        if rest_bones is not None:
            fields, rest_points, frames = self.bone_fields(rest_bones)
            outside = self._outside_at_rest(bindings, fields, frames)
            deformed, reports = keep_out_of_bones(
                deformed, fields, composed_transforms(posed_bone_transforms(rest_points, posed_bones), frames),
                np.concatenate([outside[n] for n in names]), self.value("KeepOutOfBones"))
        for name, (current, surface_points), report in zip(names, points, reports):
            report.update(_drift_report(bindings[name], current, surface_points))
        in_other, depth = vertices_in_other_muscles(
            [(d, bindings[name].triangles) for name, d in zip(names, deformed)],
            [bindings[name].rest_points for name in names])
        for report, count, deepest in zip(reports, in_other, depth):
            report.update({A.IN_OTHER_MUSCLE_VERTICES: int(count),
                           A.IN_OTHER_MUSCLE_DEPTH_MM: float(deepest)})
        return deformed, reports


def _modification_key(data, where):
    """Modification times of a multiblock and its leaves: any change to the data changes it."""
    return (data.GetMTime(),) + tuple(leaf.GetMTime() for _, leaf in V.blocks(data, where))


def _bind_muscle(name, surface, model) -> MuscleBinding:
    where = f"RestModel block '{name}'"
    rest_positions = V.point_array(model, A.REST_POSITION, where, dtype=np.float64).reshape(-1, 3)
    if len(rest_positions) == 0:
        raise MuscleMSSError(f"{where}: has no particles")
    boundary = V.point_array(model, A.BOUNDARY, where)
    fibre_id = V.point_array(model, A.FIBRE_ID, where)
    fibre_index = V.point_array(model, A.FIBRE_INDEX, where)
    fibre_grid = V.point_array(model, A.FIBRE_GRID, where, required=False)
    if not np.isfinite(rest_positions).all():
        raise MuscleMSSError(f"{where}: rest_position has NaN or infinite values")
    cage = muscle_cage(rest_positions, boundary, fibre_id, fibre_index, fibre_grid, where)
    surface_where = f"RestSurfaces block '{name}'"
    V.require_polydata(surface, surface_where, "a muscle's triangle surface")
    rest_points = V.points_of(surface)
    triangles = V.triangles_of(surface, surface_where)
    if len(rest_points) == 0 or len(triangles) == 0:
        raise MuscleMSSError(f"{surface_where}: has no triangles; a muscle surface must be a "
                             "closed triangle mesh")
    if not np.isfinite(rest_points).all():
        bad = int(np.flatnonzero(~np.isfinite(rest_points).all(axis=1))[0])
        raise MuscleMSSError(f"{surface_where}: point {bad} has a NaN or infinite coordinate; "
                             "every coordinate must be finite")
    rest_cage = np.ascontiguousarray(rest_positions[cage.vertices])
    weights = stored_weights(rest_cage, cage.triangles, rest_points, f"{where}: cage")
    order, offsets, fibre_ids = fibre_polylines(fibre_id, fibre_index, where)
    rest_lengths = polyline_lengths(rest_positions, order, offsets)
    short = np.flatnonzero(rest_lengths <= 0.0)
    if len(short):
        raise MuscleMSSError(f"{where}: fibre {int(fibre_ids[short[0]])} has zero rest length; "
                             "a fibre needs at least two distinct particles")
    grid = None if fibre_grid is None else V.shared_array(
        A.FIBRE_GRID, np.asarray(fibre_grid, dtype=np.int32).reshape(-1, 2)[order[offsets[:-1]]])
    fibres = V.make_polydata(rest_positions[order], line_offsets=offsets,
                             line_connectivity=np.arange(len(order)))
    V.set_cell_array(fibres, A.FIBRE_ID, fibre_ids.astype(np.int32))
    V.set_point_array(fibres, A.FIBRE_INDEX,
                      (np.arange(len(order)) - np.repeat(offsets[:-1], np.diff(offsets)))
                      .astype(np.int32))
    V.set_field(fibres, A.MUSCLE_NAME, name)
    return MuscleBinding(surface, rest_points, rest_positions, cage, rest_cage, weights, order,
                         offsets, fibre_ids, grid, rest_lengths,
                         polyline_chords(rest_positions, order, offsets),
                         np.ascontiguousarray(triangles),
                         fibres, cage_distances(rest_cage, cage.triangles, rest_points))


def _deformed_points(name, block, binding: MuscleBinding):
    """``(particles (n, 3), surface vertices (v, 3))`` mm of one muscle's solved ``block``."""
    where = f"SolvedModel block '{name}'"
    current = V.points_of(block)
    if len(current) != len(binding.rest_positions):
        raise MuscleMSSError(f"{where}: has {len(current)} particles but RestModel has "
                             f"{len(binding.rest_positions)}; connect the model that was solved")
    if not np.isfinite(current).all():
        raise MuscleMSSError(f"{where}: particle positions have NaN or infinite values")
    rest = V.point_array(block, A.REST_POSITION, where, required=False, dtype=np.float64)
    if rest is not None and not np.array_equal(rest, binding.rest_positions):
        scale = 1e-9 * max(1.0, float(np.abs(binding.rest_positions).max()))
        if rest.shape != binding.rest_positions.shape or \
                not np.allclose(rest, binding.rest_positions, rtol=0.0, atol=scale):
            raise MuscleMSSError(f"{where}: its rest_position differs from RestModel's; the "
                                 "solved model must come from the same Spring Builder output")
    return current, binding.rest_points + mvc_deform(
        binding.weights, current[binding.cage.vertices] - binding.rest_cage)


def _drift_report(binding: MuscleBinding, current, deformed) -> dict:
    """What one muscle's surface reports of its vertices' cage drift (before any push out of
    the bones): per vertex and the largest (mm), and how many exceed the limit."""
    drift = cage_drift(current[binding.cage.vertices], binding.cage.triangles, deformed,
                       binding.cage_distance)
    return {A.CAGE_DRIFT: drift, A.CAGE_DRIFT_MM: float(max(drift.max(initial=0.0), 0.0)),
            A.CAGE_DRIFT_VERTICES: int((drift > CAGE_DRIFT_LIMIT).sum())}


def _muscle_outputs(name, binding: MuscleBinding, current, deformed, report):
    """The deformed surface (``deformed`` (v, 3) mm, with normals, displacement and the
    ``report``'s arrays and fields) and the fibre polylines through ``current`` (n, 3) mm."""
    surface = V.with_points(binding.surface, deformed)
    V.set_normals(surface, point_normals(deformed, binding.triangles))
    V.set_point_array(surface, A.DISPLACEMENT, deformed - binding.rest_points)
    for key, value in report.items():
        if key in (A.NEW_IN_BONE_DEPTH, A.CAGE_DRIFT):
            V.set_point_array(surface, key, value)
        else:
            V.set_field(surface, key, value)
    V.set_field(surface, A.MUSCLE_NAME, name)

    polylines = V.with_points(binding.fibres, current[binding.order])
    lengths = polyline_lengths(current, binding.order, binding.offsets)
    V.set_cell_array(polylines, A.FIBRE_LENGTH, lengths)
    V.set_cell_array(polylines, A.FIBRE_STRAIN, lengths / binding.rest_lengths - 1.0)
    chords = polyline_chords(current, binding.order, binding.offsets)
    with np.errstate(divide="ignore", invalid="ignore"):   # a closed fibre has no chord
        V.set_cell_array(polylines, A.FIBRE_END_STRAIN, chords / binding.rest_chords - 1.0)
        V.set_cell_array(polylines, A.FIBRE_ARC_CHORD, lengths / chords)
        V.set_cell_array(polylines, A.FIBRE_BEND, lengths / chords * binding.rest_chords
                         / binding.rest_lengths)
    spanned = binding.rest_chords > 0.0
    ends = float((chords[spanned] / binding.rest_chords[spanned]).mean()) if spanned.any() else 1.0
    kept = kept_shape_lengths(binding.rest_positions, binding.order, binding.offsets, ends)
    V.set_cell_array(polylines, A.FIBRE_KEPT_SHAPE_STRAIN, kept / binding.rest_lengths - 1.0)
    if binding.fibre_grid is not None:
        polylines.GetCellData().AddArray(binding.fibre_grid)
    return surface, polylines
