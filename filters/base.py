"""The base of the six filters: ports and properties from one table, errors, progress, time.

A filter subclasses :class:`MuscleFilter`, lists its ``INPUTS``, ``OUTPUTS`` (:class:`Port`) and
``PROPERTIES`` (:class:`~muscle_mss.core.properties.Property`), and implements
:meth:`MuscleFilter.execute`. It then works as a plain VTK algorithm in any Python with ``vtk``::

    f = FibreResampler(); f.SetInputConnection(0, reader.GetOutputPort()); f.Update()

and ``muscle_mss.plugin`` exposes the same class to ParaView. Bad input (DESIGN §8) is raised by
the core or the filter as :class:`MuscleMSSError`; the base turns it into a VTK error message
naming the filter plus empty outputs (what ParaView shows), and :meth:`MuscleFilter.Update`
re-raises it in Python — the error of the first failing filter upstream, not a follow-on one:
a filter downstream of a failed one empties its outputs without a message of its own. Any other
exception inside a filter becomes a :class:`MuscleMSSError` naming the filter, the exception and
the line it came from (:func:`wrapped_error`; VTK would print the traceback and carry on with
empty outputs); Ctrl-C becomes :class:`~muscle_mss.core.errors.Interrupted` naming the filter,
raised the same way, also when it reaches the filter as another exception it caused.
"""
from __future__ import annotations

import os
import weakref
import traceback
from dataclasses import dataclass

from vtkmodules.util.vtkAlgorithm import VTKPythonAlgorithmBase
from vtkmodules.vtkCommonCore import vtkOutputWindow
from vtkmodules.vtkCommonDataModel import vtkDataObject
from vtkmodules.vtkCommonExecutionModel import (vtkDemandDrivenPipeline,
                                                vtkStreamingDemandDrivenPipeline)

from muscle_mss.core.errors import Interrupted, MuscleMSSError

from muscle_mss.core.properties import Property

SDDP = vtkStreamingDemandDrivenPipeline
# the folder holding core/ and filters/: frames of muscle-mss in a traceback start with it (real
# paths: the installed package src/muscle_mss/ links to those folders)
_PACKAGE_ROOT = os.path.dirname(os.path.dirname(os.path.realpath(__file__))) + os.sep


@dataclass(frozen=True)
class Port:
    """An input or output port: ``name`` is the ParaView input property / output port name."""

    name: str
    data_type: str
    doc: str
    optional: bool = False


