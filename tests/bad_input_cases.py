"""Bad inputs tried on the small demo scene, and the message each must get (issues 13 and 16).

Each :class:`Case` mutates the small demo scene (in memory before it is written, or its files
after) and/or sets options, then runs it both ways a user would: ``muscle-mss run SCENE OUT
--time 0.5`` (:func:`run_cli`) and the bare filter chain of :mod:`muscle_mss.app.motion_run`
(:func:`run_chain`, what pvpython and ParaView run). ``tests/test_bad_input.py`` asserts the
messages; run this file to regenerate the table of ``docs/bad-input.md``::

    .venv/bin/python tests/bad_input_cases.py > docs/bad-input.md
"""
from __future__ import annotations

import contextlib
import copy
import hashlib
import io
import os
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.scene import FibreSet

TIME = 0.5          # the time point asked of a single-time run (index 10 of the demo's 21)
TIME_INDEX = 10


@dataclass(frozen=True)
class Case:
    """One bad input: ``what`` it is (a line of the table), ``expect`` the regex its message
    must match (``re.search``), how to make it (``scene`` mutates a copy of the demo scene,
    ``files`` the written folder, ``options`` of ``muscle-mss run``, ``settings`` filter
    properties of the chain); ``cli`` / ``chain``: whether that way is tried; ``chain_expect``
    when the chain's message differs from the CLI's; ``warns``: the input is repaired on a copy
    and the run succeeds, and ``expect`` matches the warning that says so."""

    name: str
    what: str
    expect: str
    scene: Callable | None = None
    files: Callable | None = None
    options: tuple = ()
    settings: dict = field(default_factory=dict)
    cli: bool = True
    chain: bool = True
    chain_expect: str | None = None
    warns: bool = False


# ---- mutations ----------------------------------------------------------------------------

def _first(d):
    return next(iter(d))


def _fibres_without(fs: FibreSet, drop: int) -> FibreSet:
    keep = [f for f in range(fs.count) if f != drop]
    return FibreSet.from_polylines([fs.fibre(f) for f in keep],
                                   None if fs.grid is None else fs.grid[keep])


def grid_hole(scene):
    name = _first(scene.fibres)
    scene.fibres[name] = _fibres_without(scene.fibres[name], 5)


def flatten_fibres(axes):
    def mutate(scene):
        fs = scene.fibres[_first(scene.fibres)]
        for axis in axes:
            fs.points[:, axis] = fs.points[:, axis].mean()
    return mutate


def remove_file(relative):
    def mutate(folder):
        os.remove(folder / relative)
    return mutate


def cut_file(relative, keep):
    def mutate(folder):
        path = folder / relative
        path.write_bytes(path.read_bytes()[:keep])
    return mutate


def swap_files(a, b):
    def mutate(folder):
        first, second = (folder / a).read_bytes(), (folder / b).read_bytes()
        (folder / a).write_bytes(second)
        (folder / b).write_bytes(first)
    return mutate


def csv_cell(row, column, value=""):
    """Set ``motion.csv`` data row ``row`` (1 = first) in ``column`` to ``value``; None drops
    that cell and every cell after it."""
    def mutate(folder):
        lines = (folder / "motion.csv").read_text().splitlines()
        header = lines[0].split(",")
        cells = lines[row].split(",")
        c = header.index(column)
        lines[row] = ",".join(cells[:c] if value is None else cells[:c] + [value] + cells[c + 1:])
        (folder / "motion.csv").write_text("\n".join(lines) + "\n")
    return mutate


def extra_bone_rows(folder):
    """Rows for a bone 'patella' that bones.vtm lacks, appended at the end of motion.csv."""
    lines = (folder / "motion.csv").read_text().splitlines()
    extra = [line.replace(",tibia,", ",patella,") for line in lines[1:] if ",tibia," in line]
    (folder / "motion.csv").write_text("\n".join(lines + extra) + "\n")


def almost_rigid(scene):
    """One transform scaled by 1 + 4e-6: R^T R within the tolerance, det 1 + 1.2e-5 beyond it."""
    scene.motion.matrices[3, 1, :, :3] *= 1.0 + 4e-6


def transform_scene(scale=1.0, offset=0.0):
    """Every length times ``scale``, then shifted by ``offset`` mm (motion kept consistent:
    the bones move about the same shifted points)."""
    def mutate(scene):
        shift = np.full(3, offset)
        for surface in list(scene.muscles.values()) + list(scene.bones.values()):
            surface.points[:] = surface.points * scale + shift
        for fibres in scene.fibres.values():
            fibres.points[:] = fibres.points * scale + shift
        m = scene.motion.matrices
        m[..., 3] = m[..., 3] * scale + shift - np.einsum("tbij,j->tbi", m[..., :3], shift)
    return mutate


def move_fibres(dx):
    def mutate(scene):
        scene.fibres[_first(scene.fibres)].points[:, 0] += dx
    return mutate


