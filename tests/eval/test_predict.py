import json
import shutil

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from poseflow.cli import is_usage_error
from poseflow.data.bop import BOPDataset, Detection
from poseflow.data.rle import rle_encode
from poseflow.data.synthetic import generate_dataset
from poseflow.errors import BOPFormatError, ShapeError, UnitsError
from poseflow.eval import (
    PoseEstimate,
    StageTimer,
    evaluate_bop,
    invalidate_implausible,
    predict_dataset,
)
from poseflow.eval.timing import active_timer, stage


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds")
    generate_dataset(
        root, num_train_images=0, num_test_images=2, width=160, height=120, seed=2, progress=False
    )
    return BOPDataset(root, "test")


def _oracle(dataset):
    """An estimator that looks the answer up by mask: GT pose of the instance with that mask."""
    table = []
    for s in dataset.scene_ids:
        scene = dataset.scene(s)
        for i in scene.im_ids:
            for g, gt in enumerate(scene.gt_of(i)):
                table.append((scene.load_mask(i, g, visible=True), torch.as_tensor(gt.pose)))

    def estimate(rgb, depth, K, masks, obj_ids):
        poses = torch.stack(
            [next(p for m, p in table if torch.equal(m, mask)) for mask in masks]
        ).float()
        n = len(obj_ids)
        return PoseEstimate(poses, torch.ones(n), torch.ones(n, dtype=torch.bool))

    return estimate


def test_oracle_estimates_score_full_recall(dataset):
    results = predict_dataset(_oracle(dataset), dataset)
    assert len(results) > 0 and (results.times >= 0).all()
    report = evaluate_bop(dataset, results)
    assert report["AR"] == pytest.approx(1.0)


def test_detection_masks_drive_the_estimator(dataset):
    scene = dataset.scene(dataset.scene_ids[0])
    im = scene.im_ids[0]
    gt = scene.gt_of(im)[0]
    mask = scene.load_mask(im, 0, visible=True)
    det = Detection(scene.scene_id, im, gt.obj_id, 0.9, (0, 0, 1, 1), rle_encode(mask))
    seen = []

    def estimate(rgb, depth, K, masks, obj_ids):
        seen.append((masks, obj_ids))
        return PoseEstimate(torch.eye(4)[None], torch.ones(1), torch.zeros(1, dtype=torch.bool))

    results = predict_dataset(estimate, dataset, detections=[det])
    assert len(seen) == 1 and torch.equal(seen[0][0][0], mask) and seen[0][1] == [gt.obj_id]
    assert len(results) == 0  # the only estimate was invalid


def test_unknown_objects_are_skipped(dataset):
    calls = []

    def estimate(rgb, depth, K, masks, obj_ids):
        calls.append(obj_ids)
        n = len(obj_ids)
        return PoseEstimate(torch.eye(4).expand(n, 4, 4), torch.ones(n), torch.ones(n, dtype=bool))

    predict_dataset(estimate, dataset, object_ids=[2], load_rgb=False)
    assert calls and all(set(c) == {2} for c in calls)


def test_the_timer_is_active_while_each_image_is_estimated(dataset):
    def estimate(rgb, depth, K, masks, obj_ids):
        with stage("ransac"):  # what a part of an estimator reports
            n = len(obj_ids)
        return PoseEstimate(torch.eye(4).expand(n, 4, 4), torch.ones(n), torch.ones(n, dtype=bool))

    timer = StageTimer(synchronize=False)
    predict_dataset(estimate, dataset, timer=timer, max_images=2)
    assert timer.num_images == 2 and timer.counts == {"ransac": 2}
    predict_dataset(estimate, dataset, max_images=1)  # no timer: nothing recorded
    assert timer.counts == {"ransac": 2} and active_timer() is None


