import subprocess
import sys

import poseflow
from poseflow.cli import main


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
