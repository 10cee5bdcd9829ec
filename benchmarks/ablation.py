"""The paper's ablation table, rerun: every row of ``poseflow.models.ABLATIONS`` trained and scored.

Each row changes the base configuration (``--config``, default ``configs/demo_small.json``) as the
paper's table does (reduction, fusion variant, refinement), trains a model from scratch for
``--steps`` steps on precomputed flow inputs of the training split (``--train-data``, default 200
generated images), and scores it with the BOP 2019 AR on a generated test split (targets down to
``visib_fract`` 0.3). ``--preset NAME`` gives every row that DiT preset instead of the base
configuration's DiT sizes (``--preset paper``: the paper's 43 M-parameter DiT).

The work runs in three phases that share the ``--work`` folder, so that training can run on
another machine (one with a GPU but without Open3D or umap-learn):

- ``features``: generate the train and test images, prepare the objects of every feature
  configuration the rows need (``objects/KEY``, KEY such as ``umap_dsift_fpfh``), build their
  training sets (``train_set_KEY.safetensors``) and record the frozen encoders' observations of
  the test split (``test_observations_ENCODERS.safetensors``). Nothing is trained.
- ``train``: per row, read the prepared objects and the training set from ``--work`` (it fails
  rather than computing them), train on ``--device`` and save the model to ``rows/LABEL/NAME``
  (LABEL is the preset, ``base`` without one) with ``train.json`` (time, device, command). With
  ``--predict`` it also predicts the test split from the recorded observations on that device
  (``predictions.csv``). Needs no Open3D, umap-learn, rendering or images.
- ``score``: for every row under ``rows/``, predict the test split unless ``predictions.csv`` is
  there (``FunFlow6D.predict``, seed 7), score it and print a table (AR, AR_VSD, AR_MSSD, AR_MSPD,
  AR per object, training time and device), one JSON line and the commands.

``all`` (the default) runs the three in turn. ``benchmarks/ablation_transport.py`` moves the
``--work`` folder to the GPU machine and the trained rows back. Run::

    python benchmarks/ablation.py --phase features --work runs/ablation
    python benchmarks/ablation.py --phase train --work runs/ablation --device cuda --predict
    python benchmarks/ablation.py --phase score --work runs/ablation

or everything on one machine with ``python benchmarks/ablation.py --steps 5000`` (about 15
minutes per row on one core); ``--quick`` for CI (a tiny configuration, two rows, a few steps on a
tiny generated dataset).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from _common import clocked, command

from poseflow.data import ImageInstances
from poseflow.eval import PoseEstimate, PoseResults, predict_dataset, read_results, write_results
from poseflow.flows import PRESETS, TrainConfig
from poseflow.models import (
    ABLATIONS,
    DiTOverrides,
    FunFlow6D,
    FunFlow6DConfig,
    NetOptions,
    Observation,
    load_prepared_object,
)
from poseflow.models.training import FlowTrainingSet, build_training_set, train

TINY = {
    "num_points": 32,
    "crop_size": 32,
    "query_views": 2,
    "dit_preset": "tiny",
    "steps": 5,
    "ransac_iterations": 100,
    "net": NetOptions(fusion_heads=2, posenc_dim=16, posenc_frequencies=2),
}
QUICK_ROWS = ("3_pca_sum", "8_umap_gated")
METRICS = ("AR", "AR_VSD", "AR_MSSD", "AR_MSPD")
PHASES = ("all", "features", "train", "score")
TEST_SEED = 7
#: The tensors of an :class:`~poseflow.models.Observation`, in its field order.
#: The recorded fields of an observation: all but the dense cloud, which only verification reads.
OBSERVATION_FIELDS = tuple(
    f.name for f in dataclasses.fields(Observation) if f.name not in ("cloud", "cloud_mask")
)


def feature_key(cfg: FunFlow6DConfig) -> str:
    """The name of a row's prepared objects and training set in the work folder."""
    return f"{cfg.reducer}_{cfg.appearance_encoder}_{cfg.geometric_encoder}"


