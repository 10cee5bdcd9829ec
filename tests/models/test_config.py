import dataclasses
import json
import warnings
from pathlib import Path

import pytest

from poseflow.assets import DEMO_CHECKPOINT
from poseflow.errors import CheckpointError, MissingFileError, ValueRangeError
from poseflow.flows import PRESETS
from poseflow.models import (
    ABLATIONS,
    INFERENCE_FIELDS,
    RECIPES,
    DiTOverrides,
    FunFlow6DConfig,
    NetConfig,
    NetOptions,
    apply_overrides,
)
from poseflow.models.__main__ import main as write_configs
from poseflow.models.checkpoint import read_checkpoint, write_checkpoint
from poseflow.models.config import REMOVED_OPTIONS, RENAMED_FIELDS
from poseflow.verify import VerifierConfig

REPO = Path(__file__).resolve().parents[2]


def test_json_round_trip(tmp_path):
    cfg = FunFlow6DConfig(
        num_points=64,
        icp_distances=(0.1, 0.05),
        net=NetOptions(posenc_dim=32, dit=DiTOverrides(hidden_dim=96, attention="global")),
    )
    path = tmp_path / "c.json"
    path.write_text(json.dumps(cfg.to_dict()))
    back = FunFlow6DConfig.load(path)
    assert back == cfg and isinstance(back.net, NetOptions)
    assert isinstance(back.net.dit, DiTOverrides) and back.net.dit.hidden_dim == 96
    assert json.loads(path.read_text())["net"]["dit"] == {"hidden_dim": 96, "attention": "global"}
    net = back.net_config(geometric_dim=66, semantic_dim=64)
    assert NetConfig.from_dict(json.loads(json.dumps(net.to_dict()))) == net


def test_configs_are_frozen():
    cfg = FunFlow6DConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.steps = 4  # type: ignore[misc]
    assert hash(cfg) == hash(FunFlow6DConfig())


def test_the_verifier_field_round_trips_and_is_checked():
    assert FunFlow6DConfig().verifier == VerifierConfig()  # new configurations verify
    cfg = FunFlow6DConfig(
        verifier={"crop_size": 48, "significance": 0.01, "icp_distances": [0.1, 0.02]},
    )
    assert cfg.verifier == VerifierConfig(
        crop_size=48, significance=0.01, icp_distances=(0.1, 0.02)
    )
    data = json.loads(json.dumps(cfg.to_dict()))
    assert data["verifier"]["crop_size"] == 48 and data["verifier"]["rank_hypotheses"] is True
    assert FunFlow6DConfig.from_dict(data) == cfg
    off = cfg.replace(verifier=None)
    assert FunFlow6DConfig.from_dict(json.loads(json.dumps(off.to_dict()))).verifier is None
    assert cfg.replace(verifier={"crop_size": 32}).verifier.crop_size == 32
    with pytest.raises(ValueRangeError, match="rank_hypotheses must be true or false"):
        FunFlow6DConfig(verifier={"rank_hypotheses": 1})
    with pytest.raises(ValueRangeError, match="unknown VerifierConfig fields"):
        FunFlow6DConfig.from_dict({"verifier": {"crop": 48}})
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
        ("anchor", "noise", "pinned"),
        ("geometric_encoder", "fcgf", "fpfh, gedi, none"),
        ("appearance_encoder", "clip:vit", "dsift, dinov2, learned, surface, none"),
        ("dit_preset", "huge", ", ".join(PRESETS)),
        ("time_sampler", "beta", "uniform"),
    ],
)
def test_every_name_is_checked_at_construction(field, value, allowed):
    with pytest.raises(ValueRangeError, match=f"{field} must be one of") as info:
        FunFlow6DConfig(**{field: value})
    assert allowed in str(info.value) and repr(value) in str(info.value)


