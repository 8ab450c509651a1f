"""The options of a motion run, shared by ``muscle-mss demo`` / ``muscle-mss run`` and the
pvpython/pvbatch entry point ``muscle_mss.plugin.batch``.

The options that set a filter property are the filters' property rows that carry an
:class:`~muscle_mss.core.properties.Option` (flag, help, values), in pipeline order (DESIGN
§2: one definition): a new one is one row; the series and compressors come from
:mod:`muscle_mss.app.run_output`.
"""
from __future__ import annotations

import argparse
import importlib

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.settings import METHOD_PARTS, METHOD_RELAXATION

from muscle_mss.filters import EXPORTS, FILTER_NAMES
from .run_output import COMPRESSORS, DEFAULT_COMPRESSOR, SERIES, Writing, parse_write_option

OPTIONS_AFTER = ("--write", "--compressor")
"""The run's own options, after the filters' (``--write`` a study does not take either)."""

METHOD_OF_PART = {part: method for method, part in METHOD_PARTS.items()}
"""The method that alone reads each method's part of the solver's settings
(:class:`~muscle_mss.core.settings.SolverSettings`)."""


def run_properties() -> tuple:
    """The property rows that are run options, of every filter in pipeline order."""
    rows = []
    for name in FILTER_NAMES:
        module = importlib.import_module(f"muscle_mss.filters.{EXPORTS[name]}")
        rows += [prop for prop in getattr(module, name).PROPERTIES if prop.option]
    return tuple(rows)


def _shown(prop, value) -> str:
    """A property value as its option writes it."""
    if prop.kind == "bool":
        return "on" if value else "off"
    return next((shown for shown, choice in prop.option.values if choice == value), value)


def _method_reading(prop) -> str | None:
    """The one method that reads the property's settings field (the field sits in that
    method's part of :class:`~muscle_mss.core.settings.SolverSettings`), or None."""
    part, dot, _ = prop.field.partition(".")
    return METHOD_OF_PART.get(part) if dot else None


def add_run_options(p) -> None:
    """The options that set up a run (``argparse`` parser ``p``): what the filters compute (the
    filters' property rows with an option: ``--resolution``, ``--layout``, ``--method``, ...)
    and what is written, and how (``--write``, ``--compressor``)."""
    for prop in run_properties():
        option = prop.option
        text = option.help.format(default=_shown(prop, prop.default))
        if prop.kind == "bool":
            p.add_argument(option.flag, action=argparse.BooleanOptionalAction, default=None,
                           help=text)
        elif prop.kind == "enum":
            values = tuple(shown for shown, _ in option.values) or prop.choices
            p.add_argument(option.flag, choices=values, help=text)
        else:
            p.add_argument(option.flag, type=int if prop.kind == "int" else float, help=text)
    p.add_argument("--write", help=f"series to write, comma-separated: {','.join(SERIES)} "
                                   "(default all)")
    p.add_argument("--compressor", choices=COMPRESSORS, default=DEFAULT_COMPRESSOR,
                   help=f"compressor of the series' binary data (default {DEFAULT_COMPRESSOR}: "
                        "fast)")
    add_cache_option(p)


def add_cache_option(p) -> None:
    """``--cache DIR|off``: where solved frames are kept and looked up
    (:mod:`muscle_mss.filters.frame_cache`)."""
    from muscle_mss.filters.frame_cache import ENVIRONMENT, default_folder
    p.add_argument("--cache", metavar="DIR|off",
                   help="frame cache: load frames solved before with the same scene, "
                        f"properties and code, store those solved now (default ${ENVIRONMENT} "
                        f"or {default_folder()}); off: neither read nor write")


def add_jobs_option(p) -> None:
    """``--jobs J``: how many processes solve a whole motion's time points at once
    (:mod:`muscle_mss.app.motion_jobs`)."""
    p.add_argument("--jobs", metavar="J",
                   help="processes that solve the motion's time points at once, Numba's "
                        "threads shared out between them (default: the cores; "
                        "$MUSCLE_MSS_JOBS); the results are those of --jobs 1")


def jobs_from(args, one_time_point: bool = False) -> int:
    """The worker processes ``--jobs`` asks for (its default: the cores); more than one
    refused for ``one_time_point`` (``muscle-mss run --time``, solved in this process)."""
    from .motion_jobs import checked_jobs, default_jobs
    given = getattr(args, "jobs", None)
    jobs = default_jobs() if given is None else checked_jobs(given)
    if given is not None and jobs > 1 and one_time_point:
        raise MuscleMSSError(f"--jobs {given} applies to a whole motion; --time solves one "
                             "time point in this process: drop --jobs")
    return jobs


def cache_from(args) -> str | None:
    """The frame cache folder ``--cache`` chooses, or None when it is off."""
    from muscle_mss.filters.frame_cache import chosen_folder
    return chosen_folder(getattr(args, "cache", None))


def settings_from(args) -> dict:
    """Filter property settings from the options that were given; :class:`MuscleMSSError` for
    an option that the chosen method would ignore."""
    rows = run_properties()
    given = {prop: getattr(args, prop.option.dest) for prop in rows}
    values = {prop: dict(prop.option.values).get(value, value)
              for prop, value in given.items() if value is not None}
    method_row = next(prop for prop in rows if prop.field == "method")
    method = values.get(method_row, method_row.default)
    for prop, value in given.items():
        only = _method_reading(prop)
        if value is None or only is None or only == method:
            continue
        runs = ("runs --iterations iterations and would ignore it"
                if method == METHOD_RELAXATION else "would ignore it")
        raise MuscleMSSError(
            f"{prop.option.flag} {value} applies only to --method {_shown(method_row, only)} "
            f"({prop.option.what}); --method {_shown(method_row, method)} {runs}: drop "
            f"{prop.option.flag} or add --method {_shown(method_row, only)}")
    return {prop.name: value for prop, value in values.items()}


def study_ignored(args) -> list:
    """The options given that a study does not take (it runs every layout with the filters'
    defaults), as flags."""
    flags = [prop.option.flag for prop in run_properties() if not prop.option.study
             and getattr(args, prop.option.dest) is not None]
    return flags + [flag for flag in OPTIONS_AFTER[:1]
                    if getattr(args, flag.lstrip("-")) is not None]


def writing_from(args) -> Writing:
    """What to write and how, from ``--write`` and ``--compressor``."""
    return Writing(SERIES if args.write is None else parse_write_option(args.write),
                   args.compressor)
