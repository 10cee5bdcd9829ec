"""``poseflow view``: look at the estimates of a results file in 3D, image by image.

For each image of a BOP results CSV (``poseflow predict``'s, ``poseflow demo``'s or any BOP 2019
file) it writes, from the image, depth and camera of the BOP dataset and its object models:

- ``OUT/SSSSSS_IIIIII.rrd``: a Rerun recording (open it with ``rerun FILE.rrd``, offline) with
  the image, the camera, the depth as a coloured point cloud, every estimate as its posed mesh
  (object id, score, validity) and the ground-truth mesh where the dataset has ``scene_gt.json``;
- ``OUT/SSSSSS_IIIIII.glb``: the same meshes and cloud as one glTF scene for any mesh viewer
  (``--format ply`` writes a PLY of the meshes and one of the cloud instead).

See :mod:`poseflow.eval.scene` for the contents. Rerun and trimesh come with
``pip install 'poseflow[viz]'``.
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path
from typing import Any

from poseflow.cli.common import nonnegative_int, positive_int

__all__ = ["DESCRIPTION", "FORMATS", "HELP", "add_arguments", "run"]

#: What ``--format`` may name.
FORMATS = ("rrd", "glb", "ply")


#: ``view``'s line in ``poseflow --help``.
HELP = "write 3D views (Rerun .rrd, GLB) of the estimates of a results CSV"

#: What ``poseflow view --help`` says.
DESCRIPTION = """\
Write, per image of a BOP results CSV, a Rerun recording (.rrd: image, camera, depth as a coloured
cloud, the estimated meshes with score and validity, the ground truth) and a GLB scene of the posed
meshes and the cloud, for any viewer. Open a recording with `rerun FILE.rrd`. Needs pip install
'poseflow[viz]'."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``poseflow view`` (its ``run`` is :func:`run`)."""
    parser.add_argument("results", type=Path, help="results CSV (scene_id,im_id,obj_id,...)")
    parser.add_argument(
        "dataset", type=Path, help="BOP dataset folder (models/, the split; either order)"
    )
    parser.add_argument("--split", default="test", help="split folder (default: test)")
    parser.add_argument("--out", type=Path, default=Path("view_output"), help="output folder")
    parser.add_argument("--scene", type=int, default=None, help="only this scene (default: all)")
    parser.add_argument("--im-id", type=int, default=None, help="only this image (default: all)")
    parser.add_argument(
        "--max-images",
        type=nonnegative_int,
        default=10,
        help="at most this many images, in order (0: all)",
    )
    parser.add_argument(
        "--format",
        default="rrd,glb",
        help="comma-separated subset of rrd,glb,ply (default: rrd,glb)",
    )
    parser.add_argument(
        "--method", default=None, help="name of the method (default: the CSV's name)"
    )
    parser.add_argument(
        "--stride",
        type=positive_int,
        default=2,
        help="the cloud keeps one depth pixel in STRIDE along each axis",
    )
    parser.add_argument("--no-gt", action="store_true", help="leave out the ground truth")


def _order(results: Path, dataset: Path) -> tuple[Path, Path]:
    """``(results, dataset)``, accepting a folder first and a file second."""
    if results.is_dir() and dataset.is_file():
        return dataset, results
    return results, dataset


def _formats(text: str) -> tuple[str, ...]:
    from poseflow.errors import UsageError

    formats = tuple(dict.fromkeys(f.strip().lower() for f in text.split(",") if f.strip()))
    unknown = [f for f in formats if f not in FORMATS]
    if unknown or not formats:
        raise UsageError(f"--format takes a subset of {','.join(FORMATS)}, got {text!r}")
    return formats