def test_bad_values_and_unknown_keys_raise():
    with pytest.raises(ValueRangeError, match="unknown FunFlow6DConfig fields"):
        FunFlow6DConfig.from_dict({"num_point": 3})
    with pytest.raises(ValueRangeError, match="unknown NetOptions fields"):
        FunFlow6DConfig.from_dict({"net": {"feature_dim": 32}})
    with pytest.raises(ValueRangeError, match="unknown DiTOverrides fields"):
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
    assert "fusion" not in cfg.to_dict()["net"]
    assert cfg.net_config(geometric_dim=66, semantic_dim=64).fusion == "sum"


@pytest.mark.parametrize(
    "path", [DEMO_CHECKPOINT / "config.json", REPO / "configs" / "demo_small.json"]
)
def test_shipped_config_files_keep_loading(path):
    raw = json.loads(path.read_text())
    cfg = FunFlow6DConfig.load(path)
    assert cfg == FunFlow6DConfig.recipe("demo_small")
    assert cfg.net.posenc_dim == raw["net"]["posenc_dim"] == 32
    assert cfg.net.dit.to_dict() == raw["net"]["dit"]
    assert cfg.net.fusion_heads == NetOptions().fusion_heads  # absent: the default
    dit = cfg.net_config(geometric_dim=66, semantic_dim=64).dit_config()
    assert (dit.hidden_dim, dit.depth, dit.num_heads, dit.time_frequency_dim) == (64, 4, 4, 64)
    assert dit.cond_dim == cfg.feature_dim + 32
    for key, value in raw.items():
        if key not in ("net", "verification", "verify_hypotheses", "verifier"):
            assert cfg.to_dict()[RENAMED_FIELDS.get(key, key)] == value, key


def test_files_from_before_the_typed_network_options_are_read_as_meant():
    old = {
        "fusion": "gated",
        "net": {"fusion": "sum", "dit_preset": "tiny", "dit": {"cond_dim": 7}},
    }
    cfg = FunFlow6DConfig.from_dict(old)
    assert (cfg.fusion, cfg.dit_preset, cfg.net.dit) == ("sum", "tiny", DiTOverrides())


def test_old_names_in_files_are_read_as_the_new_fields_silently():
    old = {
        "ransac_threshold": 0.07,
        "icp_thresholds": [0.1, 0.03],
        "verification": True,
        "verify_hypotheses": False,
        "verifier": {"crop_size": 48, "rank_top_k": 4},
    }
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # checkpoints are data: no warning
        cfg = FunFlow6DConfig.from_dict(old)
    assert cfg == FunFlow6DConfig(
        ransac_distance=0.07,
        icp_distances=(0.1, 0.03),
        verifier=VerifierConfig(crop_size=48, rank_top_k=4, rank_hypotheses=False),
    )
    assert FunFlow6DConfig.from_dict({**old, "verification": False}).verifier is None
    assert FunFlow6DConfig.from_dict({"verification": True}).verifier == VerifierConfig()
    assert FunFlow6DConfig.from_dict({"verify_hypotheses": False}).verifier == VerifierConfig(
        rank_hypotheses=False
    )
    with pytest.raises(ValueRangeError, match="verification must be true or false"):
        FunFlow6DConfig.from_dict({"verification": "yes"})
    for old_name in ("icp_thresholds", "verification", "verify_hypotheses"):
        assert old_name not in cfg.to_dict()


