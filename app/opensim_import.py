"""Scenes from OpenSim (DESIGN §7 "Importers", issue 50): ``muscle-mss import-opensim MODEL.osim
MOTION.mot OUT [--muscles DIR]``.

* ``bones.vtm``: each body's mesh files (found as OpenSim finds them: beside the model, then in
  its ``Geometry`` folder), scaled by the mesh's scale factors and placed by its frame (the body
  or an offset frame on it) at the model's default pose, metres to millimetres, a body's meshes
  in one block named after it, cleaned as muscles are (closed, outward);
* ``motion.csv``: for every row of the motion, each body's transform from the default pose to
  that row's pose, ``G(t) G(default)^-1`` with OpenSim's own kinematics (the coordinates set,
  the position stage realised), translation in millimetres;
* ``muscles.vtm``: one surface file per muscle in ``--muscles DIR`` (name = file stem, sorted),
  cleaned and at the cage's density (:func:`~muscle_mss.filters.mesh_files.muscle_from_file`),
  assumed in the model's ground frame at its default pose;
* ``reference_lengths.csv``: the model's muscle-tendon lengths (``Muscle.getLength``) at every
  row, for the model's muscles named like a muscle file (:mod:`.reference_lengths`).

The fibres are added by ``muscle-mss fibres OUT``. ``opensim`` (pip, the ``opensim`` extra) is
imported only here, when the command runs.
"""
from __future__ import annotations

import os

import numpy as np

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.mesh_cleaning import clean_surface
from muscle_mss.core.scene import (BONES_FILE, MOTION_COLUMNS, MOTION_FILE, MUSCLES_FILE,
                                   Surface)
from muscle_mss.filters.mesh_files import (MESH_SUFFIXES, block_files, muscle_from_file,
                                           read_mesh_file, write_surfaces)

from . import output_folder
from .reference_lengths import REFERENCE_LENGTHS_FILE, write_reference_lengths
from .run_output import output_folder as held_folder, write_csv

INSTALL_HINT = ("pip install 'muscle-mss[opensim]' in the Python that runs muscle-mss "
                "(./setup.sh installs it into .venv)")
GEOMETRY_FOLDER = "Geometry"
"""The folder beside a model where OpenSim also looks for its mesh files."""
TO_MM = 1000.0


def opensim_module():
    """The ``opensim`` package, or an error saying how to install it. Its log file sink is
    removed: OpenSim would otherwise write ``opensim.log`` into the user's working folder."""
    try:
        import opensim
    except ImportError as err:
        raise MuscleMSSError(f"import-opensim needs the opensim package, which this Python "
                             f"cannot import ({err}); install it: {INSTALL_HINT}") from None
    opensim.Logger.removeFileSink()
    return opensim


def load_model(osim, path: str):
    """``(model, state)``: the model at ``path`` with its system built; the state holds every
    coordinate at its default value."""
    if not os.path.isfile(path):
        raise MuscleMSSError(f"{path}: no such model file")
    try:
        model = osim.Model(path)
        return model, model.initSystem()
    except RuntimeError as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise MuscleMSSError(f"{path}: OpenSim could not load the model ({first})") from None


def matrix34(transform) -> np.ndarray:
    """A SimTK Transform as a (3, 4) array ``[R | p]`` (p in the model's metres)."""
    rotation = transform.R().asMat33()
    out = np.empty((3, 4))
    out[:, :3] = [[rotation.get(i, j) for j in range(3)] for i in range(3)]
    out[:, 3] = transform.p().to_numpy()
    return out


def mesh_path(model_path: str, mesh_file: str, body: str) -> str:
    """The file of a mesh as OpenSim finds it: an absolute path as it is, else beside the model,
    then in its ``Geometry`` folder; a file in neither is an error naming the places."""
    folder = os.path.dirname(os.path.abspath(model_path))
    places = ([mesh_file] if os.path.isabs(mesh_file) else
              [os.path.join(folder, mesh_file), os.path.join(folder, GEOMETRY_FOLDER, mesh_file)])
    for place in places:
        if os.path.isfile(place):
            return place
    raise MuscleMSSError(f"{model_path}: body '{body}': mesh file '{mesh_file}' not found; "
                         f"looked in {' and '.join(places)}")


