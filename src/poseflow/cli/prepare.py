"""``poseflow prepare``: compute and cache what FunFlow6D needs of each object of a dataset.

Per object: the canonical query cloud, its geometric features, its multi-view appearance
features and the reducer fitted on them (:meth:`~poseflow.models.FunFlow6D.prepare_objects`).
They are cached under ``OUT/objects/<hash of DATASET/models>/``, which ``poseflow train`` and
``poseflow predict`` read when given the same folder (``--cache OUT``, or by default the model
folder itself), so the slow part runs once.

Example::

    poseflow prepare data/synth --out runs/small/model --preset small   # before training
    poseflow prepare data/lmo --out runs/small/model                    # a trained model's config
"""

from __future__ import annotations

import argparse
import time

from poseflow.cli.options import add_config_arguments

__all__ = ["DESCRIPTION", "HELP", "add_arguments", "run"]


#: ``prepare``'s line in ``poseflow --help``.
HELP = "prepare and cache the object models of a BOP dataset for FunFlow6D"

#: What ``poseflow prepare --help`` says.
DESCRIPTION = """\
Compute, per object of DATASET/models, FunFlow6D's query cloud, its geometric and multi-view
appearance features and the fitted reducer, and cache them under OUT/objects/. When OUT holds a
trained model (config.json + model.safetensors) its configuration is used and no configuration
option may be given."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``poseflow prepare`` (its ``run`` is :func:`run`)."""
    parser.add_argument("dataset", help="BOP dataset folder (models/ with models_info.json)")
    parser.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        help="model folder or cache folder to write objects/ into",
    )
    parser.add_argument(
        "--objects", type=int, nargs="+", default=None, metavar="ID", help="only these objects"
    )
    add_config_arguments(parser)


def run(args: argparse.Namespace) -> int:
    """Prepare the objects and print one line per object; returns 0."""
    import torch

    from poseflow._progress import progress as progress_loop
    from poseflow.cli.common import check_writable, show_progress
    from poseflow.cli.options import build_config, config_requested
    from poseflow.data.object_folder import check_dataset, load_object_models, object_cache_dir
    from poseflow.errors import UsageError
    from poseflow.models import FunFlow6D
    from poseflow.models.checkpoint import is_checkpoint, read_model_config

    start = time.perf_counter()
    root = check_dataset(args.dataset)
    check_writable(args.out, folder=True)
    if is_checkpoint(args.out):
        if config_requested(args):
            raise UsageError(
                f"{args.out} holds a trained model whose config.json fixes the configuration; "
                "drop --config/--preset/--set and the other configuration options"
            )
        config = read_model_config(args.out)
    else:
        config = build_config(args)
    show = show_progress(args)
    models = load_object_models(root, obj_ids=args.objects, progress=show)
    cache = object_cache_dir(args.out, root)
    model = FunFlow6D(config)
    rows = []
    with torch.no_grad():
        items = models.items()
        for obj_id, obj in progress_loop(
            items, total=len(items), desc="prepare objects", enabled=show
        ):
            t0 = time.perf_counter()
            model.prepare_objects({obj_id: obj}, cache_dir=cache, progress=False)
            rows.append((obj_id, obj.name, obj.diameter, time.perf_counter() - t0))
    print(
        f"objects of {root} prepared for num_points={config.num_points}, "
        f"geometric={config.geometric_encoder}, appearance={config.appearance_encoder}, "
        f"reducer={config.reducer}"
    )
    print(f"{'object':>6}  {'name':<16} {'diameter_mm':>11}  {'seconds':>7}")
    for obj_id, name, diameter, seconds in rows:
        print(f"{obj_id:>6}  {name:<16} {1000 * diameter:>11.1f}  {seconds:>7.2f}")
    print(f"cached in {cache} ({time.perf_counter() - start:.1f} s)")
    return 0
