"""``muscle-mss fibres SCENE``: write a scene's ``fibres.vtm`` from its muscles and bones.

The Fibre Generator filter (:mod:`muscle_mss.filters.fibre_generator`) on the scene's
``muscles.vtm`` and ``bones.vtm``, as ParaView would run it; the bones of each muscle come from
the scene's ``attachments.csv``, else from the ``fibres.vtm`` being replaced (its blocks'
``origin_bone`` / ``insertion_bone``), else they are inferred. An existing ``fibres.vtm`` is
replaced only when asked (``--overwrite``), with its block files.
"""
from __future__ import annotations

import os
import time as wallclock

from muscle_mss.core.attachment_areas import ATTACHMENT_COLUMNS, ATTACHMENTS_FILE
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.scene import BONES_FILE, FIBRES_FILE, MUSCLES_FILE
from muscle_mss.filters import array_names as A
from muscle_mss.filters import vtk_arrays as V
from muscle_mss.filters.fibre_generator import FibreGenerator
from muscle_mss.filters.scene_io import (fibres_from_vtk, listed_block_files, multiblock_reader,
                                         named_attachments, vtk_messages, write_multiblock)


def earlier_fibre_bones(path: str) -> dict:
    """``{muscle: (origin bone, insertion bone)}`` that the ``fibres.vtm`` at ``path`` names
    (both ends named), or {} when there is none or it cannot be read."""
    if not os.path.isfile(path):
        return {}
    try:
        fibres = fibres_from_vtk(multiblock_reader(path).GetOutputDataObject(0), path)
    except MuscleMSSError:
        return {}
    return {m: (f.origin_bone, f.insertion_bone) for m, f in fibres.items()
            if f.origin_bone is not None and f.insertion_bone is not None}


def generate_fibres_file(scene: str, count: int, points: int, overwrite: bool,
                         report=print) -> dict:
    """Write ``SCENE/fibres.vtm`` with ``count`` generated fibres of ``points`` points per
    muscle; ``report`` gets one line per muscle. Returns ``{muscle: (origin, insertion,
    how)}``, ``how`` one of ``attachments.csv``, ``fibres.vtm``, ``inferred``."""
    path = os.path.join(scene, FIBRES_FILE)
    if os.path.exists(path) and not overwrite:
        raise MuscleMSSError(f"{path} exists; --overwrite replaces it (its block files too)")
    muscles = multiblock_reader(os.path.join(scene, MUSCLES_FILE))
    bones = multiblock_reader(os.path.join(scene, BONES_FILE))
    muscle_names = [n for n, _ in V.blocks(muscles.GetOutputDataObject(0), MUSCLES_FILE)]
    bone_names = [n for n, _ in V.blocks(bones.GetOutputDataObject(0), BONES_FILE)]
    named = {m: (*bones_of, ATTACHMENTS_FILE) for m, bones_of in
             named_attachments(scene, muscle_names, bone_names).items()}
    for muscle, bones_of in earlier_fibre_bones(path).items():
        if muscle in muscle_names and set(bones_of) <= set(bone_names):
            named.setdefault(muscle, (*bones_of, FIBRES_FILE))
    generator = FibreGenerator()
    generator.SetInputConnection(0, muscles.GetOutputPort())
    generator.SetInputConnection(1, bones.GetOutputPort())
    muscle, origin, insertion = ATTACHMENT_COLUMNS
    generator.SetInputDataObject(2, V.make_table({
        muscle: list(named), origin: [bones_of[0] for bones_of in named.values()],
        insertion: [bones_of[1] for bones_of in named.values()]}))
    generator.SetFibreCount(count)
    generator.SetPointsPerFibre(points)
    start = wallclock.perf_counter()
    with vtk_messages():      # the filter's error is raised, not printed as well
        generator.Update()
    seconds = wallclock.perf_counter() - start
    fibres = generator.GetOutputDataObject(0)
    made = {}
    for muscle, block in V.blocks(fibres, FIBRES_FILE):
        origin, insertion = V.field(block, A.ORIGIN_BONE), V.field(block, A.INSERTION_BONE)
        how = named[muscle][2] if muscle in named else "inferred"
        made[muscle] = (origin, insertion, how)
        report(f"  {muscle}: {origin} -> {insertion} ({how}), "
               f"{block.GetNumberOfLines()} fibres")
    for stale in listed_block_files(path):
        os.remove(stale)
    write_multiblock(fibres, path)
    report(f"{len(made)} muscles in {seconds:.1f} s ({seconds / max(len(made), 1):.1f} s per "
           f"muscle) -> {path}")
    return made