def body_meshes(osim, model, state, model_path: str):
    """``(bones, frames, files)``: ``{body: Surface}`` in mm at the default pose (each body's
    meshes joined and cleaned; bodies without a mesh left out), ``{body: its frame}`` and the
    mesh files read."""
    parts, frames = {}, {}
    # the whole list first: an error raised inside OpenSim's iteration is reported twice
    meshes = [osim.Mesh.safeDownCast(c) for c in model.getComponentsList()
              if c.getConcreteClassName() == "Mesh"]
    for mesh in meshes:
        frame = mesh.getFrame()
        name = frame.findBaseFrame().getName()
        path = mesh_path(model_path, mesh.get_mesh_file(), name)
        points, triangles = read_mesh_file(path, f"{path} (mesh of body '{name}')")
        placed = matrix34(frame.getTransformInGround(state))
        points = points * mesh.get_scale_factors().to_numpy()
        points = TO_MM * (points @ placed[:, :3].T + placed[:, 3])
        parts.setdefault(name, []).append((points, triangles, path))
        frames[name] = frame.findBaseFrame()
    bones = {}
    for name, meshes in parts.items():
        offsets = np.cumsum([0] + [len(p) for p, _, _ in meshes[:-1]])
        triangles = np.vstack([t + o for (_, t, _), o in zip(meshes, offsets)])
        where = (f"{model_path} body '{name}' (mesh files "
                 f"{', '.join(os.path.basename(f) for _, _, f in meshes)})")
        points, triangles, _ = clean_surface(np.vstack([p for p, _, _ in meshes]), triangles,
                                             where)
        bones[name] = Surface(points, triangles)
    return bones, frames, [f for meshes in parts.values() for _, _, f in meshes]


def coordinate_columns(osim, model, state, labels, path: str) -> list:
    """The model coordinate of each motion column (``labels``; None for a ``.../speed``
    column of a coordinate, which the pose does not need), matched by name or by path
    (``/jointset/knee/knee_angle`` or ``.../value``). A column the model lacks, a coordinate
    twice, or a free coordinate (not locked, prescribed or dependent on others through a
    constraint) the motion lacks is an error naming it."""
    coordinates = list(model.getCoordinateSet())
    by_name = {c.getName(): c for c in coordinates}
    by_path = {c.getAbsolutePathString(): c for c in coordinates}
    found, used = [], set()
    for label in labels:
        stem = label[:-len("/value")] if label.endswith("/value") else label
        if label.endswith("/speed") and label[:-len("/speed")] in by_path:
            found.append(None)
            continue
        coordinate = by_name.get(stem) or by_path.get(stem)
        if coordinate is None:
            raise MuscleMSSError(f"{path}: column '{label}' is no coordinate of the model "
                                 f"(its coordinates: {', '.join(by_name)}); a motion holds "
                                 "the model's coordinates, by name or path")
        if coordinate.getName() in used:
            raise MuscleMSSError(f"{path}: column '{label}' gives coordinate "
                                 f"'{coordinate.getName()}' a second time")
        used.add(coordinate.getName())
        found.append(coordinate)
    for c in coordinates:
        free = not (c.get_locked() or c.get_prescribed() or c.isDependent(state))
        if free and c.getName() not in used:
            raise MuscleMSSError(f"{path}: the model's coordinate '{c.getName()}' "
                                 f"({c.getAbsolutePathString()}) is free (not locked, prescribed "
                                 "or constrained) but the motion has no column for it; add it "
                                 "or lock it in the model")
    return found


