"""Object-specific surface embeddings: keys, loss, training crops, folders and FunFlow6D's use."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from poseflow.cli import main as poseflow
from poseflow.data import ImageInstances, generate_dataset
from poseflow.data.bop import BOPDataset
from poseflow.data.object_folder import load_object_models
from poseflow.errors import CheckpointError, MissingWeightsError, ValueRangeError
from poseflow.features import (
    SurfaceEmbedding,
    SurfaceEmbeddingEncoder,
    SurfaceKeys,
    load_surface_embedding,
    match_surface,
    save_surface_embedding,
)
from poseflow.features.appearance import AppearanceEncoder
from poseflow.features.surface_training import surface_crops, surface_loss, train_surface_embedding
from poseflow.flows import native_bfloat16
from poseflow.models import FunFlow6D, FunFlow6DConfig
from poseflow.models.components import build_appearance_encoder
from poseflow.models.objects import select_objects
from poseflow.models.proposals import flow_proposals, surface_match_positions
from poseflow.verify import VerifierConfig

TINY = {"dim": 8, "widths": (8, 16, 16), "key_width": 16, "frequencies": 3}


def _embedding(diameters=None, seed: int = 0) -> SurfaceEmbedding:
    torch.manual_seed(seed)
    return SurfaceEmbedding(diameters or {1: 0.1, 4: 0.2}, **TINY)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return generate_dataset(
        tmp_path_factory.mktemp("surface") / "ds", num_train_images=2, num_test_images=1,
        width=160, height=120, progress=False,
    )  # fmt: skip


@given(seed=st.integers(0, 2**16), dtype=st.sampled_from([torch.float32, torch.float64]))
@settings(max_examples=20, deadline=None)
def test_keys_are_unit_per_object_and_follow_the_dtype(seed, dtype) -> None:
    torch.manual_seed(seed)
    keys = SurfaceKeys([2, 1], dim=6, frequencies=2, width=8)
    pts = torch.rand(7, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype) * 2 - 1
    k1, k2 = keys(1, pts), keys(2, pts)
    assert k1.shape == (7, 6) and k1.dtype == dtype and keys.obj_ids == (1, 2)
    torch.testing.assert_close(k1.norm(dim=-1), torch.ones(7, dtype=dtype))
    assert not torch.allclose(k1, k2)  # one MLP per object
    with pytest.raises(ValueRangeError, match="no surface keys for object 3"):
        keys(3, pts)


@given(
    seed=st.integers(0, 2**16),
    dtype=st.sampled_from([torch.float32, torch.float64]),
    scale=st.floats(0.1, 10.0),
)
@settings(max_examples=20, deadline=None)
def test_match_surface_finds_each_query_its_own_key_and_skips_padding(seed, dtype, scale) -> None:
    g = torch.Generator().manual_seed(seed)
    keys = torch.nn.functional.normalize(torch.randn(2, 12, 16, generator=g, dtype=dtype), dim=-1)
    true = torch.randint(0, 12, (2, 5), generator=g)
    queries = scale * (keys.gather(1, true[..., None].expand(-1, -1, 16)))
    queries = queries + 1e-3 * scale * torch.randn(queries.shape, generator=g, dtype=dtype)
    index, sim = match_surface(queries, keys)
    assert torch.equal(index, true) and sim.dtype == dtype
    assert bool((sim <= 1 + 1e-6).all()) and bool((sim > 0.99).all())
    key_mask = torch.ones(2, 12, dtype=torch.bool)
    key_mask[0, true[0, 0]] = False  # the true key of the first query is padding
    index, _ = match_surface(queries, keys, key_mask)
    assert bool(key_mask.gather(1, index).all()) and torch.equal(index[1], true[1])


def test_bad_sizes_are_clear_errors() -> None:
    with pytest.raises(ValueRangeError, match="at least one object"):
        SurfaceKeys([], dim=4)
    with pytest.raises(ValueRangeError, match="positive"):
        SurfaceKeys([1], dim=0)
    with pytest.raises(ValueRangeError, match="diameters must be positive"):
        SurfaceEmbedding({1: 0.0})


def test_loss_prefers_matching_queries_and_reaches_both_networks() -> None:
    torch.manual_seed(0)
    keys = SurfaceKeys([1], dim=16, frequencies=2, width=32)
    g = torch.Generator().manual_seed(0)
    surface = torch.nn.functional.normalize(torch.randn(200, 3, generator=g), dim=-1)
    surfaces = {1: (surface, torch.eye(4)[None])}
    coords = surface[:24][None]
    matching = keys(1, coords[0])[None].detach()
    other = torch.nn.functional.normalize(torch.randn(1, 24, 16, generator=g), dim=-1)

    def loss(q, seed=1):
        return surface_loss(q, coords, [1], keys, surfaces, negatives=64, temperature=0.05,
                            sigma=0.1, generator=torch.Generator().manual_seed(seed))  # fmt: skip

    with torch.no_grad():
        assert loss(matching).item() < loss(other).item()
    q = other.clone().requires_grad_(True)
    value = loss(q)
    value.backward()
    assert value.dim() == 0 and math.isfinite(value.detach().item())
    assert q.grad is not None and keys.mlps["1"][0].weight.grad is not None


def test_loss_target_treats_symmetric_points_as_one() -> None:
    # a half-turn about z: a point and its turned copy are the same point of the object
    turn = torch.eye(4)
    turn[0, 0] = turn[1, 1] = -1.0
    syms = torch.stack([torch.eye(4), turn])
    torch.manual_seed(0)
    keys = SurfaceKeys([1], dim=8, frequencies=1, width=16)
    p = torch.tensor([[0.3, 0.1, 0.2]])
    surface = torch.cat([p, p @ turn[:3, :3].T])  # the point and its turned copy
    q = torch.nn.functional.normalize(torch.randn(1, 1, 8), dim=-1)
    pick = torch.randint(2, (6,), generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        logits = (q[0] @ keys(1, torch.cat([p, surface[pick]])).T / 0.07).log_softmax(-1)

    def loss(sym):
        return surface_loss(q, p[None], [1], keys, {1: (surface, sym)}, negatives=6,
                            generator=torch.Generator().manual_seed(3)).item()  # fmt: skip

    # with the symmetry every candidate is the pixel's point: a uniform target
    assert loss(syms) == pytest.approx(float(-logits.mean()), rel=1e-5)
    # without it, only the untouched copies are
    same = torch.cat([torch.ones(1, dtype=torch.bool), pick == 0])
    assert loss(syms[:1]) == pytest.approx(float(-logits[0, same].mean()), rel=1e-4)


def test_crops_hold_canonical_points_of_the_surface(dataset) -> None:
    data = surface_crops(dataset, max_images=2, size=48, points_per_crop=32, progress=False)
    m = len(data.crops)
    assert m > 0 and data.crops.shape == (m, 5, 48, 48) and data.crops.dtype == torch.float16
    assert data.uv.shape == (m, 32, 2) and data.coords.shape == (m, 32, 3)
    assert float(data.uv.min()) >= -1 and float(data.uv.max()) <= 48
    objects = load_object_models(dataset)
    for o in data.obj_ids.unique().tolist():
        sel = data.coords[data.obj_ids == o].reshape(-1, 3)
        surface = data.surfaces[o][0]
        # every sampled pixel lies near the object's surface (depth noise: a few percent)
        near = torch.cdist(sel, surface).min(dim=1).values
        assert float(near.median()) < 0.08
        assert data.diameters[o] == pytest.approx(objects[o].diameter)


def test_folder_round_trip_and_clear_errors(tmp_path) -> None:
    emb = _embedding()
    folder = save_surface_embedding(emb, tmp_path / "emb", input_size=32)
    back, cfg = load_surface_embedding(folder)
    assert back.diameters == emb.diameters and cfg["input_size"] == 32
    x = torch.rand(1, 5, 32, 32)
    torch.testing.assert_close(back.query(x), emb.query(x))
    pts = torch.rand(5, 3) * 0.05
    torch.testing.assert_close(back.keys_of(4, pts), emb.keys_of(4, pts))
    with pytest.raises(MissingWeightsError, match="poseflow train-surface"):
        load_surface_embedding(tmp_path / "nowhere")
    text = (folder / "config.json").read_text()
    (folder / "config.json").write_text(json.dumps({**json.loads(text), "dim": 7}))
    with pytest.raises(CheckpointError, match="does not fit"):
        load_surface_embedding(folder)
    (folder / "config.json").write_text(json.dumps({**json.loads(text), "format": "other"}))
    with pytest.raises(CheckpointError, match="not a surface embedding"):
        load_surface_embedding(folder)
    (folder / "config.json").write_text("{truncated")
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_surface_embedding(folder)


def test_encoder_queries_and_keys(tmp_path, device, dtype) -> None:
    folder = save_surface_embedding(_embedding(), tmp_path / "emb", input_size=32)
    enc = build_appearance_encoder(f"surface:{folder}", crop_size=32)
    assert isinstance(enc, SurfaceEmbeddingEncoder) and isinstance(enc, AppearanceEncoder)
    enc = SurfaceEmbeddingEncoder(folder, device=device)
    maps = enc.encode(torch.rand(2, 5, 40, 40, device=device, dtype=dtype))
    assert maps.shape == (2, 8, 8, 8) and maps.dtype == dtype
    torch.testing.assert_close(
        maps.norm(dim=1), torch.ones(2, 8, 8, device=device, dtype=dtype), atol=1e-4, rtol=0
    )
    pts = torch.rand(6, 3) * 0.05
    keys = enc.point_keys(1, pts, 0.1)
    assert keys.shape == (6, 8) and keys.dtype == torch.float32 and keys.device.type == "cpu"
    torch.testing.assert_close(keys, enc.model.keys_of(1, pts.to(device)).cpu())
    with pytest.raises(ValueRangeError, match="no keys for object 2"):
        enc.point_keys(2, pts, 0.1)
    with pytest.raises(ValueRangeError, match="another mesh or mesh scale"):
        enc.point_keys(1, pts, 0.2)
    with pytest.raises(ValueRangeError, match="needs its folder"):
        build_appearance_encoder("surface", crop_size=32)


def test_training_precision_is_applied_recorded_and_checked(dataset, tmp_path) -> None:
    def trained(precision):
        folder = train_surface_embedding(
            dataset, tmp_path / precision, steps=2, batch_size=2, queries=8, negatives=16,
            dim=16, init=None, precision=precision, progress=False,
        )  # fmt: skip
        config = json.loads((folder / "config.json").read_text())["training"]
        return config["precision"], load_surface_embedding(folder)[0].state_dict()

    named = {p: trained(p) for p in ("fp32", "bf16", "auto")}
    assert named["fp32"][0] == "fp32" and named["bf16"][0] == "bf16"
    assert named["auto"][0] == ("bf16" if native_bfloat16("cpu") else "fp32")
    single, half = named["fp32"][1], named["bf16"][1]
    assert any(not torch.equal(single[k], half[k]) for k in single)  # the products were bf16
    for k in single:  # the same two steps otherwise
        torch.testing.assert_close(half[k], single[k], atol=2e-2, rtol=0)
    with pytest.raises(ValueRangeError, match="precision must be one of"):
        train_surface_embedding(dataset, tmp_path / "x", steps=1, precision="fp64")


def test_queries_are_checked_against_the_pixels_kept(dataset, tmp_path, monkeypatch) -> None:
    kept = []

    def recording(*args, **kwargs):
        kept.append(kwargs["points_per_crop"])
        return surface_crops(*args, **kwargs)

    monkeypatch.setattr("poseflow.features.surface_training.surface_crops", recording)
    out = tmp_path / "all"
    args = ["train-surface", str(dataset), "--out", str(out), "--steps", "1", "--dim", "16"]
    extra = ["--queries", "16", "--points-per-crop", "16", "--no-init", "--no-progress"]
    assert poseflow([*args, *extra]) == 0
    training = json.loads((out / "config.json").read_text())["training"]
    assert kept == [16] and (training["queries"], training["points_per_crop"]) == (16, 16)
    with pytest.raises(ValueRangeError, match="queries must be at most points_per_crop"):
        train_surface_embedding(dataset, tmp_path / "x", steps=1, queries=17, points_per_crop=16)


def test_trained_embedding_conditions_funflow6d(dataset, tmp_path) -> None:
    folder = train_surface_embedding(
        dataset, tmp_path / "emb", steps=3, batch_size=2, queries=8, negatives=16, dim=16,
        init=None, progress=False,
    )  # fmt: skip
    config = json.loads((folder / "config.json").read_text())
    assert config["training"]["steps"] == 3 and math.isfinite(config["training"]["loss"])
    cfg = FunFlow6DConfig(
        num_points=32, crop_size=48, appearance_encoder=f"surface:{folder}", feature_dim=16,
        dit_preset="tiny", verifier=None,
    )  # fmt: skip
    objects = load_object_models(dataset, num_points=256)
    with pytest.raises(ValueRangeError, match="set feature_dim to at most 16"):
        FunFlow6D(cfg.replace(feature_dim=32)).prepare_objects(objects, progress=False)
    model = FunFlow6D(cfg)
    model.prepare_objects(objects, progress=False)
    for o, prepared in model.objects.items():
        keys = model.appearance_encoder.model.keys_of(o, prepared.points)
        torch.testing.assert_close(prepared.bank.pooled(), keys)
    for o, prepared in model.objects.items():
        torch.testing.assert_close(
            prepared.dense_keys, model.appearance_encoder.model.keys_of(o, prepared.dense_points)
        )
    cached = FunFlow6D(cfg)
    for _ in range(2):  # the second reads the cache, keys included
        cached.prepare_objects(objects, cache_dir=tmp_path / "cache", progress=False)
        for o, prepared in cached.objects.items():
            torch.testing.assert_close(prepared.dense_keys, model.objects[o].dense_keys)

    scene = BOPDataset(dataset, "test").scene(BOPDataset(dataset, "test").scene_ids[0])
    im_id = scene.im_ids[0]
    gts = scene.gt_of(im_id)
    masks = torch.stack([scene.load_mask(im_id, k, visible=True) for k in range(len(gts))])
    image = ImageInstances(
        scene.load_rgb_image(im_id), scene.load_depth_image(im_id),
        torch.as_tensor(scene.camera[im_id].K, dtype=torch.float32), masks,
        [gt.obj_id for gt in gts],
    )  # fmt: skip
    obs = model.observe(image)
    inputs = model.flow_inputs(obs)
    prepared = select_objects(model.objects, obs.obj_ids)
    matched = surface_match_positions(obs, prepared, inputs.scale)
    assert matched.shape == obs.points.shape
    for b, o in enumerate(prepared):  # every position is the best-keyed dense point
        queries = torch.nn.functional.normalize(obs.appearance[b], dim=-1)
        best = (queries @ o.dense_keys.T).argmax(1)
        torch.testing.assert_close(matched[b] * inputs.scale[b], o.dense_points[best])
    ranked = cfg.replace(verifier=VerifierConfig(), num_hypotheses=2)
    rows = {}
    for match in (True, False):
        out = flow_proposals(
            model.net, inputs, obs, model.objects, ranked.replace(match_hypothesis=match),
            torch.Generator().manual_seed(0),
        )  # fmt: skip
        rows[match] = out.others.shape[1]
    assert rows == {True: 2, False: 1}  # the match is one more ranked hypothesis
    with pytest.raises(ValueRangeError, match="need a surface embedding"):
        surface_match_positions(replace(obs, appearance=None), prepared, inputs.scale)


def test_the_command_refuses_to_overwrite_and_bad_counts(dataset, tmp_path, capsys) -> None:
    train_surface_embedding(
        dataset, tmp_path / "e", steps=1, batch_size=2, queries=8, negatives=16, dim=8,
        init=None, progress=False,
    )  # fmt: skip
    assert poseflow(["train-surface", str(dataset), "--out", str(tmp_path / "e")]) == 1
    assert "already holds an embedding; pass --overwrite" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        poseflow(
            ["train-surface", str(dataset), "--out", str(tmp_path / "f"), "--max-images", "-1"]
        )
    assert "--max-images" in capsys.readouterr().err
