"""``benchmarks/gpu.py``: its CPU dry run executes every stage, and its parts do what they say."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest
import torch

from poseflow.flows import get_sampler
from poseflow.models import FunFlow6D, NetInputs

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture(scope="module")
def gpu():
    spec = importlib.util.spec_from_file_location("gpu_benchmark", BENCHMARKS / "gpu.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass resolves annotations through sys.modules
    spec.loader.exec_module(module)
    yield module
    del sys.modules[spec.name]


@pytest.fixture(scope="module")
def tiny_model(gpu, tmp_path_factory):
    """An untrained model of the dry run's sizes, with its random DINOv2 on disk."""
    work = tmp_path_factory.mktemp("gpu_work")
    gpu.write_random_dinov2(gpu.weights_dir(work, gpu.TINY), gpu.TINY)
    torch.manual_seed(0)
    return FunFlow6D(gpu.paper_config(work, gpu.TINY)).eval()


def test_the_paper_scale_is_the_papers(gpu, tmp_path):
    cfg = gpu.paper_config(tmp_path, gpu.PAPER)
    assert (cfg.num_points, cfg.dit_preset, cfg.reducer, cfg.fusion) == (
        1024,
        "paper",
        "umap",
        "gated",
    )
    assert cfg.appearance_encoder.startswith("dinov2:") and cfg.num_hypotheses == 1
    assert cfg.ransac_iterations == 1000 and gpu.PAPER.instances == 8
    assert gpu.PAPER.dinov2 == {
        "hidden_size": 384,
        "num_hidden_layers": 12,
        "num_attention_heads": 6,
    }
    assert sum(gpu.PAPER_A100_MS.values()) == pytest.approx(gpu.PAPER_A100_TOTAL_MS, abs=0.01)


def test_random_dinov2_is_the_same_from_its_seed(gpu, tmp_path):
    first = gpu.write_random_dinov2(tmp_path / "a", gpu.TINY)
    assert first == gpu.write_random_dinov2(tmp_path / "b", gpu.TINY)
    assert json.loads((tmp_path / "a" / "config.json").read_text())["hidden_size"] == 32


def test_fusion_table_names_the_kernel_of_every_case(gpu, tiny_model):
    rows = gpu.fusion_kernels(tiny_model, batch=4, device=torch.device("cpu"), repeats=2)
    cases = {(r["precision"], r["padding"], r["variant"]): r for r in rows}
    assert len(cases) == len(rows) == 2 * 2 * (1 + len(gpu.SDPA_VARIANTS))
    for precision in ("float32", "bfloat16"):
        for padded in (False, True):
            assert cases[precision, padded, "poseflow gated"]["kernel"] == "cpu-fused"
            assert cases[precision, padded, "sdpa math"]["kernel"] == "math"
            # the CPU has neither cuDNN nor the memory-efficient kernel
            for missing in ("sdpa cudnn", "sdpa efficient"):
                assert "No viable backend" in cases[precision, padded, missing]["error"]
            for row in rows:
                if "error" not in row:
                    assert row["first_ms"] > 0 and row["median_ms"] > 0


