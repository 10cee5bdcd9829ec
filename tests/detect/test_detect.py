"""``poseflow.detect``: the network's input and heads, targets, grouping, the detector's I/O."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from poseflow.data.bop import BOPDataset, read_detections, write_detections
from poseflow.data.synthetic import generate_dataset
from poseflow.detect import (
    DetectedObjects,
    Detector,
    DetectorConfig,
    InstanceSegmenter,
    detect_dataset,
    detector_images,
    detector_inputs,
    detector_loss,
    detector_targets,
    group_instances,
    head_to_image,
    mask_box,
    resample_to_focal,
    training_batch,
)
from poseflow.errors import CheckpointError, MissingWeightsError, ShapeError, ValueRangeError


@pytest.fixture(scope="module")
def twins(tmp_path_factory):
    """Generated images of the three demo objects, four instances each: one object twice."""
    root = tmp_path_factory.mktemp("det") / "ds"
    return generate_dataset(
        root,
        num_train_images=3,
        num_test_images=1,
        width=320,
        height=240,
        objects_per_image=4,
        progress=False,
        seed=3,
    )


def _tiny_detector(obj_ids=(1, 2, 3)) -> Detector:
    torch.manual_seed(0)
    return Detector(DetectorConfig(obj_ids=list(obj_ids), widths=(4, 4, 4, 4, 4))).eval()


# ------------------------------------------------------------------------------ network input


@settings(max_examples=20)
@given(slope=st.floats(-2.0, 2.0), z0=st.floats(0.4, 2.0), focal=st.floats(100.0, 600.0))
def test_detector_inputs_give_the_tilt_of_a_plane(slope, z0, focal):
    """On a plane z = z0 (1 + slope * u / f), the x slope channel is tanh(slope) at the centre."""
    u = torch.arange(-8, 9, dtype=torch.float64)
    depth = (z0 * (1 + slope * u / focal)).expand(17, 17)[None].clamp_min(1e-3)
    x = detector_inputs(
        torch.zeros(1, 3, 17, 17, dtype=torch.float64), depth, torch.tensor([focal])
    )
    expected = math.tanh(slope * z0 / float(depth[0, 8, 8]))
    assert x[0, 5, 8, 8].item() == pytest.approx(expected, abs=1e-6)
    assert x[0, 6, 8, 8].item() == pytest.approx(0.0, abs=1e-9)
    assert x[0, 3, 8, 8].abs().item() < 1e-9  # the median depth is the centre's
    assert x.dtype == torch.float64


def test_detector_inputs_zero_where_depth_is_missing():
    depth = torch.ones(1, 6, 6)
    depth[0, 2, 3] = 0
    x = detector_inputs(torch.rand(1, 3, 6, 6), depth, torch.tensor([100.0]))
    assert x[0, 4, 2, 3] == 0 and x[0, 4].sum() == 35
    assert torch.isfinite(x).all() and (x[0, 5:, 2, 3] == 0).all()


def test_resample_to_focal_keeps_depth_unmixed():
    depth = torch.zeros(40, 40)
    depth[:, 20:] = 1.0
    rgb, d = resample_to_focal(torch.rand(3, 40, 40), depth, 500.0, 250.0)
    assert rgb.shape == (3, 20, 20) and d.shape == (20, 20)
    assert set(d.unique().tolist()) <= {0.0, 1.0}


def test_segmenter_heads_and_gradients():
    net = InstanceSegmenter(2, widths=(4, 4, 4, 4, 4)).double()
    x = torch.randn(2, 7, 64, 32, dtype=torch.float64, requires_grad=True)
    sem, cen, off = net(x)
    assert (
        sem.shape == (2, 3, 32, 16) and cen.shape == (2, 2, 32, 16) and off.shape == (2, 2, 32, 16)
    )
    assert cen.sigmoid().max() < 0.05  # heatmaps start near zero
    (sem.sum() + off.sum()).backward()
    assert x.grad is not None and x.grad.abs().sum() > 0


# ------------------------------------------------------------------------------ targets, grouping


def _two_squares() -> tuple[torch.Tensor, torch.Tensor]:
    """One 40x48 instance map: two instances of object 0 and one of an unknown object."""
    inst = torch.zeros(1, 40, 48, dtype=torch.long)
    inst[0, 4:16, 4:16] = 1
    inst[0, 20:36, 24:40] = 2
    inst[0, 4:12, 30:44] = 3
    return inst, torch.tensor([[0, 0, -1]])


def test_targets_put_each_centre_at_its_instance():
    inst, labels = _two_squares()
    t = detector_targets(inst, labels, k=2)
    assert t.classes.shape == (1, 40, 48) and t.heatmaps.shape == (1, 2, 20, 24)
    assert set(t.classes.unique().tolist()) == {0, 1}  # the unknown object is background
    peaks = (t.heatmaps[0, 0] == 1).nonzero().tolist()
    assert sorted(peaks) == [[4, 4], [14, 16]]  # centres of rows 2-7 / cols 2-7 and 10-17 / 12-19
    assert t.heatmaps[0, 1].max() == 0
    votes = t.offsets[0, :, 12, 14] + torch.tensor([14.0, 12.0])
    assert votes.tolist() == pytest.approx([15.5, 13.5])  # the mean of head pixels 12..19, 10..17
    assert not t.offset_mask[0, 3, 17]  # the unknown object gets no offset


def test_grouping_the_targets_gives_back_the_instances():
    """Heads that equal the targets group into the two instances of object 0, nothing else."""
    inst, labels = _two_squares()
    t = detector_targets(inst, labels, k=2)
    sem = torch.nn.functional.one_hot(t.classes[0, ::2, ::2], 3).permute(2, 0, 1).float() * 20 - 10
    cen = torch.logit(t.heatmaps[0].clamp(1e-4, 1 - 1e-4))
    found = group_instances(
        sem, cen, t.offsets[0], input_size=(40, 48), image_size=(40, 48), min_pixels=4
    )
    assert found.labels.tolist() == [0, 0]
    truth = [inst[0] == 1, inst[0] == 2]
    for mask in found.masks:
        ious = [float((mask & m).sum() / (mask | m).sum()) for m in truth]
        assert max(ious) > 0.8
    assert not found.masks[:, inst[0] == 3].any()


def test_grouping_finds_nothing_below_the_threshold():
    found = group_instances(
        torch.zeros(2, 8, 8), torch.full((1, 8, 8), -9.0), torch.zeros(2, 8, 8),
        input_size=(16, 16), image_size=(16, 16),
    )  # fmt: skip
    assert len(found) == 0 and found.masks.shape == (0, 16, 16)


def test_head_to_image_crops_the_padding():
    x = torch.zeros(1, 8, 8)
    x[0, :, 6:] = 1.0  # the padding columns of a 12-pixel-wide input
    out = head_to_image(x, (16, 12), (16, 12))
    assert out.shape == (1, 16, 12) and out.max() < 0.5


# ------------------------------------------------------------------------------ on generated images


def test_twins_are_both_in_the_targets_and_group_back(twins):
    """Two instances of one object in a generated image: both found from the oracle heads."""
    data = detector_images(twins, progress=False)
    fy = BOPDataset(twins, "train").scene(0).camera[0].K[1][1]
    assert data.rgb.shape[-2:] == (round(240 * 290 / fy), round(320 * 290 / fy))
    n = 0
    h, w = data.instances.shape[-2:]
    inst = data.instances.long()[..., : h // 2 * 2, : w // 2 * 2]
    t = detector_targets(inst, data.labels, len(data.obj_ids))
    for b in range(len(data)):
        counts = torch.bincount(data.labels[b][data.labels[b] >= 0], minlength=3)
        twin = int(counts.argmax())
        assert counts[twin] == 2
        classes = t.classes[b, ::2, ::2]
        sem = torch.nn.functional.one_hot(classes, 4).permute(2, 0, 1).float() * 20 - 10
        cen = torch.logit(t.heatmaps[b].clamp(1e-4, 1 - 1e-4))
        found = group_instances(
            sem, cen, t.offsets[b], input_size=inst.shape[-2:], image_size=inst.shape[-2:]
        )
        twins_found = [m for m, lab in zip(found.masks, found.labels.tolist()) if lab == twin]
        members = [k + 1 for k in range(data.labels.shape[1]) if data.labels[b, k] == twin]
        for k in members:
            truth = inst[b] == k
            if truth.sum() < 60:
                continue  # almost hidden: no claim
            best = max(float((m & truth).sum() / (m | truth).sum()) for m in twins_found)
            assert best > 0.7
            n += 1
    assert n >= 3


def test_training_batch_and_loss(twins):
    data = detector_images(twins, progress=False)
    g = torch.Generator().manual_seed(0)
    x, t = training_batch(data, 2, 64, g)
    assert x.shape == (2, 7, 64, 64) and t.heatmaps.shape == (2, 3, 32, 32)
    net = InstanceSegmenter(3, widths=(4, 4, 4, 4, 4))
    losses = detector_loss(net(x), t)
    assert set(losses) == {"total", "classes", "centres", "offsets"}
    assert all(torch.isfinite(v) for v in losses.values())
    x2, _ = training_batch(data, 2, 64, torch.Generator().manual_seed(0))
    assert torch.equal(x, x2)  # seeded


def test_detector_images_rejects_a_set_without_the_objects(twins):
    with pytest.raises(Exception, match="no visible instance"):
        detector_images(twins, obj_ids=[99], progress=False)
    with pytest.raises(ValueRangeError):
        detector_images(twins, max_images=0, progress=False)


# ------------------------------------------------------------------------------ the detector


def test_detector_saves_loads_and_detects_alike(tmp_path, twins):
    det = _tiny_detector()
    det.save(tmp_path / "det", training={"steps": 0})
    back = Detector.load(tmp_path / "det")
    assert back.config == det.config and back.training_record == {"steps": 0}
    ds = BOPDataset(twins, "test")
    s = ds.scene_ids[0]
    im = ds.scene(s).im_ids[0]
    K = torch.as_tensor(ds.scene(s).camera[im].K, dtype=torch.float32)
    rgb, depth = ds.scene(s).load_rgb_image(im), ds.scene(s).load_depth_image(im)
    a, b = det.detect(rgb, depth, K), back.detect(rgb, depth, K)
    assert torch.equal(a.masks, b.masks) and torch.equal(a.scores, b.scores)
    assert a.masks.shape[1:] == depth.shape


def test_detector_load_errors(tmp_path):
    with pytest.raises(MissingWeightsError, match="train-detector"):
        Detector.load(tmp_path / "nothing")
    det = _tiny_detector()
    det.save(tmp_path / "det")
    from safetensors.torch import load_file, save_file

    state = load_file(tmp_path / "det" / "model.safetensors")
    state = {
        k: torch.full_like(v, float("nan")) if v.is_floating_point() else v
        for k, v in state.items()
    }
    save_file(state, tmp_path / "det" / "model.safetensors")
    with pytest.raises(CheckpointError, match="non-finite"):
        Detector.load(tmp_path / "det")
    with pytest.raises(ShapeError):
        det.detect(torch.rand(3, 8, 8), torch.ones(8, 9), torch.eye(3))
    with pytest.raises(ValueRangeError):
        DetectorConfig(obj_ids=[])


def test_detections_round_trip_through_the_bop_file(tmp_path):
    masks = torch.zeros(2, 10, 12, dtype=torch.bool)
    masks[0, 2:5, 3:7] = True
    masks[1, 6:9, 0:2] = True
    found = DetectedObjects(torch.tensor([4, 2]), masks, torch.tensor([0.9, 0.5]), 0.05)
    write_detections(tmp_path / "d.json", found.to_detections(7, 11))
    back = read_detections(tmp_path / "d.json")
    assert [(d.scene_id, d.im_id, d.obj_id) for d in back] == [(7, 11, 4), (7, 11, 2)]
    assert back[0].bbox == mask_box(masks[0]) == (3.0, 2.0, 4.0, 3.0)
    assert torch.equal(back[1].mask(), masks[1]) and back[0].time == pytest.approx(0.05)


def test_detect_dataset_covers_the_split(twins):
    """Every image of the split is detected: class and centre heads biased to object 1 and a
    threshold under the untrained heatmap's level make detections of any image."""
    det = _tiny_detector()
    det.config.centre_threshold = 0.005
    with torch.no_grad():
        det.net.semantic.bias.copy_(torch.tensor([-9.0, 9.0, -9.0, -9.0]))
        det.net.centres.bias.copy_(torch.tensor([-4.0, -12.0, -12.0]))
    dets = detect_dataset(det, twins, "train", progress=False)
    ds = BOPDataset(twins, "train")
    images = {(s, i) for s in ds.scene_ids for i in ds.scene(s).im_ids}
    assert {(d.scene_id, d.im_id) for d in dets} == images
    assert all(d.time > 0 and d.obj_id == 1 for d in dets)
    one = detect_dataset(det, twins, "train", images=[min(images)], progress=False)
    assert one and {(d.scene_id, d.im_id) for d in one} == {min(images)}
