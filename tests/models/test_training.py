"""Training-time augmentations: sensor noise, mask damage, crop jitter and the dense-cloud cap."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from poseflow.data import ImageInstances
from poseflow.errors import ValueRangeError
from poseflow.features.lifting import jitter_boxes
from poseflow.geometry.pointcloud import backproject_depth
from poseflow.models.training import augment


def test_augment_perturbs_valid_depth_and_shrinks_masks():
    depth = torch.full((32, 32), 0.8)
    depth[:4] = 0.0  # missing depth stays missing
    masks = torch.zeros(2, 32, 32, dtype=torch.bool)
    masks[0, 8:24, 8:24] = True
    masks[1, 4:12, 20:30] = True
    d, m = augment(depth, masks, generator=torch.Generator().manual_seed(0), max_erosion=2)
    assert (d[:4] == 0).all() and not torch.equal(d[4:], depth[4:])
    assert (d[4:] - depth[4:]).abs().max() < 0.05
    assert (m & ~masks).sum() == 0 and m.sum() < masks.sum()


@given(
    st.integers(0, 2**31 - 1),
    st.floats(0.1, 1.0),
    st.floats(0.0, 1.0),
    st.integers(6, 20),
    st.integers(6, 20),
)
def test_occlusion_cuts_a_mask_by_one_straight_edge(seed, low, width, h, w):
    from scipy.ndimage import label

    kept = (low, low + width * (1.0 - low))
    masks = torch.zeros(2, 24, 24, dtype=torch.bool)
    masks[0, 2 : 2 + h, 3 : 3 + w] = True  # a rectangle
    yy, xx = torch.meshgrid(torch.arange(24), torch.arange(24), indexing="ij")
    masks[1] = (yy - 12) ** 2 + (xx - 11) ** 2 <= 64  # a disc
    g = torch.Generator().manual_seed(seed)
    _, cut = augment(torch.ones(24, 24), masks, generator=g, max_erosion=0, mask_noise=0.0,
                     occlusion=1.0, kept=kept)  # fmt: skip
    for m, c in zip(masks, cut):
        n = int(m.sum())
        assert (c & ~m).sum() == 0  # a part of the mask
        assert kept[0] * n - 1 <= int(c.sum()) <= kept[1] * n + 1
        # what is kept of a convex mask is one piece on one side of a line (pixel centres)
        assert label(c.numpy(), structure=[[1, 1, 1]] * 3)[1] == 1
        assert _weakly_separable(c.nonzero().double().numpy(), (m & ~c).nonzero().double().numpy())
    # a random choice of as many pixels is not cut by a line
    pixels = masks[1].nonzero().double()
    order = torch.randperm(len(pixels), generator=g)
    half = len(pixels) // 2
    assert not _weakly_separable(pixels[order[:half]].numpy(), pixels[order[half:]].numpy())


def _weakly_separable(a, b) -> bool:
    """Whether a line has the points ``a`` (n, 2) on one side and ``b`` on the other (or on it).

    A direction ``d`` with ``max |d_i| = 1`` (one of four linear programs, one per fixed
    coordinate and sign) and an offset ``c`` with ``d·a <= c - t`` and ``d·b >= c + t`` for a
    margin ``t`` that is not negative.
    """
    from scipy.optimize import linprog

    if len(a) == 0 or len(b) == 0:
        return True
    rows = [[*p, -1.0, 1.0] for p in a] + [[-p[0], -p[1], 1.0, 1.0] for p in b]
    for axis in (0, 1):
        for sign in (-1.0, 1.0):
            bounds = [(-1, 1), (-1, 1), (None, None), (None, 1)]
            bounds[axis] = (sign, sign)
            res = linprog([0, 0, 0, -1], A_ub=rows, b_ub=[0.0] * len(rows), bounds=bounds)
            if res.status == 0 and -res.fun >= -1e-9:
                return True
    return False


def test_occlusion_is_off_by_default_and_checked():
    masks = torch.zeros(1, 16, 16, dtype=torch.bool)
    masks[0, 2:14, 3:12] = True
    depth = torch.ones(16, 16)
    plain = augment(depth, masks, generator=torch.Generator().manual_seed(3))
    off = augment(depth, masks, generator=torch.Generator().manual_seed(3), occlusion=0.0)
    assert torch.equal(plain[0], off[0]) and torch.equal(plain[1], off[1])
    # off draws nothing more: what follows on the generator is unchanged too
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    augment(depth, masks, generator=g1)
    augment(depth, masks, generator=g2, occlusion=0.0)
    assert torch.equal(torch.rand(4, generator=g1), torch.rand(4, generator=g2))
    for bad in ({"occlusion": 1.5}, {"occlusion": -0.1}, {"kept": (0.0, 0.5)},
                {"kept": (0.8, 0.5)}, {"kept": (0.5, 1.2)}):  # fmt: skip
        with pytest.raises(ValueRangeError):
            augment(depth, masks, generator=torch.Generator(), **bad)


@given(
    st.floats(0.0, 0.45),
    st.integers(0, 2**31 - 1),
    st.sampled_from([torch.float32, torch.float64]),
)
def test_jittered_boxes_stay_square_and_within_the_amount(amount, seed, dtype):
    g = torch.Generator().manual_seed(seed)
    box = torch.tensor([[10.0, 20.0, 50.0, 60.0], [0.0, 0.0, 8.0, 8.0]], dtype=dtype)
    out = jitter_boxes(box, amount, generator=g)
    side, new_side = box[:, 2] - box[:, 0], out[:, 2] - out[:, 0]
    tol = 1e-4 * side
    assert out.dtype == dtype
    assert torch.allclose(new_side, out[:, 3] - out[:, 1], atol=1e-4)
    assert ((new_side - side).abs() <= amount * side + tol).all()
    shift = (out[:, :2] + out[:, 2:]) / 2 - (box[:, :2] + box[:, 2:]) / 2
    assert (shift.abs() <= amount * side[:, None] + tol[:, None]).all()


def test_zero_jitter_is_the_identity_and_bad_amounts_fail():
    box = torch.tensor([[1.0, 2.0, 5.0, 6.0]])
    assert torch.equal(jitter_boxes(box, 0.0), box)
    with pytest.raises(ValueRangeError):
        jitter_boxes(box, 0.5)


def test_crop_jitter_changes_appearance_not_geometry(tiny_model, scene):
    image = ImageInstances(scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 1])
    plain = tiny_model.observe(image, generator=torch.Generator().manual_seed(0))
    jittered = tiny_model.observe(
        image, generator=torch.Generator().manual_seed(0), crop_jitter=0.2
    )
    assert torch.equal(plain.points, jittered.points)
    assert torch.equal(plain.geometric, jittered.geometric)
    assert not torch.allclose(plain.appearance, jittered.appearance)


def test_dense_cap_keeps_valid_observed_points(tiny_model, scene):
    cap = tiny_model.config.num_points
    config = tiny_model.config
    image = ImageInstances(scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 1])
    try:
        tiny_model.config = config.replace(dense_points=cap)
        obs = tiny_model.observe(image, generator=torch.Generator().manual_seed(1))
    finally:
        tiny_model.config = config
    assert obs.valid.all() and obs.mask.sum(1).min() >= 0.8 * cap
    dense = backproject_depth(scene["depth"].expand(2, -1, -1), scene["K"], scene["masks"])
    for b in range(2):  # every kept point is one of the instance's back-projected points
        kept, cloud = obs.points[b][obs.mask[b]], dense.points[b][dense.mask[b]]
        d = torch.cdist(kept, cloud, compute_mode="donot_use_mm_for_euclid_dist")
        assert d.min(dim=1).values.max() < 1e-6
    with pytest.raises(ValueRangeError):
        config.replace(dense_points=cap - 1)


def test_the_training_set_keeps_the_maps_of_symmetric_objects_only(tiny_model, tmp_path):
    from poseflow.data.demo_objects import demo_objects
    from poseflow.data.synthetic import generate_dataset
    from poseflow.models.inputs import equivalent_maps
    from poseflow.models.training import build_training_set

    root = generate_dataset(
        tmp_path / "ds", num_train_images=1, num_test_images=0, width=160, height=120,
        seed=2, progress=False,
    )  # fmt: skip
    (box,) = demo_objects(num_points=64, names=["labelled_box"], geometric_symmetries=True)
    assert len(box.symmetries) == 4  # the identity and three half turns
    kwargs = {"max_images": 1, "progress": False}
    plain = build_training_set(tiny_model, root, **kwargs)
    asymmetric = build_training_set(tiny_model, root, symmetries={1: torch.eye(4)[None]}, **kwargs)
    symmetric = build_training_set(tiny_model, root, symmetries={1: box.symmetries}, **kwargs)
    assert "equivalents" not in plain.tensors and "equivalents" not in asymmetric.tensors
    assert torch.equal(plain.tensors["x_1"], symmetric.tensors["x_1"])
    maps = symmetric.tensors["equivalents"]
    assert maps.shape == (len(symmetric), 4, 3, 4) and maps.dtype == torch.float32
    expected = equivalent_maps(box.symmetries, tiny_model.objects[1].diameter / 2).float()
    assert torch.allclose(maps, expected.expand_as(maps))
    assert set(symmetric[0]) == {*plain[0], "equivalents"}  # what the trainer's batches hold
    import copy

    from poseflow.flows import TrainConfig
    from poseflow.models.training import train

    config = TrainConfig(
        steps=2, batch_size=len(symmetric), warmup_steps=1, progress=False, ema_decay=None
    )
    metrics = train(copy.deepcopy(tiny_model), symmetric, config=config, device="cpu")
    assert torch.isfinite(torch.tensor(metrics["loss"]))


def test_the_training_set_is_the_same_from_any_number_of_workers(tiny_model, tmp_path):
    from poseflow.data.synthetic import generate_dataset
    from poseflow.models.training import build_training_set

    root = generate_dataset(
        tmp_path / "ds", num_train_images=3, num_test_images=0, width=160, height=120,
        seed=4, progress=False,
    )  # fmt: skip
    kwargs = {"copies": 2, "occlusion": 0.5, "progress": False}
    one = build_training_set(tiny_model, root, workers=1, **kwargs)
    two = build_training_set(tiny_model, root, workers=2, **kwargs)
    other_seed = build_training_set(tiny_model, root, workers=1, seed=1, **kwargs)
    assert len(one) > 3  # several instances of several images, in two copies
    assert one.tensors.keys() == two.tensors.keys()
    for k, v in one.tensors.items():
        assert torch.equal(v, two.tensors[k]), k
    # the augmentations and samplings follow the seed
    assert any(not torch.equal(v, other_seed.tensors[k]) for k, v in one.tensors.items())
    with pytest.raises(ValueRangeError):
        build_training_set(tiny_model, root, workers=0, **kwargs)


def test_a_model_cannot_teach_itself(tiny_model) -> None:
    from poseflow.models.training import train

    with pytest.raises(ValueRangeError, match="another model"):
        train(tiny_model, None, teacher=tiny_model)