def encoder_fingerprint(cfg: FunFlow6DConfig) -> dict[str, Any]:
    """The configuration fields that the observations of the test split depend on."""
    return {
        "num_points": cfg.num_points,
        "geometric_encoder": cfg.geometric_encoder,
        "geometric_radii": list(cfg.geometric_radii),
        "appearance_encoder": cfg.appearance_encoder,
        "crop_size": cfg.crop_size,
        "dense_points": cfg.dense_points,
        "seed": TEST_SEED,
    }


def observations_path(work: Path, cfg: FunFlow6DConfig) -> Path:
    """Where the recorded test observations of a configuration's encoders are."""
    return work / f"test_observations_{cfg.appearance_encoder}_{cfg.geometric_encoder}.safetensors"


def row_config(base: FunFlow6DConfig, name: str, *, quick: bool) -> FunFlow6DConfig:
    """The configuration of one ablation row (without verification, which the paper has not)."""
    cfg = base.replace(**ABLATIONS[name], verifier=None)
    if quick and cfg.reducer == "umap":
        cfg = cfg.replace(reducer="pca")  # umap-learn needs more points than TINY has
    return cfg


def demo_object_map() -> dict[int, Any]:
    """``{obj_id: ObjectModel}`` of the demo objects (ids 1, 2, 3)."""
    from poseflow.data.demo_objects import demo_objects

    return dict(enumerate(demo_objects(), start=1))


def generated(folder: Path, **params: Any) -> Path:
    """A generated BOP dataset in ``folder``, reused when one with the same parameters is there."""
    stamp = folder / "ablation_params.json"
    if stamp.is_file() and json.loads(stamp.read_text()) == params:
        return folder
    from poseflow.data.synthetic import generate_dataset

    root = generate_dataset(folder, progress=False, overwrite=True, **params)
    stamp.write_text(json.dumps(params))
    return Path(root)


def make_test_split(work: Path, *, quick: bool, images: int) -> Path:
    """The generated test split (seed 7, targets down to ``visib_fract`` 0.3)."""
    size = {"width": 160, "height": 120} if quick else {}
    return generated(
        work / "test", num_train_images=0, num_test_images=images, seed=TEST_SEED,
        min_target_visib=0.3, **size,
    )  # fmt: skip


def prepare(model: FunFlow6D, objects: Mapping[int, Any] | None, cache: Path) -> None:
    """Prepare the demo objects from ``cache``; without ``objects`` only a complete cache will do.

    Raises:
        SystemExit: ``objects`` is None and ``cache`` lacks an object.
    """
    if objects is None:
        objects = demo_object_map()
        missing = [
            i
            for i, m in objects.items()
            if load_prepared_object(cache, i, m, model.config, model.appearance_encoder) is None
        ]
        if missing:
            raise SystemExit(f"{cache} lacks objects {missing}: run --phase features first")
    model.prepare_objects(objects, cache_dir=cache, progress=False)


def record_observations(model: FunFlow6D, test_root: Path, path: Path) -> int:
    """Run the frozen encoders over the test split as ``model.predict`` does and save the result.

    Each image's :class:`~poseflow.models.Observation` (instances concatenated) is saved with its
    scene and image ids, so that :func:`predict_recorded` needs neither the images nor the
    encoders. Returns the number of images.
    """
    from safetensors.torch import save_file

    g = torch.Generator().manual_seed(TEST_SEED)
    recorded: list[Observation] = []
    cameras: list[tuple[torch.Tensor, tuple[int, int]]] = []  # K and (H, W) of each image

    def record(rgb, depth, K, masks, obj_ids) -> PoseEstimate:
        image = ImageInstances(rgb, depth, K, masks, obj_ids)
        recorded.append(model.observe(image, generator=g))
        cameras.append((torch.as_tensor(K, dtype=torch.float32), tuple(depth.shape)))
        B = len(obj_ids)
        # every instance "valid" (a pose in front of the camera), so that the results list each
        # call's image, in call order
        poses = torch.eye(4).repeat(B, 1, 1)
        poses[:, 2, 3] = 1.0
        return PoseEstimate(poses, torch.zeros(B), torch.ones(B, dtype=torch.bool))

    listing = predict_dataset(record, test_root, object_ids=sorted(model.objects))
    if not recorded:
        raise SystemExit(f"{test_root} holds no target of a prepared object")
    sizes = torch.tensor([len(o.obj_ids) for o in recorded])
    first = torch.cumsum(sizes, 0) - sizes
    tensors = {
        "sizes": sizes,
        "scene_ids": listing.scene_ids[first],
        "im_ids": listing.im_ids[first],
        "K": torch.stack([K for K, _ in cameras]),
        "image_size": torch.tensor([hw for _, hw in cameras]),
    }
    for field in OBSERVATION_FIELDS:
        if getattr(recorded[0], field) is not None:
            tensors[field] = torch.cat([getattr(o, field) for o in recorded]).contiguous()
    fingerprint = json.dumps(encoder_fingerprint(model.config))
    save_file(tensors, str(path), metadata={"fingerprint": fingerprint})
    return len(recorded)