def read_motion(osim, model, state, path: str):
    """``(times (T,) s, [(coordinate, values (T,) rad or m)])`` of a ``.mot``/``.sto`` file;
    rotational coordinates converted from degrees when its header says ``inDegrees=yes``."""
    if not os.path.isfile(path):
        raise MuscleMSSError(f"{path}: no such motion file")
    try:
        table = osim.TimeSeriesTable(path)
    except RuntimeError as err:
        raise MuscleMSSError(f"{path}: OpenSim could not read the motion "
                             f"({str(err).strip().splitlines()[0]})") from None
    keys = list(table.getTableMetaDataKeys())
    if "inDegrees" not in keys:
        raise MuscleMSSError(f"{path}: the header has no inDegrees line; add inDegrees=yes "
                             "(angles in degrees) or inDegrees=no (radians) before endheader")
    degrees = table.getTableMetaDataAsString("inDegrees").strip().lower()
    if degrees not in ("yes", "no"):
        raise MuscleMSSError(f"{path}: inDegrees={degrees}; the header says inDegrees=yes "
                             "(angles in degrees) or inDegrees=no (radians)")
    times = np.array(table.getIndependentColumn(), dtype=np.float64)
    values = table.getMatrix().to_numpy().reshape(len(times), -1)
    labels = list(table.getColumnLabels())
    if len(times) == 0 or (np.diff(times) <= 0).any():
        raise MuscleMSSError(f"{path}: its times must rise from row to row (and there must be "
                             "a row)")
    bad = np.argwhere(~np.isfinite(values))
    if len(bad):
        r, c = bad[0]
        raise MuscleMSSError(f"{path} row {r + 1}, column {labels[c]}: not a number")
    rotational = osim.Coordinate.Rotational
    columns = []
    for coordinate, column in zip(coordinate_columns(osim, model, state, labels, path),
                                  values.T):
        if coordinate is None or coordinate.get_locked():   # locked: its default value
            continue
        turn = degrees == "yes" and coordinate.getMotionType() == rotational
        columns.append((coordinate, np.radians(column) if turn else column))
    return times, columns


def kinematics(osim, model, state, times, columns, frames: dict, muscles: list):
    """``(matrices (T, B, 3, 4), lengths (T, K))``: per motion row, each of ``frames``'s
    transform from the default pose (translation mm) and each of ``muscles``'s length (mm).
    A prescribed coordinate the motion lacks follows its function of time; with constraints
    the model is assembled (dependent coordinates)."""
    bodies = list(frames.values())
    default = [matrix34(b.getTransformInGround(state)) for b in bodies]
    prescribed = [c for c in model.getCoordinateSet() if c.get_prescribed()
                  and all(c.getName() != d.getName() for d, _ in columns)]
    constrained = model.getConstraintSet().getSize() > 0
    pose = osim.State(state)
    matrices = np.empty((len(times), len(bodies), 3, 4))
    lengths = np.empty((len(times), len(muscles)))
    for k, time in enumerate(times):
        pose.setTime(float(time))
        for coordinate, values in columns:
            coordinate.setValue(pose, float(values[k]), False)
        for coordinate in prescribed:
            value = coordinate.get_prescribed_function().calcValue(osim.Vector(1, float(time)))
            coordinate.setValue(pose, value, False)
        if constrained:
            model.assemble(pose)
        model.realizePosition(pose)
        for b, (body, rest) in enumerate(zip(bodies, default)):
            now = matrix34(body.getTransformInGround(pose))
            rotation = now[:, :3] @ rest[:, :3].T
            matrices[k, b, :, :3] = rotation
            matrices[k, b, :, 3] = TO_MM * (now[:, 3] - rotation @ rest[:, 3])
        lengths[k] = [TO_MM * m.getLength(pose) for m in muscles]
    return matrices, lengths


def muscle_files(folder: str | None) -> dict:
    """``{name: path}`` of the surface files in ``folder`` (name = file stem), sorted by name;
    ``{}`` without a folder. Two files of one name, or none at all, is an error."""
    if folder is None:
        return {}
    if not os.path.isdir(folder):
        raise MuscleMSSError(f"--muscles {folder}: no such folder")
    found = {}
    for entry in sorted(os.listdir(folder)):
        stem, suffix = os.path.splitext(entry)
        if suffix.lower() not in MESH_SUFFIXES or not os.path.isfile(os.path.join(folder, entry)):
            continue
        if stem in found:
            raise MuscleMSSError(f"--muscles {folder}: two files for muscle '{stem}' "
                                 f"({os.path.basename(found[stem])}, {entry}); one file per "
                                 "muscle")
        found[stem] = os.path.join(folder, entry)
    if not found:
        raise MuscleMSSError(f"--muscles {folder}: holds no surface file "
                             f"({', '.join(MESH_SUFFIXES)})")
    return dict(sorted(found.items()))


def write_motion(path: str, times, bones: list, matrices) -> None:
    """``motion.csv``: one row per (time, bone), time by time, with the scene's header."""
    write_csv(path, MOTION_COLUMNS, ((float(t), bone, *matrices[k, b].ravel())
                                     for k, t in enumerate(times)
                                     for b, bone in enumerate(bones)))


