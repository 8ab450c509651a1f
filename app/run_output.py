"""The files a run of a whole motion writes in its output folder (DESIGN §7).

What :mod:`muscle_mss.app.motion_run` computes, written the same way by ``muscle-mss demo``
/ ``muscle-mss run`` and the pvpython/pvbatch entry point ``muscle_mss.plugin.batch``:

* ``surfaces.pvd``, ``fibres.pvd``, ``particles.pvd``: time series (one ``.vtm`` per time point
  under ``series/``) of the deformed muscle surfaces, fibre polylines and solved particles;
* ``summary.csv``: one row per (time, muscle) with the columns of :data:`SUMMARY_COLUMNS`;
* ``convergence/convergence_<k>.csv``: the solver's per-iteration table of each time point.

Every file is written atomically (a reader sees the old file or the whole new one), and a
``.vtm`` never names files that are not there.
"""
from __future__ import annotations

import contextlib
import csv
import os
import re
import shutil
import tempfile
import time as wallclock
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from vtkmodules.vtkCommonCore import vtkAbstractArray, vtkDataArray, vtkVersion
from vtkmodules.vtkIOXML import vtkXMLMultiBlockDataWriter

from muscle_mss.core.errors import MuscleMSSError

from muscle_mss.filters import array_names as A
from . import output_folder as folder

SUMMARY_COLUMNS = (A.TIME, A.MUSCLE, A.REST_VOLUME, A.VOLUME, A.VOLUME_ERROR_PCT,
                   A.MEAN_FIBRE_STRAIN, A.MAX_FIBRE_STRAIN, A.MEAN_END_TO_END_STRAIN,
                   A.MEAN_KEPT_SHAPE_STRAIN,
                   A.MAX_ARC_CHORD, A.MAX_FIBRE_BEND, A.SPHERE_OVERLAP_MM,
                   A.NEW_IN_BONE_VERTICES, A.NEW_IN_BONE_DEPTH_MM, A.NEW_IN_BONE_VERTICES_AFTER,
                   A.NEW_IN_BONE_DEPTH_AFTER_MM, A.IN_OTHER_MUSCLE_VERTICES,
                   A.IN_OTHER_MUSCLE_DEPTH_MM, A.CAGE_DRIFT_VERTICES, A.CAGE_DRIFT_MM,
                   *A.FREE_IN_BONE_FIELDS, A.TISSUE_SHARE_PCT,
                   A.ITERATIONS, A.CONVERGED, A.SECONDS)
"""``mean_end_to_end_strain``: the mean over the muscle's fibres of their end-to-end distance over
that at rest, minus 1 (how much the muscle's origin-insertion length changed, to set beside
``mean_fibre_strain``, how much its fibres did); ``mean_kept_shape_strain``: the mean fibre
strain the muscle would have if it kept its rest shape and volume, stretched along its
origin-insertion line as far as its ends moved (a reference for ``mean_fibre_strain``: the
curved fibres of a muscle that thickens as it shortens change less than its ends);
``max_arc_chord``: the largest ratio of a fibre's length to its end-to-end distance (1 straight;
a fibre that folds instead of shortening goes well above); ``max_fibre_bend``: the largest ratio
of a fibre's arc / chord to its arc / chord at rest (1: as curved as at rest, so a fibre curved
at rest is not counted as folded; above: it folds, or wraps a bone the motion brings against
it); ``sphere_overlap_mm``: the deepest overlap of the muscle's collision spheres with spheres
of other muscles (:mod:`muscle_mss.core.contacts.penetration`) and with the bones as the
solver saw them (the solver's bone contact: solids, by their distance fields, or sphere sets);
``new_in_bone_*``: deformed surface vertices inside a bone they were outside at rest, before and
after the MVC Surface Deformer pushes them out; ``in_other_muscle_*``: deformed surface vertices inside another
muscle's deformed surface and the deepest, mm (what the spheres' overlap does not show: the
surfaces between them, and an overlap the scene had at rest); ``cage_drift_*``: how many
deformed surface vertices drifted off their cage by more than
:data:`~muscle_mss.core.cage_drift.CAGE_DRIFT_LIMIT` (the mean value coordinates carried them
far from the particles around them) and the largest drift, mm;
``free_particle*``: solved particles that are not tendon attachments with their centre inside a
bone, and the deepest (by the bones' signed distance fields), all of them and those not inside a
bone at rest (``*new_in_bone*``), as the MSS Collision Solver reports them;
``tissue_share_pct``: the connective tissue's force over the muscle's springs' force (%, 0
without tissue: the solver's connective tissue 0)."""
SURFACES, FIBRES, PARTICLES = "surfaces", "fibres", "particles"
SERIES = (SURFACES, FIBRES, PARTICLES)
"""The series a run writes (``--write`` picks some), each as ``<name>.pvd``."""
SUMMARY_FILE = "summary.csv"
SERIES_FOLDER = "series"
CONVERGENCE_FOLDER = "convergence"
CONVERGENCE_PICTURE = "convergence.png"
POSES_PICTURE = "poses.png"
RUN_FILES = (SUMMARY_FILE, *(f"{name}.pvd" for name in SERIES), CONVERGENCE_PICTURE,
             POSES_PICTURE, SERIES_FOLDER, CONVERGENCE_FOLDER)