def predict_recorded(model: FunFlow6D, path: Path) -> PoseResults:
    """``model.predict`` of the test split from :func:`record_observations`'s file.

    Runs on the model's device with a generator seeded 7, as ``predict`` does; each image's time
    leaves out the encoders.

    Raises:
        SystemExit: the file was recorded with other encoder settings.
    """
    from safetensors import safe_open
    from safetensors.torch import load_file

    with safe_open(str(path), "pt") as f:
        fingerprint = json.loads(f.metadata()["fingerprint"])
    if fingerprint != encoder_fingerprint(model.config):
        raise SystemExit(f"{path} was recorded with other encoder settings: rerun --phase features")
    t = load_file(str(path))
    device = next(model.net.parameters()).device
    g = torch.Generator(device=device).manual_seed(TEST_SEED)
    parts, start = [], 0
    images = zip(t["scene_ids"].tolist(), t["im_ids"].tolist(), t["sizes"].tolist(), t["K"])
    for (s, i, n, K), (h, w) in zip(images, t["image_size"].tolist()):
        fields = {
            f: t[f][start : start + n].to(device) if f in t else None for f in OBSERVATION_FIELDS
        }
        start += n
        obs = Observation(**fields)
        model.observe = lambda *args, obs=obs, **kwargs: obs  # the encoders' work, done already
        try:
            tic = time.perf_counter()
            depth = torch.zeros(h, w, device=device)  # for the checks only: observe is replaced
            est = model.estimate(None, depth, K.to(device), None, obs.obj_ids, generator=g)
            ok = est.valid.cpu()
            elapsed = time.perf_counter() - tic
        finally:
            del model.observe
        ids = obs.obj_ids.cpu()[ok]
        if len(ids):
            scores, poses = est.scores.cpu()[ok], est.poses.cpu()[ok]
            parts.append(
                PoseResults.from_columns(
                    [s] * len(ids), [i] * len(ids), ids, scores, poses, elapsed
                )
            )
    return PoseResults.concat(parts)


def build_features(
    work: Path,
    configs: list[FunFlow6DConfig],
    train_root: Path,
    test_root: Path,
    objects: Mapping[int, Any],
) -> None:
    """Prepare the objects, build the training sets and record the test observations."""
    keys: set[str] = set()
    recordings: set[Path] = set()
    for cfg in configs:
        key = feature_key(cfg)
        if key in keys:
            continue
        keys.add(key)
        model = FunFlow6D(cfg)
        start = time.perf_counter()
        prepare(model, objects, work / "objects" / key)
        cached = work / f"train_set_{key}.safetensors"
        if not cached.is_file():
            build_training_set(model, train_root, progress=False).save(cached)
        size = len(FlowTrainingSet.load(cached))
        print(f"features {key}: {size} instances, {time.perf_counter() - start:.1f} s", flush=True)
        recorded = observations_path(work, cfg)
        if recorded not in recordings:
            recordings.add(recorded)
            images = record_observations(model, test_root, recorded)
            print(f"recorded the test observations of {images} images: {recorded.name}")


