r"""``poseflow estimate``: the poses of the objects in one RGB-D frame, from plain files.

No BOP tree: a colour image, a depth image, the intrinsics, one mask per instance (or a BOP
detections file) and the object's mesh. Writes ``OUT/poses.json`` (per instance: ``R``, ``t`` in
metres and millimetres, score, validity) and ``OUT/overlay.png`` (the valid estimates drawn on
the image). Without ``--model`` the classic training-free baseline (FPFH + RANSAC + ICP)
estimates; ``--model`` takes a FunFlow6D model folder (or ``demo``, the shipped one, trained on
the demo objects only).

The same from Python: :func:`poseflow.data.read_frame`, then
:func:`poseflow.eval.estimate_frame` with ``ClassicBaseline(objects).estimator()`` or a prepared
``FunFlow6D``'s ``estimator()``, then :func:`poseflow.eval.write_poses_json`.

Example::

    poseflow estimate --rgb rgb.png --depth depth.png --depth-scale 0.001 \
        --K 572.4 0 325.3 0 573.6 242.0 0 0 1 --mask mask.png --mesh drill.ply --mesh-scale 0.001
    poseflow estimate --rgb rgb.png --depth depth.png --K scene_camera.json --im-id 3 \
        --detections cnos.json --mesh lmo/models --model runs/lmo/model --out out/
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path
from typing import Any

from poseflow.cli.common import add_device_argument, add_model_argument, add_seed_argument
from poseflow.cli.predict import METHOD_LABELS, METHODS

__all__ = ["DESCRIPTION", "FORMATTER", "HELP", "add_arguments", "load_meshes", "run"]

#: ``estimate``'s line in ``poseflow --help``.
HELP = "estimate object poses in one RGB-D frame (image files and a mesh)"

#: What ``poseflow estimate --help`` says.
DESCRIPTION = """\
Estimate the 6D pose of each object instance in one RGB-D frame and write OUT/poses.json
(R, t in metres and in millimetres, score and validity per instance) and OUT/overlay.png.

Inputs: --rgb, --depth (a 16-bit PNG with --depth-scale metres per unit, 0.001 by default, or a
float TIFF/.npy in metres), --K (9 numbers row-major, a JSON file or text, or a BOP
scene_camera.json with --im-id), the instances (--mask PNGs, one per instance, or a BOP
--detections file) and the objects (--mesh: a mesh file with --mesh-scale to metres, or a BOP
models folder in millimetres). Depth, intrinsics and mesh sizes are checked for plausible units,
and the depth inside each mask against its object's size. --depth-scale is metres per unit; a
BOP scene_camera.json's depth_scale is millimetres per unit (BOP's 0.1 is --depth-scale 0.0001).

Estimator (--method): the classic baseline (FPFH + RANSAC + ICP, no training) unless --model
names a trained FunFlow6D model folder (or demo, the small model shipped with poseflow); with a
model, --method hybrid pools both estimators' hypotheses and --method baseline ignores it."""

