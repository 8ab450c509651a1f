"""The frame cache bound to a pipeline: what the MSS Collision Solver (:class:`SolverFrames`)
and the MVC Surface Deformer (:class:`SurfaceFrames`) store and load per time, and whether a
pipeline's frames are determined by the key at all (:func:`upstream_scene`: fed by one scene
folder's readers through the Muscle MSS filters, nothing else) (DESIGN §6 "Frame cache"; the
store, the key and the entries: :mod:`~muscle_mss.filters.frame_cache`).
"""
from __future__ import annotations

import dataclasses
import importlib
import os

import numpy as np
from vtkmodules.vtkCommonCore import vtkOutputWindow

from muscle_mss.core.attachment_areas import ATTACHMENTS_FILE
from muscle_mss.core.scene import BONES_FILE, FIBRES_FILE, MOTION_FILE, MUSCLES_FILE

from .base import MuscleFilter, reader_files
from .frame_cache import (KEYED_FILTERS, SURFACES, DamagedEntry, FrameStore, filter_name,
                          frame_key, scene_digest)


def result_parts(result) -> tuple:
    """``(arrays, scalars)`` of a solver result (a :class:`~muscle_mss.core.model.SolveResult`
    dataclass): its arrays and NumPy scalars (as 0-d arrays, keeping their dtype) for the
    payload, the rest (text, Python numbers, dicts, None) and its class for the header."""
    arrays, scalars = {}, {"__class__": f"{type(result).__module__}:{type(result).__qualname__}"}
    for f in dataclasses.fields(result):
        value = getattr(result, f.name)
        if isinstance(value, (np.ndarray, np.generic)):
            arrays[f.name] = np.asarray(value)
        elif isinstance(value, dict):
            scalars[f.name] = {k: v.item() if isinstance(v, np.generic) else v
                               for k, v in value.items()}
        else:
            scalars[f.name] = value
    return arrays, scalars


def result_from_parts(arrays: dict, scalars: dict):
    """The solver result :func:`result_parts` took apart."""
    module, _, name = scalars["__class__"].partition(":")
    if not module.startswith("muscle_mss.core."):
        raise DamagedEntry(f"names the class {scalars['__class__']}, not a solver result")
    cls = getattr(importlib.import_module(module), name)
    values = {k: v for k, v in scalars.items() if k != "__class__"}
    for k, v in arrays.items():
        values[k] = v[()] if v.ndim == 0 else v
    return cls(**values)


class SolverFrames:
    """A :class:`FrameStore` bound to a pipeline: what the MSS Collision Solver asks at each
    solve (:meth:`load`, :meth:`save` by time), keyed by the scene's files (hashed once, or
    their digest ``scene``) and the ``filters``' properties as they are at that moment (a
    study changes the solver's between solves). Counts ``loaded``, ``solved`` (saved),
    ``damaged`` and ``uncached`` (solves whose answer depends on more than the key)."""

    STAGE = None
    """The key's ``stage`` (:func:`frame_key`)."""

    @staticmethod
    def parts(value) -> tuple:
        """``(arrays, scalars)`` of what is stored (:func:`result_parts`)."""
        return result_parts(value)

    @staticmethod
    def value_of(arrays: dict, scalars: dict):
        """What :meth:`parts` took apart (:func:`result_from_parts`)."""
        return result_from_parts(arrays, scalars)

    def __init__(self, cache: FrameStore, scene_folder, filters, scene: str | None = None):
        self.cache = cache
        self.scene = scene_digest(scene_folder) if scene is None else scene
        self.filters = tuple(filters)
        self.loaded = self.solved = self.uncached = 0
        self._told = False

    def cacheable(self) -> bool:
        """Whether the solver's answer is a function of the key (the solver's
        ``history_dependence``: not when it starts from the frame solved before, nor when it
        stops on the clock)."""
        solver = next(f for f in self.filters if hasattr(f, "history_dependence"))
        reason = solver.history_dependence()
        if reason and not self._told:
            self._told = True
            self.cache.warn(f"note: the frame cache is not used: {reason}, so a stored frame "
                            "would not be the one solved now")
        return reason is None

    def key(self, time: float) -> dict:
        return frame_key(self.scene, self.filters, time, self.STAGE)

    def load(self, time: float):
        """What is stored for ``time``, or None (then the filter computes it)."""
        if not self.cacheable():
            self.uncached += 1
            return None
        parts = self.cache.load(self.key(time))
        if parts is None:
            return None
        try:
            result = self.value_of(*parts)
        except (DamagedEntry, TypeError, ValueError, KeyError, AttributeError,
                ImportError) as err:
            self.cache.warn(f"warning: frame cache entry {self.cache.path(self.key(time))} "
                            f"does not hold what it should ({err}); computing the frame again")
            return None
        self.loaded += 1
        return result

    def save(self, time: float, result) -> None:
        """Store ``result`` of ``time`` (nothing when it is not cacheable)."""
        self.solved += 1
        if self.cacheable():
            self.cache.save(self.key(time), *self.parts(result))

    def summary(self) -> str:
        """``frame cache: 21 of 21 frames loaded, 0 solved (DIR)``."""
        total = self.loaded + self.solved
        return (f"frame cache: {self.loaded} of {total} frames loaded, {self.solved} solved "
                f"({self.cache.folder})")


