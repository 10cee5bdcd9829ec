"""FunFlow6D at the paper's scale on one GPU: the paper's stage breakdown in float32 and bfloat16.

Times, per image of 8 instances, the ``paper`` DiT preset (43.5 M trainable parameters) at
N = 1,024 points per cloud (the scale of ``benchmarks/networks.py``; the paper does not give its
N) with a DINOv2 ViT-S/14 of random weights as appearance encoder (the weights do not change the
time), UMAP to 64 channels (refitted with TorchDR on the run's device where TorchDR imports, as in
the paper), FPFH as geometric encoder (the weight-free default; the paper uses dGeDi), gated
fusion, one hypothesis per instance and 1,000 RANSAC hypotheses: every stage of the paper's
breakdown (DINOv2, UMAP, geometric encoder, fusion, flow net, integration, RANSAC, ICP, other), at
Euler 50 and at ``--fast-steps`` (5: the fewest Euler steps that kept the AR of the trained
``small`` model on the H100, ``benchmarks/RESULTS.md``), in float32 and in bfloat16. The shipped
``small`` checkpoint is timed on the same images at several step counts and its estimates written
as BOP results CSVs, so that ``score`` finds the fewest steps that keep its AR in each precision.

bfloat16 is autocast around the networks only, DINOv2 and the velocity network (fusion and DiT):
the geometry (lifting, RANSAC, ICP) and dense SIFT stay in float32. Autocast around all of
:meth:`~poseflow.models.FunFlow6D.estimate` moves the shipped model's poses by degrees on a
generated image (its matrix products run in bfloat16 too), so it would time a less accurate
pipeline.

It also times the gated fusion's attention alone (the 2 × 8 clouds of an image): poseflow's layer
and plain SDPA with each of PyTorch's backends forced, float32 and bfloat16, with and without key
padding, the first call at a shape not seen before and the median of ``--repeats`` calls, and names
the kernel that ran (from the profiler).

Phases (the GPU machine needs neither Open3D nor umap-learn)::

    python benchmarks/gpu.py prepare --work runs/gpu          # CPU machine, Open3D + umap-learn
    python benchmarks/gpu.py run --work runs/gpu --out OUT    # GPU machine
    python benchmarks/gpu.py score --work runs/gpu --out OUT  # CPU machine: the small model's AR
    python benchmarks/gpu.py --work runs/gpu                  # all three where all is at hand
    python benchmarks/gpu.py --dry-run                        # all three, tiny, on the CPU (CI)

``prepare`` generates ``--images`` test images with 8 demo objects each in ``WORK/data``, the
query objects of the paper-scale model in ``WORK/objects`` and ``WORK/prepare.json``: these three
go to the GPU machine (32 MiB for 10 images). The random DINOv2 weights (88 MB, in
``WORK/weights``) stay behind: ``run`` rebuilds them from the same seed and reports whether they
came out equal. ``run`` prints the fusion table and the paper-style table (ms and share of every
stage beside the paper's A100 figures), one JSON line, and the command; it writes ``gpu.json``
and the results CSVs to ``OUT``. ``score`` reads them back and prints the small model's AR per
setting and precision. ``--dry-run`` (or ``--quick``) runs all three on the CPU at tiny sizes
(2 instances per image, N = 64, the ``tiny`` DiT, a 2-layer ViT) and executes every stage.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import hashlib
import itertools
import json
import platform
import sys
import tempfile
import warnings
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch.nn.attention import SDPBackend, sdpa_kernel
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _common, also when imported by path
from _common import clocked, command, timed

from poseflow.assets import DEMO_CHECKPOINT
from poseflow.cli.bench import benchmark_settings, fastest_equal_setting
from poseflow.data.object_folder import load_object_models, object_cache_dir
from poseflow.errors import MissingDependencyError
from poseflow.features import UMAPReducer
from poseflow.fusion import key_padding_mask
from poseflow.models import FunFlow6D, FunFlow6DConfig, NetOptions, load_prepared_object

#: The paper's per-image breakdown on an A100 (LM-O, 8 instances, Euler 50), ms.
PAPER_A100_MS = {
    "appearance_encoder": 151.29,
    "reducer": 75.10,
    "geometric_encoder": 79.90,
    "flow_net": 91.21,
    "integration": 381.11,
    "ransac": 148.45,
    "icp": 84.59,
    "other": 4.25,
}
PAPER_A100_TOTAL_MS = 1015.90

#: Table labels of the timer's stages, in the paper's order (verification, which the paper does
#: not have, before "other"; the paper's "other" holds what poseflow times as lifting and flow
#: inputs too).
STAGE_LABELS = {
    "lifting": "lifting",
    "appearance_encoder": "DINOv2",
    "reducer": "UMAP",
    "geometric_encoder": "geometric encoder",
    "flow_inputs": "flow inputs",
    "fusion": "fusion",
    "flow_net": "flow net (DiT)",
    "integration": "integration",
    "ransac": "RANSAC",
    "icp": "ICP",
    "verification": "verification",
    "other": "other",
}

PRECISIONS: dict[str, torch.dtype | None] = {"float32": None, "bfloat16": torch.bfloat16}
SHORT = {"float32": "fp32", "bfloat16": "bf16"}


@dataclass(frozen=True)
class Scale:
    """Sizes of a run: the generated images, the paper-scale model and the fusion timing."""

    name: str
    instances: int
    width: int
    height: int
    num_points: int
    dense_points: int
    crop_size: int
    query_views: int
    feature_dim: int
    fusion_heads: int
    posenc_dim: int
    posenc_frequencies: int
    dit_preset: str
    ransac_iterations: int
    dinov2: dict[str, int]


#: The paper's scale: 8 instances, N = 1,024, DINOv2 ViT-S/14 (384 channels, 12 layers, 6 heads).
PAPER = Scale(
    name="paper", instances=8, width=640, height=480, num_points=1024, dense_points=4096,
    crop_size=224, query_views=4, feature_dim=64, fusion_heads=4, posenc_dim=64,
    posenc_frequencies=6, dit_preset="paper", ransac_iterations=1000,
    dinov2={"hidden_size": 384, "num_hidden_layers": 12, "num_attention_heads": 6},
)  # fmt: skip
#: The CPU dry run: the same code path at sizes that run in seconds.
TINY = Scale(
    name="tiny", instances=2, width=160, height=120, num_points=64, dense_points=256,
    crop_size=28, query_views=4, feature_dim=8, fusion_heads=2, posenc_dim=16,
    posenc_frequencies=2, dit_preset="tiny", ransac_iterations=100,
    dinov2={"hidden_size": 32, "num_hidden_layers": 2, "num_attention_heads": 2,
            "intermediate_size": 64, "image_size": 28},
)  # fmt: skip
SCALES = {s.name: s for s in (PAPER, TINY)}


# --- the models -------------------------------------------------------------------------------


def weights_dir(work: Path, scale: Scale) -> Path:
    """Where the random DINOv2 of ``scale`` is written (not carried: rebuilt from its seed)."""
    return work / "weights" / f"dinov2-{scale.name}-random"


def write_random_dinov2(folder: Path, scale: Scale) -> str:
    """Write a DINOv2 of random weights (seed 0) as a Hugging Face folder; returns its digest."""
    from transformers import Dinov2Config, Dinov2Model

    torch.manual_seed(0)
    net = Dinov2Model(Dinov2Config(**scale.dinov2))
    digest = hashlib.sha1()
    for name, tensor in sorted(net.state_dict().items()):
        digest.update(name.encode())
        digest.update(tensor.detach().contiguous().numpy().tobytes())
    if not (folder / "config.json").is_file():
        net.save_pretrained(folder)
    return digest.hexdigest()[:16]


def paper_config(work: Path, scale: Scale) -> FunFlow6DConfig:
    """The paper-scale configuration (untrained: the weights do not change the time)."""
    return FunFlow6DConfig(
        num_points=scale.num_points,
        dense_points=scale.dense_points,
        appearance_encoder=f"dinov2:{weights_dir(work, scale)}",
        crop_size=scale.crop_size,
        query_views=scale.query_views,
        reducer="umap",
        feature_dim=scale.feature_dim,
        fusion="gated",
        dit_preset=scale.dit_preset,
        num_hypotheses=1,
        ransac_iterations=scale.ransac_iterations,
        net=NetOptions(
            fusion_heads=scale.fusion_heads,
            posenc_dim=scale.posenc_dim,
            posenc_frequencies=scale.posenc_frequencies,
        ),
    )


def load_prepared_objects(model: FunFlow6D, root: Path, cache: Path, device: torch.device) -> None:
    """Give ``model`` its prepared objects from ``cache``, never preparing one here.

    Preparing renders the textured models (Open3D), which the GPU machine lacks.

    Raises:
        SystemExit: an object of the dataset is not in the cache for this configuration.
    """
    models = load_object_models(root)
    missing = [
        i
        for i in sorted(models)
        if load_prepared_object(cache, i, models[i], model.config, model.appearance_encoder) is None
    ]
    if missing:
        raise SystemExit(
            f"objects {missing} are not prepared in {cache} for this configuration: run "
            "`python benchmarks/gpu.py prepare --work WORK` on a machine with Open3D and carry "
            "WORK here under the same path"
        )
    model.prepare_objects(models, cache_dir=cache, progress=False)


def refit_umap(
    model: FunFlow6D, device: torch.device, *, epochs: int | None = None
) -> dict[str, Any]:
    """Refit every object's UMAP with TorchDR on ``device`` on the same rows, where it imports.

    The paper fits UMAP with TorchDR on the GPU; preparation fitted it with umap-learn on the CPU.
    The per-image UMAP stage (poseflow's torch transform) is the same code for both fits.

    Args:
        model: a model with prepared objects.
        device: where TorchDR fits.
        epochs: TorchDR's iterations (None: the prepared reducer's, by default 500).

    Returns:
        ``{"backend", "device", "fit_s"}``: who fitted the reducers used in the timing, and
        TorchDR's fit time of each object (none when TorchDR is absent).
    """
    try:
        UMAPReducer(fit_backend="torchdr").resolve_fit_backend(device)
    except MissingDependencyError:
        return {"backend": "umap-learn (at preparation)", "device": "cpu", "fit_s": []}
    seconds = []
    for obj in model.objects.values():
        old = obj.reducer
        if not isinstance(old, UMAPReducer):
            continue
        new = UMAPReducer(
            old.n_components,
            n_neighbors=old.n_neighbors,
            min_dist=old.min_dist,
            metric=old.metric,
            normalize=old.normalize,
            random_state=old.random_state,
            n_epochs=old.n_epochs if epochs is None else epochs,
            fit_backend="torchdr",
        )
        fit_s, _ = clocked(lambda new=new, old=old: new.fit(old.train_.to(device)), device=device)
        seconds.append(round(fit_s, 3))
        obj.reducer = new
    return {"backend": "torchdr", "device": str(device), "fit_s": seconds}


@contextlib.contextmanager
def autocast_networks(model: FunFlow6D, dtype: torch.dtype | None) -> Iterator:
    """Run ``model``'s networks in ``dtype``; geometry stays in float32.

    The velocity network samples in the model's ``flow_precision`` and a network appearance
    encoder (DINOv2, the learned descriptor) computes in its ``appearance_precision``, both set
    to ``"fp32"`` for ``dtype=None``, ``"bf16"`` for bfloat16; dense SIFT, a fixed filter bank,
    stays in float32.
    """
    config = model.config
    name = {None: "fp32", torch.bfloat16: "bf16", torch.float16: "fp16"}[dtype]
    model.config = config.with_inference(flow_precision=name, appearance_precision=name)
    try:
        yield
    finally:
        model.config = config


# --- the fusion's attention alone -------------------------------------------------------------

#: Forced SDPA backends of the fusion table (None: PyTorch's own choice).
SDPA_VARIANTS: dict[str, SDPBackend | None] = {
    "sdpa default": None,
    "sdpa cudnn": SDPBackend.CUDNN_ATTENTION,
    "sdpa flash": SDPBackend.FLASH_ATTENTION,
    "sdpa efficient": SDPBackend.EFFICIENT_ATTENTION,
    "sdpa math": SDPBackend.MATH,
}

KERNELS = {
    "aten::_scaled_dot_product_flash_attention_for_cpu": "cpu-fused",
    "aten::_scaled_dot_product_flash_attention": "flash",
    "aten::_scaled_dot_product_efficient_attention": "efficient",
    "aten::_scaled_dot_product_cudnn_attention": "cudnn",
    "aten::_scaled_dot_product_attention_math": "math",
}


def _kernels(fn: Callable[[], Any]) -> str:
    """The SDPA kernels ``fn()`` ran, by short name."""
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        fn()
    names = {KERNELS[e.name] for e in prof.events() if e.name in KERNELS}
    return "+".join(sorted(names)) or "none"


def _time_case(
    make: Callable[[int], Callable[[], Any]],
    batch: int,
    fresh: int,
    device: torch.device,
    repeats: int,
) -> dict[str, Any]:
    """Time ``make(fresh)()`` once (a new shape), then the median of ``make(batch)()``.

    Returns:
        ``{"kernel", "first_ms", "median_ms"}``, the kernel read by the profiler.
    """
    first, _ = clocked(make(fresh), device=device)
    call = make(batch)
    median, _ = timed(call, repeats, device=device)
    return {
        "kernel": _kernels(call),
        "first_ms": round(1e3 * first, 3),
        "median_ms": round(1e3 * median, 3),
    }


def _fusion_call(
    fusion: torch.nn.Module,
    geo: torch.Tensor,
    sem: torch.Tensor,
    mask: torch.Tensor,
    dtype: torch.dtype | None,
    batch: int,
) -> Callable[[], Any]:
    """The fusion block on the first ``batch`` clouds, autocast to ``dtype`` as in the pipeline."""

    def call() -> Any:
        autocast = torch.autocast(geo.device.type, dtype=dtype or torch.bfloat16)
        with torch.no_grad(), autocast if dtype is not None else contextlib.nullcontext():
            return fusion(geo[:batch], sem[:batch], mask[:batch])

    return call


def _sdpa_call(
    qkv: torch.Tensor,
    mask: torch.Tensor | None,
    dtype: torch.dtype,
    backend: SDPBackend | None,
    batch: int,
) -> Callable[[], Any]:
    """Plain SDPA on the first ``batch`` clouds with the boolean key mask, ``backend`` forced."""
    q, k, v = (t[:batch].to(dtype) for t in qkv)
    attn_mask = None if mask is None else key_padding_mask(mask[:batch])

    def call() -> Any:
        chosen = sdpa_kernel([backend]) if backend is not None else contextlib.nullcontext()
        with torch.no_grad(), chosen, warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the reasons a forced backend cannot run
            return F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask)

    return call


def fusion_kernels(model: FunFlow6D, batch: int, device: torch.device, repeats: int) -> list[dict]:
    """Time the model's gated fusion and plain SDPA per backend on the clouds of one image.

    Every case runs float32 and bfloat16 (autocast for the fusion block, bfloat16 tensors for
    SDPA), without padding (the fusion block gets an all-valid mask, as in the pipeline) and with
    every other cloud padded by a tenth of its points.

    Args:
        model: the paper-scale model (its fusion block and sizes are used).
        batch: clouds per call (2 per instance: the query and the target).
        device: where to run.
        repeats: timed calls after the warm-up.

    Returns:
        One row per (precision, padding, variant): ``kernel``, ``first_ms`` (first call at a
        batch size not seen before), ``median_ms``, or ``error`` when the backend cannot run.
    """
    fusion = model.net.fusion
    dim, heads, n = fusion.dim, model.config.net.fusion_heads, model.config.num_points
    fresh = itertools.count(batch + 1)  # one unseen batch size per case, for its first call
    largest = batch + 1 + 2 * len(PRECISIONS) * (1 + len(SDPA_VARIANTS))
    gen = torch.Generator().manual_seed(0)
    geo, sem = torch.randn(2, largest, n, dim, generator=gen).to(device)
    qkv = torch.randn(3, largest, heads, n, dim // heads, generator=gen).to(device)
    rows = []
    for precision, dtype in PRECISIONS.items():
        for padded in (False, True):
            mask = torch.ones(largest, n, dtype=torch.bool, device=device)
            if padded:
                mask[1::2, -(n // 10) :] = False
            cases = {
                "poseflow gated": functools.partial(_fusion_call, fusion, geo, sem, mask, dtype)
            }
            for label, backend in SDPA_VARIANTS.items():
                cases[label] = functools.partial(
                    _sdpa_call, qkv, mask if padded else None, dtype or torch.float32, backend
                )
            for label, make in cases.items():
                row: dict[str, Any] = {"precision": precision, "padding": padded, "variant": label}
                try:
                    row.update(_time_case(make, batch, next(fresh), device, repeats))
                except RuntimeError as err:
                    row["error"] = str(err).strip().splitlines()[0][:120]
                rows.append(row)
    return rows


# --- the phases --------------------------------------------------------------------------------


def prepare(work: Path, scale: Scale, images: int, seed: int) -> dict[str, Any]:
    """Generate the test images and prepare the paper-scale model's objects (CPU, Open3D).

    Args:
        work: the work folder (``data/``, ``objects/``, ``weights/`` and ``prepare.json``).
        scale: the sizes.
        images: test images, each with ``scale.instances`` demo objects.
        seed: seed of the generated images.

    Returns:
        What ``prepare.json`` records (the scale, the DINOv2 digest, the times).
    """
    from poseflow.data.synthetic import generate_dataset

    work.mkdir(parents=True, exist_ok=True)
    root = work / "data"
    generated, _ = clocked(
        functools.partial(
            generate_dataset, root, num_train_images=0, num_test_images=images,
            objects_per_image=scale.instances, width=scale.width, height=scale.height, seed=seed,
            min_target_visib=0.3, progress=False,
            overwrite=True,  # the work folder's split of an earlier run is generated again
        )
    )  # fmt: skip
    digest = write_random_dinov2(weights_dir(work, scale), scale)
    model = FunFlow6D(paper_config(work, scale))
    prepared, _ = clocked(
        lambda: model.prepare_objects(
            load_object_models(root), cache_dir=work / "objects", progress=False
        )
    )
    info = {
        "scale": scale.name,
        "images": images,
        "seed": seed,
        "dinov2_digest": digest,
        "generate_s": round(generated, 1),
        "prepare_objects_s": round(prepared, 1),
    }
    (work / "prepare.json").write_text(json.dumps(info, indent=1))
    print(f"prepared {work}: {json.dumps(info)}")
    return info


def _rows(rows: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    keep = ("ms_per_image", "total_ms", "stages_ms", "percent", "instances_per_image")
    return {
        name: {k: _round(row[k]) for k in keep if k in row} | {"num_images": row["num_images"]}
        for name, row in rows.items()
    }


def _round(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _round(v) for k, v in value.items()}
    return round(value, 2) if isinstance(value, float) else value


def _describe(device: torch.device) -> dict[str, Any]:
    out: dict[str, Any] = {
        "device": str(device),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
    }
    if device.type == "cuda":
        out["device_name"] = torch.cuda.get_device_name(device)
        out["capability"] = ".".join(map(str, torch.cuda.get_device_capability(device)))
        out["cuda"] = torch.version.cuda
        out["cudnn"] = torch.backends.cudnn.version()
    else:
        out["device_name"] = platform.processor() or platform.machine()
    return out


def run(
    work: Path,
    out: Path,
    device: torch.device,
    *,
    paper_samplers: list[str],
    small_samplers: list[str],
    warmup: int,
    repeats: int,
    seed: int,
    umap_epochs: int | None = None,
) -> dict[str, Any]:
    """Time the fusion kernels, the paper-scale model and the small model; write ``gpu.json``.

    Args:
        work: the folder ``prepare`` filled.
        out: where ``gpu.json`` and the results CSVs go.
        device: where to run.
        paper_samplers: ``SOLVER:STEPS`` settings of the paper-scale model.
        small_samplers: settings of the shipped small model, the reference first.
        warmup: untimed images before each setting.
        repeats: timed calls of each fusion case.
        seed: seeds the noise, sampling and RANSAC.
        umap_epochs: TorchDR's iterations when refitting UMAP (None: 500).

    Returns:
        Everything printed in the JSON line.
    """
    info = json.loads((work / "prepare.json").read_text())
    scale = SCALES[info["scale"]]
    root = work / "data"
    out.mkdir(parents=True, exist_ok=True)
    digest = write_random_dinov2(weights_dir(work, scale), scale)
    result: dict[str, Any] = {"benchmark": "gpu", "scale": scale.name, **_describe(device)}
    result["sizes"] = asdict(scale) | {"images": info["images"]}
    result["dinov2_weights_as_prepared"] = digest == info["dinov2_digest"]

    torch.manual_seed(0)
    paper = FunFlow6D(paper_config(work, scale)).to(device).eval()
    load_prepared_objects(paper, root, work / "objects", device)
    result["paper_parameters"] = sum(p.numel() for p in paper.net.parameters())
    result["umap_fit"] = refit_umap(paper, device, epochs=umap_epochs)
    result["fusion_kernels"] = fusion_kernels(paper, 2 * scale.instances, device, repeats)
    result["paper_scale"] = {}
    for precision, dtype in PRECISIONS.items():
        with autocast_networks(paper, dtype):
            rows = benchmark_settings(
                paper, root, paper_samplers, max_images=info["images"], warmup=warmup, seed=seed,
                evaluate=False, out_dir=out / "paper" / precision,
            )  # fmt: skip
        result["paper_scale"][precision] = _rows(rows)
    del paper

    demo = FunFlow6D.load(DEMO_CHECKPOINT, device=device)
    load_prepared_objects(demo, root, object_cache_dir(DEMO_CHECKPOINT, root), device)
    result["small_model"] = {"samplers": small_samplers, "settings": {}}
    for precision, dtype in PRECISIONS.items():
        with autocast_networks(demo, dtype):
            rows = benchmark_settings(
                demo, root, small_samplers, max_images=info["images"], warmup=warmup, seed=seed,
                evaluate=False, out_dir=out / "small" / precision,
            )  # fmt: skip
        result["small_model"]["settings"][precision] = _rows(rows)
    result["paper_a100_ms"] = PAPER_A100_MS | {"total": PAPER_A100_TOTAL_MS}

    print_fusion_table(result)
    print_stage_table(result)
    (out / "gpu.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(result))
    return result


def score(work: Path, out: Path, tolerance: float) -> dict[str, Any]:
    """The small model's AR per setting and precision, from ``run``'s CSVs (CPU, Open3D).

    Args:
        work: the work folder (its ``data/`` is scored; ``scores.json`` is written there).
        out: ``run``'s output folder (read only).
        tolerance: AR a setting may lose against the first and still count as equal.

    Returns:
        ``{"device", "precisions": {precision: {"settings", "fastest_equal_ar"}}}``.
    """
    from poseflow.data.bop import BOPDataset
    from poseflow.eval import evaluate_bop, read_results

    report = json.loads((out / "gpu.json").read_text())
    dataset = BOPDataset(work / "data", "test")
    scores: dict[str, Any] = {"device": report.get("device_name"), "precisions": {}}
    print(f"\nsmall model, {report['sizes']['images']} images: AR per setting and precision")
    print(f"{'precision':<10} {'setting':<10} {'ms/image':>9} {'AR':>6}")
    for precision, rows in report["small_model"]["settings"].items():
        for name, row in rows.items():
            csv = out / "small" / precision / f"results_{name.replace(':', '-')}.csv"
            row["AR"] = round(evaluate_bop(dataset, read_results(csv))["AR"], 4)
            print(f"{precision:<10} {name:<10} {row['ms_per_image']:>9.1f} {row['AR']:>6.3f}")
        best = fastest_equal_setting(rows, tolerance)
        scores["precisions"][precision] = {"settings": rows, "fastest_equal_ar": best}
        print(f"{precision}: fastest setting within {tolerance} AR of the first: {best}")
    (work / "scores.json").write_text(json.dumps(scores, indent=1))
    print(json.dumps(scores))
    return scores


# --- printing ----------------------------------------------------------------------------------


def print_fusion_table(result: dict[str, Any]) -> None:
    """Print the fusion's attention: first call and median per variant, precision, padding."""
    rows = result["fusion_kernels"]
    sizes = result["sizes"]
    print(
        f"\ngated fusion attention, {2 * sizes['instances']} clouds x {sizes['num_points']} "
        f"points, {sizes['fusion_heads']} heads: first call at a new shape / median ms [kernel]"
    )
    columns = [(p, pad) for p in PRECISIONS for pad in (False, True)]
    head = "".join(f" {SHORT[p] + (' padded' if pad else ' dense'):>30}" for p, pad in columns)
    print(f"{'variant':<16}{head}")
    by_case = {(r["variant"], r["precision"], r["padding"]): r for r in rows}
    for variant in dict.fromkeys(r["variant"] for r in rows):
        cells = []
        for p, pad in columns:
            row = by_case[variant, p, pad]
            if "error" in row:
                cells.append(f" {'cannot run':>30}")
            else:
                text = f"{row['first_ms']:.2f} / {row['median_ms']:.3f} [{row['kernel']}]"
                cells.append(f" {text:>30}")
        print(f"{variant:<16}{''.join(cells)}")