def muscle_into_bone(scene):
    """The first muscle (surface and fibres) shrunk to a fifth about its centre and moved to
    the middle of the femur's shaft."""
    name = _first(scene.muscles)
    surface, fibres = scene.muscles[name], scene.fibres[name]
    femur = scene.bones["femur"].points
    target = 0.5 * (femur.min(axis=0) + femur.max(axis=0))
    centre = surface.points.mean(axis=0)
    surface.points[:] = (surface.points - centre) * 0.2 + target
    fibres.points[:] = (fibres.points - centre) * 0.2 + target


def far_point(kind, point, block=None, fibre=None):
    """Point ``point`` of the first (or named) block of ``kind`` (muscles, bones, fibres; of
    fibre ``fibre``) moved to 1e12 mm in x: one wrong vertex in an otherwise right scene."""
    def mutate(scene):
        items = getattr(scene, kind)
        target = items[block or _first(items)]
        first = 0 if fibre is None else target.offsets[fibre]
        target.points[first + point, 0] = 1e12
    return mutate


def fibres_as_poly_vertices(relative):
    """The fibres of one ``.vtp`` as one poly-vertex cell each (VTK_POLY_VERTEX), same points."""
    def mutate(folder):
        from vtkmodules.vtkCommonDataModel import vtkCellArray
        from vtkmodules.vtkIOXML import vtkXMLPolyDataReader, vtkXMLPolyDataWriter
        reader = vtkXMLPolyDataReader()
        reader.SetFileName(str(folder / relative))
        reader.Update()
        fibres = reader.GetOutput()
        vertices = vtkCellArray()
        vertices.DeepCopy(fibres.GetLines())
        fibres.SetVerts(vertices)
        fibres.SetLines(vtkCellArray())
        writer = vtkXMLPolyDataWriter()
        writer.SetFileName(str(folder / relative))
        writer.SetInputData(fibres)
        writer.Write()
    return mutate


def reverse_every_second_fibre(scene):
    """Every second fibre of the first muscle digitised from its insertion (points reversed)."""
    fs = scene.fibres[_first(scene.fibres)]
    for f in range(1, fs.count, 2):
        fs.points[fs.offsets[f]:fs.offsets[f + 1]] = fs.fibre(f)[::-1].copy()


def name_attachment(end, bone):
    def mutate(scene):
        setattr(scene.fibres[_first(scene.fibres)], f"{end}_bone", bone)
    return mutate


def copy_muscle(scale=1.0):
    """The second muscle replaced by the first one (surface and fibres) scaled by ``scale``
    about the first one's centre: two identical muscles (1), or one inside the other (< 1)."""
    def mutate(scene):
        first, second = list(scene.muscles)[:2]
        centre = scene.muscles[first].points.mean(axis=0)
        surface, fibres = copy.deepcopy(scene.muscles[first]), copy.deepcopy(scene.fibres[first])
        surface.points[:] = (surface.points - centre) * scale + centre
        fibres.points[:] = (fibres.points - centre) * scale + centre
        scene.muscles[second], scene.fibres[second] = surface, fibres
    return mutate


def muscle_partly_into_femur(share):
    """The first muscle (surface and fibres) moved toward the middle of the femur's shaft until
    ``share`` of its surface vertices lie inside the femur."""
    def mutate(scene):
        from muscle_mss.core.volume import winding_numbers
        name = _first(scene.muscles)
        surface, fibres, femur = scene.muscles[name], scene.fibres[name], scene.bones["femur"]
        target = 0.5 * (femur.points.min(axis=0) + femur.points.max(axis=0))
        step = (target - surface.points.mean(axis=0)) / 200.0
        for _ in range(200):
            inside = winding_numbers(surface.points, femur.points, femur.triangles) > 0.5
            if inside.mean() >= share:
                return
            surface.points += step
            fibres.points += step
    return mutate


def muscle_half_in_copy(scene):
    """The second muscle replaced by a copy of the first (surface and fibres) moved sideways
    (across the first's fibres, toward the second) until just half of its fibre midpoints lie
    inside the first and half of the first's inside it: the most the overlap rule accepts."""
    from muscle_mss.core.validation import fibre_midpoints
    from muscle_mss.core.volume import winding_numbers
    first, second = list(scene.muscles)[:2]
    surface, fibres = scene.muscles[first], scene.fibres[first]
    along = fibres.points[fibres.offsets[1:] - 1] - fibres.points[fibres.offsets[:-1]]
    along = along.mean(axis=0) / np.linalg.norm(along.mean(axis=0))
    side = scene.muscles[second].points.mean(axis=0) - surface.points.mean(axis=0)
    side -= side.dot(along) * along
    side /= np.linalg.norm(side)
    middle = fibre_midpoints(fibres.points, fibres.offsets)
    for shift in np.arange(0.0, 50.0, 0.1):   # the copy's midpoints in the first, and back
        moved = np.concatenate([middle + shift * side, middle - shift * side])
        inside = winding_numbers(moved, surface.points, surface.triangles) > 0.5
        if max(inside[:len(middle)].mean(), inside[len(middle):].mean()) <= 0.5:
            break
    copied_surface, copied_fibres = copy.deepcopy(surface), copy.deepcopy(fibres)
    copied_surface.points += shift * side
    copied_fibres.points += shift * side
    scene.muscles[second], scene.fibres[second] = copied_surface, copied_fibres


