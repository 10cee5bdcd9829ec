import json

import pytest

from poseflow.errors import ValueRangeError
from poseflow.models import ABLATIONS, FunFlow6DConfig


def test_json_round_trip(tmp_path):
    cfg = FunFlow6DConfig(num_points=64, icp_thresholds=(0.1, 0.05), net={"posenc_dim": 32})
    path = tmp_path / "c.json"
    path.write_text(json.dumps(cfg.to_json()))
    assert FunFlow6DConfig.from_json(path) == cfg


def test_unknown_keys_and_bad_values_raise():
    with pytest.raises(ValueRangeError, match="unknown"):
        FunFlow6DConfig.from_json({"num_point": 3})
    with pytest.raises(ValueRangeError):
        FunFlow6DConfig(pose_solver="icp")
    with pytest.raises(ValueRangeError):
        FunFlow6DConfig(geometric_encoder="none", appearance_encoder="none")


@pytest.mark.parametrize("name", sorted(ABLATIONS))
def test_every_ablation_row_is_a_valid_config(name):
    cfg = FunFlow6DConfig().replace(**ABLATIONS[name])
    assert cfg.fusion == ABLATIONS[name]["fusion"]
    net = cfg.net_config(geometric_dim=66, semantic_dim=64)
    assert net.fusion == cfg.fusion