class MuscleFilter(VTKPythonAlgorithmBase):
    """Base of the muscle-mss filters; see the module docstring."""

    LABEL = ""          # ParaView label, e.g. "Fibre Resampler" (constructor FibreResampler())
    HELP = ""           # one paragraph: what the filter does, shown as its documentation
    INPUTS: tuple = ()
    OUTPUTS: tuple = ()
    PROPERTIES: tuple = ()

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        for prop in cls.PROPERTIES:
            if "Set" + prop.name not in vars(cls):
                setattr(cls, "Set" + prop.name, _make_setter(prop))
            if "Get" + prop.name not in vars(cls):
                setattr(cls, "Get" + prop.name, _make_getter(prop))

    def __init__(self):
        super().__init__(nInputPorts=len(self.INPUTS), nOutputPorts=len(self.OUTPUTS),
                         outputType=self.OUTPUTS[0].data_type)
        self._values = {p.name: p.stored_default for p in self.PROPERTIES}
        self._error = None
        self._request = None
        self._out_info = None

    # ---- properties ------------------------------------------------------------------------
    def value(self, name: str):
        """The stored value of a property (an enum's index)."""
        return self._values[name]

    def choice(self, name: str) -> str:
        """The text of an enum property's current choice."""
        prop = next(p for p in self.PROPERTIES if p.name == name)
        return prop.choices[self._values[name]]

    def _check_properties(self):
        for prop in self.PROPERTIES:
            problem = prop.range_problem(self._values[prop.name])
            if problem:
                raise MuscleMSSError(problem)

    # ---- ports -----------------------------------------------------------------------------
    def FillInputPortInformation(self, port, info):
        # every port optional for VTK: for a required one left unconnected VTK's executive
        # would skip RequestData with a message naming no input and leave the outputs empty
        # without an error; RequestData refuses it, naming the input (Port.optional is what
        # ParaView is told)
        info.Set(self.INPUT_REQUIRED_DATA_TYPE(), self.INPUTS[port].data_type)
        info.Set(self.INPUT_IS_OPTIONAL(), 1)
        return 1

    def FillOutputPortInformation(self, port, info):
        info.Set(vtkDataObject.DATA_TYPE_NAME(), self.OUTPUTS[port].data_type)
        return 1

    # ---- execution ---------------------------------------------------------------------------
    def RequestData(self, request, inInfo, outInfo):
        _running.append(self.LABEL)
        try:
            return self._request_data(request, inInfo, outInfo)
        except KeyboardInterrupt:   # before the filter's own handling began: not into VTK
            self._fail(interruption(self.LABEL), [])
            return 1
        finally:
            self._request = self._out_info = None
            _running.pop()

    def _request_data(self, request, inInfo, outInfo):
        # VTK 9.2/9.3 keep an abort flag set from the previous run (paraview-python-plugins §6).
        self.SetAbortExecute(0)
        self._error = None
        self._request, self._out_info = request, outInfo
        data_object = vtkDataObject.DATA_OBJECT()     # its Get: see vtk_arrays.blocks
        outputs = [data_object.Get(outInfo.GetInformationObject(i))
                   for i in range(self.GetNumberOfOutputPorts())]
        if upstream_error(self) is not None:
            # an upstream filter refused its input and emptied its outputs: its message is the
            # one to show (Update raises it), not a complaint about the empty data it left here
            for out in outputs:
                out.Initialize()
            return 1
        try:
            self._check_properties()
            inputs = []
            for i, port in enumerate(self.INPUTS):
                data = None
                if inInfo[i].GetNumberOfInformationObjects() > 0:
                    data = data_object.Get(inInfo[i].GetInformationObject(0))
                if data is None and not port.optional:
                    raise MuscleMSSError(f"input '{port.name}' is not connected; this input is "
                                         f"required: {port.doc[:1].lower()}{port.doc[1:]}")
                inputs.append(data)
            self._check_sources(inputs)
            self.execute(inputs, outputs)
        except MuscleMSSError as err:
            self._fail(err, outputs)
        except KeyboardInterrupt:
            self._fail(interruption(self.LABEL), outputs)
        except Exception as err:    # VTK would print it and go on with this filter's outputs
            self._fail(interruption(self.LABEL) if caused_by_ctrl_c(err)
                       else wrapped_error(self.LABEL, err), outputs)
        return 1

    @property
    def _error(self):
        """The :class:`MuscleMSSError` of this filter's last update, or None."""
        return self.__dict__.get("_recorded_error")

    @_error.setter
    def _error(self, err):
        self.__dict__["_recorded_error"] = err
        if err is None:
            _failing.discard(self)
        else:
            _failing.add(self)

    def _check_sources(self, inputs):
        """Refuse an empty input that a reader left empty because its file does not exist or
        cannot be read, naming the file: the filter's own check would call the input empty
        ("fibres.vtm has no blocks") when the file is what is missing (a state file loaded
        away from its data folder, after ParaView's reader error)."""
        for i, (port, data) in enumerate(zip(self.INPUTS, inputs)):
            if data is None or not is_empty(data):
                continue
            for c in range(self.GetNumberOfInputConnections(i)):
                problem = unread_file(self.GetInputConnection(i, c).GetProducer())
                if problem is not None:
                    name, why = problem
                    what = f"{os.path.basename(name)}: " if name else ""
                    raise MuscleMSSError(f"{what}the reader produced nothing for input "
                                         f"'{port.name}': {why}; {STATE_HINT}")

    def _fail(self, err, outputs):
        """Record ``err`` for :meth:`Update`, empty the outputs and show the message (ParaView's
        output messages; stderr in Python)."""
        err.filter_label = self.LABEL
        self._error = err
        for out in outputs:
            out.Initialize()
        vtkOutputWindow.GetInstance().DisplayErrorText(f"{self.LABEL}: {err}\n")

    def execute(self, inputs, outputs):
        """Compute ``outputs`` (the output data objects, to fill) from ``inputs`` (data objects,
        None for an unconnected optional port). Raise :class:`MuscleMSSError` on bad input."""
        raise TypeError(f"{type(self).__name__} does not define execute()")

    def SetInputData(self, *args):
        """``SetInputData(data)`` or ``SetInputData(port, data)``: connect a data object (as
        VTK's typed algorithms do; VTKPythonAlgorithmBase only has SetInputDataObject)."""
        port, data = (0, args[0]) if len(args) == 1 else args
        self.SetInputDataObject(port, data)

    def Update(self, *args):
        """Update the pipeline; raise the :class:`MuscleMSSError` of the first filter upstream
        (or this one) that refused its input."""
        return self._raising(super().Update(*args))

    def UpdateTimeStep(self, *args):
        """Update at a time (``UpdateTimeStep(t)``); raise like :meth:`Update`."""
        return self._raising(super().UpdateTimeStep(*args))

    def _raising(self, result):
        error = pipeline_error(self)
        if error is not None:
            raise error
        return result

    # ---- helpers for execute() ---------------------------------------------------------------
    def progress(self, fraction: float) -> bool:
        """Report progress (0..1) to ParaView; return True when the user asked to abort."""
        self.UpdateProgress(min(max(float(fraction), 0.0), 1.0))
        check = getattr(self, "CheckAbort", None)
        return bool(check()) if check is not None else bool(self.GetAbortExecute())

    def requested_time(self, default: float | None = None):
        """The time asked of this filter's outputs (UPDATE_TIME_STEP), or ``default``."""
        port = self._request.Get(vtkDemandDrivenPipeline.FROM_OUTPUT_PORT()) \
            if self._request is not None else 0
        info = self._out_info.GetInformationObject(max(port, 0))
        if info.Has(SDDP.UPDATE_TIME_STEP()):
            return info.Get(SDDP.UPDATE_TIME_STEP())
        return default