def print_stage_table(result: dict[str, Any]) -> None:
    """Print the paper-scale breakdown beside the paper's A100 figures, and the small model."""
    paper = result["paper_scale"]
    columns = [(p, s) for p in paper for s in paper[p]]
    sizes = result["sizes"]
    print(
        f"\npaper preset ({result['paper_parameters'] / 1e6:.1f} M parameters), N = "
        f"{sizes['num_points']}, {sizes['instances']} instances per image, {sizes['images']} "
        f"images on {result['device_name']}: ms per image (share)"
    )
    head = "".join(f" {SHORT[p] + ' ' + s:>18}" for p, s in columns)
    print(f"{'stage':<18}{head} {'paper A100 euler:50':>20}")
    for stage, label in STAGE_LABELS.items():
        cells = "".join(
            f" {paper[p][s]['stages_ms'].get(stage, 0.0):>9.1f} "
            f"({paper[p][s]['percent'].get(stage, 0.0):>4.1f}%)"
            for p, s in columns
        )
        ref = PAPER_A100_MS.get(stage)
        paper_cell = (
            f"{ref:>9.1f} ({100 * ref / PAPER_A100_TOTAL_MS:>4.1f}%)" if ref is not None else "-"
        )
        print(f"{label:<18}{cells} {paper_cell:>20}")
    totals = "".join(f" {paper[p][s]['total_ms']:>17.1f} " for p, s in columns)
    print(f"{'total (staged)':<18}{totals} {PAPER_A100_TOTAL_MS:>20.1f}")
    ends = "".join(f" {paper[p][s]['ms_per_image']:>17.1f} " for p, s in columns)
    print(f"{'end to end':<18}{ends}")
    small = result["small_model"]["settings"]
    print("\nsmall model (shipped checkpoint), ms per image end to end; AR: `gpu.py score`")
    print(f"{'precision':<10}" + "".join(f" {s:>10}" for s in result["small_model"]["samplers"]))
    for precision, rows in small.items():
        print(f"{precision:<10}" + "".join(f" {r['ms_per_image']:>10.1f}" for r in rows.values()))