def fibres_as_segments(scene):
    """The first muscle's fibres written as two-point segments, one per step of each fibre, in
    fibre order (each segment with its fibre's ``fibre_grid`` cell), as some exporters write
    polylines."""
    name = _first(scene.fibres)
    fs = scene.fibres[name]
    steps = np.diff(fs.offsets) - 1
    segments = [fs.fibre(f)[i:i + 2] for f in range(fs.count) for i in range(steps[f])]
    grid = None if fs.grid is None else np.repeat(fs.grid, steps, axis=0)
    scene.fibres[name] = FibreSet.from_polylines(segments, grid)
    scene.fibres[name].origin_bone = fs.origin_bone
    scene.fibres[name].insertion_bone = fs.insertion_bone


def insertion_onto_origin(muscle="rectus_femoris", index=TIME_INDEX):
    """At time point ``index`` the insertion bone of ``muscle`` translated so that its fibres'
    insertion centroid lands on their origin centroid (both posed): origin and insertion meet."""
    def mutate(scene):
        fibres = scene.fibres[muscle]
        first = fibres.points[fibres.offsets[:-1]].mean(axis=0)
        last = fibres.points[fibres.offsets[1:] - 1].mean(axis=0)
        bones = list(scene.motion.bones)
        origin = scene.motion.matrices[index, bones.index(fibres.origin_bone)]
        insertion = scene.motion.matrices[index, bones.index(fibres.insertion_bone)]
        insertion[:, 3] = origin[:, :3] @ first + origin[:, 3] - insertion[:, :3] @ last
    return mutate


# ---- the cases ----------------------------------------------------------------------------

MEET = (r"MSS Collision Solver: muscle 'rectus_femoris' at time 0.5 s: its origin and "
        r"insertion \(its fibres' end centroids\) are [0-9.e+-]+ mm apart, [0-9.e+-]+ % of "
        r"their 488 mm at rest; FibreShortening gives no rest shape to a muscle or fibre whose "
        r"ends come closer than 50% of their rest distance")
"""The message of a pose that moves the rectus femoris' insertion onto its origin."""