_failing = weakref.WeakSet()
"""The muscle-mss filters whose last update failed: while there is none, no pipeline has an
error to find (walking the upstream pipeline cost about 1.4 ms a filter update in pvpython)."""


def pipeline_error(algorithm):
    """The recorded error of the furthest-upstream muscle-mss filter feeding ``algorithm``
    (itself included), or None."""
    if not _failing:
        return None
    seen = set()

    def visit(alg):
        if alg is None or id(alg) in seen:
            return None
        seen.add(id(alg))
        for port in range(alg.GetNumberOfInputPorts()):
            for c in range(alg.GetNumberOfInputConnections(port)):
                upstream = visit(alg.GetInputConnection(port, c).GetProducer())
                if upstream is not None:
                    return upstream
        return getattr(alg, "_error", None)

    return visit(algorithm)


def upstream_error(algorithm):
    """The recorded error of a muscle-mss filter upstream of ``algorithm`` (not itself), or
    None."""
    if not _failing:
        return None
    for port in range(algorithm.GetNumberOfInputPorts()):
        for c in range(algorithm.GetNumberOfInputConnections(port)):
            error = pipeline_error(algorithm.GetInputConnection(port, c).GetProducer())
            if error is not None:
                return error
    return None


STATE_HINT = ("if the pipeline comes from a state file, load it with its data folder: "
              "LoadState(STATE, data_directory=FOLDER) in pvpython, 'Search files under "
              "specified directory' in ParaView's Load State dialog (see state_files/README.md)")
"""What the message of a reader's missing file advises: a state file keeps the file names it
was saved with."""


def is_empty(data) -> bool:
    """Whether a data object holds nothing: a multiblock without a non-empty leaf, a table
    without columns, a dataset without points."""
    if data.IsA("vtkCompositeDataSet"):
        it = data.NewIterator()
        it.SkipEmptyNodesOn()
        it.InitTraversal()
        return bool(it.IsDoneWithTraversal())
    if data.IsA("vtkTable"):
        return data.GetNumberOfColumns() == 0
    if data.IsA("vtkDataSet"):
        return data.GetNumberOfPoints() == 0
    return False


def reader_files(algorithm):
    """The file names ``algorithm`` reads if it is a reader (an empty name where none is set),
    else None: ParaView's file-series wrapper (``vtkFileSeriesReader``, which ParaView puts
    around its XML and CSV readers) gives the names it was given, another reader its
    ``FileName``."""
    count = getattr(algorithm, "GetNumberOfFileNames", None)
    if count is not None:
        return [algorithm.GetFileName(i) or "" for i in range(count())] or [""]
    get = getattr(algorithm, "GetFileName", None)
    if get is None:
        return None
    try:
        name = get()
    except TypeError:   # a GetFileName that needs an argument: not a reader's
        return None
    return [name if isinstance(name, str) else ""]


