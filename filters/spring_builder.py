"""Spring Builder: the mass-spring model of every muscle (DESIGN §5–6, paper §3.2–3.3).

Inputs: ``Particles`` (the Fibre Resampler's output), ``Surfaces`` (the rest muscle surfaces,
``muscles.vtm``, blocks named as the particles' blocks) and, optional, ``Bones`` (the rest bone
surfaces, ``bones.vtm``). Output ``Model``: the particle blocks in
the same order, each a vtkPolyData with

* points: the particles; cells: the springs, two-point line cells (each once, never from a
  particle to itself, never between muscles) with cell data ``rest_length``, ``stiffness``,
  ``damping``;
* point data: every numeric array of the input block, plus ``boundary``, ``radius`` (0 where not
  boundary) and ``mass`` (and ``rest_position`` from the points when the input lacks it);
* field data: the input block's field data, ``muscle_name`` and this filter's properties.

The rest pose is the ``rest_position`` array when present, else the points. Boundary particles
and radii follow :mod:`muscle_mss.core.radii`; the radii of all muscles are shrunk together so
that no two spheres of different muscles overlap in the rest pose (with either radius rule), and,
with ``Bones``, so that no muscle sphere overlaps a bone (its sphere set or its solid) in the
rest pose (:func:`~muscle_mss.filters.bone_sets.clear_of_bones`): DESIGN §6, no two spheres of
different objects overlap at rest. A particle inside a bone at rest (the scenes embed the ends
of some fibres in their attachment bone) gets no sphere: it belongs to the bone, and the solver
would push it out of it. The Rigid Pose Transform clears the radii of the bones again from its
own Bones input (clearing cleared radii changes nothing), so a pipeline built without this
filter's Bones input solves the same; without it this output's ``radius`` is not yet cleared,
and the filter warns.
"""
from __future__ import annotations

import numpy as np
from vtkmodules.vtkCommonCore import vtkOutputWindow

from muscle_mss.core import errors
from muscle_mss.core.errors import MuscleMSSError, first_problem
from muscle_mss.core.mesh_checks import surface_problems
from muscle_mss.core.radii import (boundary_from_grid, boundary_from_surface, shrink_radii,
                                   sphere_radii)
from muscle_mss.core.scene import BONES_FILE, MUSCLES_FILE, FibreSet, Scene, Surface
from muscle_mss.core.springs import (DELAUNAY_REACH, delaunay_springs, fibre_step,
                                     knn_springs, lattice_springs, rest_lengths)
from muscle_mss.core.validation import far_point_problem

from . import array_names as A
from . import vtk_arrays as V
from .base import MuscleFilter, Port
from .bone_sets import clear_of_bones
from .check_cache import placement_verdict
from muscle_mss.core.properties import Option, Property

LAYOUT_LATTICE_6, LAYOUT_LATTICE_26 = "lattice-6", "lattice-26"
LAYOUT_DELAUNAY, LAYOUT_KNN = "Delaunay", "k-NN"
LAYOUTS = (LAYOUT_LATTICE_6, LAYOUT_LATTICE_26, LAYOUT_DELAUNAY, LAYOUT_KNN)
DEFAULT_LAYOUT = LAYOUT_LATTICE_26
NO_BONES_WARNING = (
    "the Bones input is not connected, so this output's radius array is not cleared of the "
    "bones: muscle spheres that overlap a bone at rest keep their radius here. The Rigid Pose "
    "Transform clears them from its own Bones input before the solve, so the solved pose is the "
    "same; but this model fed to the MSS Collision Solver without the Rigid Pose Transform "
    "would push those spheres out even when nothing moves and crush a muscle. Connect bones.vtm "
    "(the reader that feeds the Rigid Pose Transform's Bones) to the Spring Builder's Bones "
    "input to see the radii the solver uses.")
LATTICE_NEIGHBOURHOOD = {LAYOUT_LATTICE_6: 6, LAYOUT_LATTICE_26: 26}
MIN_PARTICLES_PER_FIBRE = {LAYOUT_LATTICE_6: 8, LAYOUT_LATTICE_26: 8, LAYOUT_DELAUNAY: 8,
                           LAYOUT_KNN: 5}