"""What a run writes in its output folder (files and folders): another run's results."""
PARALLEL_WRITES = (vtkVersion.GetVTKMajorVersion(), vtkVersion.GetVTKMinorVersion()) > (9, 2)
"""Whether :func:`write_time_point` writes the series each by its own thread: the pip VTK (9.7)
lets go of Python's lock in a writer's ``Write()`` (the demo thigh's three series at N = 20:
30 → 25 ms alone, 40 → 33 ms in a run on two cores), ParaView 5.11's VTK 9.2 does not (60 →
63 ms with threads)."""
COMPRESSOR_LZ4, COMPRESSOR_ZLIB, COMPRESSOR_NONE = "lz4", "zlib", "none"
COMPRESSORS = (COMPRESSOR_LZ4, COMPRESSOR_ZLIB, COMPRESSOR_NONE)
"""Compressors of the series' appended binary data: LZ4 (default: fast, readable by ParaView
5.x), ZLib (smaller, slower: VTK's own default) or none (fastest, largest)."""
DEFAULT_COMPRESSOR = COMPRESSOR_LZ4
STAGING_PREFIX = ".writing-"
"""The name of a time point's private folder under ``series/`` while it is written."""


@dataclass(frozen=True)
class Writing:
    """What is written of each time point, and how: the series (some of :data:`SERIES`, in
    that order) and the compressor of their binary data (one of :data:`COMPRESSORS`)."""

    series: tuple = SERIES
    compressor: str = DEFAULT_COMPRESSOR


def series_file(name: str, index: int) -> str:
    """Relative path of one time point's file of a series."""
    return os.path.join(SERIES_FOLDER, f"{name}_{index:04d}.vtm")


def series_blocks_folder(name: str, index: int) -> str:
    """Relative path of the folder of one time point's ``.vtp`` files of a series (VTK's
    writer names it after the ``.vtm``), moved into place whole."""
    return os.path.splitext(series_file(name, index))[0]


def time_point_places(index: int, series_names=SERIES) -> list:
    """``(relative path, is_folder)`` of what :func:`write_time_point` places for time point
    ``index``: each series' ``.vtm`` and its folder of blocks, and the convergence table."""
    places = []
    for name in series_names:
        places += [(series_file(name, index), False), (series_blocks_folder(name, index), True)]
    return places + [(convergence_file(index), False)]


def run_places(indices, series_names=SERIES) -> list:
    """:func:`time_point_places` of every time point of ``indices``: what a run writing them
    places below ``series/`` and ``convergence/``, checked before it solves."""
    return [place for index in indices for place in time_point_places(index, series_names)]


def index_file(name: str) -> str:
    """The ``.pvd`` index of a series: its time points' files and times."""
    return f"{name}.pvd"


def convergence_file(index: int) -> str:
    """Relative path of one time point's convergence table."""
    return os.path.join(CONVERGENCE_FOLDER, f"convergence_{index:04d}.csv")


