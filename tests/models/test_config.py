import dataclasses
import json
from pathlib import Path

import pytest

from poseflow.assets import DEMO_CHECKPOINT
from poseflow.errors import ValueRangeError
from poseflow.flows import PRESETS
from poseflow.models import ABLATIONS, DiTOverrides, FunFlow6DConfig, NetConfig, NetOptions
from poseflow.verify import VerifierConfig

REPO = Path(__file__).resolve().parents[2]


def test_json_round_trip(tmp_path):
    cfg = FunFlow6DConfig(
        num_points=64,
        icp_thresholds=(0.1, 0.05),
        net=NetOptions(posenc_dim=32, dit=DiTOverrides(hidden_dim=96, attention="global")),
    )
    path = tmp_path / "c.json"
    path.write_text(json.dumps(cfg.to_json()))
    back = FunFlow6DConfig.from_json(path)
    assert back == cfg and isinstance(back.net, NetOptions)
    assert isinstance(back.net.dit, DiTOverrides) and back.net.dit.hidden_dim == 96
    assert json.loads(path.read_text())["net"]["dit"] == {"hidden_dim": 96, "attention": "global"}
    net = back.net_config(geometric_dim=66, semantic_dim=64)
    assert NetConfig.from_json(json.loads(json.dumps(net.to_json()))) == net


def test_verification_fields_round_trip_and_are_checked():
    assert FunFlow6DConfig().verification is True  # new configurations verify
    cfg = FunFlow6DConfig(
        verification=False,
        verify_hypotheses=False,
        verifier={"crop_size": 48, "significance": 0.01, "icp_distances": [0.1, 0.02]},
    )
    assert cfg.verifier == VerifierConfig(
        crop_size=48, significance=0.01, icp_distances=(0.1, 0.02)
    )
    data = json.loads(json.dumps(cfg.to_json()))
    assert data["verifier"]["crop_size"] == 48 and data["verification"] is False
    assert FunFlow6DConfig.from_json(data) == cfg
    assert cfg.replace(verifier={"crop_size": 32}).verifier.crop_size == 32
    with pytest.raises(ValueRangeError, match="verification must be true or false"):
        FunFlow6DConfig(verification="yes")
    with pytest.raises(ValueRangeError, match="verify_hypotheses must be true or false"):
        FunFlow6DConfig(verify_hypotheses=1)
    with pytest.raises(ValueRangeError, match="unknown VerifierConfig fields"):
        FunFlow6DConfig.from_json({"verifier": {"crop": 48}})
    with pytest.raises(ValueRangeError, match="block_size"):
        FunFlow6DConfig(verifier={"crop_size": 60})
    with pytest.raises(ValueRangeError, match="verifier must be a VerifierConfig"):
        FunFlow6DConfig(verifier=3)


def test_mappings_are_read_as_the_typed_parts():
    cfg = FunFlow6DConfig(net={"fusion_heads": 2, "dit": {"depth": 3}})
    assert cfg.net == NetOptions(fusion_heads=2, dit=DiTOverrides(depth=3))
    assert cfg.replace(net={"posenc_dim": 8}).net.posenc_dim == 8


@pytest.mark.parametrize(
    ("field", "value", "allowed"),
    [
        ("fusion", "attention", "gated, cross, concat_mlp, sum"),
        ("solver", "dopri5", "euler, midpoint, heun, rk4"),
        ("reducer", "tsne", "umap, pca, identity"),
        ("reducer", "pca:8", "umap, pca, identity"),
        ("pose_solver", "icp", "ransac, svd"),
        ("anchor", "free", "pinned, noise"),
        ("geometric_encoder", "fcgf", "fpfh, gedi, none"),
        ("appearance_encoder", "clip:vit", "dsift, dinov2, learned, none"),
        ("dit_preset", "huge", ", ".join(PRESETS)),
        ("time_sampler", "beta", "uniform"),
    ],
)
def test_every_name_is_checked_at_construction(field, value, allowed):
    with pytest.raises(ValueRangeError, match=f"{field} must be one of") as info:
        FunFlow6DConfig(**{field: value})
    assert allowed in str(info.value) and repr(value) in str(info.value)


def test_bad_values_and_unknown_keys_raise():
    with pytest.raises(ValueRangeError, match="unknown FunFlow6D config keys"):
        FunFlow6DConfig.from_json({"num_point": 3})
    with pytest.raises(ValueRangeError, match="unknown NetOptions keys"):
        FunFlow6DConfig.from_json({"net": {"feature_dim": 32}})
    with pytest.raises(ValueRangeError, match="unknown DiT override keys"):
        FunFlow6DConfig(net={"dit": {"width": 3}})
    with pytest.raises(ValueRangeError, match="multiple of num_heads"):
        FunFlow6DConfig(net=NetOptions(dit=DiTOverrides(num_heads=5)))
    with pytest.raises(ValueRangeError, match="dropout"):
        NetOptions(dropout=1.5)
    with pytest.raises(ValueRangeError, match="fusion must be one of"):
        NetConfig(fusion="concat")
    with pytest.raises(ValueRangeError):
        FunFlow6DConfig(geometric_encoder="none", appearance_encoder="none")
    with pytest.raises(ValueRangeError, match="net must be a NetOptions"):
        FunFlow6DConfig(net=3)


