import argparse
import subprocess
import sys

import pytest

import poseflow
from poseflow.cli import SUBCOMMANDS, build_parser, is_usage_error, main, subcommand_parsers
from poseflow.errors import (
    MissingFileError,
    ResultsFormatError,
    UnitsError,
    UsageError,
    ValueRangeError,
)


def test_version(capsys):
    try:
        main(["--version"])
    except SystemExit as exc:
        assert exc.code == 0
    assert capsys.readouterr().out.strip() == f"poseflow {poseflow.__version__}"


def test_help_lists_the_program():
    out = subprocess.run(
        [sys.executable, "-m", "poseflow.cli", "--help"], capture_output=True, text=True, check=True
    ).stdout
    assert "usage: poseflow" in out


def test_no_subcommand_prints_the_help_and_is_a_usage_error(capsys):
    assert main([]) == 2
    err = capsys.readouterr().err
    assert "usage: poseflow" in err and "estimate" in err


def test_the_command_line_exit_codes():
    proc = subprocess.run(
        [sys.executable, "-m", "poseflow.cli"], capture_output=True, text=True, check=False
    )
    assert proc.returncode == 2 and "usage: poseflow" in proc.stderr
    proc = subprocess.run(
        [sys.executable, "-m", "poseflow.cli", "demo", "--images", "0"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert proc.returncode == 2 and "must be at least 1" in proc.stderr


@pytest.mark.parametrize("command", SUBCOMMANDS)
def test_every_command_has_no_progress_and_quiet(command, capsys):
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = capsys.readouterr().out
    assert "--no-progress" in text and "--quiet" in text
    assert "--progress " not in text.replace("--no-progress", "")


@pytest.mark.parametrize("command", SUBCOMMANDS)
def test_help_shows_no_restructured_text(command, capsys):
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = capsys.readouterr().out
    assert "``" not in text and ":func:" not in text and ":class:" not in text


def _shown(default):
    """The texts of a default that its help may show (as typed, or a float as %g)."""
    if default is True:
        return {"on"}
    if isinstance(default, list):
        return {" ".join(map(str, default))}
    return {str(default), f"{default:g}"} if isinstance(default, float) else {str(default)}


@pytest.mark.parametrize("parser", list(subcommand_parsers(build_parser())), ids=lambda p: p.prog)
def test_every_option_has_a_help_that_shows_its_default(parser):
    formatter = parser._get_formatter()
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        name = "/".join(action.option_strings) or action.dest
        assert action.help and action.help.strip(), f"{parser.prog} {name} has no help"
        default = action.default
        if default is None or default is False or default is argparse.SUPPRESS or default == []:
            continue
        text = " ".join(formatter._expand_help(action).split())
        assert any(shown in text for shown in _shown(default)), (
            f"{parser.prog} {name}: the help does not show the default {default!r}: {text!r}"
        )


def test_usage_and_failure_are_told_apart(capsys):
    assert is_usage_error(UsageError("--copies must be at least 1"))
    assert is_usage_error(ValueRangeError("solver must be one of euler, heun"))
    assert not is_usage_error(UnitsError("median depth of 800 m"))
    assert not is_usage_error(ResultsFormatError("r.csv:3: R is not a rotation"))
    assert not is_usage_error(MissingFileError("no such file"))


def test_status_lines_go_to_stderr_and_quiet_silences_them(capsys):
    import argparse
    import logging

    from poseflow.cli.common import LOG, command_output

    for quiet in (False, True):
        with command_output(argparse.Namespace(quiet=quiet)):
            LOG.info("[1/2] working")
            LOG.warning("something odd")
        out, err = capsys.readouterr()
        assert out == ""
        assert ("[1/2] working\n" in err) is not quiet
        assert "warning: something odd\n" in err
    assert logging.getLogger("poseflow").handlers == []  # restored