def train_row(
    work: Path,
    name: str,
    cfg: FunFlow6DConfig,
    folder: Path,
    *,
    steps: int,
    quick: bool,
    device: str,
) -> FunFlow6D:
    """Train one row from the cached features and save it to ``folder`` with ``train.json``.

    Returns:
        The trained model, on ``device``.
    """
    key = feature_key(cfg)
    cached = work / f"train_set_{key}.safetensors"
    if not cached.is_file():
        raise SystemExit(f"{cached} is missing: run --phase features first")
    torch.manual_seed(0)
    model = FunFlow6D(cfg)
    prepare(model, None, work / "objects" / key)
    data = FlowTrainingSet.load(cached)
    schedule = TrainConfig(
        steps=steps, batch_size=4 if quick else 16, lr=1e-3, warmup_steps=steps // 10,
        ema_decay=0.995, progress=False,
    )  # fmt: skip
    train_s, _ = clocked(lambda: train(model, data, config=schedule, device=device))
    info = {
        "row": name,
        "steps": steps,
        "train_s": round(train_s, 1),
        "device": device_name(device),
        "torch": torch.__version__,
        "command": command(__file__),
    }
    model.save(folder)
    (folder / "train.json").write_text(json.dumps(info, indent=1))
    print(f"{folder.parent.name}/{name}: {steps} steps on {info['device']} in {train_s:.1f} s")
    return model


def save_predictions(folder: Path, results: PoseResults, *, device: str, seconds: float) -> None:
    """Write ``predictions.csv`` and note where and how fast it was predicted in ``train.json``."""
    write_results(folder / "predictions.csv", results)
    info = json.loads((folder / "train.json").read_text())
    info.update({"predicted_on": device_name(device), "predict_s": round(seconds, 1)})
    (folder / "train.json").write_text(json.dumps(info, indent=1))


def score_row(work: Path, folder: Path, test_root: Path) -> dict[str, Any]:
    """Score a row's predictions of the test split, predicting them first when there are none."""
    from poseflow.eval import evaluate_bop

    predictions = folder / "predictions.csv"
    if not predictions.is_file():
        if not (folder / "model.safetensors").is_file():
            raise SystemExit(f"{folder} holds neither predictions.csv nor model.safetensors")
        model = FunFlow6D.load(folder)
        prepare(model, demo_object_map(), work / "objects" / feature_key(model.config))
        seconds, results = clocked(lambda: model.predict(test_root, seed=TEST_SEED))
        save_predictions(folder, results, device="cpu", seconds=seconds)
    report = evaluate_bop(test_root, read_results(predictions))
    info = json.loads((folder / "train.json").read_text())
    return {
        **{k: round(report[k], 4) for k in METRICS},
        "per_object": {o: round(v["AR"], 4) for o, v in report["per_object"].items()},
        **{k: info[k] for k in ("steps", "train_s", "device", "predicted_on", "predict_s")},
    }