def import_opensim(model_path: str, motion_path: str, out: str, muscles_dir: str | None = None,
                   overwrite: bool = False, muscle_units: str = "auto", say=print,
                   log_level: str | None = None) -> dict:
    """Build the scene folder ``out`` from an OpenSim model, a motion and optionally a folder
    of muscle surface files (module docstring); ``say`` prints the summary lines;
    ``log_level``: OpenSim's log level from now on (the command's ``"error"``: OpenSim's info
    lines and its warnings about files it looks for itself would bury the summary, and setting
    the level back prints a line of its own), None: left as it is. Returns
    ``{"bones": [...], "muscles": [...], "skipped": [...], "matched": [...], "times": T}``."""
    osim = opensim_module()
    if log_level is not None:
        osim.Logger.setLevelString(log_level)
    files = muscle_files(muscles_dir)
    model, state = load_model(osim, model_path)
    bones, frames, mesh_files = body_meshes(osim, model, state, model_path)
    if not bones:
        raise MuscleMSSError(f"{model_path}: no body has a mesh; a scene needs bones")
    times, columns = read_motion(osim, model, state, motion_path)
    model_muscles = {m.getName(): m for m in model.getMuscles()}
    matched = [name for name in files if name in model_muscles]
    matrices, lengths = kinematics(osim, model, state, times, columns, frames,
                                   [model_muscles[name] for name in matched])
    muscles, notes = {}, {}
    for name, path in files.items():
        muscles[name], notes[name] = muscle_from_file(path, muscle_units)
    skipped = [b.getName() for b in model.getBodySet() if b.getName() not in bones]
    inputs = [model_path, motion_path, *mesh_files, *files.values()]
    write_scene_files(out, overwrite, inputs, bones, muscles, times, matrices,
                      {name: lengths[:, k] for k, name in enumerate(matched)}, say)
    say(f"bones: {len(bones)} bodies with meshes -> {BONES_FILE} ({', '.join(bones)})"
        + (f"; skipped, no mesh: {', '.join(skipped)}" if skipped else ""))
    say(f"motion: {len(times)} time points ({times[0]:g} to {times[-1]:g} s), "
        f"{len(columns)} coordinates -> {MOTION_FILE}")
    for name, note in notes.items():
        say(f"muscle {name}: {note}")
    if matched:
        say(f"reference lengths of {', '.join(matched)} -> {REFERENCE_LENGTHS_FILE}")
    unmatched = [name for name in files if name not in model_muscles]
    if unmatched:
        say(f"no reference length for {', '.join(unmatched)}: the model has no muscle of "
            "that name")
    say(f"wrote {out}; next: muscle-mss fibres {out}, then muscle-mss validate {out}"
        if muscles else f"wrote {out} without muscles (no --muscles folder given)")
    return {"bones": list(bones), "muscles": list(muscles), "skipped": skipped,
            "matched": matched, "times": len(times)}


def write_scene_files(out, overwrite, inputs, bones, muscles, times, matrices, lengths,
                      say=print):
    """Write the scene's files into ``out`` held as a run's output folder (its lock, manifest and
    ``--overwrite`` rules, :mod:`.output_folder`; inputs never removed or written over)."""
    names = [BONES_FILE, MOTION_FILE] + ([MUSCLES_FILE] if muscles else []) + (
        [REFERENCE_LENGTHS_FILE] if lengths else [])
    folders = [os.path.splitext(n)[0] for n in names if n.endswith(".vtm")]
    with held_folder(out, overwrite, names=names + folders, folders=folders,
                     inputs=inputs) as (removed, note):
        if note:
            say(note)
        if removed:
            say(f"replacing the earlier import in {out} ({len(removed)} files it wrote removed)")
        for filename, surfaces in ((BONES_FILE, bones), (MUSCLES_FILE, muscles)):
            if surfaces:
                output_folder.claim(out, filename, *block_files(filename, len(surfaces)))
                write_surfaces(surfaces, os.path.join(out, filename))
        output_folder.claim(out, MOTION_FILE)
        write_motion(os.path.join(out, MOTION_FILE), times, list(bones), matrices)
        if lengths:
            output_folder.claim(out, REFERENCE_LENGTHS_FILE)
            write_reference_lengths(os.path.join(out, REFERENCE_LENGTHS_FILE), times, lengths)