# --- the command -------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> dict[str, dict[str, Any]]:
    """Run the phases the command line asks for; returns each phase's result by name."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    phases = ["all", "prepare", "run", "score"]
    parser.add_argument("phase", nargs="?", default="all", choices=phases, help="default: all")
    parser.add_argument("--work", default=None, help="work folder (default runs/gpu)")
    parser.add_argument("--out", default=None, help="run's output folder (default WORK/run)")
    parser.add_argument("--device", default=None, help="run's device (default cuda)")
    parser.add_argument("--images", type=int, default=10, help="test images to prepare (10)")
    parser.add_argument("--fast-steps", type=int, default=5, help="the fast Euler setting (5)")
    parser.add_argument(
        "--small-samplers", nargs="+", default=["euler:50", "euler:5", "euler:3", "euler:2"],
        metavar="SOLVER:STEPS", help="settings of the small model, the reference first",
    )  # fmt: skip
    parser.add_argument("--warmup", type=int, default=1, help="untimed images per setting")
    parser.add_argument("--repeats", type=int, default=20, help="timed calls of each fusion case")
    parser.add_argument("--seed", type=int, default=7, help="seed of the images and the noise")
    parser.add_argument("--ar-tolerance", type=float, default=0.01, help="AR a setting may lose")
    parser.add_argument(
        "--dry-run", "--quick", dest="dry_run", action="store_true",
        help="all phases on the CPU at tiny sizes, in a temporary folder without --work (CI)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    scale = TINY if args.dry_run else PAPER
    with contextlib.ExitStack() as stack:
        if args.dry_run:
            work = Path(args.work or stack.enter_context(tempfile.TemporaryDirectory()))
            images, repeats, umap_epochs = 1, 2, 50
            paper_samplers = small_samplers = ["euler:2", "euler:1"]
            device = torch.device(args.device or "cpu")
        else:
            work = Path(args.work or "runs/gpu")
            images, repeats, umap_epochs = args.images, args.repeats, None
            paper_samplers = ["euler:50", f"euler:{args.fast_steps}"]
            small_samplers = args.small_samplers
            device = torch.device(args.device or "cuda")
        if device.type == "cuda" and not torch.cuda.is_available() and args.phase in ("all", "run"):
            parser.error(
                "no CUDA device here: `--dry-run` runs the tiny CPU version, `prepare` the inputs "
                "for a GPU machine, `--device cpu` the full scale on the CPU (hours)"
            )
        out = Path(args.out) if args.out else work / "run"
        result: dict[str, dict[str, Any]] = {}
        if args.phase in ("all", "prepare"):
            result["prepare"] = prepare(work, scale, images, args.seed)
        if args.phase in ("all", "run"):
            result["run"] = run(
                work, out, device, paper_samplers=paper_samplers, small_samplers=small_samplers,
                warmup=args.warmup, repeats=repeats, seed=args.seed, umap_epochs=umap_epochs,
            )  # fmt: skip
        if args.phase in ("all", "score"):
            result["score"] = score(work, out, args.ar_tolerance)
    print("command:", command(__file__, argv))
    return result


if __name__ == "__main__":
    main()
