"""The options of a motion run, shared by ``muscle-mss demo`` / ``muscle-mss run`` and the
pvpython/pvbatch entry point ``muscle_mss.plugin.batch``.

Every choice and default comes from where the filters take it (DESIGN §2: one definition): the
layouts from the Spring Builder, the particles per fibre from the Fibre Resampler, the methods,
iterations and tolerance from :mod:`muscle_mss.core.settings`, the series and compressors from
:mod:`muscle_mss.filters.run_output`.
"""
from __future__ import annotations

import argparse

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.settings import (DEFAULT_CONNECTIVE_TISSUE, DEFAULT_FIBRE_SHORTENING,
                                      DEFAULT_ITERATIONS, DEFAULT_METHOD, DEFAULT_SPRINGS,
                                      DEFAULT_TISSUE_ALONG, DEFAULT_TOLERANCE,
                                      METHOD_QUASI_STATIC, METHOD_RELAXATION, METHODS,
                                      SPRING_ENERGIES)

from .fibre_resampler import DEFAULT_PARTICLES_PER_FIBRE
from .run_output import COMPRESSORS, DEFAULT_COMPRESSOR, SERIES, Writing, parse_write_option
from .spring_builder import DEFAULT_LAYOUT, LAYOUTS

METHOD_OPTIONS = {method.split()[0]: method for method in METHODS}
"""``--method`` values: each of the solver's methods by its first word (``paper`` for
``paper relaxation``)."""


def method_option(method: str) -> str:
    """The ``--method`` value of one of the solver's :data:`~muscle_mss.core.settings.METHODS`."""
    return next(option for option, name in METHOD_OPTIONS.items() if name == method)


def add_run_options(p) -> None:
    """The options that set up a run (``argparse`` parser ``p``): what the filters compute
    (``--resolution``, ``--layout``, ``--iterations``, ``--method``, ``--tolerance``,
    ``--springs``, ``--connective-tissue``, ``--tissue-along``, ``--[no-]fibre-shortening``) and
    what is written, and how (``--write``, ``--compressor``)."""
    p.add_argument("--resolution", type=int,
                   help=f"particles per fibre N (default {DEFAULT_PARTICLES_PER_FIBRE})")
    p.add_argument("--layout", choices=LAYOUTS, help=f"spring layout (default {DEFAULT_LAYOUT})")
    p.add_argument("--iterations", type=int,
                   help=f"solver iterations per time point (default {DEFAULT_ITERATIONS})")
    p.add_argument("--write", help=f"series to write, comma-separated: {','.join(SERIES)} "
                                   "(default all)")
    p.add_argument("--compressor", choices=COMPRESSORS, default=DEFAULT_COMPRESSOR,
                   help=f"compressor of the series' binary data (default {DEFAULT_COMPRESSOR}: "
                        "fast)")
    p.add_argument("--method", choices=tuple(METHOD_OPTIONS),
                   help=f"solver: {method_option(METHOD_RELAXATION)}, the paper's relaxation, or "
                        f"{method_option(METHOD_QUASI_STATIC)}, the quasi-static equilibrium "
                        f"(default {method_option(DEFAULT_METHOD)})")
    p.add_argument("--tolerance", type=float,
                   help="quasi-static tolerance: largest particle move of a step, mm "
                        f"(default {DEFAULT_TOLERANCE:g})")
    p.add_argument("--springs", choices=SPRING_ENERGIES,
                   help="quasi-static spring energy: the paper's Hooke springs or co-rotational "
                        f"springs, stiff across themselves as well (default {DEFAULT_SPRINGS})")
    p.add_argument("--connective-tissue", type=float,
                   help="connective tissue holding each free particle toward its posed position, "
                        "as a ratio to the springs' stiffness; 0: the paper's model "
                        f"(default {DEFAULT_CONNECTIVE_TISSUE:g})")
    p.add_argument("--tissue-along", type=float,
                   help="the connective tissue's stiffness along the fibres as a fraction of "
                        f"that across, 0 to 1; 1: isotropic (default {DEFAULT_TISSUE_ALONG:g})")
    p.add_argument("--fibre-shortening", action=argparse.BooleanOptionalAction, default=None,
                   help="fibres shorten with their muscle instead of folding (the solver's "
                        "FibreShortening; default "
                        f"{'on' if DEFAULT_FIBRE_SHORTENING else 'off'})")


def settings_from(args) -> dict:
    """Filter property settings from the options that were given; :class:`MuscleMSSError` for
    an option that the chosen method would ignore."""
    method = METHOD_OPTIONS.get(args.method) or DEFAULT_METHOD
    for option, value, what in (
            ("--tolerance", args.tolerance, "the largest particle move of its last step"),
            ("--springs", args.springs, "its spring energy")):
        if value is not None and method != METHOD_QUASI_STATIC:
            raise MuscleMSSError(
                f"{option} {value} applies only to --method "
                f"{method_option(METHOD_QUASI_STATIC)} ({what}); --method "
                f"{method_option(method)} runs --iterations iterations and would ignore it: "
                f"drop {option} or add --method {method_option(METHOD_QUASI_STATIC)}")
    pairs = (("ParticlesPerFibre", args.resolution), ("Layout", args.layout),
             ("Iterations", args.iterations), ("Method", METHOD_OPTIONS.get(args.method)),
             ("Tolerance", args.tolerance), ("Springs", args.springs),
             ("ConnectiveTissue", args.connective_tissue),
             ("TissueAlongFibres", args.tissue_along),
             ("FibreShortening", args.fibre_shortening))
    return {name: value for name, value in pairs if value is not None}


def writing_from(args) -> Writing:
    """What to write and how, from ``--write`` and ``--compressor``."""
    return Writing(SERIES if args.write is None else parse_write_option(args.write),
                   args.compressor)