def unread_file(algorithm):
    """Why a reader at or upstream of ``algorithm`` (not through a muscle-mss filter, which
    reports its own inputs) has nothing to read: ``(file name, why)`` for the first of its
    files that is not set (name "") or does not exist or cannot be read, or None."""
    seen = set()

    def visit(alg):
        if alg is None or id(alg) in seen or isinstance(alg, MuscleFilter):
            return None
        seen.add(id(alg))
        for name in reader_files(alg) or ():
            if not name:
                return "", ("the reader has no file name (LoadState leaves it empty for a "
                            "file it does not find under its data_directory)")
            path = os.path.abspath(name)
            if not os.path.exists(path):
                return name, f"the file {path} does not exist"
            if not os.path.isfile(path):
                return name, f"{path} is not a file"
            if not os.access(path, os.R_OK):
                return name, f"the file {path} cannot be read (no permission)"
        for port in range(alg.GetNumberOfInputPorts()):
            for c in range(alg.GetNumberOfInputConnections(port)):
                problem = visit(alg.GetInputConnection(port, c).GetProducer())
                if problem is not None:
                    return problem
        return None

    return visit(algorithm)


_running = []
"""The labels of the muscle-mss filters executing now, innermost last: what a Ctrl-C that
reaches the caller outside a filter's error handling interrupted (:func:`running_filter`)."""


def running_filter():
    """The label of the muscle-mss filter executing now, or None."""
    return _running[-1] if _running else None


def interruption(label: str) -> Interrupted:
    """The :class:`Interrupted` of a Ctrl-C while filter ``label`` ran."""
    return Interrupted(f"Ctrl-C while {label} ran")


def interrupted_message(err: KeyboardInterrupt, command: str) -> str:
    """What the CLI and the batch print for a Ctrl-C that stopped ``command``: the filter's
    :class:`Interrupted`, or for a bare KeyboardInterrupt (between filters, while writing) the
    filter running then, else the command."""
    text = str(err) or str(interruption(running_filter() or command))
    return f"interrupted: {text}; the output folder may hold part of the results"


def caused_by_ctrl_c(err: BaseException) -> bool:
    """Whether ``err`` comes from a Ctrl-C: a compiled kernel (Numba) that finds the signal
    pending returns a result with KeyboardInterrupt set, which Python reports as a SystemError
    caused by it."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, KeyboardInterrupt):
            return True
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return False


def wrapped_error(label: str, err: BaseException) -> MuscleMSSError:
    """A :class:`MuscleMSSError` for an unexpected exception raised inside filter ``label``:
    its type, its message (numpy's MemoryError says the size it asked for) and the line of
    muscle-mss it came from, so that the user sees which filter failed and why."""
    frames = [f for f in traceback.extract_tb(err.__traceback__)
              if os.path.realpath(f.filename).startswith(_PACKAGE_ROOT)]
    place = ""
    if frames:
        place = f" at {os.path.basename(frames[-1].filename)}:{frames[-1].lineno}"
    text = str(err) or "no message"
    if isinstance(err, MemoryError):
        wrapped = MuscleMSSError(f"ran out of memory ({text}){place}; lower the sizes asked "
                                 "of it (particles per fibre, bone sphere spacing, iterations)")
    else:
        wrapped = MuscleMSSError(f"failed unexpectedly with {type(err).__name__}: {text}{place}; "
                                 "this input is not checked — please report it with the scene")
    wrapped.__cause__ = err
    return wrapped


def _make_setter(prop: Property):
    def setter(self, value):
        stored = prop.coerce(value, self.LABEL)
        if self._values[prop.name] != stored:
            self._values[prop.name] = stored
            self.Modified()
    setter.__name__ = "Set" + prop.name
    setter.__doc__ = prop.doc
    return setter


def _make_getter(prop: Property):
    def getter(self):
        return self._values[prop.name]
    getter.__name__ = "Get" + prop.name
    getter.__doc__ = prop.doc
    return getter