def test_a_pose_behind_the_camera_never_becomes_a_row(dataset):
    oracle = _oracle(dataset)

    def mirrored(rgb, depth, K, masks, obj_ids):
        est = oracle(rgb, depth, K, masks, obj_ids)
        poses = est.poses.clone()
        poses[0, :3, 3] *= -1  # e.g. depth divided by 1000 on its way in: flagged valid
        return PoseEstimate(poses, est.scores, est.valid)

    full = predict_dataset(oracle, dataset)
    kept = predict_dataset(mirrored, dataset)
    images = len({(s, i) for s, i in zip(full.scene_ids.tolist(), full.im_ids.tolist())})
    assert len(kept) == len(full) - images
    assert bool((kept.poses[:, 2, 3] > 0).all())


def test_before_image_runs_before_each_image_and_can_stop_the_loop(dataset):
    calls = []
    oracle = _oracle(dataset)

    def estimate(rgb, depth, K, masks, obj_ids):
        calls.append(("estimate", len(obj_ids)))
        return oracle(rgb, depth, K, masks, obj_ids)

    timer = StageTimer(synchronize=False)
    predict_dataset(estimate, dataset, timer=timer, before_image=lambda s, i: calls.append((s, i)))
    images = sorted((s, i) for s in dataset.scene_ids for i in dataset.scene(s).im_ids)
    assert [c for c in calls if c[0] != "estimate"] == images
    assert [c[0] == "estimate" for c in calls] == [False, True] * len(images)  # hook, image, ...
    assert timer.num_images == len(images)

    def stop(s, i):
        if (s, i) == images[1]:
            raise RuntimeError("another process failed")

    calls.clear()
    with pytest.raises(RuntimeError, match="another process failed"):
        predict_dataset(estimate, dataset, before_image=stop)
    assert len(calls) == 1  # the first image only


@settings(max_examples=25)
@given(seed=st.integers(0, 2**31 - 1), B=st.integers(0, 12), nan_ratio=st.floats(0.0, 0.5))
def test_invalidate_implausible_keeps_exactly_the_finite_poses_in_front(seed, B, nan_ratio):
    g = torch.Generator().manual_seed(seed)
    for dtype in (torch.float32, torch.float64):
        poses = torch.eye(4, dtype=dtype).repeat(B, 1, 1)
        poses[:, :3, 3] = torch.randn(B, 3, generator=g, dtype=dtype)
        poses[torch.rand(B, generator=g) < 0.2, 2, 3] = 0.0  # exactly on the camera plane
        poses[torch.rand(B, generator=g) < nan_ratio, 0, 1] = float("nan")
        scores = torch.rand(B, generator=g, dtype=dtype)
        valid = torch.rand(B, generator=g) < 0.7
        out = invalidate_implausible(PoseEstimate(poses, scores, valid))
        for b in range(B):
            plausible = bool(torch.isfinite(poses[b]).all()) and float(poses[b, 2, 3]) > 0
            assert bool(out.valid[b]) == (bool(valid[b]) and plausible)
            assert float(out.scores[b]) == (float(scores[b]) if out.valid[b] else 0.0)
        assert torch.equal(out.poses.nan_to_num(7.0), poses.nan_to_num(7.0))  # kept as they are
        assert out.scores.dtype == dtype and out.valid.dtype == torch.bool


def _copy_with_camera(dataset, tmp_path, edit):
    """A copy of ``dataset``; its first image's ``scene_camera.json`` entry passed to ``edit``."""
    root = tmp_path / "copy"
    shutil.copytree(dataset.root, root)
    s = dataset.scene_ids[0]
    i = dataset.scene(s).im_ids[0]
    path = root / "test" / f"{s:06d}" / "scene_camera.json"
    cameras = json.loads(path.read_text())
    edit(cameras[str(i)])
    path.write_text(json.dumps(cameras))
    return BOPDataset(root, "test"), path, i