#: :data:`DESCRIPTION` is shown as written.
FORMATTER = argparse.RawDescriptionHelpFormatter


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``poseflow estimate`` (its ``run`` is :func:`run`)."""
    _add_frame_arguments(parser.add_argument_group("the frame"))
    _add_instance_arguments(parser.add_argument_group("the instances"))
    _add_object_arguments(parser.add_argument_group("the objects and the estimator"))
    parser.add_argument("--out", default="estimate_output", help="folder for poses.json, overlay")
    parser.add_argument(
        "--view",
        action="store_true",
        help="also write the frame in 3D: scene.rrd (a Rerun recording: the image, the depth as a "
        "coloured cloud, each posed mesh with its score and validity) and scene.glb (any mesh "
        "viewer); needs pip install 'poseflow[viz]'",
    )
    add_device_argument(parser)


def _add_frame_arguments(frame: Any) -> None:
    """``--rgb``, ``--depth``, ``--depth-scale``, ``--K``, ``--im-id`` and ``--scene-id``."""
    frame.add_argument("--rgb", required=True, metavar="IMAGE", help="colour image")
    frame.add_argument("--depth", required=True, metavar="IMAGE", help="depth image")
    frame.add_argument(
        "--depth-scale",
        type=float,
        default=None,
        metavar="M",
        help="metres per unit of the depth image (default: 0.001 for integer images, i.e. "
        "millimetres, 1 for float images; a BOP camera entry's depth_scale when --K is one). "
        "Not BOP's depth_scale, which is millimetres per unit: BOP's 0.1 is --depth-scale 0.0001",
    )
    frame.add_argument(
        "--K",
        required=True,
        nargs="+",
        metavar="K",
        help="intrinsics: 9 numbers (row-major), or a JSON file or text (a 3x3 list, cam_K, "
        "fx/fy/cx/cy, or a BOP scene_camera.json)",
    )
    frame.add_argument(
        "--im-id", type=int, default=None, help="image id in scene_camera.json / detections"
    )
    frame.add_argument("--scene-id", type=int, default=None, help="scene id in the detections")


def _add_instance_arguments(inst: Any) -> None:
    """``--mask``, ``--obj-id``, ``--detections`` and ``--score-threshold``."""
    inst.add_argument(
        "--mask",
        action="extend",
        nargs="+",
        default=[],
        metavar="PNG",
        help="instance masks, one binary PNG per instance (non-zero = the object): --mask a.png "
        "b.png, or --mask repeated",
    )
    inst.add_argument(
        "--obj-id",
        type=int,
        action="append",
        default=[],
        metavar="ID",
        help="object id of each --mask (one for all; default: the one mesh's id)",
    )
    inst.add_argument(
        "--detections", default=None, metavar="JSON", help="BOP detections with COCO-RLE masks"
    )
    inst.add_argument(
        "--detector",
        default=None,
        metavar="DIR",
        help="without --mask and --detections: find the instances with this detector folder "
        "(default: MODEL_DIR/detector when --model has one)",
    )
    inst.add_argument(
        "--score-threshold",
        type=float,
        default=0.0,
        help="drop detections scoring below this (default: 0)",
    )


def _add_object_arguments(objs: Any) -> None:
    """``--mesh``, ``--mesh-scale``, ``--model``, ``--cache`` and ``--seed``."""
    objs.add_argument(
        "--mesh",
        action="append",
        required=True,
        metavar="PATH",
        help="a mesh file (.ply/.obj; obj_000005.ply is object 5, another name object 1, 2, ... "
        "in order) or a BOP models folder; repeatable",
    )
    objs.add_argument(
        "--mesh-scale",
        type=float,
        default=None,
        help="factor from the mesh's units to metres (default 1; 0.001 for a BOP models folder)",
    )
    add_model_argument(objs, without="the classic baseline")
    objs.add_argument(
        "--method",
        choices=METHODS,
        default=None,
        help="the estimator (default: funflow6d with --model, else baseline); funflow6d and "
        "hybrid (the model's and the baseline's hypotheses pooled) need --model",
    )
    objs.add_argument(
        "--cache", default=None, metavar="DIR", help="cache prepared objects here (FunFlow6D)"
    )
    add_seed_argument(objs, draws="sampling and RANSAC")


def _mesh_id(path: Path, index: int) -> int:
    m = re.fullmatch(r"obj_(\d+)", path.stem)
    return int(m.group(1)) if m else index


def load_meshes(
    specs: list[str], *, mesh_scale: float | None, num_points: int = 2048, progress: bool = False
) -> dict[int, Any]:
    """The objects named by ``--mesh``: mesh files and BOP models folders, in metres.

    Args:
        specs: mesh files (``obj_XXXXXX`` names keep their id, others are numbered 1, 2, ... in
            order) or BOP models folders (``models_info.json`` beside ``obj_XXXXXX.ply``, in mm).
        mesh_scale: factor to metres (default 1 for files, 0.001 for BOP folders).
        num_points: size of each model's surface sample.
        progress: show a progress bar.

    Returns:
        ``{obj_id: ObjectModel}``.

    Raises:
        MissingFileError: a path does not exist.
        UnitsError: a mesh's diameter is implausible (the message gives the ``--mesh-scale``).
        UsageError: two meshes get the same object id.
    """
    from poseflow.data.bop import read_models_info
    from poseflow.data.objects import ObjectModel
    from poseflow.errors import MissingFileError, UsageError

    out: dict[int, Any] = {}
    counter = 0
    for spec in specs:
        path = Path(spec)
        if path.is_dir():
            info_path = path / "models_info.json"
            if not info_path.is_file():
                raise MissingFileError(
                    f"--mesh {path} is a folder without models_info.json; give mesh files or a "
                    "BOP models folder"
                )
            infos = read_models_info(info_path)
            scale = 0.001 if mesh_scale is None else mesh_scale
            found = [(o, path / f"obj_{o:06d}.ply") for o in sorted(infos)]
            entries = [(o, p, infos[o]) for o, p in found]
        elif path.is_file():
            counter += 1
            scale = 1.0 if mesh_scale is None else mesh_scale
            entries = [(_mesh_id(path, counter), path, None)]
        else:
            raise MissingFileError(f"--mesh {path} does not exist")
        for obj_id, file, info in entries:
            if obj_id in out:
                raise UsageError(f"--mesh: two meshes are object {obj_id}; rename one")
            if not file.is_file():
                raise MissingFileError(f"missing model of obj {obj_id}: {file}")
            out[obj_id] = ObjectModel.from_file(
                file, scale=scale, info=info, num_points=num_points, scale_name="--mesh-scale"
            )
    return out


def _obj_ids(args: argparse.Namespace, objects: dict[int, Any]) -> list[int] | None:
    from poseflow.errors import UsageError

    if not args.mask:
        if args.obj_id:
            raise UsageError("--obj-id names the objects of --mask files; give --mask too")
        return None
    if args.obj_id:
        if len(args.obj_id) not in (1, len(args.mask)):
            raise UsageError(
                f"give one --obj-id for all masks or one per mask: {len(args.mask)} masks, "
                f"{len(args.obj_id)} ids"
            )
        unknown = sorted(set(args.obj_id) - set(objects))
        if unknown:
            raise UsageError(f"--obj-id {unknown} has no --mesh (objects: {sorted(objects)})")
        return list(args.obj_id)
    if len(objects) != 1:
        raise UsageError(
            f"--mesh gives {len(objects)} objects: say which one each --mask shows with --obj-id"
        )
    return [next(iter(objects))]


def _method(args: argparse.Namespace) -> str:
    """``--method``, or its default: ``funflow6d`` with ``--model``, else ``baseline``.

    Raises:
        UsageError: ``funflow6d`` or ``hybrid`` without ``--model``.
    """
    from poseflow.errors import UsageError

    method = args.method or ("baseline" if args.model is None else "funflow6d")
    if method != "baseline" and args.model is None:
        raise UsageError(f"--method {method} needs --model (a FunFlow6D model folder, or demo)")
    return method


def _estimator(
    args: argparse.Namespace, method: str, objects: dict[int, Any], progress: bool
) -> Any:
    """The estimator of ``method`` (:func:`_method`) and its name."""
    from poseflow.baselines import ClassicBaseline
    from poseflow.cli.common import LOG, load_model, resolve_device, resolve_model

    if method == "baseline":
        LOG.info("estimating with the classic baseline (FPFH + RANSAC + ICP)")
        return ClassicBaseline(objects, seed=args.seed).estimator(), METHOD_LABELS[method]
    folder = resolve_model(args.model)
    model = load_model(folder, device=resolve_device(args.device))
    cache = None if args.cache is None else Path(args.cache) / "objects"  # keyed by each mesh
    LOG.info(f"preparing {len(objects)} object(s) for FunFlow6D from {folder}")
    model.prepare_objects(objects, cache_dir=cache, progress=progress)
    if method == "funflow6d":
        return model.estimator(seed=args.seed), f"FunFlow6D ({folder})"
    from poseflow.models import Hybrid

    hybrid = Hybrid(model, ClassicBaseline(objects, verifier=None, seed=args.seed))
    return hybrid.estimator(seed=args.seed), f"hybrid ({folder})"


def run(args: argparse.Namespace) -> int:
    """Read the frame and the meshes, estimate, write the JSON and the overlay; returns 0.

    A folder ``--out`` that this run created is removed again when the run fails before
    writing into it.
    """
    out = Path(args.out)
    existed = out.exists()
    try:
        return _run(args)
    except BaseException:
        if not existed and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        raise


def _run(args: argparse.Namespace) -> int:
    from poseflow.cli.common import check_writable, resolve_model, show_progress
    from poseflow.eval.frame import estimate_frame, write_poses_json
    from poseflow.eval.validity import apply_validity, mesh_key, read_validity

    method = _method(args)  # a usage error before any work
    detector, detector_dir = None, None
    if not args.mask and args.detections is None:
        from poseflow.cli.detect import load_detector

        detector, detector_dir = load_detector(
            args.detector,
            args.model,
            needs="give the instances: one --mask PNG per instance, --detections, or a detector",
        )
    if args.view:
        _check_view_dependencies()
    out = check_writable(args.out, flag="--out", folder=True)
    progress = show_progress(args)
    objects = load_meshes(args.mesh, mesh_scale=args.mesh_scale, progress=progress)
    frame = _read_checked_frame(args, objects, detector)
    estimator, name = _estimator(args, method, objects, progress)
    diameters = {o: m.diameter for o, m in objects.items()}
    result, meaning = apply_validity(
        estimate_frame(estimator, frame, diameters=diameters),
        None if args.model is None else read_validity(resolve_model(args.model), method),
        {o: mesh_key(m) for o, m in objects.items()},
    )
    meta = {
        "method": name,
        "valid_means": meaning,
        "rgb": str(args.rgb),
        "depth": str(args.depth),
        "depth_scale": frame.depth_scale,
        "K": frame.K.tolist(),
        "meshes": {str(o): m.name for o, m in objects.items()},
    }
    missed = missed_objects(frame.obj_ids, objects) if detector is not None else []
    if detector is not None:
        meta["detector"] = detector_dir
        meta["missed"] = missed
    write_poses_json(out / "poses.json", result, meta=meta)
    notes = [f"obj {o}: not found" for o in missed]
    _write_overlay(out / "overlay.png", frame, objects, result, name, notes)
    for o in missed:
        print(f"obj {o}: not found by the detector")
    if args.view:
        _write_view(out, frame, objects, result, name, name=f"{name}: {args.rgb}")
    _print_poses(result, name, out)
    return 0


def _read_checked_frame(
    args: argparse.Namespace, objects: dict[int, Any], detector: Any = None
) -> Any:
    """The frame of the options, its objects known and its depth in plausible units.

    Raises:
        UsageError: the detections name an object that no ``--mesh`` gives.
        UnitsError: the masked depth spans far more or less than the objects (before any
            preparation: a depth off by a power of ten stops here).
    """
    from poseflow._units import check_depth_extent
    from poseflow.cli.common import LOG
    from poseflow.data.frame import read_frame
    from poseflow.errors import UsageError

    K: Any = args.K[0] if len(args.K) == 1 else [_number(x) for x in args.K]
    frame = read_frame(
        args.rgb,
        args.depth,
        K,
        masks=args.mask,
        obj_ids=_obj_ids(args, objects),
        detections=args.detections,
        depth_scale=args.depth_scale,
        scene_id=args.scene_id,
        im_id=args.im_id,
        score_threshold=args.score_threshold,
        detector=None if detector is None else detector.detect,
    )
    if detector is not None:
        frame = _known_only(frame, objects)
    unknown = sorted({int(o) for o in frame.obj_ids.tolist()} - set(objects))
    if unknown:
        raise UsageError(f"the detections name objects {unknown} that no --mesh gives")
    if len(frame) == 0:
        LOG.warning("no instance to estimate: the detections hold none for this image")
    check_depth_extent(
        frame.depth,
        frame.K,
        frame.masks,
        [objects[int(o)].diameter for o in frame.obj_ids.tolist()],
        where=f"depth {args.depth}",
        scale_name="--depth-scale",
        scale=frame.depth_scale,
    )
    return frame


def _known_only(frame: Any, objects: dict[int, Any]) -> Any:
    """The frame without the detector's instances of objects that no ``--mesh`` gives."""
    import dataclasses

    import torch

    from poseflow.cli.common import LOG

    keep = [int(o) in objects for o in frame.obj_ids.tolist()]
    dropped = sorted({int(o) for o, k in zip(frame.obj_ids.tolist(), keep) if not k})
    if dropped:
        LOG.info("the detector found objects %s, which no --mesh gives: skipped", dropped)
    mask = torch.tensor(keep, dtype=torch.bool)
    return dataclasses.replace(
        frame,
        masks=frame.masks[mask],
        obj_ids=frame.obj_ids[mask],
        scores=frame.scores[mask],
        sources=[s for s, k in zip(frame.sources, keep) if k],
    )


