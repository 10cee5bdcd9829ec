"""Each example of ``examples/`` runs in its quick mode and does what its docstring says."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def _example(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_quickstart_estimates_every_instance_of_the_test_image(capsys):
    result = _example("quickstart").main(["--quick"])
    n = len(result["obj_ids"])
    assert n >= 1 and set(result["obj_ids"]) <= {1, 2, 3}  # the three demo objects
    assert len(result["valid"]) == len(result["rotation_deg"]) == len(result["translation_mm"]) == n
    for deg, mm in zip(result["rotation_deg"], result["translation_mm"]):
        assert math.isfinite(deg) and 0.0 <= deg <= 180.0 + 1e-3
        assert math.isfinite(mm) and mm >= 0.0
    out = capsys.readouterr().out
    assert "rotation deg" in out and len(out.strip().splitlines()[-n:]) == n
    assert "20 steps" in out and "over a hundred degrees are expected" in out  # says it is bad


def test_custom_pipeline_recovers_the_poses(capsys):
    rows = _example("custom_pipeline").main(["--quick"])
    assert len(rows["icp_deg"]) == 2
    # Measured on the quick run: RANSAC 4-23 degrees, ICP 0.6-0.8 degrees and 0.1-0.2 mm.
    assert max(rows["icp_deg"]) < 3.0 and max(rows["icp_mm"]) < 3.0
    assert sum(rows["icp_deg"]) < sum(rows["ransac_deg"])  # ICP refines RANSAC's poses
    assert "model bank" in capsys.readouterr().out


def test_gated_fusion_learns_the_lookup_a_pointwise_sum_cannot(capsys):
    result = _example("fusion_in_your_model").main(["--quick"])
    # Measured on the quick run: gated 0.66, sum 0.86 (chance 1.0).
    assert result["gated"] < 0.8
    assert result["gated"] < result["sum"] - 0.1
    for gate in result["gates"].values():
        assert 0.0 < gate < 1.0 and gate != pytest.approx(0.5, abs=1e-4)  # the gates learnt
    out = capsys.readouterr().out
    assert "gated fusion" in out and "sum fusion" in out


def test_verifier_on_its_own_ranks_the_truth_first_and_turns_flips_back(capsys):
    result = _example("verify_your_poses").main(["--quick"])
    assert result["best"] == [0, 0]  # the true pose outscores the flip and the shifted pose
    assert all(c != 0 for c in result["chosen"])  # a candidate replaced each flipped estimate
    assert all(before > 150 for before in result["error_before_deg"])
    # Measured on the quick run: 0.6 and 0.3 degrees.
    assert all(after < 3.0 for after in result["error_after_deg"])
    assert all(0.5 < s <= 1.0 for s in result["scores"])
    assert "end for end" in capsys.readouterr().out