class SurfaceFrames(SolverFrames):
    """The MVC Surface Deformer's :class:`SolverFrames`: per time, each muscle's deformed
    surface points (after the push out of the bones) and its report (the field data: the push,
    the drift, the vertices in other muscles), keyed by the solver's key and the deformer's
    properties (:data:`SURFACE_KEYED_FILTERS`). What the deformer makes of them (the surfaces'
    arrays, the fibres) is computed on every frame, loaded or not."""

    STAGE = SURFACES

    @staticmethod
    def parts(value) -> tuple:
        surfaces, reports = value
        arrays = {f"surface {k}": np.asarray(points) for k, points in enumerate(surfaces)}
        fields = []
        for k, report in enumerate(reports):
            fields.append({})
            for name, v in report.items():
                if isinstance(v, np.ndarray):
                    arrays[f"report {k} {name}"] = v
                else:
                    fields[k][name] = v.item() if isinstance(v, np.generic) else v
        return arrays, {"reports": fields, "order": [list(report) for report in reports]}

    @staticmethod
    def value_of(arrays: dict, scalars: dict):
        values = [dict(fields) for fields in scalars["reports"]]
        surfaces = [arrays.pop(f"surface {k}") for k in range(len(values))]
        for name, v in arrays.items():
            _, k, field = name.split(" ", 2)
            values[int(k)][field] = v
        return surfaces, [{name: report[name] for name in order}      # in the computed order
                          for report, order in zip(values, scalars["order"])]


SCENE_READS = (MUSCLES_FILE, FIBRES_FILE, BONES_FILE, MOTION_FILE)
OPTIONAL_READS = (ATTACHMENTS_FILE,)
"""The scene files a cached pipeline's readers read: all of the first, any of the second."""
PASSING = ("vtkPVPostFilter",)
"""What ParaView puts behind every output port: it passes the data on (adding only arrays a view
asks for)."""


def pipeline_frames(owner, upstream, frames_class):
    """The ``frames_class`` (:class:`SolverFrames` or a
    subclass) of the filter ``owner``, fed by the filters named ``upstream`` and the scene's
    readers, in the frame cache folder of the solver (``owner`` or among ``upstream``:
    :meth:`~muscle_mss.filters.collision_solver.MSSCollisionSolver.frame_folder`); None when that is off or when the pipeline's
    frames are not determined by the key (said once among the messages). Kept on ``owner``
    while the folder, the scene files and the filters are the same."""
    found = upstream_scene(owner, upstream)
    if isinstance(found, str):
        folder = owner.frame_folder() if hasattr(owner, "frame_folder") else None
        if folder is not None and found != owner._frames_note:
            vtkOutputWindow.GetInstance().DisplayText(
                f"{owner.LABEL}: the frame cache is not used: {found}\n")
        owner._frames_note = found
        return None
    owner._frames_note = None
    filters, scene_folder, stamps = found
    solver = next(f for f in (*filters, owner) if hasattr(f, "frame_folder"))
    folder = solver.frame_folder()
    if folder is None:
        return None
    if owner._scene[0] != stamps:
        owner._scene = (stamps, scene_digest(scene_folder))
    made_for = (folder, owner._scene[1], tuple(id(f) for f in filters))
    if owner._frames[0] != made_for:
        warn = lambda text: vtkOutputWindow.GetInstance().DisplayWarningText(  # noqa: E731
            f"{owner.LABEL}: {text}\n")
        owner._frames = (made_for, frames_class(FrameStore(folder, warn=warn), scene_folder,
                                                (*filters, owner), scene=owner._scene[1]))
    return owner._frames[1]


def upstream_scene(owner, upstream=KEYED_FILTERS[:-1]):
    """``(filters, scene folder, stamps)`` of the pipeline feeding the filter ``owner``: the
    Muscle MSS filters upstream of it (one of each named in ``upstream``, in that order) and
    the folder whose four scene files its readers read, with the readers' output times
    (``stamps``: the files are hashed again when a reader read again). A text saying why
    not when anything else feeds it: another filter, a reader of other files, files of two
    folders. Then the scene files and the properties do not determine the frame."""
    filters, files, stamps, seen, stack = {}, {}, [], {}, [owner]
    while stack:
        algorithm = stack.pop()
        for port in range(algorithm.GetNumberOfInputPorts()):
            for c in range(algorithm.GetNumberOfInputConnections(port)):
                producer = algorithm.GetInputConnection(port, c).GetProducer()
                if producer.__this__ in seen:      # the C++ object: wrappers come and go
                    continue
                seen[producer.__this__] = producer
                if producer.GetClassName() in PASSING:
                    stack.append(producer)
                    continue
                if isinstance(producer, MuscleFilter):
                    name = filter_name(producer)
                    if name not in upstream or name in filters:
                        return f"{producer.LABEL} feeds it where the scene's filters do"
                    filters[name] = producer
                    stack.append(producer)
                    continue
                names = reader_files(producer)
                if names is None or producer.GetNumberOfInputPorts() > 0 or len(names) != 1:
                    return (f"{producer.GetClassName()} feeds it, not a reader of one scene "
                            "file")
                path = os.path.abspath(names[0])
                if os.path.basename(path) not in SCENE_READS + OPTIONAL_READS or \
                        files.get(os.path.basename(path), path) != path:
                    return (f"a reader of {names[0]} feeds it, not one of "
                            f"{', '.join(SCENE_READS + OPTIONAL_READS)}")
                files[os.path.basename(path)] = path
                data = producer.GetOutputDataObject(0)
                stamps.append((path, data.GetMTime() if data is not None else 0))
    folders = {os.path.dirname(p) for p in files.values()}
    if not set(SCENE_READS) <= set(files) or len(folders) != 1:
        return "its readers do not read the four files of one scene folder"
    if set(filters) != set(upstream):
        return f"it is not fed by the {', '.join(upstream)}"
    return (tuple(filters[n] for n in upstream), folders.pop(), tuple(sorted(stamps)))
