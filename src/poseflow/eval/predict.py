"""Run any pose estimator over a BOP split and collect BOP results, timed per image.

The loop that FunFlow6D, the classic baseline and the ``poseflow predict`` command share: for
every image that holds target instances, all of its instances (ground-truth visible masks, or the
masks of a detection file) go to the estimator in one call, and the estimates become
:class:`~poseflow.eval.results.PoseResults` rows whose ``time`` is the image's wall-clock time.
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from math import nan
from typing import Any

import torch

from poseflow._progress import progress as progress_loop
from poseflow._units import check_depth_extent, check_intrinsics, in_front_of_camera
from poseflow._workers import check_workers, map_forked
from poseflow.data.bop import BOPDataset, BOPScene, Detection
from poseflow.data.frame import ImageInstances
from poseflow.errors import BOPFormatError, ShapeError, ValueRangeError
from poseflow.eval.recall import Target
from poseflow.eval.results import PoseResults
from poseflow.eval.timing import StageTimer

__all__ = [
    "Estimator",
    "PoseEstimate",
    "SeededEstimator",
    "invalidate_implausible",
    "on_device",
    "predict_dataset",
    "predict_seeded",
    "seeded_estimator",
]


@dataclass
class PoseEstimate:
    """Poses of the instances of one image, as every estimator in poseflow returns them.

    Attributes:
        poses: model-to-camera transforms ``(B, 4, 4)``, metres (identity where no pose was
            found; a pose :func:`invalidate_implausible` rejected is kept, flagged invalid).
        scores: confidences in ``[0, 1]`` ``(B,)``, used to rank estimates (0 where invalid).
        valid: ``(B,)`` False where no pose could be estimated (too few points, no consensus)
            or the pose cannot be right (not finite, or behind the camera).
        agreement: ``(B,)`` the share of the estimator's pose hypotheses of each instance that
            lie within a tenth of the diameter of its pose (how much of the sampled posterior
            agrees with the choice), or None for an estimator that samples none.
    """

    poses: torch.Tensor
    scores: torch.Tensor
    valid: torch.Tensor
    agreement: torch.Tensor | None = None

    def cpu(self) -> PoseEstimate:
        """This estimate with every tensor on the CPU."""
        agreement = None if self.agreement is None else self.agreement.cpu()
        return PoseEstimate(self.poses.cpu(), self.scores.cpu(), self.valid.cpu(), agreement)

    @classmethod
    def empty(
        cls, *, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
    ) -> PoseEstimate:
        """The estimate of an image without instances (``B = 0``).

        Example:
            >>> e = PoseEstimate.empty(dtype=torch.float64)
            >>> e.poses.shape, e.scores.dtype, e.valid.shape
            (torch.Size([0, 4, 4]), torch.float64, torch.Size([0]))
        """
        kw = {"dtype": dtype, "device": device}
        return cls(
            torch.zeros(0, 4, 4, **kw),
            torch.zeros(0, **kw),
            torch.zeros(0, dtype=torch.bool, device=device),
        )


def invalidate_implausible(estimate: PoseEstimate) -> PoseEstimate:
    """Flag invalid (score 0) every pose that cannot be right: not finite, or behind the camera.

    The one rule every estimator's output goes through (FunFlow6D, the classic baseline,
    :func:`predict_dataset` for any other estimator): a pose with ``t_z <= 0`` puts the object's
    origin behind the camera (e.g. depth in the wrong unit), so it is never valid. The rejected
    poses are kept as they are, so that a caller can say why they were rejected.

    Args:
        estimate: the poses ``(B, 4, 4)``, scores ``(B,)`` and validity ``(B,)`` of an image.

    Returns:
        A new :class:`PoseEstimate` on the same device and dtype.

    Example:
        >>> T = torch.eye(4).repeat(3, 1, 1); T[0, 2, 3] = 0.5; T[1, 2, 3] = -0.5
        >>> T[2, 0, 0] = float("nan")
        >>> out = invalidate_implausible(PoseEstimate(T, torch.ones(3), torch.ones(3).bool()))
        >>> out.valid.tolist(), out.scores.tolist()
        ([True, False, False], [1.0, 0.0, 0.0])
    """
    poses = estimate.poses
    finite = torch.isfinite(poses).flatten(1).all(1)
    valid = estimate.valid.bool() & finite & in_front_of_camera(poses)
    scores = torch.where(valid, estimate.scores, torch.zeros_like(estimate.scores))
    return PoseEstimate(poses, scores, valid, estimate.agreement)


#: ``estimator(rgb (3,H,W) | None, depth (H,W) m, K (3,3), masks (B,H,W), obj_ids (B,))``.
Estimator = Callable[..., PoseEstimate]


def on_device(estimator: Estimator, device: torch.device | str) -> Estimator:
    """``estimator`` with the image, depth, intrinsics and masks moved to ``device`` first.

    Args:
        estimator: any :data:`Estimator`, e.g. a model's ``estimate`` on a GPU.
        device: where its inputs must be.

    Returns:
        An :data:`Estimator` (``rgb`` may stay None; the object ids are passed unchanged).

    Example:
        >>> seen = on_device(lambda rgb, depth, K, masks, obj_ids: depth.dtype, "cpu")
        >>> seen(None, torch.zeros(2, 2, dtype=torch.float64), torch.eye(3),
        ...      torch.ones(1, 2, 2, dtype=torch.bool), [1])
        torch.float64
    """

    def estimate(*image: Any) -> PoseEstimate:
        """The estimate of ``image = (rgb, depth, K, masks, obj_ids)``, tensors on ``device``."""
        *tensors, obj_ids = image
        return estimator(*(None if t is None else t.to(device) for t in tensors), obj_ids)

    return estimate


def seeded_estimator(
    estimate: Callable[..., PoseEstimate],
    device: torch.device | str,
    *,
    seed: int = 0,
    generator: torch.Generator | None = None,
) -> Estimator:
    """An estimator's ``estimate`` as an :data:`Estimator` that draws from one generator.

    Inputs are moved to ``device``; one generator serves all calls: ``generator`` (on
    ``device``), e.g. to be reseeded per image, or a new one seeded ``seed``, so that a sequence
    of images gives the same estimates on every run.

    Args:
        estimate: called as ``estimate(rgb, depth, K, masks, obj_ids, generator=generator)``.
        device: the estimator's device.
        seed: the seed of a new generator.
        generator: the generator to draw from instead.
    """
    if generator is None:
        generator = torch.Generator(device=device).manual_seed(seed)
    return on_device(functools.partial(estimate, generator=generator), device)


class SeededEstimator:
    """Base of the estimators that draw from a generator: ``estimate``, ``estimator``, ``predict``.

    A subclass gives :meth:`_estimate` (of an :class:`~poseflow.data.ImageInstances`), its
    ``device`` and :meth:`_object_ids`.
    """

    device: torch.device

    @torch.no_grad()
    def estimate(
        self,
        rgb: torch.Tensor,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: torch.Tensor | Sequence[int],
        *,
        generator: torch.Generator | None = None,
    ) -> PoseEstimate:
        """Estimate the pose of every masked instance of one RGBD image, in one batch.

        Stages are charged to the active :class:`~poseflow.eval.timing.StageTimer`, if any.

        Args:
            rgb: the image ``(3, H, W)``, uint8 or float in ``[0, 1]``.
            depth: depth ``(H, W)`` in metres.
            K: intrinsics ``(3, 3)``: a tensor, an array, nested lists or 9 numbers.
            masks: instance masks ``(B, H, W)`` bool (``B`` may be 0).
            obj_ids: object id of each mask ``(B,)``; every id must be prepared.
            generator: seeds the noise, the sampling of the clouds and RANSAC; None: a generator
                seeded 0, so that the same call gives the same poses (pass a generator seeded
                at random for independent draws).

        Returns:
            A :class:`PoseEstimate` of the ``B`` instances (float32 on the depth's device); a pose
            that is not finite or puts the object behind the camera is flagged invalid
            (:func:`invalidate_implausible`).

        Raises:
            ShapeError: inconsistent shapes, or ``K`` not 9 numbers.
            ValueRangeError: an object id that is not prepared (for verification too, when on),
                or a ``K`` that is not a pinhole matrix of this image.
            UnitsError: the masked depth spans far more or far less than the objects (a depth
                in the wrong unit; :func:`~poseflow._units.check_depth_extent`).
        """
        return self._estimate(ImageInstances(rgb, depth, K, masks, obj_ids), generator)

    def _estimate(self, image: ImageInstances, generator: torch.Generator | None) -> PoseEstimate:
        raise NotImplementedError

    def _object_ids(self) -> list[int]:
        """The objects this estimator knows."""
        raise NotImplementedError

    def estimator(self, *, seed: int = 0, generator: torch.Generator | None = None) -> Estimator:
        """This estimator as an :data:`Estimator` of one generator: :func:`seeded_estimator`."""
        return seeded_estimator(self.estimate, self.device, seed=seed, generator=generator)

    def predict(
        self, dataset: str | os.PathLike[str] | BOPDataset, *, seed: int = 0, **options: Any
    ) -> PoseResults:
        """Estimate every target instance of a BOP split: :func:`predict_seeded`.

        ``seed`` seeds the noise, sampling and RANSAC of each image with its ids, as ``poseflow
        predict`` does; ``options`` (``split``, ``targets``, ``detections``, ``max_images``,
        ``timer``, ``progress``, ``workers``) are those of :func:`predict_dataset`. Returns
        :class:`~poseflow.eval.results.PoseResults`, one row per valid estimate.
        """
        return predict_seeded(
            lambda generator: self.estimator(generator=generator),
            dataset,
            device=self.device,
            object_ids=self._object_ids(),
            seed=seed,
            **options,
        )


def predict_dataset(
    estimator: Estimator,
    dataset: str | os.PathLike[str] | BOPDataset,
    *,
    split: str = "test",
    object_ids: Sequence[int] | None = None,
    targets: Sequence[Target] | None = None,
    detections: Sequence[Detection] | None = None,
    load_rgb: bool = True,
    max_images: int | None = None,
    timer: StageTimer | None = None,
    progress: bool = False,
    before_image: Callable[[int, int], None] | None = None,
    after_image: Callable[[int, int, list[int], PoseEstimate], None] | None = None,
    diameters: Mapping[int, float] | None = None,
    workers: int = 1,
) -> PoseResults:
    """Estimate the poses of the target instances of every image of a split.

    Args:
        estimator: called once per image as ``estimator(rgb, depth, K, masks, obj_ids)`` and
            returning a :class:`PoseEstimate` (see :data:`Estimator`).
        dataset: the dataset folder or a :class:`~poseflow.data.bop.BOPDataset`.
        split: the split folder, when ``dataset`` is a path.
        object_ids: objects the estimator knows (others are skipped); None: all.
        targets: the targets; default the dataset's ``test_targets_bop19.json`` when present,
            else every ground-truth instance.
        detections: use these masks (e.g. a BOP segmentation file) instead of the ground truth.
        load_rgb: read the colour image (False passes ``rgb=None``).
        max_images: stop after this many images.
        timer: optional :class:`~poseflow.eval.timing.StageTimer`; each image runs in
            ``timer.image()`` with the timer active (``timer.active()``), so that the stages the
            estimator reports through :func:`~poseflow.eval.timing.stage` are charged to it.
        progress: show a progress bar.
        before_image: called as ``before_image(scene_id, im_id)`` before each image is read,
            outside its time, in the process that estimates it: e.g. to reseed the estimator's
            generator per image (:func:`~poseflow.eval.distributed.image_seed`), or to stop
            when another process of a split run failed
            (:meth:`~poseflow.eval.distributed.Ranks.check_peers`).
        after_image: called here as ``after_image(scene_id, im_id, obj_ids, estimate)`` with
            each estimated image's instances and vetted estimate (on the CPU), in image order.
        diameters: ``{obj_id: diameter in metres}`` against which each image's masked depth is
            checked (:func:`~poseflow._units.check_depth_extent`: a ``depth_scale`` off by a
            power of ten stops the run); None: those of the dataset's
            ``models/models_info.json`` when it exists; ``{}``: no check.
        workers: estimate the images in this many forked processes of one thread each
            (``poseflow._workers.map_forked``; CPU estimators only): the same rows,
            in the same order, when an image's estimate does not depend on the images before
            it (:func:`predict_seeded`).

    Returns:
        One row per valid estimate; a pose behind the camera (``t_z <= 0``) is never valid
        (:func:`invalidate_implausible`).

    Raises:
        UnitsError: an image's masked depth disagrees with its objects' diameters; the message
            names the image, its ``scene_camera.json`` and the ``depth_scale`` that fixes it.
        BOPFormatError: an image's ``cam_K`` is not a pinhole matrix of the image (transposed,
            zero, another resolution), named with its file and image id.
        ShapeError: an image's colour, depth and masks differ in size (the files are named).
    """
    ds = dataset if isinstance(dataset, BOPDataset) else BOPDataset(dataset, split)
    keys = sorted(_images_to_predict(ds, targets).items())[:max_images]
    by_image = _by_image(detections or ())
    known = None if object_ids is None else {int(o) for o in object_ids}
    if diameters is None:
        diameters = _model_diameters(ds)
    workers = check_workers(workers)

    def estimate_image(n: int) -> _ImageEstimate | None:
        (s, i), wanted = keys[n]
        if before_image is not None:
            before_image(s, i)
        scene = ds.scene(s)
        dets = None if detections is None else by_image.get((s, i), [])
        obj_ids, masks, mask_names = _instances(scene, i, dets, wanted, known)
        if not masks:
            return None
        depth, rgb, K = _read_image(scene, i, load_rgb, masks, mask_names)
        stacked = torch.stack(masks)
        if diameters:
            _check_depth(scene, i, depth, K, stacked, [diameters.get(o, nan) for o in obj_ids])
        est, elapsed = _timed(estimator, timer, rgb, depth, K, stacked, obj_ids)
        return _ImageEstimate(s, i, obj_ids, est.cpu(), elapsed)

    def in_worker(n: int) -> tuple[_ImageEstimate | None, StageTimer | None]:
        """An image estimated in a worker, with the stage times it took there."""
        if timer is None:
            return estimate_image(n), None
        timer.reset()
        out = estimate_image(n)
        taken = StageTimer(synchronize=False, excluded=timer.excluded)
        taken.add(timer)
        return out, taken

    if workers == 1:
        outcomes = ((estimate_image(n), None) for n in range(len(keys)))
    else:
        outcomes = map_forked(in_worker, len(keys), workers)
    parts = []
    for out, taken in progress_loop(outcomes, total=len(keys), desc="predict", enabled=progress):
        if taken is not None:
            timer.add(taken)  # type: ignore[union-attr]
        if out is None:
            continue
        if after_image is not None:
            after_image(out.scene_id, out.im_id, out.obj_ids, out.estimate)
        if bool(out.estimate.valid.any()):
            parts.append(out.results())
    return PoseResults.concat(parts)


def predict_seeded(
    make_estimator: Callable[[torch.Generator], Estimator],
    dataset: str | os.PathLike[str] | BOPDataset,
    *,
    device: torch.device | str,
    object_ids: Sequence[int],
    seed: int = 0,
    **options: Any,
) -> PoseResults:
    """:func:`predict_dataset` of an estimator drawing from one generator, reseeded per image.

    The ``predict`` of every estimator of poseflow (FunFlow6D, the classic baseline, the
    hybrid): each image's draws come from ``seed`` and its ids
    (:func:`~poseflow.eval.distributed.image_seed`), as in ``poseflow predict``, so that an
    image's estimate does not depend on the images before it.

    Args:
        make_estimator: builds the :data:`Estimator` that draws from the generator it is given.
        dataset: the dataset folder or a :class:`~poseflow.data.bop.BOPDataset`.
        device: the generator's device.
        object_ids: the objects the estimator knows (others are skipped).
        seed: the run's seed.
        options: more keyword arguments of :func:`predict_dataset` (``split``, ``targets``,
            ``detections``, ``load_rgb``, ``max_images``, ``timer``, ``progress``,
            ``workers``).

    Returns:
        One row per valid estimate.
    """
    from poseflow.eval.distributed import image_seed

    generator = torch.Generator(device=device)

    def reseed(scene_id: int, im_id: int) -> None:
        generator.manual_seed(image_seed(seed, scene_id, im_id))

    return predict_dataset(
        make_estimator(generator), dataset, object_ids=object_ids, before_image=reseed, **options
    )


@dataclass
class _ImageEstimate:
    """One image's instances and their vetted estimate (on the CPU), and the image's seconds."""

    scene_id: int
    im_id: int
    obj_ids: list[int]
    estimate: PoseEstimate
    seconds: float

    def results(self) -> PoseResults:
        """The rows of the valid estimates (at least one)."""
        ok = self.estimate.valid
        k = int(ok.sum())
        ids = [o for o, v in zip(self.obj_ids, ok.tolist()) if v]
        est = self.estimate
        return PoseResults.from_columns(
            [self.scene_id] * k, [self.im_id] * k, ids, est.scores[ok], est.poses[ok], self.seconds
        )


def _timed(
    estimator: Estimator, timer: StageTimer | None, *inputs: Any
) -> tuple[PoseEstimate, float]:
    """The estimate of one image, vetted by :func:`invalidate_implausible`, and its seconds.

    With a ``timer``, the call runs in ``timer.image()`` with the timer active.
    """
    start = time.perf_counter()
    if timer is None:
        est = estimator(*inputs)
    else:
        with timer.active(), timer.image():
            est = estimator(*inputs)
    elapsed = time.perf_counter() - start
    return invalidate_implausible(est), elapsed


def _images_to_predict(
    ds: BOPDataset, targets: Sequence[Target] | None
) -> dict[tuple[int, int], set[int] | None]:
    """The images to predict, each with its target objects (None: every instance).

    The targets default to the dataset's ``test_targets_bop19.json`` when present, else every
    image of the split.
    """
    if targets is None and (ds.root / "test_targets_bop19.json").is_file():
        targets = [Target(t.scene_id, t.im_id, t.obj_id, t.inst_count) for t in ds.test_targets()]
    if targets is None:
        return {(s, i): None for s in ds.scene_ids for i in ds.scene(s).im_ids}
    images: dict[tuple[int, int], set[int] | None] = {}
    for t in targets:
        images.setdefault((t.scene_id, t.im_id), set()).add(t.obj_id)  # type: ignore[union-attr]
    return images


def _by_image(detections: Sequence[Detection]) -> dict[tuple[int, int], list[Detection]]:
    """The detections grouped by ``(scene_id, im_id)``, in their order."""
    by_image: dict[tuple[int, int], list[Detection]] = {}
    for d in detections:
        by_image.setdefault((d.scene_id, d.im_id), []).append(d)
    return by_image


def _model_diameters(ds: BOPDataset) -> dict[int, float]:
    """``{obj_id: diameter}`` in metres from ``models/models_info.json``; ``{}`` without it."""
    if not (ds.root / "models" / "models_info.json").is_file():
        return {}
    return {o: m.diameter for o, m in ds.models_info().items()}


def _instances(
    scene: BOPScene,
    im_id: int,
    detections: Sequence[Detection] | None,
    wanted: set[int] | None,
    known: set[int] | None,
) -> tuple[list[int], list[torch.Tensor], list[str]]:
    """The instances of an image to estimate: object ids, masks ``(H, W)`` and the masks' names.

    From the ground truth's visible masks, or from ``detections`` (those of the image) if given;
    only objects in ``wanted`` (the image's targets) and ``known`` (the estimator's), None: any.
    """

    def usable(obj_id: int) -> bool:
        return (wanted is None or obj_id in wanted) and (known is None or obj_id in known)

    if detections is None:
        gts = scene.gt_of(im_id)
        sel = [g for g, gt in enumerate(gts) if usable(gt.obj_id)]
        obj_ids = [gts[g].obj_id for g in sel]
        masks = [scene.load_mask(im_id, g, visible=True) for g in sel]
        return obj_ids, masks, [str(scene.mask_path(im_id, g, visible=True)) for g in sel]
    dets = [d for d in detections if usable(d.obj_id)]
    names = [f"the detection mask of obj {d.obj_id}" for d in dets]
    return [d.obj_id for d in dets], [d.mask() for d in dets], names


def _read_image(
    scene: BOPScene,
    im_id: int,
    load_rgb: bool,
    masks: Sequence[torch.Tensor],
    mask_names: Sequence[str],
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """An image's depth ``(H, W)``, colour ``(3, H, W)`` (if ``load_rgb``) and checked ``K``."""
    depth = scene.load_depth_image(im_id)
    rgb = scene.load_rgb_image(im_id) if load_rgb else None
    _check_sizes(scene, im_id, depth, rgb, masks, mask_names)
    return depth, rgb, _checked_K(scene, im_id, depth)