CASES = [
    Case("resolution-1", "`--resolution 1` (ParticlesPerFibre 1)",
         r"Fibre Resampler: property ParticlesPerFibre is 1; it must be at least 2",
         options=("--resolution", "1"), settings={"ParticlesPerFibre": 1}),
    Case("resolution-0", "`--resolution 0`",
         r"Fibre Resampler: property ParticlesPerFibre is 0; it must be at least 2",
         options=("--resolution", "0"), settings={"ParticlesPerFibre": 0}),
    Case("resolution-negative", "`--resolution -1`",
         r"Fibre Resampler: property ParticlesPerFibre is -1; it must be at least 2",
         options=("--resolution", "-1"), settings={"ParticlesPerFibre": -1}),
    Case("resolution-fraction", "ParticlesPerFibre 2.7 (a filter property set from Python)",
         r"ParticlesPerFibre: 2.7 is not a whole number", cli=False,
         settings={"ParticlesPerFibre": 2.7}),
    Case("iterations-0", "`--iterations 0`",
         r"MSS Collision Solver: property Iterations is 0; it must be at least 1",
         options=("--iterations", "0"), settings={"Iterations": 0}),
    Case("iterations-1e9", "Iterations 1e9 with a time budget (a 60 GiB history here)",
         r"Iterations 1000000000 would need a .* GiB history .*lower Iterations",
         options=("--iterations", "1000000000"),
         settings={"Iterations": 10 ** 9, "Termination": "time budget"}),
    Case("grid-hole-lattice", "a `fibre_grid` with a hole (one fibre removed), lattice-26",
         r"Spring Builder: particles block 'rectus_femoris': fibre_grid has no fibre at "
         r"\(row \d+, col \d+\); lattice layouts need a full rectangular grid",
         scene=grid_hole),
    Case("coplanar-delaunay", "a muscle's fibres all in one plane, `--layout Delaunay`",
         r"Spring Builder: particles block 'rectus_femoris': the Delaunay layout needs "
         r"particles spanning 3D space",
         scene=flatten_fibres((1,)), options=("--layout", "Delaunay"),
         settings={"Layout": "Delaunay"}),
    Case("collinear-delaunay", "a muscle's fibres all on one line, `--layout Delaunay`",
         r"Spring Builder: particles block 'rectus_femoris': the Delaunay layout needs "
         r"particles spanning 3D space",
         scene=flatten_fibres((0, 1)), options=("--layout", "Delaunay"),
         settings={"Layout": "Delaunay"}),
    Case("mass-1e-8", "Spring Builder Mass 1e-8 g (segfault, exit 139, before)",
         r"MSS Collision Solver: the model cannot be solved with TimeStep 0.05 s: particle \d+ "
         r"of muscle 'rectus_femoris' \(mass 1e-08 g.*lower the MSS Collision Solver's "
         r"TimeStep below .* or raise the Spring Builder's Mass",
         cli=False, settings={"Mass": 1e-8, "Method": "paper relaxation"}),
    Case("stiffness-1e9", "Spring Builder Stiffness 1e9 g/s^2 (segfault, exit 139, before)",
         r"MSS Collision Solver: the model cannot be solved with TimeStep 0.05 s: .*springs of "
         r"total stiffness 2.6e\+10 g/s\^2.*lower its Stiffness",
         cli=False, settings={"Stiffness": 1e9, "Method": "paper relaxation"}),
    Case("bone-spacing-tiny",
         "BoneContact sphere set, BoneSphereSpacing 0.001 mm (17.8 TiB asked, before)",
         r"bone spheres 0.001 mm apart \(\d+ candidate points, a grid of .* cells\) would need "
         r".* GiB, more than the .* GiB .*raise the MSS Collision Solver's BoneSphereSpacing",
         cli=False, settings={"BoneContact": "sphere set", "BoneSphereSpacing": 1e-3}),
    Case("bone-spacing-1e6", "BoneContact sphere set, BoneSphereSpacing 1e6 mm (one sphere a "
         "bone: volume errors of 3e14 % without a word, before)",
         r"MSS Collision Solver: PosedBones block 'pelvis': bone spheres 1e\+06 mm apart are too "
         r"large for a bone whose bounding box is 133 mm at its thinnest.*lower the MSS Collision "
         r"Solver's BoneSphereSpacing",
         cli=False, settings={"BoneContact": "sphere set", "BoneSphereSpacing": 1e6}),
    # a pose that moves a muscle's insertion onto its origin (the tibia onto the pelvis)
    Case("origin-meets-insertion-8", "at 0.5 s the tibia posed onto the pelvis (the rectus "
         "femoris' insertion on its origin), `--resolution 8` (29.6 million % volume error, "
         "coordinates 16.6 m out, 'raise Iterations', before)",
         MEET, scene=insertion_onto_origin(), options=("--resolution", "8"),
         settings={"ParticlesPerFibre": 8}),
    Case("origin-meets-insertion-20", "the same, `--resolution 20`",
         MEET, scene=insertion_onto_origin(), options=("--resolution", "20"),
         settings={"ParticlesPerFibre": 20}),
    Case("origin-meets-insertion-paper-8", "the same, `--resolution 8 --method paper` "
         "('lower the TimeStep', before)",
         MEET, scene=insertion_onto_origin(), options=("--resolution", "8", "--method", "paper"),
         settings={"ParticlesPerFibre": 8, "Method": "paper relaxation"}),
    Case("origin-meets-insertion-paper-20", "the same, `--resolution 20 --method paper`",
         MEET, scene=insertion_onto_origin(), options=("--resolution", "20", "--method", "paper"),
         settings={"ParticlesPerFibre": 20, "Method": "paper relaxation"}),
    # scene files (issue 16 item 2, issue 13 item 4)
    Case("muscle-vtp-missing", "`muscles/muscles_1.vtp` deleted (muscles.vtm still names it)",
         r"muscles.vtm block 'vastus_lateralis': its file .*muscles_1.vtp is missing",
         files=remove_file("muscles/muscles_1.vtp")),
    Case("bone-vtp-cut-header", "`bones/bones_1.vtp` cut inside its XML header (first 120 bytes)",
         r"bones.vtm block 'femur': its file .*bones_1.vtp could not be read as VTK polydata",
         files=cut_file("bones/bones_1.vtp", 120)),
    Case("fibre-vtp-cut", "`fibres/fibres_2.vtp` cut in the middle of its data",
         r"fibres.vtm block 'vastus_intermedius': its file .*fibres_2.vtp could not be read",
         files=cut_file("fibres/fibres_2.vtp", 3000)),
    Case("muscles-vtm-cut", "`muscles.vtm` cut inside its XML",
         r"muscles.vtm: is not a readable VTK multiblock file",
         files=cut_file("muscles.vtm", 200)),
    Case("fibre-files-swapped", "`fibres_0.vtp` and `fibres_3.vtp` swapped (names kept)",
         r"fibres.vtm block 'rectus_femoris': \d+ % of its fibres' midpoints lie inside "
         r"muscles.vtm block 'rectus_femoris'; a muscle's fibres must run inside its surface",
         files=swap_files("fibres/fibres_0.vtp", "fibres/fibres_3.vtp")),
    # motion.csv (issue 16 item 3, issue 13 item 5)
    Case("csv-empty-translation", "one translation cell of `motion.csv` emptied",
         r"motion.csv row 6 \(line 7\), column m13: the cell is empty",
         files=csv_cell(6, "m13")),
    Case("csv-empty-rotation", "one rotation cell of `motion.csv` emptied",
         r"motion.csv row 6 \(line 7\), column m01: the cell is empty",
         files=csv_cell(6, "m01")),
    Case("csv-missing-cells", "a `motion.csv` row cut short (its last two cells missing)",
         r"motion.csv row 4 \(line 5\), column m22: the cell is missing",
         files=csv_cell(4, "m22", None)),
    Case("csv-not-a-number", "a `motion.csv` cell holding `abc`",
         r"motion.csv row 5, column m03: 'abc' is not a number",
         files=csv_cell(5, "m03", "abc")),
    Case("almost-rigid", "a transform scaled by 1 + 4e-6 (det 1 + 1.2e-5)",
         r"motion.csv row \d+ \(bone 'femur', time 0.15\): the transform is not rigid: its 3x3 "
         r"part scales volumes by det = 1.000012",
         scene=almost_rigid),
    Case("unknown-bone", "rows for a bone `patella` that bones.vtm lacks, appended to motion.csv",
         r"motion.csv row 64: bone 'patella' is not a bone of the scene \(bones: pelvis, femur, "
         r"tibia\)",
         files=extra_bone_rows),
    # implausible scenes (issue 16 item 5, issue 13 item 5)
    Case("scene-in-metres", "the whole scene in metres (every length / 1000)",
         r"muscles.vtm block 'rectus_femoris': the muscle is 0.\d+ mm across; .*is the scene "
         r"in metres\? scale it by 1000",
         scene=transform_scene(scale=1e-3)),
    Case("scene-offset-1e12", "the whole scene moved by 1e12 mm",
         r"(muscles|fibres).vtm block 'rectus_femoris': a vertex lies 1e\+12 mm from the origin; "
         r"a scene farther than 10000 mm \(10 m\)",
         scene=transform_scene(offset=1e12)),
    Case("muscle-inside-bone", "a muscle shrunk to a fifth and placed inside the femur",
         r"muscles.vtm block 'rectus_femoris': \d+ % of its surface lies inside bones.vtm block "
         r"'femur' at rest; a muscle must lie outside the bones",
         scene=muscle_into_bone),
    Case("fibres-200mm-out", "a muscle's fibres moved 200 mm out of its surface",
         r"fibres.vtm block 'rectus_femoris': 0 % of its fibres' midpoints lie inside",
         scene=move_fibres(200.0)),
    # issue 30: fibre direction, coarse resolutions, attachments and overlaps
    Case("fibres-reversed", "every second fibre of one muscle reversed (digitised from both "
         "ends); the run then gives the unmodified scene's results",
         r"Fibre Resampler: fibres.vtm block 'rectus_femoris': 8 of its 16 fibres ran from "
         r"insertion to origin and were reversed on a copy \(8 by their ends' distances to the "
         r"origin bone 'pelvis' and the insertion bone 'tibia'\)",
         scene=reverse_every_second_fibre, warns=True),
    Case("resolution-3", "`--resolution 3` on the valid scene (40 % volume error, surface "
         "points 770 mm off, before)",
         r"Spring Builder: particles block 'rectus_femoris': 3 particles per fibre \(the Fibre "
         r"Resampler's ParticlesPerFibre, muscle-mss --resolution\) are too few for the "
         r"lattice-26 layout, which needs at least 8",
         options=("--resolution", "3"), settings={"ParticlesPerFibre": 3}),
    Case("resolution-2", "`--resolution 2` (blamed the fibre files, before)",
         r"Spring Builder: particles block 'rectus_femoris': 2 particles per fibre .* too few "
         r"for the lattice-26 layout, which needs at least 8",
         options=("--resolution", "2"), settings={"ParticlesPerFibre": 2}),
    Case("resolution-4-knn", "`--resolution 4 --layout k-NN`",
         r"Spring Builder: particles block 'rectus_femoris': 4 particles per fibre .* too few "
         r"for the k-NN layout, which needs at least 5",
         options=("--resolution", "4", "--layout", "k-NN"),
         settings={"ParticlesPerFibre": 4, "Layout": "k-NN"}),
    Case("insertion-bone-wrong", "`insertion_bone = pelvis` for fibre ends on the tibia",
         r"fibres.vtm block 'rectus_femoris': insertion_bone is 'pelvis', but the fibres' "
         r"insertion ends lie \d+ mm from it on average and \d+\.\d mm from bones.vtm block "
         r"'tibia'; a fibre end is attached to a bone it lies on",
         scene=name_attachment("insertion", "pelvis")),
    Case("muscle-copy", "two identical muscles (the second replaced by a copy of the first)",
         r"muscles.vtm blocks 'rectus_femoris' and 'vastus_lateralis': 100 % of the fibre "
         r"midpoints of 'rectus_femoris' lie inside the surface of 'vastus_lateralis'; muscles "
         r"may touch but not overlap",
         scene=copy_muscle()),
    Case("muscle-inside-muscle", "a muscle inside another (the first at half size in its "
         "middle, in place of the second)",
         r"muscles.vtm blocks 'vastus_lateralis' and 'rectus_femoris': 100 % of the fibre "
         r"midpoints of 'vastus_lateralis' lie inside the surface of 'rectus_femoris'",
         scene=copy_muscle(0.5)),
    Case("muscle-40pct-in-bone", "a muscle moved 40 % into the femur (ran with nothing in the "
         "table, before)",
         r"muscles.vtm block 'rectus_femoris': (3[1-9]|[4-9]\d) % of its surface lies inside "
         r"bones.vtm block 'femur' at rest; a muscle must lie outside the bones in the rest pose "
         r"\(at most 30 %",
         scene=muscle_partly_into_femur(0.4)),
    Case("muscle-27pct-in-bone", "a muscle moved until 27 % of its surface lies in the femur, "
         "under the 30 % rule (ran without a word, 'in bone mm' 0.000, before)",
         r"Spring Builder: muscles.vtm block 'rectus_femoris': 44 % of its fibre midpoints \(7 "
         r"of 16\) and 27 % of its surface vertices lie inside bones.vtm block 'femur' at rest, "
         r"up to 15.\d mm deep; a muscle's belly lies outside the bones",
         scene=muscle_partly_into_femur(0.27), warns=True),
    Case("muscle-half-in-muscle", "a copy of a muscle in place of another, half of each one's "
         "fibre midpoints inside the other (the most the overlap rule accepts; surfaces "
         "interpenetrating while 'overlap mm' read 0.001, before)",
         r"Spring Builder: muscles.vtm blocks 'rectus_femoris' and 'vastus_lateralis': 50 % of "
         r"the fibre midpoints of 'rectus_femoris' \(8 of 16\) and \d+ % of its surface "
         r"vertices lie inside the surface of 'vastus_lateralis' at rest, up to \d+\.\d mm deep",
         scene=muscle_half_in_copy, warns=True),
    # --time (issue 16 item 6)
    Case("time-after-end", "`--time 5` (the motion ends at 1 s)",
         r"--time 5 is outside the motion's time range \[0, 1\] s", options=("--time", "5"),
         chain=False),
    Case("time-before-start", "`--time -3`",
         r"--time -3 is outside the motion's time range \[0, 1\] s", options=("--time", "-3"),
         chain=False),
    Case("time-nan", "`--time nan`", r"--time nan: not a finite number",
         options=("--time", "nan"), chain=False),
    # issue 30: messages that pointed the wrong way or hid the cause
    Case("muscle-vertex-1e12", "one muscle surface vertex (point 17) moved to 1e12 mm "
         "(\"surface is oriented inward\", a SystemError in mvc.py, before)",
         r"muscles.vtm block 'rectus_femoris': point 17 lies 1e\+12 mm from the origin; a point "
         r"farther than 10000 mm \(10 m\) from the origin is implausible .*1 of the block's \d+ "
         r"points is, the rest not: correct or remove it",
         scene=far_point("muscles", 17)),
    Case("bone-vertex-1e12", "one bone vertex (the femur's point 5) moved to 1e12 mm",
         r"bones.vtm block 'femur': point 5 lies 1e\+12 mm from the origin; a point farther "
         r"than 10000 mm \(10 m\)", scene=far_point("bones", 5, block="femur")),
    Case("fibre-point-1e12", "one fibre point (fibre 2's point 1) moved to 1e12 mm",
         r"fibres.vtm block 'rectus_femoris': fibre 2's point 1 lies 1e\+12 mm from the origin; "
         r"a point farther than 10000 mm \(10 m\)", scene=far_point("fibres", 1, fibre=2)),
    Case("fibres-poly-vertex", "a muscle's fibres as poly-vertex cells (VTK_POLY_VERTEX), not "
         "polylines (a raw `ValueError: cannot reshape array`, before)",
         r"fibres.vtm block 'rectus_femoris': holds \d+ vertex or poly-vertex cells "
         r"\(VTK_VERTEX, VTK_POLY_VERTEX\); fibres must be polylines \(VTK_POLY_LINE\)",
         files=fibres_as_poly_vertices("fibres/fibres_0.vtp")),
    Case("fibres-as-segments", "a muscle's 16 fibres written as 176 two-point segments (read "
         "as 176 fibres, fibre strain 1.62, before); the run then gives the unmodified scene's "
         "particles",
         r"Fibre Resampler: fibres.vtm block 'rectus_femoris': 176 polylines joined end to end "
         r"into 16 fibres", scene=fibres_as_segments, warns=True),
    Case("fibres-as-segments-knn", "the same, `--layout k-NN`",
         r"Fibre Resampler: fibres.vtm block 'rectus_femoris': 176 polylines joined end to end "
         r"into 16 fibres", scene=fibres_as_segments, options=("--layout", "k-NN"),
         settings={"Layout": "k-NN"}, warns=True),
    Case("tolerance-with-paper", "`--method paper --tolerance 0.01` (ignored silently, before)",
         r"--tolerance 0.01 applies only to --method quasi-static .*drop --tolerance or add "
         r"--method quasi-static", options=("--method", "paper", "--tolerance", "0.01"),
         chain=False),
    Case("springs-with-paper", "`--method paper --springs co-rotational`",
         r"--springs co-rotational applies only to --method quasi-static \(its spring energy\)"
         r".*drop --springs or add --method quasi-static",
         options=("--method", "paper", "--springs", "co-rotational"), chain=False),
    Case("tissue-along-without-tissue", "`--connective-tissue 0 --tissue-along 0.5` "
         "(TissueAlongFibres 0.5, ConnectiveTissue 0; ignored silently, before): the run gives "
         "the paper model's results",
         r"MSS Collision Solver: TissueAlongFibres 0.5 has no effect with ConnectiveTissue 0: "
         r"it is the connective tissue's stiffness along the fibres, and the tissue is off",
         options=("--connective-tissue", "0", "--tissue-along", "0.5"),
         settings={"ConnectiveTissue": 0.0, "TissueAlongFibres": 0.5}, warns=True),
    Case("timestep-nan", "MSS Collision Solver TimeStep NaN under the quasi-static method "
         "(accepted, before)",
         r"MSS Collision Solver: property TimeStep is nan; it must be a finite number",
         settings={"TimeStep": float("nan")}, cli=False),
    Case("bone-spacing-with-solid", "BoneSphereSpacing 3 mm with BoneContact solid (the "
         "default; ignored silently, before)",
         r"MSS Collision Solver: BoneSphereSpacing 3 mm has no effect with BoneContact 'solid': "
         r"the bones are solids, not spheres",
         settings={"BoneSphereSpacing": 3.0}, cli=False, warns=True),
    Case("write-nothing", "`--write ''` (everything written, before)",
         r"--write '' names no series to write; give one or more of surfaces,fibres,particles",
         options=("--write", ""), chain=False),
]