@contextlib.contextmanager
def output_folder(out: str, overwrite: bool = False, names=RUN_FILES,
                  folders=(SERIES_FOLDER, CONVERGENCE_FOLDER), places=(), inputs=(), check=None):
    """Hold ``out`` for a run (its lock, :mod:`~muscle_mss.app.output_folder`) for the
    ``with`` block, after checking it before solving: created if missing, writable, no name of
    ``names`` (the run's files and ``folders``; default a motion run's, :data:`RUN_FILES`)
    taken by a file or folder the run did not write, nor any of ``places`` (the files and
    folders it places deeper, :func:`run_places`), no manifest line naming one of ``inputs``
    (the files the run reads; ``check``, called first with the lock held, checks more), and no
    previous run's results, which ``overwrite`` removes (the files its manifest lists, so that
    no file of the earlier run, e.g. a time point it had in addition, stays beside the new
    ones). Yields
    ``(removed, note)``: the relative paths removed and the note of a lock taken over (or
    None). Raises :class:`MuscleMSSError` naming the folder and the cause."""
    if os.path.exists(out) and not os.path.isdir(out):
        raise MuscleMSSError(f"output folder {out} is a file; give a folder")
    try:
        os.makedirs(out, exist_ok=True)
    except OSError as err:
        raise MuscleMSSError(f"output folder {out} cannot be written: "
                             f"{err.strerror or err}") from None
    with folder.output_lock(out) as note:
        if check is not None:
            check()
        yield folder.prepare(out, overwrite, names, folders, places, inputs), note


def write_time_point(result, out: str, series_names=SERIES,
                     compressor: str = DEFAULT_COMPRESSOR) -> None:
    """Write one time point's (a :class:`~muscle_mss.app.motion_run.TimePointResult`) series
    files (those of ``series_names``, a subset of
    :data:`SERIES`) and convergence table under ``out``; the series as appended raw binary
    compressed with ``compressor`` (one of :data:`COMPRESSORS`). Adds the seconds taken to
    ``result.timings["write"]``.

    Each ``.vtm`` is written with its ``.vtp`` files into a private folder first
    (:func:`stage_time_point`), checked (the writer succeeded and every file the ``.vtm`` names
    exists), then renamed into ``series/`` (:func:`place_time_point`): a failed write raises
    :class:`MuscleMSSError` and never leaves a ``.vtm`` pointing at missing files. Where VTK
    lets it (:data:`PARALLEL_WRITES`) the series are written at the same time, each by its own
    thread (they share no array); this returns when all are written."""
    start = wallclock.perf_counter()
    place_time_point(result, stage_time_point(result, out, series_names, compressor), out)
    result.timings["write"] = wallclock.perf_counter() - start


@dataclass
class Staged:
    """One time point's series written into its private folder ``staging`` (under
    ``OUT/series``) by :func:`stage_time_point`, not yet in place: ``written`` holds
    ``(series name, staged .vtm, whether its writer succeeded)``. A worker process stages, the
    run's process places (:mod:`~muscle_mss.app.motion_jobs`)."""

    staging: str
    written: list


def stage_time_point(result, out: str, series_names=SERIES,
                     compressor: str = DEFAULT_COMPRESSOR) -> Staged:
    """Write the series of ``result`` (as :func:`write_time_point`) into a new private folder
    under ``OUT/series``, nothing in place yet: :func:`place_time_point` checks and places
    them, :func:`discard_staged` removes them."""
    series = os.path.join(out, SERIES_FOLDER)
    try:
        os.makedirs(series, exist_ok=True)
        os.makedirs(os.path.join(out, CONVERGENCE_FOLDER), exist_ok=True)
        staging = tempfile.mkdtemp(dir=series, prefix=STAGING_PREFIX)
    except OSError as err:
        raise MuscleMSSError(f"cannot write {series}: {err.strerror or err}") from None

    def write(name, data):
        staged = os.path.join(staging, os.path.basename(series_file(name, result.index)))
        writer = vtkXMLMultiBlockDataWriter()
        writer.SetFileName(staged)
        writer.SetInputData(data)
        configure_writer(writer, compressor)
        return name, staged, writer.Write() == 1 and writer.GetErrorCode() == 0

    jobs = [(name, data) for name, data in
            zip(SERIES, (result.surfaces, result.fibres, result.particles))
            if name in series_names]
    for _, data in jobs:
        forget_ranges(data)
    try:
        with ThreadPoolExecutor(max(len(jobs), 1) if PARALLEL_WRITES else 1) as writers:
            return Staged(staging, list(writers.map(lambda job: write(*job), jobs)))
    except OSError as err:
        shutil.rmtree(staging, ignore_errors=True)
        raise MuscleMSSError(f"cannot write {series}: {err.strerror or err}") from None
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise


_RANGE_KEYS = (vtkAbstractArray.PER_COMPONENT(), vtkAbstractArray.PER_FINITE_COMPONENT(),
               vtkDataArray.L2_NORM_RANGE(), vtkDataArray.L2_NORM_FINITE_RANGE())


def forget_ranges(data) -> None:
    """Remove the value ranges VTK keeps in the information of each array of the multiblock
    ``data`` (computed when an array was written before): the XML writer writes an array
    that holds them in a longer form, so that a time point's file would depend on whether
    its arrays passed through the writer at an earlier time point (the arrays the stages
    before the solver make once and pass on) in the same process."""
    for index in range(data.GetNumberOfBlocks()):
        block = data.GetBlock(index)
        if block is None:
            continue
        if block.IsA("vtkMultiBlockDataSet"):
            forget_ranges(block)
            continue
        for attributes in (block.GetPointData(), block.GetCellData(), block.GetFieldData()):
            for k in range(attributes.GetNumberOfArrays()):
                array = attributes.GetAbstractArray(k)
                if array is not None and array.HasInformation():
                    information = array.GetInformation()
                    for key in _RANGE_KEYS:
                        information.Remove(key)


def place_time_point(result, staged: Staged, out: str) -> None:
    """Check the series :func:`stage_time_point` wrote for ``result`` and rename them into
    place (each ``.vtm`` after its folder of blocks), then write its convergence table; the
    private folder is removed either way."""
    try:
        for name, vtm, succeeded in staged.written:
            final = series_file(name, result.index)
            named = _check_written(vtm, os.path.join(out, final), succeeded)
            folder.claim(out, final, *(os.path.join(os.path.dirname(final), n) for n in named))
            _move_into_place(vtm, os.path.join(out, final),
                             os.path.join(out, series_blocks_folder(name, result.index)))
    except OSError as err:
        raise MuscleMSSError(f"cannot write {os.path.join(out, SERIES_FOLDER)}: "
                             f"{err.strerror or err}") from None
    finally:
        discard_staged(staged)
    folder.claim(out, convergence_file(result.index))
    write_columns(os.path.join(out, convergence_file(result.index)), result.convergence)


def discard_staged(staged: Staged) -> None:
    """Remove what :func:`stage_time_point` wrote and was not placed."""
    shutil.rmtree(staged.staging, ignore_errors=True)


def remove_stale_staging(out: str) -> None:
    """Remove the private folders of :func:`stage_time_point` left under ``OUT/series`` by
    processes that were stopped while they wrote (the caller holds ``out``: no other run
    writes there)."""
    with contextlib.suppress(FileNotFoundError):
        for entry in os.scandir(os.path.join(out, SERIES_FOLDER)):
            if entry.name.startswith(STAGING_PREFIX) and entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path, ignore_errors=True)


def configure_writer(writer, compressor: str) -> None:
    """Appended raw binary (no base64) with ``compressor`` (one of :data:`COMPRESSORS`)."""
    writer.SetDataModeToAppended()
    writer.EncodeAppendedDataOff()
    {COMPRESSOR_LZ4: writer.SetCompressorTypeToLZ4,
     COMPRESSOR_ZLIB: writer.SetCompressorTypeToZLib,
     COMPRESSOR_NONE: writer.SetCompressorTypeToNone}[compressor]()