def test_removed_options_at_their_kept_value_load_and_others_name_the_option(tmp_path):
    # a config.json written while the options existed holds every field, at the defaults
    old = FunFlow6DConfig().to_dict()
    old["net"]["soft_match"] = False
    cfg = FunFlow6DConfig.from_dict(old)
    assert cfg == FunFlow6DConfig() and "soft_match" not in cfg.to_dict()["net"]
    folder = write_checkpoint(tmp_path / "old", FunFlow6DConfig(), {})
    (folder / "config.json").write_text(json.dumps(old))
    assert read_checkpoint(folder)[0] == FunFlow6DConfig()
    removed = {"net.soft_match": True, "anchor": "noise", "time_sampler": "logit_normal"}
    assert set(removed) == set(REMOVED_OPTIONS)
    for key, value in removed.items():
        data = json.loads(json.dumps(old))
        *parents, name = key.split(".")
        holder = data[parents[0]] if parents else data
        holder[name] = value
        with pytest.raises(ValueRangeError, match=rf"{key}={value!r}: this option was removed"):
            FunFlow6DConfig.from_dict(data)
        (folder / "config.json").write_text(json.dumps(data))
        with pytest.raises(CheckpointError, match=f"{key}.*removed.*commit"):
            read_checkpoint(folder)
    with pytest.raises(ValueRangeError, match="soft_match"):
        apply_overrides(FunFlow6DConfig(), {"net.soft_match": True})


def test_the_shipped_checkpoint_keeps_its_settings_under_the_new_names():
    raw = json.loads((DEMO_CHECKPOINT / "config.json").read_text())
    assert "icp_thresholds" in raw and raw["verification"] is True  # written before the renames
    config, _ = read_checkpoint(DEMO_CHECKPOINT)
    # written before the flow's precision was a field: it samples in float32, as it did
    assert "flow_precision" not in raw and config.flow_precision == "fp32"
    assert "appearance_precision" not in raw and config.appearance_precision == "fp32"
    assert config == FunFlow6DConfig.recipe("demo_small").replace(
        flow_precision="fp32", appearance_precision="fp32"
    )
    new = config.to_dict()
    assert new["ransac_distance"] == raw["ransac_threshold"]
    assert new["icp_distances"] == raw["icp_thresholds"]
    # the verifier's options added since (the polish, the slides) keep their defaults
    old_verifier = {**raw["verifier"], "rank_hypotheses": raw["verify_hypotheses"]}
    assert new["verifier"] == {**VerifierConfig().to_dict(), **old_verifier}
    renamed = ("ransac_threshold", "icp_thresholds", "verification", "verify_hypotheses")
    for key, value in raw.items():
        if key == "net":  # the network's options added since keep their defaults
            assert new[key] == {**NetOptions().to_dict(), **value}, key
        elif key not in (*renamed, "verifier"):
            assert new[key] == value, key


def test_recipes_are_the_configs_files(tmp_path):
    for name in RECIPES:
        path = REPO / "configs" / f"{name}.json"
        assert FunFlow6DConfig.load(name) == FunFlow6DConfig.load(path)
        assert FunFlow6DConfig.recipe(name) == FunFlow6DConfig.from_dict(RECIPES[name])
    learned = FunFlow6DConfig.recipe("learned_small")
    got = (learned.appearance_encoder, learned.num_hypotheses, learned.solver, learned.steps)
    assert got == ("learned", 24, "midpoint", 1)
    demo = FunFlow6DConfig.recipe("demo_small")
    as_demo = learned.replace(
        appearance_encoder="dsift", solver="euler", steps=4, ransac_iterations=1000,
        num_hypotheses=12,
        verifier=dataclasses.replace(learned.verifier, search_top_k=demo.verifier.search_top_k),
    )  # fmt: skip
    assert as_demo == demo
    write_configs(["--write-configs", str(tmp_path)])
    for name in RECIPES:  # the checkout's files are what the command writes: in sync
        written = (tmp_path / f"{name}.json").read_text()
        assert (REPO / "configs" / f"{name}.json").read_text() == written, name
    with pytest.raises(ValueRangeError, match="recipe must be one of"):
        FunFlow6DConfig.recipe("large")
    with pytest.raises(MissingFileError, match="nor a recipe name"):
        FunFlow6DConfig.load(tmp_path / "none.json")


