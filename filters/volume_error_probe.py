"""Volume-Error Probe: each deformed muscle's volume against its rest volume (paper §4.2).

Volumes by the divergence theorem (:func:`muscle_mss.core.volume.signed_volume`); the error is
``100 |V - V_rest| / V_rest`` %. The paper's method reached 2.71 % on average and counts up to
6 % as acceptable.
"""
from __future__ import annotations

import numpy as np

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.mesh_checks import surface_problems
from muscle_mss.core.volume import signed_volume, volume_error

from . import array_names as A
from . import vtk_arrays as V
from .base import MuscleFilter, Port
from .check_cache import rest_surface_problems

MEAN_ROW = "mean"
"""Name (``muscle`` column) of the table's last row."""
IN_BONE_COLUMNS = (A.NEW_IN_BONE_VERTICES, A.NEW_IN_BONE_DEPTH_MM, A.NEW_IN_BONE_VERTICES_AFTER,
                   A.NEW_IN_BONE_DEPTH_AFTER_MM)
"""Columns copied from the deformed surfaces' field data (MVC Surface Deformer with bones)."""
SURFACE_COLUMNS = IN_BONE_COLUMNS + (A.IN_OTHER_MUSCLE_VERTICES, A.IN_OTHER_MUSCLE_DEPTH_MM,
                                     A.CAGE_DRIFT_VERTICES, A.CAGE_DRIFT_MM)
"""Every column copied from the deformed surfaces' field data (NaN where a surface has none)."""


class VolumeErrorProbe(MuscleFilter):
    """Rest volume, deformed volume and volume error of every muscle."""

    LABEL = "Volume-Error Probe"
    HELP = ("Measures each deformed muscle's enclosed volume (divergence theorem) against its "
            "rest surface's: field data rest_volume, volume (mm^3) and volume_error_pct "
            "(100 |V - V_rest| / V_rest) on each surface, and a table with one row per muscle "
            "and a last row 'mean' holding the mean of the muscles' rest volumes, volumes and "
            "errors (the mean error, not the error of the mean volume). The paper reached "
            "2.71 % and accepts up to 6 %. The table also carries, from the MVC Surface "
            "Deformer's field data, the surface vertices newly inside a bone and their deepest "
            "depth (mm) before and after its push out (NaN when it had no bones connected).")
    INPUTS = (
        Port("DeformedSurfaces", "vtkMultiBlockDataSet",
             "the deformed muscle surfaces (MVC Surface Deformer), closed triangle meshes"),
        Port("RestSurfaces", "vtkMultiBlockDataSet",
             "muscles.vtm: the rest surfaces, blocks named as the deformed ones"),
    )
    OUTPUTS = (
        Port("Surfaces", "vtkMultiBlockDataSet",
             "the deformed surfaces with field data rest_volume, volume (mm^3), "
             "volume_error_pct"),
        Port("VolumeTable", "vtkTable",
             "columns muscle, rest_volume, volume (mm^3), volume_error_pct, "
             "new_in_bone_vertices, new_in_bone_depth_mm, new_in_bone_vertices_after_push, "
             "new_in_bone_depth_after_push_mm, in_other_muscle_vertices, "
             "in_other_muscle_depth_mm, cage_drift_vertices, cage_drift_mm; one row "
             "per muscle, then a row 'mean' of the "
             "means of each column"),
    )
    PROPERTIES = ()

    def __init__(self):
        super().__init__()
        self._rest = {}     # muscle name -> (block identity, triangles (m, 3), volume mm^3)

    def rest_surface(self, name, rest):
        """``(triangles (m, 3), volume mm^3)`` of the muscle's rest surface block ``rest``,
        checked (closed, manifold, outward); remembered per block (its VTK object and
        modification time, which its points and cells raise): the scene's rest surfaces are the
        same at every time point."""
        where = f"RestSurfaces block '{name}'"
        if not rest.IsA("vtkPolyData"):
            raise MuscleMSSError(f"{where}: is a {rest.GetClassName()}; a muscle surface must "
                                 "be a triangle vtkPolyData")
        identity = (rest.__this__, rest.GetMTime())
        known = self._rest.get(name)
        if known is None or known[0] != identity:
            points, triangles = V.points_of(rest), V.triangles_of(rest, where)
            problems = rest_surface_problems(points, triangles)
            if problems:
                raise MuscleMSSError(f"{where} {problems[0]}; a volume needs a closed, "
                                     "outward-oriented surface")
            known = self._rest[name] = (identity, triangles, signed_volume(points, triangles))
        return known[1:]

    def execute(self, inputs, outputs):
        deformed_blocks = V.blocks(inputs[0], where="DeformedSurfaces")
        rest_blocks = dict(V.blocks(inputs[1], where="RestSurfaces"))
        if not deformed_blocks:
            raise MuscleMSSError("DeformedSurfaces: has no muscle blocks; connect the MVC "
                                 "Surface Deformer's DeformedSurfaces output")
        names, rest_volumes, volumes, errors, surfaces = [], [], [], [], []
        in_bone = {key: [] for key in SURFACE_COLUMNS}
        for i, (name, block) in enumerate(deformed_blocks):
            if name not in rest_blocks:
                raise MuscleMSSError(f"RestSurfaces: has no block '{name}'; every deformed "
                                     "muscle needs its rest surface (block names must match)")
            rest_triangles, rest_volume = self.rest_surface(name, rest_blocks[name])
            volume = _volume(name, block, rest_triangles)
            error_pct = 100.0 * volume_error(volume, rest_volume)
            out = block.NewInstance()
            out.ShallowCopy(block)
            V.set_field(out, A.REST_VOLUME, rest_volume)
            V.set_field(out, A.VOLUME, volume)
            V.set_field(out, A.VOLUME_ERROR_PCT, error_pct)
            names.append(name)
            rest_volumes.append(rest_volume)
            volumes.append(volume)
            errors.append(error_pct)
            for key, values in in_bone.items():
                values.append(float(V.field(block, key, default=np.nan)))
            surfaces.append((name, out))
            self.progress((i + 1) / len(deformed_blocks))
        V.fill_multiblock(outputs[0], surfaces)
        V.fill_table(outputs[1], {
            A.MUSCLE: names + [MEAN_ROW],
            A.REST_VOLUME: np.append(rest_volumes, np.mean(rest_volumes)),
            A.VOLUME: np.append(volumes, np.mean(volumes)),
            A.VOLUME_ERROR_PCT: np.append(errors, np.mean(errors)),
            **{key: np.append(values, np.mean(values)) for key, values in in_bone.items()},
        })


def _volume(name, deformed, rest_triangles):
    """The volume (mm^3) of one muscle's deformed surface, checked (its own checks when its
    triangles are not the rest surface's ``rest_triangles``)."""
    where = f"DeformedSurfaces block '{name}'"
    if not deformed.IsA("vtkPolyData"):
        raise MuscleMSSError(f"{where}: is a {deformed.GetClassName()}; a muscle surface must "
                             "be a triangle vtkPolyData")
    points = V.points_of(deformed)
    triangles = V.triangles_of(deformed, where)
    if not np.isfinite(points).all():
        raise MuscleMSSError(f"{where}: has NaN or infinite coordinates")
    if not np.array_equal(triangles, rest_triangles):
        # Not the rest mesh moved (as the MVC Surface Deformer makes): check it on its own.
        problems = surface_problems(points, triangles)
        if problems:
            raise MuscleMSSError(f"{where} {problems[0]}; a volume needs a closed, "
                                 "outward-oriented surface")
    return signed_volume(points, triangles)
