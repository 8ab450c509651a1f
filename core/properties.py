"""One definition of every filter property (DESIGN §2, STYLE "One definition of everything").

A filter lists its :class:`Property` objects in ``PROPERTIES``. From that one table
:class:`muscle_mss.filters.base.MuscleFilter` generates the ``SetX`` / ``GetX`` methods used in
plain VTK, and ``muscle_mss.plugin`` generates the ParaView declarations (name, default, range,
enumeration, tooltip, panel group). A row may also name the core setting it fills (``field``, a
:class:`~muscle_mss.core.settings.SolverSettings` field: the filter's ``settings()`` is built
from these) and its command-line :class:`Option` (``muscle-mss run`` / ``demo`` and the batch:
:mod:`muscle_mss.app.run_options` builds the options from these), so that a new setting is
one row plus its use. The ``name`` is the ParaView property name, the Python attribute in
``paraview.simple`` and the key in state files: never rename one casually.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from .errors import MuscleMSSError

KINDS = ("int", "double", "bool", "enum", "string")


@dataclass(frozen=True)
class Option:
    """The command-line option that sets a property in a run (``muscle-mss run`` / ``demo``, the
    batch). ``flag`` (``--connective-tissue``; its ``argparse`` destination
    ``connective_tissue``); ``help``, in which ``{default}`` stands for the property's default
    as the option writes it (an enum's text, ``on`` / ``off`` for a bool); ``values`` maps the
    option's values to the property's choices where they differ (``--method paper``), else the
    choices are the values; ``study``: whether a study (which runs every layout with the
    filters' defaults) takes it; ``what``: what the setting is to the one method that reads it
    (a field of a method's part of the settings), for the refusal of the option under the
    other method."""

    flag: str
    help: str
    values: tuple = ()
    study: bool = False
    what: str = ""

    @property
    def dest(self) -> str:
        """The ``argparse`` attribute of the option."""
        return self.flag.lstrip("-").replace("-", "_")


@dataclass(frozen=True)
class Property:
    """A filter property.

    ``kind`` is one of ``int``, ``double``, ``bool``, ``enum``, ``string``. An enum stores the
    index of its choice (ParaView stores the int) and accepts the choice's text in ``SetX``; a
    string stores its text (a folder, say: ParaView shows a text field).
    ``minimum`` / ``maximum`` bound int and double values (inclusive, None = unbounded).
    ``doc`` becomes the tooltip and the setter's docstring; ``group`` the panel group.
    ``field``: the :class:`~muscle_mss.core.settings.SolverSettings` field the property sets
    (its part first: ``contacts.structure``; enums give their choice's text); ``option``: its
    command-line :class:`Option`, if a run takes it.
    """

    name: str
    kind: str
    default: object
    doc: str
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple = ()
    group: str = ""
    field: str = ""
    option: Option | None = None

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"property {self.name}: kind {self.kind!r} not in {KINDS}")
        if self.kind == "enum" and not self.choices:
            raise ValueError(f"property {self.name}: an enum needs choices")

    def coerce(self, value, owner: str = ""):
        """Turn a user value into the stored type; an unknown enum text raises :class:`MuscleMSSError`."""
        where = f"{owner}.{self.name}" if owner else self.name
        if self.kind == "enum":
            if isinstance(value, str):
                if value not in self.choices:
                    raise MuscleMSSError(f"{where}: {value!r} is not one of {', '.join(self.choices)}")
                return self.choices.index(value)
            index = int(value)
            if not 0 <= index < len(self.choices):
                raise MuscleMSSError(f"{where}: choice {index} is out of range 0..{len(self.choices) - 1}")
            return index
        if self.kind == "bool":
            return bool(value)
        if self.kind == "string":
            if value is None:           # ParaView sets an empty text as None
                return ""
            if not isinstance(value, str):
                raise MuscleMSSError(f"{where}: {value!r} is not a text")
            return value
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise MuscleMSSError(f"{where}: {value!r} is not a number") from None
        if self.kind == "int":
            if number != number or number in (float("inf"), float("-inf")) \
                    or number != int(number):
                raise MuscleMSSError(f"{where}: {value!r} is not a whole number; "
                                     f"{self.name} counts, so it must be an integer")
            return int(number)
        return number

    def range_problem(self, value, owner: str = "") -> str | None:
        """Why a stored value is outside the property's range, or None.

        Ranges are checked when the filter runs (not in the setter), so that ParaView reports
        them as a filter error with an empty output rather than a traceback from a setter. A
        NaN or an infinity is out of every range (a NaN compares false with both bounds, and
        a property a method does not read, the relaxation's time step under the quasi-static one, was taken).
        """
        if self.kind not in ("int", "double"):
            return None
        where = f"{owner} property {self.name}" if owner else f"property {self.name}"
        if not math.isfinite(value):
            return f"{where} is {value}; it must be a finite number"
        if self.minimum is not None and value < self.minimum:
            return f"{where} is {value}; it must be at least {self.minimum}"
        if self.maximum is not None and value > self.maximum:
            return f"{where} is {value}; it must be at most {self.maximum}"
        return None

    @property
    def stored_default(self):
        """The default as stored (an enum's index)."""
        return self.coerce(self.default)
