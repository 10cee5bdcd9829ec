"""``poseflow onboard``: the whole recipe for a user's meshes, from the meshes to a model folder.

One command runs the recipe's phases in order, each into its place under ``--out RUN``:

1. ``synth``: training images of the meshes (``RUN/train_data``, ``poseflow synth``);
2. ``surface``: the surface embedding of the objects learned on them (``RUN/model/surface``);
3. ``detector``: the detector of the objects (``RUN/model/detector``, ``poseflow train-detector``);
4. ``train``: FunFlow6D by the recipe's settings on the embedding (``RUN/model``, ``poseflow
   train``; its checkpoints let a killed run resume);
5. ``prepare``: the objects prepared for the model (``RUN/model/objects``, ``poseflow prepare``);
6. ``calibrate``: what ``valid`` means, fitted on other renders of the meshes
   (``RUN/calibration_data``, another seed) with ground truth (``RUN/model/validity.json``,
   ``poseflow calibrate``).

``RUN/onboard.json`` records the settings and each finished phase (with its minutes): a phase
already finished is skipped, one that was interrupted (Ctrl-C, a kill) is done again, the
training from its last checkpoint. The model folder holds everything it needs (the embedding is
referenced relative to it), so it can be copied or moved.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path
from typing import Any

from poseflow.cli.common import nonnegative_int, positive_int

__all__ = ["DESCRIPTION", "HELP", "PHASES", "add_arguments", "run"]

#: ``onboard``'s line in ``poseflow --help``.
HELP = "the whole recipe for your meshes: images, embedding, detector, FunFlow6D, preparation"

#: What ``poseflow onboard --help`` says.
DESCRIPTION = """\
Train poseflow on your own objects in one command: render training images of the meshes, learn
their surface embedding, train the detector and FunFlow6D, and prepare the objects. MESHES is a
BOP models folder (obj_XXXXXX.ply + models_info.json, millimetres by default) or a BOP dataset
folder holding one in models/. The model is RUN/model: use it with `poseflow estimate --model
RUN/model` (no mask needed) or `poseflow predict DATASET --model RUN/model`. A finished phase is
skipped when run again; an interrupted one is redone (training resumes from its checkpoint)."""

#: The phases in order.
PHASES = ("synth", "surface", "detector", "train", "prepare", "calibrate")

#: Channels of the recipe's surface embedding (its reducer keeps them all).
SURFACE_DIM = 32

#: ``poseflow train``'s settings in the recipe (besides the configuration and the embedding).
TRAIN_SETTINGS = ("--batch-size", "16", "--lr", "1e-3", "--ema-decay", "0.995", "--copies", "2",
                  "--occlusion", "0.5")  # fmt: skip


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``poseflow onboard`` (its ``run`` is :func:`run`)."""
    parser.add_argument("meshes", help="BOP models folder, or a BOP dataset with models/")
    parser.add_argument("--out", required=True, metavar="RUN", help="the run folder")
    parser.add_argument(
        "--mesh-scale", type=float, default=0.001, help="factor from the meshes' units to metres"
    )
    parser.add_argument(
        "--images", type=positive_int, default=3200, help="training images to render"
    )
    parser.add_argument(
        "--surface-steps",
        type=nonnegative_int,
        default=10000,
        help="embedding steps (0: no embedding; FunFlow6D keeps its configuration's encoder)",
    )
    parser.add_argument(
        "--surface-images", type=positive_int, default=1600, help="images the embedding learns from"
    )
    parser.add_argument(
        "--detector-steps",
        type=nonnegative_int,
        default=4000,
        help="detector steps (0: no detector)",
    )
    parser.add_argument(
        "--steps", type=positive_int, default=10000, help="FunFlow6D training steps"
    )
    parser.add_argument(
        "--config", default="learned_small", help="FunFlow6D's configuration (recipe name or JSON)"
    )
    parser.add_argument(
        "--calibration-images",
        type=nonnegative_int,
        default=80,
        help="renders (seed + 1) that `valid` is calibrated on (0: not calibrated)",
    )
    parser.add_argument("--seed", type=int, default=1, help="seed of the training images")
    parser.add_argument(
        "--train-args", default="", help="more `poseflow train` options, one string (e.g. --set)"
    )


def _settings(args: argparse.Namespace, models: Path) -> dict[str, Any]:
    keys = ("mesh_scale", "images", "surface_steps", "surface_images", "detector_steps", "steps",
            "config", "seed", "train_args", "calibration_images")  # fmt: skip
    return {"meshes": str(models.resolve()), **{k: getattr(args, k) for k in keys}}


def _models_folder(path: str) -> Path:
    """The BOP models folder of ``MESHES``.

    Raises:
        MissingFileError: neither ``MESHES`` nor ``MESHES/models`` holds ``models_info.json``.
    """
    from poseflow.errors import MissingFileError

    for folder in (Path(path), Path(path) / "models"):
        if (folder / "models_info.json").is_file():
            return folder
    raise MissingFileError(
        f"{path} is not a BOP models folder (obj_XXXXXX.ply + models_info.json) nor a dataset "
        "holding one in models/"
    )