def test_networks_run_in_the_precision_and_the_model_is_restored(gpu, tiny_model):
    from poseflow.models.observe import observe

    seen = {"dit": [], "encoder": []}
    encoder, config = tiny_model.appearance_encoder, tiny_model.config
    hooks = [
        module.register_forward_pre_hook(
            lambda module, args, key=key: seen[key].append(torch.is_autocast_enabled("cpu"))
        )
        for key, module in (("dit", tiny_model.net.dit), ("encoder", encoder.model))
    ]
    try:
        with gpu.autocast_networks(tiny_model, torch.bfloat16):
            assert tiny_model.config.flow_precision == "bf16"
            assert tiny_model.config.appearance_precision == "bf16"
            inputs = _inputs(tiny_model)
            frozen = torch.zeros(inputs.mask.shape, dtype=torch.bool)
            frozen[:, : inputs.mask.shape[1] // 2] = True  # the query half
            tiny_model.net.sample(
                inputs, get_sampler("euler", steps=2), frozen_mask=frozen,
                precision=tiny_model.config.flow_precision,
            )  # fmt: skip
            obs = observe(
                *_image(), [0.1], num_points=16, dense_points=256, appearance_encoder=encoder,
                appearance_precision=tiny_model.config.appearance_precision,
            )  # fmt: skip
            assert not torch.is_autocast_enabled("cpu")  # only inside the networks' calls
    finally:
        for hook in hooks:
            hook.remove()
    assert obs.appearance.dtype == torch.float32
    assert seen["dit"] and all(seen["dit"]) and seen["encoder"] and all(seen["encoder"])
    assert tiny_model.config == config
    with gpu.autocast_networks(tiny_model, None):
        assert tiny_model.config.flow_precision == tiny_model.config.appearance_precision == "fp32"
    assert tiny_model.config == config


def _image():
    """A 64 × 64 image with one square instance of object 1 at half a metre."""
    from poseflow.data import ImageInstances

    g = torch.Generator().manual_seed(1)
    depth = torch.full((64, 64), 0.5) + 0.01 * torch.rand(64, 64, generator=g)
    masks = torch.zeros(1, 64, 64, dtype=torch.bool)
    masks[0, 16:48, 16:48] = True
    K = torch.tensor([[80.0, 0, 31.5], [0, 80.0, 31.5], [0, 0, 1]])
    return ImageInstances(torch.rand(3, 64, 64, generator=g), depth, K, masks, [1])


def _inputs(model):
    g = torch.Generator().manual_seed(0)
    cfg = model.net.config
    n = 2 * 8
    return NetInputs(
        geometric=torch.randn(2, n, cfg.geometric_dim, generator=g),
        semantic=torch.randn(2, n, cfg.semantic_dim, generator=g),
        points=torch.randn(2, n, 3, generator=g),
        normals=torch.randn(2, n, 3, generator=g),
        mask=torch.ones(2, n, dtype=torch.bool),
    )


def test_run_refuses_objects_it_would_have_to_render(gpu, tiny_model, tmp_path):
    from poseflow.data.synthetic import generate_dataset

    root = generate_dataset(
        tmp_path / "data", num_train_images=0, num_test_images=1, objects_per_image=1,
        width=96, height=72, progress=False,
    )  # fmt: skip
    with pytest.raises(SystemExit, match="not prepared"):
        gpu.load_prepared_objects(tiny_model, root, tmp_path / "objects", torch.device("cpu"))
    assert not (tmp_path / "objects").exists()


def test_without_cuda_the_full_run_says_what_to_do(gpu, capsys):
    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    with pytest.raises(SystemExit):
        gpu.main(["run", "--work", "nowhere"])
    assert "--dry-run" in capsys.readouterr().err


@pytest.mark.slow
def test_dry_run_executes_every_stage_and_prints_the_tables(gpu, tmp_path, capsys):
    """The CI dry run: prepare, run and score at tiny sizes on the CPU (about 90 s here)."""
    result = gpu.main(["--dry-run", "--work", str(tmp_path)])
    run = result["run"]
    stages = set(gpu.STAGE_LABELS)
    for model in ("paper_scale", "small_model"):
        table = run[model] if model == "paper_scale" else run[model]["settings"]
        assert set(table) == {"float32", "bfloat16"}
        for rows in table.values():
            assert list(rows) == ["euler:2", "euler:1"]
            for row in rows.values():
                assert set(row["stages_ms"]) == stages
                assert all(ms > 0 for ms in row["stages_ms"].values())
                assert row["instances_per_image"] == gpu.TINY.instances
    assert run["umap_fit"]["backend"] == "torchdr" and len(run["umap_fit"]["fit_s"]) == 3
    assert run["dinov2_weights_as_prepared"]
    for precision in ("float32", "bfloat16"):
        for name in ("euler-2", "euler-1"):
            assert (tmp_path / "run" / "small" / precision / f"results_{name}.csv").is_file()
    scores = result["score"]["precisions"]
    for precision in ("float32", "bfloat16"):
        for row in scores[precision]["settings"].values():
            assert 0.0 <= row["AR"] <= 1.0
        assert scores[precision]["fastest_equal_ar"] in ("euler:2", "euler:1")
    out = capsys.readouterr().out
    assert "gated fusion attention" in out and "paper A100 euler:50" in out
    assert json.loads(next(line for line in out.splitlines() if line.startswith('{"benchmark"')))
    assert out.rstrip().splitlines()[-1].startswith("command: python benchmarks/gpu.py")