HEAD = """# Bad input: what each gets

Every bad input below was tried on the small demo scene (`muscle-mss demo-scene OUT --size
small`), through `muscle-mss run SCENE OUT --time 0.5` and through the bare filter chain (what
pvpython, pvbatch and ParaView run: there the message appears in the Output Messages window,
prefixed by the failing filter, and every filter downstream of it shows an empty output without
a complaint of its own). In Python, `Update()` raises the `MuscleMSSError`. No input file or
object is ever changed (`tests/test_bad_input.py` checks each folder's files before and after).

Anything a filter raises that is not one of our errors reaches the caller the same way, as
`FILTER: failed unexpectedly with EXCEPTION: MESSAGE at FILE:LINE` (a
`MemoryError` as `ran out of memory (SIZE ASKED)`); Ctrl-C stops `muscle-mss run` with exit
code 130 and `interrupted: Ctrl-C while FILTER ran` (also when a compiled kernel reports it as
a `SystemError`; `Ctrl-C while muscle-mss run ran` outside the filters). A filter whose required
input is not connected says so: `MSS Collision Solver: input 'PosedBones' is not connected; this
input is required: the posed bone surfaces, …`. Read right, not refused: a `motion.csv` header
with spaces after its commas, and surfaces made of triangle strips (read as triangles, with a
warning naming the block; the file is not changed). These, and what a run may do to its output
folder, are tested in `tests/test_input_messages.py` and `tests/test_output_safety.py`. Also
right: a muscle surface as dense as a segmented one (221,184 triangles; it deforms within
0.45 mm mean of its coarse surface at the most flexed pose, and a vertex that leaves its cage by
more than 10 mm is reported in `cage_drift_vertices` and by a CLI warning; at
ParticlesPerFibre 8, where the lattice cage folds over itself, the surface's weights are bounded
and it still follows: `tests/test_dense_surface.py`), and bones thinner than their distance
fields can resolve (what is inside a bone is decided by its triangles: `tests/test_thin_bones.py`).

What a run may write, tested in `tests/test_output_safety.py`: anything of the user's where the
run writes (a file at `OUT/series/surfaces_0010`, a folder where a file goes) is refused before
solving, naming it, with or without `--overwrite`; a manifest that lists a file the run reads is
refused (`--overwrite` never removes an input); `muscle-mss demo OUT` refuses an `OUT/scene` it
did not write as it is (a scene you edited) unless `--overwrite`. A state file loaded without
its scene (or with a `data_directory` that lacks it) names the missing file in ParaView's
messages, and `muscle_mss.plugin.pipeline.load_state` raises with it (`tests/test_paraview.py`).

The scene-file cases (missing or cut `.vtp`, empty `motion.csv` cells) are checked when a scene
folder is read by muscle-mss: `muscle-mss validate/run`, the batch, and the plugin's pipeline
builder (`muscle_mss.plugin.pipeline.build_pipeline`, which refuses the folder before building).
A pipeline assembled by hand from ParaView's own readers gets only what the filters can see: a
missing `.vtp` shows up as a copy of the previous block and ParaView's CSV reader reads an
empty cell as 0 — run `muscle-mss validate SCENE` on such a folder. The ParaView time slider
still clamps a time outside the motion, with a warning (`--time` outside it is an error).

This table is generated: `.venv/bin/python tests/bad_input_cases.py > docs/bad-input.md`
(the test suite checks that each message still matches its case's pattern).

"""


