"""The filters' property rows are the one definition of a setting: the solver's settings, their
checks, the messages that name them, the run's command-line options and the study's refusals
are read off them."""
import argparse
import dataclasses

import pytest

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.settings import SolverSettings
from muscle_mss.core.solver_properties import by_name, check_settings, name_of
from muscle_mss.filters.collision_solver import MSSCollisionSolver
from muscle_mss.app.run_options import (add_run_options, run_properties, settings_from,
                                            study_ignored)

FIELD_ROWS = [p for p in MSSCollisionSolver.PROPERTIES if p.field]
OWN_DEFAULT = {"FibreShortening"}
"""Rows whose default is not the core's: SolverSettings() keeps the paper's springs."""


def _at(settings, path):
    for part in path.split("."):
        settings = getattr(settings, part)
    return settings


def _other(prop):
    """A valid value of ``prop`` other than its default."""
    if prop.kind == "enum":
        return next(c for c in prop.choices if c != prop.default)
    if prop.kind == "bool":
        return not prop.default
    if prop.maximum is not None:
        return (prop.minimum + prop.maximum) / 2 if prop.kind == "double" else prop.maximum
    return prop.default * 2 + 1


@pytest.mark.parametrize("prop", FIELD_ROWS, ids=lambda p: p.name)
def test_a_row_sets_its_field_and_shares_its_default(prop):
    assert (_at(SolverSettings(), prop.field) == prop.default) is (prop.name not in OWN_DEFAULT)
    assert _at(MSSCollisionSolver().settings(), prop.field) == prop.default
    solver = MSSCollisionSolver()
    getattr(solver, "Set" + prop.name)(_other(prop))
    assert _at(solver.settings(), prop.field) == _other(prop)
    assert dataclasses.replace(solver.settings()) == solver.settings()


def test_every_solver_setting_but_the_internal_ones_has_a_row():
    def paths(obj, prefix=""):
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            if dataclasses.is_dataclass(value):
                yield from paths(value, f"{prefix}{f.name}.")
            else:
                yield prefix + f.name
    internal = {"quasi_static.contact_weight", "quasi_static.history",
                "quasi_static.soft_start", "quasi_static.contact_preconditioner"}
    assert set(paths(SolverSettings())) - internal == {p.field for p in FIELD_ROWS}


def _out_of_range(prop):
    """Values of ``prop`` its row refuses: below its minimum, above its maximum, a fraction of
    a count, NaN; an enum's unknown text."""
    if prop.kind == "enum":
        return ["no such choice"]
    if prop.kind == "bool":
        return []
    values = [float("nan")]
    if prop.minimum is not None:
        values.append(prop.minimum - 1 if prop.kind == "int" else prop.minimum - 1e-3)
    if prop.maximum is not None:
        values.append(prop.maximum + 1)
    if prop.kind == "int":
        values.append(prop.default + 0.5)
    return values


@pytest.mark.parametrize("prop, value", [(p, v) for p in FIELD_ROWS for v in _out_of_range(p)],
                         ids=lambda x: getattr(x, "name", str(x)))
def test_the_settings_check_refuses_what_the_row_refuses_naming_the_property(prop, value):
    settings = SolverSettings.build(**{prop.field.rpartition(".")[2]: value})
    with pytest.raises(MuscleMSSError, match=f"^property {prop.name} is "):
        check_settings(settings)
    check_settings(SolverSettings.build(**{prop.field.rpartition(".")[2]: prop.default}))


def test_names_and_flat_settings_come_from_the_rows():
    assert name_of("relaxation.time_step") == "TimeStep"
    assert by_name(time_step=0.01, structure="octree BVH") == {"TimeStep": 0.01,
                                                               "CollisionStructure": "octree BVH"}
    with pytest.raises(TypeError, match="no solver property sets time_stop"):
        by_name(time_stop=0.01)


def _parser():
    parser = argparse.ArgumentParser()
    add_run_options(parser)
    return parser


@pytest.mark.parametrize("prop", run_properties(), ids=lambda p: p.name)
def test_each_option_sets_its_property(prop):
    value = _other(prop)
    if prop.kind == "bool":
        argv = [prop.option.flag if value else "--no-" + prop.option.flag[2:]]
    else:
        shown = dict((c, s) for s, c in prop.option.values).get(value, value)
        argv = [prop.option.flag, str(shown)]
    if prop.field.startswith("quasi_static."):
        argv += ["--method", "quasi-static"]
    settings = settings_from(_parser().parse_args(argv))
    assert settings[prop.name] == value
    flags = [arg.replace("--no-", "--") for arg in argv if arg.startswith("-")]
    assert sorted(study_ignored(_parser().parse_args(argv))) == (
        [] if prop.option.study else sorted(flags))


def test_no_option_given_sets_nothing_and_the_study_takes_it():
    args = _parser().parse_args([])
    assert settings_from(args) == {}
    assert study_ignored(args) == []
    assert study_ignored(_parser().parse_args(["--write", "fibres"])) == ["--write"]