def _check_depth(
    scene: BOPScene,
    im_id: int,
    depth: torch.Tensor,
    K: torch.Tensor,
    masks: torch.Tensor,
    diameters: Sequence[float],
) -> None:
    """:func:`~poseflow._units.check_depth_extent` naming the image and its depth scale."""
    check_depth_extent(
        depth,
        K,
        masks,
        [float(d) for d in diameters],
        where=f"scene {scene.scene_id} image {im_id} (depth {scene.depth_path(im_id)})",
        scale_name=f"the depth_scale of image {im_id} in {scene.path / 'scene_camera.json'} to",
        scale=float(scene.camera[im_id].depth_scale),
    )


def _check_sizes(
    scene: BOPScene,
    im_id: int,
    depth: torch.Tensor,
    rgb: torch.Tensor | None,
    masks: Sequence[torch.Tensor],
    mask_names: Sequence[str],
) -> None:
    """Raise a :class:`ShapeError` naming the files when colour, depth and masks differ in size."""
    H, W = depth.shape
    where = f"scene {scene.scene_id} image {im_id}"
    if rgb is not None and tuple(rgb.shape[-2:]) != (H, W):
        raise ShapeError(
            f"{where}: the colour image {scene.rgb_path(im_id)} is {rgb.shape[-1]}x"
            f"{rgb.shape[-2]} but the depth {scene.depth_path(im_id)} is {W}x{H}"
        )
    for m, name in zip(masks, mask_names):
        if tuple(m.shape) != (H, W):
            raise ShapeError(
                f"{where}: {name} is {m.shape[-1]}x{m.shape[-2]} but the depth "
                f"{scene.depth_path(im_id)} is {W}x{H}"
            )


def _checked_K(scene: BOPScene, im_id: int, depth: torch.Tensor) -> torch.Tensor:
    """The image's ``cam_K`` as float32, checked against its size (a data error, not usage)."""
    try:
        K = check_intrinsics(scene.camera[im_id].K, depth.shape[1], depth.shape[0], name="cam_K")
    except ValueRangeError as exc:
        raise BOPFormatError(
            f"{scene.path / 'scene_camera.json'} (scene {scene.scene_id}, image {im_id}): {exc}"
        ) from None
    return K.to(torch.float32)