def parse_write_option(text: str) -> tuple:
    """The series named by a ``--write`` option (``surfaces,fibres,particles`` or a part of it,
    in any order), in :data:`SERIES` order; :class:`MuscleMSSError` naming an unknown one."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in SERIES]
    if not names:
        raise MuscleMSSError(f"--write {text!r} names no series to write; give one or more of "
                             f"{','.join(SERIES)} (without --write all are written)")
    if unknown:
        raise MuscleMSSError(f"--write {text!r}: {', '.join(unknown)} is not a series; give "
                             f"one or more of {','.join(SERIES)}")
    return tuple(n for n in SERIES if n in names)


def _check_written(vtm: str, final: str, writer_ok: bool) -> list:
    """The files ``vtm`` names (relative to its folder); raise unless the writer reported
    success and wrote ``vtm`` and every file it names."""
    missing = [] if os.path.isfile(vtm) else [os.path.basename(final)]
    named = []
    if not missing:
        with open(vtm) as f:
            named = re.findall(r'file="([^"]+)"', f.read())
        missing = [n for n in named if not os.path.isfile(os.path.join(os.path.dirname(vtm), n))]
    if missing or not writer_ok:
        raise MuscleMSSError(f"writing {final} failed"
                             + (f": {', '.join(missing)} not written" if missing else "")
                             + "; check the free space and permissions of the output folder")
    return named


def _move_into_place(staged_vtm: str, final_vtm: str, final_dir: str) -> None:
    """Rename a staged ``.vtm`` and its folder of ``.vtp`` files into place (``final_vtm``,
    ``final_dir``: :func:`series_blocks_folder`); the ``.vtm`` last,
    so that it never names files that are not there. A folder in the way is not ours (the
    output folder's check removed the previous run's files): refused, never removed."""
    staged_dir = os.path.splitext(staged_vtm)[0]
    for path in (final_dir, final_vtm):
        if os.path.lexists(path) and (path == final_dir or os.path.isdir(path)
                                      or os.path.islink(path)):
            raise MuscleMSSError(f"cannot write {final_vtm}: {path} is in the way and muscle-mss "
                                 f"did not write it; move it away")
    if os.path.isdir(staged_dir):
        os.replace(staged_dir, final_dir)
    os.replace(staged_vtm, final_vtm)


def _write_atomically(path: str, text_lines) -> None:
    """Write ``path`` through a temporary file renamed over it; raise :class:`MuscleMSSError`
    naming the file when it cannot be written."""
    temporary = f"{path}.{os.getpid()}.tmp"
    try:
        with open(temporary, "w", newline="") as f:
            text_lines(f)
        os.replace(temporary, path)
    except OSError as err:
        if os.path.exists(temporary):
            os.remove(temporary)
        raise MuscleMSSError(f"cannot write {path}: {err.strerror or err}") from None


def write_csv(path, header, rows) -> None:
    """Write a CSV file (atomically: a reader sees the old file or the whole new one)."""
    def lines(f):
        out = csv.writer(f)
        out.writerow(header)
        for row in rows:
            out.writerow([_csv_value(v) for v in row])
    _write_atomically(path, lines)


def write_columns(path, columns: dict) -> None:
    """Write a table of ``columns`` (name → NumPy array or list) as :func:`write_csv` would
    write its rows (the same bytes), column by column: a time point's convergence table (500 x
    17 values) took 11 ms through ``csv.writer``, most of it per-value Python calls."""
    texts = [[str(name) for name in columns]]
    for values in columns.values():
        if isinstance(values, np.ndarray) and values.dtype.kind == "f":
            texts.append(list(map(repr, values.tolist())))     # float repr, as _csv_value
        elif isinstance(values, np.ndarray) and values.dtype.kind in "iub":
            texts.append(list(map(str, values.tolist())))           # ints; bools as True
        else:
            texts.append(None)
    if any(t is None for t in texts[1:]):        # text or mixed columns: the csv module
        write_csv(path, list(columns), zip(*columns.values()))
        return
    header, *cells = texts
    rows = [",".join(header)] + [",".join(row) for row in zip(*cells)]
    _write_atomically(path, lambda f: f.write("\r\n".join(rows) + "\r\n"))


def _csv_value(v):
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, np.integer):
        return int(v)
    return v


def write_index(out: str, times, indices=None, series_names=SERIES) -> None:
    """Write the ``.pvd`` index of each series of ``series_names`` for time points ``indices``
    (default ``0..len(times)-1``) at ``times``."""
    indices = range(len(times)) if indices is None else indices
    folder.claim(out, *map(index_file, series_names))
    for name in series_names:
        entries = "\n".join(f'    <DataSet timestep="{t!r}" group="" part="0" '
                            f'file="{series_file(name, i)}"/>' for i, t in zip(indices, times))
        _write_atomically(os.path.join(out, index_file(name)), lambda f: f.write(
            '<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n'
            f"  <Collection>\n{entries}\n  </Collection>\n</VTKFile>\n"))


def write_summary(out: str, rows) -> str:
    """Write ``summary.csv`` (rows sorted by time point, muscles in scene order)."""
    folder.claim(out, SUMMARY_FILE)
    path = os.path.join(out, SUMMARY_FILE)
    write_csv(path, SUMMARY_COLUMNS, ([r[c] for c in SUMMARY_COLUMNS] for r in rows))
    return path