def print_table(rows: dict[str, dict[str, Any]]) -> None:
    """A Markdown table of the scores, one line per row."""
    objs = sorted({o for r in rows.values() for o in r["per_object"]}, key=int)
    head = ["row", *METRICS, *(f"obj {o}" for o in objs), "steps", "training", "prediction"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for name, r in rows.items():
        per = [f"{r['per_object'][o]:.3f}" if o in r["per_object"] else "-" for o in objs]
        cells = [name, *(f"{r[k]:.3f}" for k in METRICS), *per, str(r["steps"])]
        cells += [
            f"{r['train_s']:.0f} s ({r['device']})",
            f"{r['predict_s']:.0f} s ({r['predicted_on']})",
        ]
        print("| " + " | ".join(cells) + " |")


def device_name(device: str | torch.device) -> str:
    """The GPU's or the CPU's model name."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine() or "cpu"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--phase", choices=PHASES, default="all")
    parser.add_argument("--config", default="configs/demo_small.json", help="base configuration")
    parser.add_argument("--preset", choices=sorted(PRESETS), default=None, help="DiT of every row")
    parser.add_argument("--train-data", default=None, help="BOP dataset with a train split")
    parser.add_argument("--rows", nargs="+", default=None, help="rows of ABLATIONS to run")
    parser.add_argument("--steps", type=int, default=5000)
    parser.add_argument("--test-images", type=int, default=24)
    parser.add_argument("--work", default=None, help="work folder (default: temporary)")
    parser.add_argument("--device", default=None, help="training device (default: cuda if any)")
    parser.add_argument("--predict", action="store_true", help="predict after training (train)")
    parser.add_argument("--skip-trained", action="store_true", help="keep rows already saved")
    parser.add_argument("--threads", type=int, default=1, help="CPU threads")
    parser.add_argument("--quick", action="store_true", help="tiny configuration and data (CI)")
    args = parser.parse_args()
    if args.phase != "all" and args.work is None:
        parser.error(f"--phase {args.phase} needs --work")
    torch.set_num_threads(args.threads)
    names = args.rows or list(QUICK_ROWS if args.quick else sorted(ABLATIONS))
    unknown = sorted(set(names) - set(ABLATIONS))
    if unknown:
        parser.error(f"unknown rows {unknown}; choose from {sorted(ABLATIONS)}")
    base = FunFlow6DConfig(**TINY) if args.quick else FunFlow6DConfig.load(args.config)
    if args.preset is not None:
        base = base.replace(
            dit_preset=args.preset, net=dataclasses.replace(base.net, dit=DiTOverrides())
        )
    n_test = 2 if args.quick else args.test_images
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.work or tmp)
        if args.phase in ("all", "features"):
            size = {"width": 160, "height": 120} if args.quick else {}
            train_root = Path(args.train_data) if args.train_data else generated(
                work / "train", num_train_images=3 if args.quick else 200, num_test_images=0,
                seed=1, **size,
            )  # fmt: skip
            test_root = make_test_split(work, quick=args.quick, images=n_test)
            configs = [row_config(base, n, quick=args.quick) for n in names]
            build_features(work, configs, train_root, test_root, demo_object_map())
        if args.phase in ("all", "train"):
            _train_rows(args, work, names, base)
        if args.phase in ("all", "score"):
            _score_rows(work, names, make_test_split(work, quick=args.quick, images=n_test), n_test)
    print("command:", command(__file__))


def _train_rows(args: argparse.Namespace, work: Path, names: list[str], base: Any) -> None:
    """Train every row (or keep a saved one with ``--skip-trained``); predict with ``--predict``."""
    label = args.preset or "base"
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    steps = 10 if args.quick else args.steps
    for name in names:
        cfg = row_config(base, name, quick=args.quick)
        folder = work / "rows" / label / name
        if args.skip_trained and (folder / "train.json").is_file():
            print(f"{label}/{name}: already trained, kept")
            if not args.predict or (folder / "predictions.csv").is_file():
                continue
            model = FunFlow6D.load(folder, device=device)
            prepare(model, None, work / "objects" / feature_key(cfg))
        else:
            model = train_row(work, name, cfg, folder, steps=steps, quick=args.quick, device=device)
        if args.predict:
            seconds, results = clocked(
                lambda model=model, cfg=cfg: predict_recorded(model, observations_path(work, cfg))
            )
            save_predictions(folder, results, device=device, seconds=seconds)
            print(f"{label}/{name}: predicted the test split in {seconds:.1f} s")


def _score_rows(work: Path, names: list[str], test_root: Path, n_test: int) -> None:
    """Score every trained row of ``names``; print the table, the JSON line and their commands."""
    out: dict[str, Any] = {"test_images": n_test, "rows": {}}
    commands = {}
    for info in sorted((work / "rows").glob("*/*/train.json")):
        folder = info.parent
        if folder.name not in names:
            continue
        row = f"{folder.parent.name}/{folder.name}"
        out["rows"][row] = score_row(work, folder, test_root)
        commands[folder.parent.name] = json.loads(info.read_text())["command"]
        print(row, out["rows"][row], flush=True)
    if not out["rows"]:
        raise SystemExit(f"no trained row under {work / 'rows'}: run --phase train first")
    print_table(out["rows"])
    print(json.dumps(out))
    for lab, trained in sorted(commands.items()):
        print(f"trained ({lab}):", trained)


if __name__ == "__main__":
    main()