def _images(results: Any, args: argparse.Namespace) -> list[tuple[int, int]]:
    """The ``(scene_id, im_id)`` of the results that the options select, in order."""
    from poseflow.errors import UsageError

    keys = sorted(set(zip(results.scene_ids.tolist(), results.im_ids.tolist())))
    keys = [
        (s, i)
        for s, i in keys
        if (args.scene is None or s == args.scene) and (args.im_id is None or i == args.im_id)
    ]
    if not keys:
        where = "" if args.scene is None and args.im_id is None else " for --scene/--im-id"
        raise UsageError(f"{args.results} holds no estimate{where}")
    return keys


def run(args: argparse.Namespace) -> int:
    """Write the recordings and scenes; prints one line per image."""
    import torch

    from poseflow._units import in_front_of_camera
    from poseflow.cli.common import LOG, check_writable, show_progress
    from poseflow.data.bop import BOPDataset
    from poseflow.data.object_folder import check_dataset, load_object_models
    from poseflow.errors import MissingDependencyError, MissingFileError
    from poseflow.eval import build_scene, export_scene, read_results, write_recording

    formats = _formats(args.format)
    for fmt, package, pip_name in (("rrd", "rerun", "rerun-sdk"), ("glb", "trimesh", "trimesh"),
                                   ("ply", "trimesh", "trimesh")):  # fmt: skip
        if fmt in formats and importlib.util.find_spec(package) is None:
            raise MissingDependencyError(pip_name, "viz", f"--format {fmt}")
    results_path, root = _order(args.results, args.dataset)
    args.results = results_path
    if not results_path.is_file():
        raise MissingFileError(f"results file {results_path} does not exist")
    check_dataset(root, args.split)
    out = check_writable(args.out, folder=True)
    results = read_results(results_path)
    keys = _images(results, args)
    if args.max_images and len(keys) > args.max_images:
        LOG.info(
            f"note: {len(keys)} images have estimates; writing the first {args.max_images} "
            "(--max-images 0 for all, --scene/--im-id to choose)"
        )
        keys = keys[: args.max_images]
    method = args.method or results_path.stem.split("_")[0]
    dataset = BOPDataset(root, args.split)
    wanted = {int(o) for s, i in keys for o in results.obj_ids[_rows(results, s, i)].tolist()}
    if not args.no_gt:
        for s, i in keys:
            wanted |= {g.obj_id for g in dataset.scene(s).gt_of(i)}
    models = load_object_models(
        root, obj_ids=sorted(wanted), num_points=256, progress=show_progress(args)
    )
    for s, i in keys:
        scene = dataset.scene(s)
        rows = _rows(results, s, i)
        poses = results.poses[rows]
        gts = [] if args.no_gt else scene.gt_of(i)
        view = build_scene(
            scene.load_rgb_image(i),
            scene.load_depth_image(i),
            scene.camera[i].K,
            models,
            poses,
            results.obj_ids[rows],
            scores=results.scores[rows],
            valid=in_front_of_camera(poses.to(torch.float64)),
            gt_poses=torch.stack([torch.as_tensor(g.pose) for g in gts]) if gts else None,
            gt_obj_ids=[g.obj_id for g in gts] if gts else None,
            method=method,
            name=f"{method}: scene {s} image {i}",
            stride=args.stride,
        )
        stem = out / f"{s:06d}_{i:06d}"
        written = []
        if "rrd" in formats:
            written.append(write_recording(view, stem.with_suffix(".rrd")))
        for fmt in ("glb", "ply"):
            if fmt in formats:
                written += export_scene(view, stem.with_suffix(f".{fmt}"))
        print(
            f"scene {s} image {i}: {len(view.estimates)} estimates, {len(view.ground_truth)} "
            f"ground truth, {len(view.cloud)} points -> {', '.join(p.name for p in written)}"
        )
    if "rrd" in formats:
        print(f"wrote {len(keys)} images to {out}; open a recording with `rerun FILE.rrd`")
    else:
        print(f"wrote {len(keys)} images to {out}")
    return 0


def _rows(results: Any, scene_id: int, im_id: int) -> Any:
    """The rows of ``results`` of one image, a ``(E,)`` bool tensor."""
    return (results.scene_ids == scene_id) & (results.im_ids == im_id)