# ---- running a case -------------------------------------------------------------------------

def make_scene(case: Case, folder) -> Path:
    """Write the small demo scene with ``case``'s mutations into ``folder``."""
    from muscle_mss.filters.scene_io import write_scene
    scene = copy.deepcopy(_small())
    if case.scene is not None:
        case.scene(scene)
    folder = Path(folder)
    write_scene(scene, folder)
    if case.files is not None:
        case.files(folder)
    return folder


_SMALL = []


def _small():
    if not _SMALL:
        from muscle_mss.core.demo.scene import demo_scene
        _SMALL.append(demo_scene("small"))
    return _SMALL[0]


def folder_digest(folder) -> str:
    """A digest of every file under ``folder`` (names and contents): inputs must not change."""
    digest = hashlib.sha1()
    for root, dirs, files in sorted(os.walk(folder)):
        dirs.sort()
        for name in sorted(files):
            path = os.path.join(root, name)
            digest.update(os.path.relpath(path, folder).encode())
            with open(path, "rb") as f:
                digest.update(f.read())
    return digest.hexdigest()


def warning_of(case: Case, text: str):
    """The line of VTK's output window ``text`` (warnings, which ParaView shows in its Output
    Messages and the CLI on stderr) that matches ``case.expect``, or None."""
    return next((line for line in text.splitlines() if matches(case.expect, line)), None)