"""The coarsest resolution N each layout supports, measured on the small demo scenes (the thigh
at t = 0.5 s, the arm at 130 degrees): below it a muscle's surface was carried up to
0.3-4.6 m off and its volume error reached 11-2767 % (lattice-26 at N = 3: 40 % and 418 mm on
the thigh, 753 % and 4.6 m on the arm); from it on, at most 5.4 % and 59 mm on the thigh and 31 %
(k-NN at N = 5; 28 % lattice-26 at N = 8) on the arm, whose default N = 20 gives 8.5 %."""
RESOLUTION_RULE = ("with fewer particles along the fibres the cage of boundary particles that "
                   "carries the muscle surface (mean value coordinates) is too coarse to follow "
                   "it, and surface points are flung far from the muscle")
PARTICLES = "particles"


def _field_names(dataset) -> list:
    fd = dataset.GetFieldData()
    return [fd.GetAbstractArray(i).GetName() for i in range(fd.GetNumberOfArrays())
            if fd.GetAbstractArray(i).GetName()]


def surface_mesh(surfaces: dict, name: str):
    """``(points (V, 3) float64 mm, triangles (T, 3) int64)`` of muscle ``name``'s rest
    surface, checked: triangles that refer to existing, finite points."""
    where = f"{MUSCLES_FILE} block '{name}'"
    surface = surfaces.get(name)
    if surface is None:
        raise MuscleMSSError(f"{MUSCLES_FILE} has no block '{name}'; the Surfaces input needs "
                             "the rest surface of every muscle of the Particles input")
    V.require_polydata(surface, where, "a muscle's triangle surface")
    triangles = V.triangles_of(surface, where)
    if len(triangles) == 0:
        raise MuscleMSSError(f"{where} has no triangles; a muscle surface must be a closed "
                             "triangle mesh")
    points = V.points_of(surface)
    if triangles.max() >= len(points):
        raise MuscleMSSError(f"{where} has triangles referring to missing points")
    if not np.isfinite(points[np.unique(triangles)]).all():
        raise MuscleMSSError(f"{where} has a NaN or infinite coordinate; every coordinate "
                             "must be finite")
    return points, triangles


def _checked_surface(block, where):
    """A :class:`Surface` of a block, or None when it is not a closed, oriented triangle
    surface (the filters that need one say so; a winding number around it means nothing)."""
    if block is None or not block.IsA("vtkPolyData"):
        return None
    try:
        surface = Surface(V.points_of(block), V.triangles_of(block, where))
    except MuscleMSSError:
        return None
    if len(surface.triangles) == 0 or surface_problems(surface.points, surface.triangles):
        return None
    return surface


def _attachment_names(block) -> tuple:
    """The ``(origin_bone, insertion_bone)`` a particle block names (None where not one
    string)."""
    return tuple(value if isinstance(value, str) else None
                 for value in (V.field(block, A.ORIGIN_BONE), V.field(block, A.INSERTION_BONE)))


def check_resolution(blocks, layout: str) -> None:
    """Refuse particles too coarse along the fibres for ``layout``
    (:data:`MIN_PARTICLES_PER_FIBRE`), naming the block, N and the rule."""
    least = MIN_PARTICLES_PER_FIBRE[layout]
    for name, block in blocks:
        fibre_id = (V.point_array(block, A.FIBRE_ID, required=False, dtype=np.int64)
                    if block.IsA("vtkPolyData") else None)
        if fibre_id is None or len(fibre_id) == 0:
            continue
        n = int(np.unique(fibre_id, return_counts=True)[1].min())
        if n < least:
            raise MuscleMSSError(
                f"{PARTICLES} block '{name}': {n} particles per fibre (the Fibre Resampler's "
                f"ParticlesPerFibre, muscle-mss --resolution) are too few for the {layout} "
                f"layout, which needs at least {least}: {RESOLUTION_RULE}; set "
                f"ParticlesPerFibre (--resolution) to {least} or more")