def missed_objects(found: Any, objects: dict[int, Any]) -> list[int]:
    """The objects given (``--mesh``) of which no instance was found.

    Example:
        >>> import torch
        >>> missed_objects(torch.tensor([2, 2]), {1: None, 2: None})
        [1]
    """
    return sorted(set(objects) - {int(o) for o in found.tolist()})


def _write_overlay(
    path: Path, frame: Any, objects: dict, result: Any, method: str, notes: list[str]
) -> None:
    """Every instance drawn on the image: an invalid one dashed and named so in the legend.

    ``notes`` end the legend (the objects the detector did not find).
    """
    from poseflow.eval.overlay import write_overlay

    order = sorted(objects)
    write_overlay(
        path,
        frame.rgb,
        frame.K.float(),
        [objects[o].mesh for o in order],
        result.poses.float(),
        object_ids=[order.index(int(o)) for o in result.obj_ids],
        method=method,
        scores=result.scores,
        valid=result.valid,
        mesh_names=[f"obj {o}" for o in order],
        notes=notes,
    )


def _print_poses(result: Any, method: str, out: Path) -> None:
    """One line per pose (its score and translation, or why it is invalid), then a summary."""
    import torch

    for pose in result.to_json():
        where = f"obj {pose['obj_id']} ({pose['source']})"
        if pose["valid"]:
            t = " ".join(f"{x:.1f}" for x in pose["t_mm"])
            print(f"{where}: score {pose['score']:.3f}, t = [{t}] mm")
        else:
            print(f"{where}: invalid: {pose['note']}")
    n_valid = int(torch.as_tensor(result.valid).sum())
    print(
        f"{method}: {n_valid} of {len(result)} poses valid in {result.seconds:.1f} s; wrote "
        f"{out / 'poses.json'} and {out / 'overlay.png'}"
    )