def run_cli(case: Case, folder, out) -> tuple:
    """``muscle-mss run folder out --time 0.5 [options]`` in this process: ``(exit code,
    the message of its "error:" line, or for a case that ``warns`` its warning, or None, its
    stderr with VTK's messages)``."""
    from muscle_mss.app.cli import main
    from muscle_mss.filters.scene_io import vtk_messages
    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()), \
            vtk_messages() as window:
        code = main(["run", str(folder), str(out), "--time", str(TIME), *case.options])
    text = stderr.getvalue() + window.GetOutput()
    if case.warns:
        return code, warning_of(case, window.GetOutput()), text
    lines = [line[len("error: "):] for line in text.splitlines() if line.startswith("error: ")]
    return code, (lines[-1] if lines else None), text


def run_chain(case: Case, folder):
    """The filter chain on ``folder`` with ``case.settings`` at time point 10: the message of
    the :class:`MuscleMSSError` it raises (with the failing filter's label), else for a case
    that ``warns`` its warning, else None."""
    from muscle_mss.app import motion_run
    from muscle_mss.filters.scene_io import vtk_messages
    try:
        with vtk_messages() as window:
            pipeline = motion_run.build_pipeline(str(folder), case.settings)
            motion_run.solve_time_point(pipeline, TIME_INDEX)
    except MuscleMSSError as err:
        label = getattr(err, "filter_label", None)
        return f"{label}: {err}" if label else str(err)
    return warning_of(case, window.GetOutput()) if case.warns else None