class _Record:
    """``RUN/onboard.json``: the settings and the finished phases, written after each phase."""

    def __init__(self, path: Path, settings: dict[str, Any]) -> None:
        from poseflow.errors import UsageError

        self.path = path
        self.data: dict[str, Any] = {"settings": settings, "done": {}}
        if path.is_file():
            old = json.loads(path.read_text())
            before = old.get("settings", {})
            # a setting newer than the run (absent from its record) takes its value now
            changed = sorted(k for k in settings if k in before and before[k] != settings[k])
            if changed or "settings" not in old:
                raise UsageError(
                    f"{path.parent} was onboarded with other settings ({', '.join(changed)}); "
                    "give another --out, or the same settings to go on"
                )
            self.data = {**old, "settings": settings}

    def done(self, phase: str) -> bool:
        return phase in self.data["done"]

    def finish(self, phase: str, minutes: float) -> None:
        from poseflow._cache import atomic_write

        self.data["done"][phase] = {"minutes": round(minutes, 2)}
        text = json.dumps(self.data, indent=1)
        atomic_write(self.path, lambda tmp: Path(tmp).write_text(text))


def run(args: argparse.Namespace) -> int:
    """Run the phases not yet finished; prints each phase's minutes. Returns 0."""
    from poseflow.cli import main as poseflow
    from poseflow.cli.common import LOG, check_writable
    from poseflow.errors import PoseflowError

    models = _models_folder(args.meshes)
    out = check_writable(args.out, folder=True)
    record = _Record(out / "onboard.json", _settings(args, models))
    train_data, model = out / "train_data", out / "model"
    common = ["--threads", str(args.threads)] if args.threads else []
    common += ["--no-progress"] if args.no_progress else []
    common += ["-q"] if args.quiet else []

    def poseflow_run(command: list[str]) -> None:
        LOG.info("$ poseflow %s", " ".join(command))
        if poseflow([*command, *common]) != 0:
            raise PoseflowError(f"onboard: `poseflow {command[0]}` failed (see above)")

    def synth() -> None:
        poseflow_run(["synth", str(train_data), "--objects", str(models), "--mesh-scale",
                      str(args.mesh_scale), "--train", str(args.images), "--test", "0",
                      "--seed", str(args.seed), "--overwrite"])  # fmt: skip

    def surface() -> None:
        from poseflow.features.surface_training import train_surface_embedding

        shutil.rmtree(model / "surface", ignore_errors=True)
        train_surface_embedding(
            train_data, model / "surface", steps=args.surface_steps, dim=SURFACE_DIM,
            max_images=args.surface_images, progress=not (args.quiet or args.no_progress),
            log=lambda line: LOG.info("%s", line),
        )  # fmt: skip

    def detector() -> None:
        poseflow_run(["train-detector", str(train_data), "--out", str(model / "detector"),
                      "--steps", str(args.detector_steps), "--overwrite"])  # fmt: skip

    def train() -> None:
        resume = ["--resume"] if any((out / "checkpoints").glob("*")) else []
        surface = f"surface:{(model / 'surface').resolve()}"
        embedding = ["--appearance-encoder", surface, "--set", f"feature_dim={SURFACE_DIM}"]
        embedding = embedding if args.surface_steps else []
        poseflow_run(["train", str(train_data), "--out", str(out), "--config", args.config,
                      *embedding, "--steps", str(args.steps), *TRAIN_SETTINGS, *resume,
                      *args.train_args.split()])  # fmt: skip

    def prepare() -> None:  # the user's meshes, as `predict` on their dataset will read them
        dataset = models.parent if models.name == "models" else train_data
        poseflow_run(["prepare", str(dataset), "--out", str(model)])

    def calibrate() -> None:  # renders no training saw (another seed), one per layout
        data = out / "calibration_data"
        poseflow_run(["synth", str(data), "--objects", str(models), "--mesh-scale",
                      str(args.mesh_scale), "--train", "0", "--test",
                      str(args.calibration_images), "--seed", str(args.seed + 1),
                      "--images-per-scene", "1", "--overwrite"])  # fmt: skip
        poseflow_run(["calibrate", str(data), "--model", str(model)])

    steps = {"synth": synth, "surface": surface, "detector": detector, "train": train,
             "prepare": prepare, "calibrate": calibrate}  # fmt: skip
    skipped = {"surface": not args.surface_steps, "detector": not args.detector_steps,
               "calibrate": not args.calibration_images}  # fmt: skip
    for n, phase in enumerate(PHASES, 1):
        if skipped.get(phase):
            LOG.info("onboard %d/%d %s: not made (its count is 0)", n, len(PHASES), phase)
            continue
        if record.done(phase):
            LOG.info("onboard %d/%d %s: done before, skipped", n, len(PHASES), phase)
            continue
        LOG.info("onboard %d/%d %s", n, len(PHASES), phase)
        start = time.perf_counter()
        steps[phase]()
        minutes = (time.perf_counter() - start) / 60
        record.finish(phase, minutes)
        LOG.info("onboard %d/%d %s: %.1f min", n, len(PHASES), phase, minutes)
    total = sum(d["minutes"] for d in record.data["done"].values())
    print(
        f"onboarded {models} into {model} ({total:.1f} min of phases); use it with "
        f"`poseflow estimate --model {model}` or `poseflow predict DATASET --model {model}`"
    )
    return 0