def _number(text: str) -> float:
    from poseflow.errors import UsageError

    try:
        return float(text)
    except ValueError:
        raise UsageError(f"--K takes 9 numbers or one JSON file/text, got {text!r}") from None


def _check_view_dependencies() -> None:
    """``--view`` needs rerun-sdk and trimesh: say so before any work."""
    import importlib.util

    from poseflow.errors import MissingDependencyError

    for module, package in (("rerun", "rerun-sdk"), ("trimesh", "trimesh")):
        if importlib.util.find_spec(module) is None:
            raise MissingDependencyError(package, "viz", "--view")


def _write_view(out: Path, frame: Any, objects: dict, result: Any, method: str, name: str) -> None:
    """``out/scene.rrd`` and ``out/scene.glb``: the frame's cloud and every finite posed mesh."""
    import torch

    from poseflow.eval import build_scene, export_scene, write_recording

    shown = torch.isfinite(result.poses).flatten(1).all(1)  # a non-finite pose has no place
    view = build_scene(
        frame.rgb,
        frame.depth,
        frame.K,
        objects,
        result.poses[shown],
        result.obj_ids[shown],
        scores=result.scores[shown],
        valid=result.valid[shown],
        method=method,
        name=name,
    )
    written = [write_recording(view, out / "scene.rrd"), *export_scene(view, out / "scene.glb")]
    print(f"3D view: {', '.join(str(p) for p in written)} (open scene.rrd with `rerun`)")