def check_placement(blocks, surfaces: dict, bones) -> list:
    """The plausibility rules of a scene in millimetres
    (:func:`muscle_mss.core.validation.placement_problems`: sizes, distance from the origin,
    fibres inside their muscle, muscles outside the bones at rest) on the filter's inputs, each
    muscle's particles taken as its fibres (in fibre order). The same rules ``muscle-mss
    validate`` applies, so that ParaView refuses the same scenes. Returns the warnings of a
    scene accepted but implausibly placed (:func:`~muscle_mss.core.validation.placement_warnings`:
    a muscle's belly in a bone or another muscle). The verdict of a scene checked before (in
    any process) is read back (:func:`~muscle_mss.filters.check_cache.placement_verdict`)."""
    far = [far_point_problem(V.points_of(block), f"{where} block '{name}'")
           for where, items in ((PARTICLES, blocks), (MUSCLES_FILE, surfaces.items()),
                                (BONES_FILE, V.blocks(bones, where=BONES_FILE) if bones else ()))
           for name, block in items if block is not None and block.IsA("vtkPointSet")]
    if any(far):   # before the surface checks, which such a point breaks for that reason alone
        raise first_problem([p for p in far if p])
    muscles, fibres = {}, {}
    for name, block in blocks:
        surface = _checked_surface(surfaces.get(name), f"{MUSCLES_FILE} block '{name}'")
        if surface is None or not block.IsA("vtkPolyData") or block.GetNumberOfPoints() == 0:
            continue
        muscles[name] = surface
        fibre_id = V.point_array(block, A.FIBRE_ID, required=False, dtype=np.int64)
        fibre_index = V.point_array(block, A.FIBRE_INDEX, required=False, dtype=np.int64)
        rest = V.point_array(block, A.REST_POSITION, required=False, dtype=np.float64)
        rest = V.points_of(block) if rest is None else rest.reshape(-1, 3)
        if fibre_id is None or fibre_index is None or len(rest) != len(fibre_id):
            continue
        order = np.lexsort((fibre_index.reshape(-1), fibre_id.reshape(-1)))
        counts = np.unique(fibre_id, return_counts=True)[1]
        offsets = np.concatenate([[0], np.cumsum(counts)])
        points = rest[order]
        midpoints = V.cell_array(block, A.FIBRE_MIDPOINT, required=False)
        if midpoints is not None and midpoints.size == 3 * len(counts):
            # the fibres' own midpoints (the Fibre Resampler's): a few particles per fibre
            # would put a curved fibre's middle outside its muscle
            first, last = points[offsets[:-1]], points[offsets[1:] - 1]
            points = np.stack([first, midpoints.reshape(-1, 3), last], axis=1).reshape(-1, 3)
            offsets = 3 * np.arange(len(counts) + 1)
        fibres[name] = FibreSet(points, offsets, None, *_attachment_names(block))
    rest_bones = {}
    if bones is not None:
        for name, block in V.blocks(bones, where=BONES_FILE):
            surface = _checked_surface(block, f"{BONES_FILE} block '{name}'")
            if surface is not None:
                rest_bones[name] = surface
    problems, warnings = placement_verdict(Scene(muscles, fibres, rest_bones))
    if problems:
        raise first_problem(problems)
    return warnings