def test_fusion_lives_in_one_field():
    cfg = FunFlow6DConfig(fusion="sum")
    assert "fusion" not in cfg.to_json()["net"]
    assert cfg.net_config(geometric_dim=66, semantic_dim=64).fusion == "sum"


@pytest.mark.parametrize(
    "path", [DEMO_CHECKPOINT / "config.json", REPO / "configs" / "demo_small.json"]
)
def test_shipped_config_files_keep_loading(path):
    raw = json.loads(path.read_text())
    cfg = FunFlow6DConfig.from_json(path)
    assert cfg.net.posenc_dim == raw["net"]["posenc_dim"] == 32
    assert cfg.net.dit.to_json() == raw["net"]["dit"]
    assert cfg.net.fusion_heads == NetOptions().fusion_heads  # absent: the default
    dit = cfg.net_config(geometric_dim=66, semantic_dim=64).dit_config()
    assert (dit.hidden_dim, dit.depth, dit.num_heads, dit.time_frequency_dim) == (64, 4, 4, 64)
    assert dit.cond_dim == cfg.feature_dim + 32
    for key, value in raw.items():
        if key != "net":
            assert cfg.to_json()[key] == value, key


def test_files_from_before_the_typed_network_options_are_read_as_meant():
    old = {
        "fusion": "gated",
        "net": {"fusion": "sum", "dit_preset": "tiny", "dit": {"cond_dim": 7}},
    }
    cfg = FunFlow6DConfig.from_json(old)
    assert (cfg.fusion, cfg.dit_preset, cfg.net.dit) == ("sum", "tiny", DiTOverrides())


@pytest.mark.parametrize("name", sorted(ABLATIONS))
def test_every_ablation_row_is_a_valid_config(name):
    cfg = FunFlow6DConfig().replace(**ABLATIONS[name])
    assert cfg.fusion == ABLATIONS[name]["fusion"]
    net = cfg.net_config(geometric_dim=66, semantic_dim=64)
    assert net.fusion == cfg.fusion
    assert dataclasses.asdict(net)["dit"] == dataclasses.asdict(cfg.net.dit)


def test_a_missing_descriptor_stream_takes_the_other_width():
    cfg = FunFlow6DConfig(geometric_encoder="none")
    assert cfg.net_config(None, 64).geometric_dim == 64
    assert cfg.net_config(66, None).semantic_dim == 66
    with pytest.raises(ValueRangeError, match="at least one"):
        cfg.net_config(None, None)


@pytest.mark.parametrize(
    ("data", "match"),
    [
        ({"num_points": "abc"}, r"FunFlow6DConfig\.num_points must be an int, got 'abc' \(str\)"),
        ({"num_points": 64.0}, r"num_points must be an int, got 64\.0 \(float\)"),
        ({"steps": True}, r"FunFlow6DConfig\.steps must be an int, got True \(bool\)"),
        ({"ransac_threshold": "0.05"}, r"ransac_threshold must be a number, got '0\.05'"),
        ({"verification": 1}, r"verification must be true or false, got 1 \(int\)"),
        ({"icp_thresholds": ["a"]}, r"icp_thresholds must be a list of numbers"),
        ({"fusion": 3}, r"FunFlow6DConfig\.fusion must be a string, got 3 \(int\)"),
        ({"net": {"dropout": "0.1"}}, r"NetOptions\.dropout must be a number"),
        ({"net": {"dit": {"depth": "2"}}}, r"DiTOverrides\.depth must be an int or null"),
        ({"net": {"dit": {"attention": "none"}}}, r"attention must be one of 'global'"),
        ({"verifier": {"crop_size": "x"}}, r"VerifierConfig\.crop_size must be an int"),
        ({"verifier": {"icp_distances": "0.1"}}, r"icp_distances must be a list of numbers"),
    ],
)
def test_values_of_the_wrong_type_name_the_field_the_type_and_the_value(data, match):
    with pytest.raises(ValueRangeError, match=match):
        FunFlow6DConfig.from_json(data)


def test_numbers_of_any_kind_that_fit_the_field_are_accepted():
    import numpy as np

    cfg = FunFlow6DConfig(num_points=np.int64(64), ransac_threshold=1, icp_thresholds=[0.1])
    assert cfg.num_points == 64 and cfg.icp_thresholds == (0.1,)
    dit = FunFlow6DConfig(net={"dit": {"depth": None, "attention": "global"}}).net.dit
    assert dit.depth is None and dit.attention == "global"
    with pytest.raises(ValueRangeError, match=r"NetConfig\.geometric_dim must be an int"):
        NetConfig(geometric_dim="64")
