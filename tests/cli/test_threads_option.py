"""``--threads N`` on every subcommand, set through poseflow.num_threads for the whole command."""

from __future__ import annotations

import argparse

import numba
import pytest
import torch

import poseflow
from poseflow.cli import SUBCOMMANDS, build_parser, main, subcommand_parsers


def _argv(parser: argparse.ArgumentParser) -> list[str]:
    """The shortest command line ``parser`` accepts: its words and its required arguments."""
    words = parser.prog.split()[1:]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            continue
        value = str(action.choices[0]) if action.choices else "1"
        if not action.option_strings and action.nargs not in ("?", "*"):
            words.append(value)
        elif action.required:
            words += [action.option_strings[0], value]
    return words


PARSERS = {p.prog: p for p in subcommand_parsers(build_parser())}


def test_every_subcommand_is_checked():
    nested = {"poseflow demo registration"}
    assert set(PARSERS) == {f"poseflow {c}" for c in SUBCOMMANDS} | nested


@pytest.mark.parametrize("prog", PARSERS)
def test_every_subcommand_takes_threads(prog):
    parser, argv = build_parser(), _argv(PARSERS[prog])
    assert parser.parse_args([*argv, "--threads", "3"]).threads == 3
    assert parser.parse_args(argv).threads is None


@pytest.mark.parametrize("bad", ["0", "-2", "two", "1.5"])
def test_bad_thread_counts_are_usage_errors(bad, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--threads", bad])
    assert exc.value.code == 2 and "--threads" in capsys.readouterr().err


def test_nested_subcommand_keeps_its_parents_threads():
    parser = build_parser()
    assert parser.parse_args(["demo", "--threads", "2", "registration"]).threads == 2
    assert parser.parse_args(["demo", "registration", "--threads", "2"]).threads == 2


@pytest.fixture
def seen(monkeypatch):
    """Replace ``demo``'s and ``demo registration``'s work by a record of the thread counts."""
    record: list[tuple[int, int, int]] = []

    def run(args):
        record.append(
            (poseflow.get_num_threads(), torch.get_num_threads(), numba.get_num_threads())
        )
        return 0

    monkeypatch.setattr("poseflow.cli.demo.run", run)
    monkeypatch.setattr("poseflow.cli.registration_demo.run", run)
    with poseflow.num_threads(2):
        yield record
        assert torch.get_num_threads() == poseflow.get_num_threads() == 2  # restored


def test_threads_1_runs_the_command_on_one_thread(seen):
    assert main(["demo", "--threads", "1"]) == 0
    assert main(["demo", "registration", "--threads", "1"]) == 0
    assert seen == [(1, 1, 1), (1, 1, 1)]


def test_default_is_omp_num_threads_else_one(seen, monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert main(["demo"]) == 0
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    assert main(["demo"]) == 0
    assert [s[:2] for s in seen] == [(1, 1), (2, 2)]


def test_malformed_omp_num_threads_is_a_usage_error(seen, monkeypatch, capsys):
    monkeypatch.setenv("OMP_NUM_THREADS", "all")
    assert main(["demo"]) == 2
    assert "OMP_NUM_THREADS='all'" in capsys.readouterr().err
    assert main(["demo", "--threads", "1"]) == 0  # --threads wins over the variable
