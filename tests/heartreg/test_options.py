"""Options written once: the command's flags fill the library's option
dataclasses, and every stage flag of ``model`` and ``register`` is a flag of
``pipeline`` too."""

from __future__ import annotations

import argparse
import dataclasses

import pytest

from heartreg import cli, cli_commands, cli_parser
from hrcore.errors import UsageError
from modeling.options import AUTO, ModelOptions
from registration.motion_model import Harmonics
from registration.options import RegistrationOptions


def _subparsers():
    parser = cli_parser._build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices


def _flags(p) -> set[str]:
    return {s for a in p._actions for s in a.option_strings if s.startswith("--")}


def test_every_stage_flag_is_a_pipeline_flag():
    sub = _subparsers()
    pipeline = _flags(sub["pipeline"])
    assert _flags(sub["model"]) - {"--list-series"} <= pipeline
    # the pipeline measures the CT's phase itself: --cardiac-phase is register's alone
    assert _flags(sub["register"]) - {"--cardiac-phase"} <= pipeline


def test_flags_fill_the_option_dataclasses():
    parser = cli.command_parser()
    args = parser.parse_args(["pipeline", "study", "session", "-o", "out", "--faces", "5000", "--fiducials", "0",
                              "--keep-vessels", "--harmonics", "3", "2", "1", "1", "--step", "0.02",
                              "--estimator", "eq10", "--icp-max-iterations", "80", "--no-view",
                              "--no-slice-phases"])
    m = cli_commands._model_options(args)
    assert m == ModelOptions(target_faces=5000, expected_fiducials=None, trim_vessels=False)
    r = cli_commands._registration_options(args)
    assert r.harmonics == Harmonics(3, 2, 1, 1) and r.phase_step == 0.02 and r.estimator == "eq10"
    assert dict(r.icp_options) == {"max_iterations": 80}
    assert r.slice_phases is False and RegistrationOptions().slice_phases is True
    # no flags: exactly the library's defaults
    plain = parser.parse_args(["pipeline", "study", "session", "-o", "out"])
    assert cli_commands._model_options(plain) == ModelOptions() and cli_commands._registration_options(plain) == RegistrationOptions()
    assert ModelOptions().expected_fiducials == AUTO  # the command's default is the library's


@pytest.mark.parametrize(("make", "field", "flag"), [
    (lambda: ModelOptions(target_faces=10), "target_faces", "--faces"),
    (lambda: ModelOptions(expected_fiducials=-1), "expected_fiducials", "--fiducials"),
    (lambda: RegistrationOptions(harmonics=(1, 2)), "harmonics", "--harmonics"),
    (lambda: RegistrationOptions(estimator="best"), "estimator", "--estimator"),
    (lambda: RegistrationOptions(breath_hold_phase=1.5), "breath_hold_phase", "--breath-hold-phase"),
])
def test_bad_values_name_the_keyword_then_the_flag(make, field, flag):
    with pytest.raises(UsageError) as info:
        make()
    message = str(info.value)
    assert message.startswith(f"{field} ({flag})") and "\n" not in message


def test_the_sweeps_need_a_cardiac_and_a_respiratory_harmonic():
    with pytest.raises(UsageError, match=r"^harmonics \(--harmonics HC HR HMC HMR\): the sweeps need at least one "
                                         r"cardiac and one respiratory harmonic, got Hc=2, Hr=0$"):
        RegistrationOptions(harmonics=(2, 0, 0, 0))


def test_options_are_frozen_and_overridable():
    opts = RegistrationOptions(icp_options={"max_iterations": 10})
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.phase_step = 0.5
    with pytest.raises(TypeError):
        opts.icp_options["max_iterations"] = 20  # a read-only view: the caller's dict cannot change it
    assert RegistrationOptions.of(opts, phase_step=0.05).icp_options["max_iterations"] == 10
    with pytest.raises(TypeError, match="no_such_option"):
        RegistrationOptions.of(None, no_such_option=1)



@pytest.mark.parametrize("n", [2, 8, 18])
def test_given_fiducials_are_the_staples_register_needs(tmp_path, n):
    """A review: a markups file of 18 points (two sets of staples) made a model that ``register`` refused later;
    ``model --fiducials FILE`` now asks for the count ``register`` needs (the session's 9 staples), in one line."""
    import json

    from registration.session_format import N_FIDUCIALS

    points = [{"position": [float(k), 10.0 * (k % 3), 5.0 * k], "positionStatus": "defined"} for k in range(n)]
    given = tmp_path / "staples.mrk.json"
    given.write_text(json.dumps({"markups": [{"type": "Fiducial", "coordinateSystem": "LPS",
                                              "controlPoints": points}]}))
    args = cli.command_parser().parse_args(["model", "study", "-o", "out", "--fiducials", str(given)])
    with pytest.raises(UsageError) as info:
        cli_commands._model_options(args)
    message = str(info.value)
    assert message.startswith(f"--fiducials: the markups file {given} holds {n} placed point(s); heartreg register "
                              f"needs the {N_FIDUCIALS} staples the session touches") and "\n" not in message
    nine = [{"position": [float(k), 10.0 * (k % 3), 5.0 * k], "positionStatus": "defined"} for k in range(N_FIDUCIALS)]
    given.write_text(json.dumps({"markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "controlPoints": nine}]}))
    assert len(cli_commands._model_options(args).fiducials_mm) == N_FIDUCIALS