def test_a_depth_scale_a_thousand_times_too_large_stops_naming_the_image(dataset, tmp_path):
    def scale(cam):
        cam["depth_scale"] *= 1000

    copy, path, im_id = _copy_with_camera(dataset, tmp_path, scale)
    oracle = _oracle(dataset)
    with pytest.raises(UnitsError, match="1000 times too large") as err:
        predict_dataset(oracle, copy)
    assert f"image {im_id}" in str(err.value) and str(path) in str(err.value)
    assert len(predict_dataset(oracle, copy, diameters={})) > 0  # {}: no check


@pytest.mark.parametrize("bad", ["transposed", "zero"])
def test_a_bad_cam_k_is_a_format_error_naming_the_file_and_image(dataset, tmp_path, bad):
    def edit(cam):
        K = np.asarray(cam["cam_K"], dtype=float).reshape(3, 3)
        cam["cam_K"] = (K.T if bad == "transposed" else np.zeros((3, 3))).reshape(-1).tolist()

    copy, path, im_id = _copy_with_camera(dataset, tmp_path, edit)
    with pytest.raises(BOPFormatError, match=f"image {im_id}") as err:
        predict_dataset(_oracle(dataset), copy)
    assert str(path) in str(err.value) and "cam_K" in str(err.value)
    assert not is_usage_error(err.value)


def test_a_mask_of_another_size_is_a_shape_error_naming_both_files(dataset, tmp_path):
    copy, _, im_id = _copy_with_camera(dataset, tmp_path, lambda cam: None)
    scene = copy.scene(copy.scene_ids[0])
    mask = scene.mask_path(im_id, 0)
    Image.fromarray(np.zeros((10, 12), np.uint8)).save(mask)
    with pytest.raises(ShapeError, match="12x10 but the depth") as err:
        predict_dataset(_oracle(dataset), copy)
    assert str(mask) in str(err.value) and str(scene.depth_path(im_id)) in str(err.value)


def _seeded_noise(generator):
    """An estimator whose poses are drawn from ``generator`` (reseeded per image by the caller)."""

    def estimate(rgb, depth, K, masks, obj_ids):
        n = len(obj_ids)
        poses = torch.eye(4).repeat(n, 1, 1)
        poses[:, :3, 3] = torch.rand(n, 3, generator=generator) + torch.tensor([0.0, 0.0, 0.5])
        with stage("icp"):
            scores = torch.rand(n, generator=generator)
        return PoseEstimate(poses, scores, scores > 0.2)

    return estimate


def test_workers_give_the_rows_one_process_gives_with_the_timer_and_hooks(dataset):
    from poseflow.eval import predict_seeded

    object_ids = sorted({g.obj_id for s in dataset.scene_ids for g in dataset.scene(s).gt_of(0)})
    runs = {}
    for workers in (1, 2):
        timer, seen = StageTimer(), []
        results = predict_seeded(
            _seeded_noise,
            dataset,
            device="cpu",
            object_ids=object_ids,
            seed=3,
            timer=timer,
            workers=workers,
            after_image=lambda s, i, ids, est, seen=seen: seen.append(
                (s, i, len(ids), len(est.valid))
            ),
        )
        runs[workers] = results, timer, seen
    (one, t1, seen1), (two, t2, seen2) = runs[1], runs[2]
    for name in ("scene_ids", "im_ids", "obj_ids", "scores", "poses"):
        assert torch.equal(getattr(one, name), getattr(two, name)), name
    assert len(one) > 0 and seen1 == seen2 and len(seen1) == t1.num_images == t2.num_images
    assert all(n == v for _, _, n, v in seen1)
    assert t1.counts["icp"] == t2.counts["icp"] == t1.num_images and t2.totals["icp"] > 0


def test_a_workers_units_error_stops_the_run_naming_the_image(dataset, tmp_path):
    def scale(cam):
        cam["depth_scale"] *= 1000

    copy, path, im_id = _copy_with_camera(dataset, tmp_path, scale)
    with pytest.raises(UnitsError, match="1000 times too large") as err:
        predict_dataset(_oracle(dataset), copy, workers=2)
    assert f"image {im_id}" in str(err.value) and str(path) in str(err.value)