class SpringBuilder(MuscleFilter):
    """Joins each muscle's particles by springs and gives its boundary particles collision
    spheres; see the module docstring."""

    LABEL = "Spring Builder"
    HELP = ("Builds each muscle's mass-spring model from its particles: springs in the chosen "
            "layout with rest lengths, stiffness and damping, particle masses, the boundary "
            "particles and their collision sphere radii. Boundary: the surface of the fibre "
            "lattice when the fibres have a fibre_grid, else the particles nearest to the muscle "
            "surface's vertices. Radii follow the paper's heuristic (or the simpler rule) and "
            "are then shrunk so that spheres of different muscles do not overlap at rest, nor "
            "(with the optional Bones input) muscle spheres and bones; a particle inside a "
            "bone at rest gets no sphere. Connect bones.vtm to Bones (the same reader as the "
            "Rigid Pose Transform's Bones) to see here the radii the solver uses: without it "
            "the filter warns, and the Rigid Pose Transform clears the radii of the bones "
            "before the solve instead.")
    INPUTS = (Port("Particles", "vtkMultiBlockDataSet",
                   "particles per muscle (the Fibre Resampler's output)"),
              Port("Surfaces", "vtkMultiBlockDataSet",
                   "muscles.vtm: the rest muscle surfaces, blocks named as the particles' blocks"),
              Port("Bones", "vtkMultiBlockDataSet",
                   "bones.vtm: the rest bone surfaces (optional, but connect it); muscle spheres "
                   "are then kept clear of the bones in the rest pose. Without it a warning: "
                   "the radii are cleared by the Rigid Pose Transform instead, and this "
                   "output's radius array is not what the solver uses", optional=True))
    OUTPUTS = (Port("Model", "vtkMultiBlockDataSet",
                    "the mass-spring model per muscle: particles and springs"),)
    PROPERTIES = (
        Property("Layout", "enum", DEFAULT_LAYOUT,
                 "Which particles are joined by springs. lattice-6: the particles as a cubic "
                 "lattice (fibre_grid row, col and place along the fibre) with springs on the "
                 "cube sides; lattice-26: sides, face and space diagonals (the paper's fastest "
                 "converging layout); both need a full rectangular fibre_grid. Delaunay: the edges "
                 "of the Delaunay tetrahedralisation of each muscle's particles, restricted to the "
                 "muscle: its tetrahedra inside the rest surface with no edge longer than "
                 f"{DELAUNAY_REACH:g} times the longest step between consecutive particles of a "
                 "fibre (the whole tetrahedralisation fills the particles' convex hull and joins "
                 "a curved muscle across its bend). k-NN: each "
                 "particle to its NeighbourCount nearest particles.",
                 choices=LAYOUTS, group="Springs",
                 option=Option("--layout", "spring layout (default {default})")),
        Property("NeighbourCount", "int", 15,
                 "k of the k-NN layout: springs from each particle to its k nearest particles of "
                 "the same muscle (every particle gets at least k springs, or all others in a "
                 "muscle of k particles or fewer). The paper suggests 15.",
                 minimum=1, group="Springs"),
        Property("Stiffness", "double", 10.0,
                 "Spring stiffness, force per mm of stretch (g/s^2), the same for every spring; "
                 "must be positive.", minimum=0.0, group="Springs"),
        Property("Damping", "double", 0.5,
                 "Spring damping along the spring (g/s), the same for every spring; 0 or more.",
                 minimum=0.0, group="Springs"),
        Property("Mass", "double", 1.0,
                 "Mass of every particle (g); must be positive.", minimum=0.0, group="Springs"),
        Property("RadiusHeuristic", "bool", True,
                 "Collision sphere radii by the paper's heuristic: each surface vertex is "
                 "collected by its nearest boundary particle and a particle's radius is the mean "
                 "distance to its collected vertices (the distance to the nearest surface vertex "
                 "for a particle that collects none). Off: every boundary particle gets the "
                 "distance to its nearest surface vertex. Either way, radii are then shrunk until "
                 "no two spheres of different muscles overlap in the rest pose.",
                 group="Collision spheres"),
    )

    def execute(self, inputs, outputs):
        layout = self.choice("Layout")
        for prop in ("Stiffness", "Mass"):
            if self.value(prop) <= 0.0:
                raise MuscleMSSError(f"property {prop} is {self.value(prop)}; it must be positive")
        blocks = V.blocks(inputs[0], where=PARTICLES)
        if not blocks:
            raise MuscleMSSError("the Particles input has no blocks; it needs one block per "
                                 "muscle")
        surfaces = dict(V.blocks(inputs[1], where=MUSCLES_FILE))
        for warning in check_placement(blocks, surfaces, inputs[2]):
            vtkOutputWindow.GetInstance().DisplayWarningText(f"{self.LABEL}: {warning}\n")
        models = []
        for done, (name, block) in enumerate(blocks):
            models.append(self._muscle_model(name, block, surface_mesh(surfaces, name),
                                             layout))
            if self.progress(0.9 * (done + 1) / len(blocks)):
                raise MuscleMSSError(f"stopped by the user after {done + 1} of {len(blocks)} "
                                     "muscles")
        # after each block's own checks (grid, surface), before anything is solved
        check_resolution(blocks, layout)
        sizes = [len(m["rest"]) for m in models]
        radii = shrink_radii(np.concatenate([m["rest"] for m in models]),
                             np.concatenate([m["radius"] for m in models]),
                             np.repeat(np.arange(len(models)), sizes))
        if inputs[2] is None:
            vtkOutputWindow.GetInstance().DisplayWarningText(f"{self.LABEL}: {NO_BONES_WARNING}\n")
        else:
            radii = clear_of_bones(np.concatenate([m["rest"] for m in models]), radii,
                                   inputs[2], BONES_FILE)[0]
        starts = np.concatenate([[0], np.cumsum(sizes)])
        items = [(name, self._output_block(name, block, model, radii[starts[i]:starts[i + 1]],
                                           layout))
                 for i, ((name, block), model) in enumerate(zip(blocks, models))]
        self.progress(1.0)
        V.fill_multiblock(outputs[0], items)

    def _muscle_model(self, name, block, surface, layout) -> dict:
        """Rest positions, springs, boundary and unshrunk radii of one muscle (``surface``:
        its rest surface's points and triangles)."""
        vertices = surface[0][np.unique(surface[1])]
        where = f"{PARTICLES} block '{name}'"
        V.require_polydata(block, where, "a particle block")
        if block.GetNumberOfPoints() == 0:
            raise MuscleMSSError(f"{where} has no particles")
        rest = V.point_array(block, A.REST_POSITION, where, required=False, dtype=np.float64)
        if rest is None:
            rest = V.points_of(block)
        rest = rest.reshape(len(rest), -1)
        if rest.shape != (block.GetNumberOfPoints(), 3):
            raise MuscleMSSError(f"{where}: rest_position must have 3 components per particle")
        if not np.isfinite(rest).all():
            bad = int(np.flatnonzero(~np.isfinite(rest).all(axis=1))[0])
            raise MuscleMSSError(f"{where}: particle {bad} has a NaN or infinite rest position")
        grid = V.point_array(block, A.FIBRE_GRID, where, required=False, dtype=np.int64)
        if grid is not None or layout == LAYOUT_DELAUNAY:
            fibre_id = V.point_array(block, A.FIBRE_ID, where, dtype=np.int64)
            fibre_index = V.point_array(block, A.FIBRE_INDEX, where, dtype=np.int64)
        if layout in LATTICE_NEIGHBOURHOOD:
            if grid is None:
                raise MuscleMSSError(
                    f"{where} has no fibre_grid; layout {layout} needs each fibre's place in a "
                    "full rectangular grid (fibres.vtm cell data fibre_grid); choose Delaunay or "
                    "k-NN for fibres without one")
            springs = lattice_springs(grid, fibre_id, fibre_index,
                                      LATTICE_NEIGHBOURHOOD[layout], where)
        elif layout == LAYOUT_DELAUNAY:
            springs = delaunay_springs(rest, where, surface, DELAUNAY_REACH * fibre_step(
                rest, fibre_id, fibre_index))
        else:
            springs = knn_springs(rest, self.value("NeighbourCount"))
        if grid is not None:
            boundary = boundary_from_grid(grid, fibre_id, fibre_index)
        else:
            boundary = boundary_from_surface(rest, vertices)
        # the MVC Surface Deformer's weights (surface vertices x cage = boundary particles),
        # refused here, before the solve, rather than after it
        errors.check_memory(f"{where}: the surface's mean value coordinates ({len(vertices)} "
                            f"surface vertices on {int(boundary.sum())} boundary particles)",
                            8.0 * len(vertices) * int(boundary.sum()),
                            "lower the Fibre Resampler's ParticlesPerFibre")
        radius = sphere_radii(rest, boundary, vertices, self.value("RadiusHeuristic"))
        return {"rest": rest, "springs": springs, "boundary": boundary, "radius": radius}

    def _output_block(self, name, block, model, radius, layout):
        """The model block of one muscle: a new vtkPolyData, the input block untouched."""
        springs = model["springs"]
        out = V.make_polydata(V.points_of(block), segments=springs)
        for array_name, values in V.point_arrays(block).items():
            V.set_point_array(out, array_name, values)
        V.set_point_array(out, A.REST_POSITION, model["rest"])
        V.set_point_array(out, A.BOUNDARY, model["boundary"].astype(np.uint8))
        V.set_point_array(out, A.RADIUS, radius)
        V.set_point_array(out, A.MASS, np.full(len(model["rest"]), self.value("Mass")))
        V.set_cell_array(out, A.REST_LENGTH, rest_lengths(model["rest"], springs))
        V.set_cell_array(out, A.STIFFNESS, np.full(len(springs), self.value("Stiffness")))
        V.set_cell_array(out, A.DAMPING, np.full(len(springs), self.value("Damping")))
        for field_name in _field_names(block):
            V.set_field(out, field_name, V.field(block, field_name))
        V.set_field(out, A.MUSCLE_NAME, name)
        V.set_field(out, "Layout", layout)
        for prop in ("NeighbourCount", "Stiffness", "Damping", "Mass"):
            V.set_field(out, prop, self.value(prop))
        V.set_field(out, "RadiusHeuristic", int(self.value("RadiusHeuristic")))
        return out