def matches(pattern: str, message) -> bool:
    return message is not None and re.search(pattern, message) is not None


def table(rows) -> str:
    """The markdown table of ``rows`` = ``(case, cli message, chain message)``."""
    def cell(text):
        return "—" if text is None else text.replace("|", "\\|").replace("\n", " ")
    lines = ["| case | bad input | `muscle-mss run` says (exit 2) | filter chain / ParaView says |",
             "|---|---|---|---|"]
    for case, cli, chain in rows:
        note = "(exit 0, a warning) " if case.warns else ""
        lines.append(f"| `{case.name}` | {case.what} | "
                     f"{note + cell(cli) if case.cli else '(no option)'} "
                     f"| {cell(chain) if case.chain else '(not a filter input)'} |")
    return "\n".join(lines)


def main(out=sys.stdout) -> int:
    """Run every case and print ``docs/bad-input.md``."""
    import tempfile
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, case in enumerate(CASES):
            folder = make_scene(case, os.path.join(tmp, f"scene{k}"))
            cli = run_cli(case, folder, os.path.join(tmp, f"out{k}"))[1] if case.cli else None
            chain = run_chain(case, folder) if case.chain else None
            rows.append((case, *(None if m is None else m.replace(str(folder), "SCENE")
                                 for m in (cli, chain))))
    out.write(HEAD + table(rows) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