def test_overrides_merge_into_nested_configurations():
    demo = FunFlow6DConfig.recipe("demo_small").replace(verifier=VerifierConfig(crop_size=48))
    cfg = apply_overrides(demo, {"verifier": {"rank_top_k": 4}, "steps": 2})
    assert cfg.steps == 2 and cfg.verifier == VerifierConfig(crop_size=48, rank_top_k=4)
    assert apply_overrides(demo, {"verifier.rank_top_k": 4}) == cfg.replace(steps=4)
    deep = apply_overrides(demo, {"net.dit.depth": 2, "net": {"dropout": 0.2}})
    assert deep.net == NetOptions(
        dropout=0.2, posenc_dim=32, posenc_frequencies=4,
        dit=DiTOverrides(hidden_dim=64, num_heads=4, depth=2, time_frequency_dim=64),
    )  # fmt: skip
    off = demo.replace(verifier=None)
    assert apply_overrides(off, {"verifier.rank_top_k": 2}).verifier == VerifierConfig(rank_top_k=2)
    assert apply_overrides(off, {"verifier": {}}).verifier == VerifierConfig()
    assert apply_overrides(demo, {"verifier": None}).verifier is None
    assert apply_overrides(demo, {"icp_distances": []}).icp_distances == ()
    with pytest.raises(ValueRangeError, match=r"VerifierConfig field 'crop' in 'verifier\.crop'"):
        apply_overrides(demo, {"verifier.crop": 3})
    with pytest.raises(ValueRangeError, match="unknown FunFlow6DConfig field 'colour'"):
        apply_overrides(demo, {"colour": "red"})
    with pytest.raises(ValueRangeError, match=r"'steps\.x': FunFlow6DConfig\.steps has no fields"):
        apply_overrides(demo, {"steps.x": 1})


def test_inference_settings_change_through_with_inference_only():
    demo = FunFlow6DConfig.recipe("demo_small")
    cfg = demo.with_inference({"verifier.rank_hypotheses": False}, steps=8, icp_distances=[0.1])
    assert (cfg.steps, cfg.icp_distances, cfg.verifier.rank_hypotheses) == (8, (0.1,), False)
    assert cfg.replace(steps=4, icp_distances=demo.icp_distances, verifier=demo.verifier) == demo
    assert demo.with_inference(verifier=None).verifier is None
    for key in ("num_points", "net.dit.depth", "verification", "fusion"):
        with pytest.raises(ValueRangeError, match="not an inference setting") as info:
            demo.with_inference({key: 1})
        assert ", ".join(INFERENCE_FIELDS) in str(info.value)


@pytest.mark.parametrize("name", ["flow_precision", "appearance_precision"])
def test_the_precisions_are_inference_settings_with_named_values(name):
    demo = FunFlow6DConfig.recipe("demo_small")
    assert getattr(demo, name) == "auto"
    assert getattr(demo.with_inference(**{name: "fp32"}), name) == "fp32"
    with pytest.raises(ValueRangeError, match=name):
        demo.with_inference(**{name: "int8"})


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
        ({"ransac_distance": "0.05"}, r"ransac_distance must be a number, got '0\.05'"),
        ({"verifier": 1}, r"verifier must be a VerifierConfig .* or null, got 1 \(int\)"),
        ({"icp_distances": ["a"]}, r"icp_distances must be a list of numbers"),
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
        FunFlow6DConfig.from_dict(data)


def test_numbers_of_any_kind_that_fit_the_field_are_accepted():
    import numpy as np

    cfg = FunFlow6DConfig(num_points=np.int64(64), ransac_distance=1, icp_distances=[0.1])
    assert cfg.num_points == 64 and cfg.icp_distances == (0.1,)
    dit = FunFlow6DConfig(net={"dit": {"depth": None, "attention": "global"}}).net.dit
    assert dit.depth is None and dit.attention == "global"
    with pytest.raises(ValueRangeError, match=r"NetConfig\.geometric_dim must be an int"):
        NetConfig(geometric_dim="64")
