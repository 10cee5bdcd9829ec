"""Tests of PoseVerifier on rendered scenes of a textured box."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from poseflow.data import ImageInstances
from poseflow.data.demo_objects import demo_mesh
from poseflow.data.objects import ObjectModel
from poseflow.errors import ShapeError, ValueRangeError
from poseflow.geometry.se3 import axis_angle_to_rotation, rotation_angle_error
from poseflow.render import Light, Renderer
from poseflow.verify import (
    PoseVerifier,
    VerifierConfig,
)

K = torch.tensor([[320.0, 0.0, 79.5], [0.0, 320.0, 59.5], [0.0, 0.0, 1.0]])
W, H = 160, 120
# the first pass alone: the global search of low scores and the polish are tested on their own
CONFIG = VerifierConfig(
    num_points=2048,
    crop_size=48,
    coarse_crop_size=24,
    turn_steps=4,
    search_below=0.0,
    polish_levels=0,
)


def half_turn(axis: list[float]) -> torch.Tensor:
    T = torch.eye(4)
    T[:3, :3] = axis_angle_to_rotation(torch.tensor(axis), torch.tensor(math.pi))
    return T


def box_pose(x: float = 0.0) -> torch.Tensor:
    T = torch.eye(4)
    T[:3, :3] = axis_angle_to_rotation(torch.tensor([1.0, 0.3, 0.0]), torch.tensor(0.45))
    T[:3, 3] = torch.tensor([x, 0.0, 0.55])
    return T


@pytest.fixture(scope="module")
def box() -> ObjectModel:
    return ObjectModel.from_mesh(demo_mesh("labelled_box"), num_points=256)


@pytest.fixture(scope="module")
def verifier(box: ObjectModel) -> PoseVerifier:
    v = PoseVerifier(CONFIG)
    v.prepare(1, box)
    return v


@pytest.fixture(scope="module")
def scene(box: ObjectModel) -> dict[str, torch.Tensor]:
    """One image of the box: colour in [0, 1] (3, H, W), depth (H, W), mask (1, H, W)."""
    light = Light(direction=(0.3, -0.4, -1.0), ambient=0.4, diffuse=0.6)
    out = Renderer([box.mesh]).render(box_pose()[None], K, W, H, light=light)
    rgb = out.rgb.permute(2, 0, 1).float() / 255.0
    return {"rgb": rgb, "depth": out.depth, "masks": out.masks_visible}


def is_at(pose: torch.Tensor, truth: torch.Tensor) -> bool:
    """``pose`` within 3 degrees and 3 mm of ``truth``."""
    angle = float(rotation_angle_error(pose[:3, :3], truth[:3, :3]))
    return angle < 3.0 and float((pose[:3, 3] - truth[:3, 3]).norm()) < 0.003


def one_box(scene: dict[str, torch.Tensor]) -> ImageInstances:
    """The scene's image and its one instance, the box (object 1)."""
    return ImageInstances(scene["rgb"], scene["depth"], K, scene["masks"], [1])


def test_prepare_finds_the_box_flips(verifier: PoseVerifier) -> None:
    cand = verifier.objects[1].candidates
    angles = rotation_angle_error(torch.eye(3), cand[:, :3, :3])
    assert (angles > 179).sum() >= 3  # the three half-turns of a box
    assert verifier.prepare(1, verifier.objects[1]) is verifier.objects[1]  # cached by id


def test_exact_flip_is_told_apart_by_appearance_not_depth(
    verifier: PoseVerifier, scene: dict[str, torch.Tensor]
) -> None:
    true = box_pose()
    flips = torch.stack([true @ half_turn(a) for a in ([0, 0, 1.0], [1.0, 0, 0], [0, 1.0, 0])])
    hyps = torch.cat((true[None], flips))[None]  # (1, 4, 4, 4)
    s = verifier.score(one_box(scene), hyps)
    assert s.valid.all()
    # geometry cannot tell: each flip fits depth and silhouette as well as the truth
    assert (s.depth[0, 1:] - s.depth[0, 0]).abs().max() < 0.03
    assert (s.silhouette[0, 1:] - s.silhouette[0, 0]).abs().max() < 0.03
    # the print can
    assert s.appearance[0, 0] > 0.3
    assert (s.appearance[0, 0] - s.appearance[0, 1:]).min() > 0.1
    assert int(s.total[0].argmax()) == 0

    # a flipped estimate is corrected, by appearance only
    flipped = flips[:1]
    out = verifier.verify(one_box(scene), flipped)
    assert int(out.chosen[0]) != 0
    assert float(rotation_angle_error(out.poses[0, :3, :3], true[:3, :3])) < 3.0
    assert float((out.poses[0, :3, 3] - true[:3, 3]).norm()) < 0.003
    depth_only = PoseVerifier(VerifierConfig(**{**CONFIG.to_dict(), "appearance_weight": 0.0}))
    depth_only.objects = verifier.objects
    kept = depth_only.verify(one_box(scene), flipped)
    assert int(kept.chosen[0]) == 0  # the flip stays (refined by ICP, so not bit-equal)
    assert float(rotation_angle_error(kept.poses[0, :3, :3], flipped[0, :3, :3])) < 1.0


def test_right_estimate_is_kept(verifier: PoseVerifier, scene: dict[str, torch.Tensor]) -> None:
    true = box_pose()[None]
    args = (one_box(scene), true)
    out = verifier.verify(*args)
    assert int(out.chosen[0]) == 0 and bool(out.valid[0])
    # refined with the candidates by the same ICP: it stays where it was, within the sampling
    assert float(rotation_angle_error(out.poses[0, :3, :3], true[0, :3, :3])) < 1.0
    assert float((out.poses[0, :3, 3] - true[0, :3, 3]).norm()) < 0.0035
    assert 0.5 < float(out.scores[0]) <= 1.0
    as_given = PoseVerifier(VerifierConfig(**{**CONFIG.to_dict(), "refine_estimate": False}))
    as_given.objects = verifier.objects
    kept = as_given.verify(*args)
    assert int(kept.chosen[0]) == 0 and torch.equal(kept.poses, true)


def test_an_estimate_off_by_millimetres_is_refined(
    verifier: PoseVerifier, scene: dict[str, torch.Tensor]
) -> None:
    true = box_pose()
    nudged = true.clone()
    nudged[:3, 3] += torch.tensor([0.004, -0.003, 0.005])
    out = verifier.verify(one_box(scene), nudged[None])
    assert int(out.chosen[0]) == 0
    assert float((out.poses[0, :3, 3] - true[:3, 3]).norm()) < 0.0035
    torch.testing.assert_close(out.hypotheses[0, 0], out.poses[0])


@settings(deadline=None, max_examples=6)
@given(
    seed=st.integers(0, 2**31 - 1),
    double=st.booleans(),
    angle=st.floats(0.0, 3.0),
    shift=st.floats(0.002, 0.008),
)
def test_polish_moves_a_pose_off_by_millimetres_back(
    verifier: PoseVerifier,
    scene: dict[str, torch.Tensor],
    seed: int,
    double: bool,
    angle: float,
    shift: float,
) -> None:
    dtype = torch.float64 if double else torch.float32
    g = torch.Generator().manual_seed(seed)
    true = box_pose().to(dtype)
    axis, direction = torch.randn(2, 3, generator=g, dtype=dtype)
    off = true.clone()
    off[:3, :3] = (
        axis_angle_to_rotation(axis / axis.norm(), torch.tensor(math.radians(angle))).to(dtype)
        @ true[:3, :3]
    )
    off[:3, 3] += shift * direction / direction.norm()
    image = ImageInstances(
        scene["rgb"].to(dtype), scene["depth"].to(dtype), K.to(dtype), scene["masks"], [1]
    )
    polisher = PoseVerifier(VerifierConfig(**{**CONFIG.to_dict(), "polish_levels": 4}))
    polisher.objects = verifier.objects
    polished, total = polisher.polish(image, off[None])
    assert polished.dtype == dtype and total.dtype == dtype
    before = polisher.score(image, off[None, None]).total[0, 0]
    assert float(total[0]) >= float(before)  # a move is taken only where it scores higher
    boxes = polisher.crop_boxes(off[None], [1], image.K, image.masks)  # the crop of the search
    # scored beside the starting pose there, alone here: float32 rounds the two batches apart
    torch.testing.assert_close(
        total,
        polisher.score(image, polished[:, None], boxes=boxes).total[:, 0],
        atol=1e-9 if double else 1e-3,  # float32 sums over the crop: ~3e-4 apart seen
        rtol=0,
    )
    # one pixel of the 48-pixel crop is about 4 mm on this 15 cm box
    assert float((polished[0, :3, 3] - true[:3, 3]).norm()) < 0.003
    # and turns it by at most about a pixel at the box's corners (4 mm at 7.5 cm) beyond where
    # it was: the turn a pixel of this crop can show
    assert float(rotation_angle_error(polished[0, :3, :3], true[:3, :3])) < angle + 3.5
    R = polished[0, :3, :3]
    torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=dtype))


def test_polish_off_or_unscorable_leaves_the_pose(
    verifier: PoseVerifier, scene: dict[str, torch.Tensor]
) -> None:
    off = box_pose()
    off[:3, 3] += 0.005
    behind = box_pose()
    behind[2, 3] = -0.5
    poses = torch.stack((off, behind))
    image = ImageInstances(
        scene["rgb"], scene["depth"], K, scene["masks"].expand(2, -1, -1), [1, 1]
    )
    unchanged, _ = verifier.polish(image, poses)  # CONFIG: polish_levels = 0
    assert torch.equal(unchanged, poses)
    polisher = PoseVerifier(VerifierConfig(**{**CONFIG.to_dict(), "polish_levels": 2}))
    polisher.objects = verifier.objects
    polished, total = polisher.polish(image, poses)
    assert torch.equal(polished[1], behind) and total[1] == -torch.inf
    assert not torch.equal(polished[0], off) and torch.isfinite(total[0])


def test_verify_polishes_the_chosen_pose(
    verifier: PoseVerifier, scene: dict[str, torch.Tensor]
) -> None:
    true = box_pose()
    nudged = true.clone()
    nudged[:3, :3] = (
        axis_angle_to_rotation(torch.tensor([0.0, 1.0, 0.0]), torch.tensor(0.05)) @ (true[:3, :3])
    )
    nudged[:3, 3] += torch.tensor([0.004, -0.003, 0.0])
    polisher = PoseVerifier(VerifierConfig(**{**CONFIG.to_dict(), "polish_levels": 4}))
    polisher.objects = verifier.objects
    plain = verifier.verify(one_box(scene), nudged[None])
    polished = polisher.verify(one_box(scene), nudged[None])
    torch.testing.assert_close(polished.hypotheses, plain.hypotheses)  # the same contest
    assert int(polished.chosen[0]) == int(plain.chosen[0])
    again, total = polisher.polish(one_box(scene), plain.poses)
    torch.testing.assert_close(polished.poses, again)
    torch.testing.assert_close(polished.scores, total.clamp(0, 1))
    assert float(polished.scores[0]) >= float(plain.scores[0]) - 0.02  # another crop


def test_global_brightness_and_colour_change_changes_nothing(
    verifier: PoseVerifier, scene: dict[str, torch.Tensor]
) -> None:
    hyps = torch.stack((box_pose(), box_pose() @ half_turn([0, 0, 1.0])))[None]
    ref = verifier.score(one_box(scene), hyps)
    for gain in ([0.5, 0.5, 0.5], [1.3, 0.9, 0.6], [0.2, 0.35, 0.3]):
        rgb = scene["rgb"] * torch.tensor(gain).reshape(3, 1, 1)
        got = verifier.score(ImageInstances(rgb, scene["depth"], K, scene["masks"], [1]), hyps)
        torch.testing.assert_close(got.appearance, ref.appearance, atol=1e-4, rtol=0)
        torch.testing.assert_close(got.total, ref.total, atol=1e-4, rtol=0)


def test_empty_mask_and_missing_depth_give_flagged_finite_scores(
    verifier: PoseVerifier, scene: dict[str, torch.Tensor]
) -> None:
    hyps = box_pose()[None, None].repeat(2, 2, 1, 1)
    masks = scene["masks"].repeat(2, 1, 1)
    masks[1] = False
    s = verifier.score(ImageInstances(scene["rgb"], scene["depth"], K, masks, [1, 1]), hyps)
    assert s.valid[0].all() and not s.valid[1].any()
    nan_depth = torch.full_like(scene["depth"], float("nan"))
    for depth in (torch.zeros_like(scene["depth"]), nan_depth):
        s = verifier.score(ImageInstances(scene["rgb"], depth, K, masks, [1, 1]), hyps)
        assert not s.valid.any()
        assert all(torch.isfinite(getattr(s, f)).all() for f in ("total", "depth", "appearance"))
        out = verifier.verify(ImageInstances(scene["rgb"], depth, K, masks, [1, 1]), hyps[:, 0])
        assert not out.valid.any() and (out.scores == 0).all()
        assert torch.equal(out.poses, hyps[:, 0])


def test_behind_the_camera_is_flagged(
    verifier: PoseVerifier, scene: dict[str, torch.Tensor]
) -> None:
    behind = box_pose()
    behind[2, 3] = -0.5
    s = verifier.score(one_box(scene), behind[None, None])
    assert not s.valid.any() and torch.isfinite(s.total).all()


def test_batched_equals_per_instance(box: ObjectModel, verifier: PoseVerifier) -> None:
    poses = torch.stack((box_pose(-0.07), box_pose(0.07) @ half_turn([0, 1.0, 0])))
    out = Renderer([box.mesh]).render(poses, K, W, H, object_ids=[0, 0])
    rgb = out.rgb.permute(2, 0, 1).float() / 255.0
    masks = out.masks_visible
    hyps = torch.stack((poses, poses @ half_turn([0, 0, 1.0])), dim=1)  # (2, 2, 4, 4)
    both = verifier.score(ImageInstances(rgb, out.depth, K, masks, [1, 1]), hyps)
    for b in range(2):
        one = verifier.score(
            ImageInstances(rgb, out.depth, K, masks[b : b + 1], [1]), hyps[b : b + 1]
        )
        torch.testing.assert_close(one.total[0], both.total[b])
        torch.testing.assert_close(one.evidence[0], both.evidence[b])
    assert (both.total[:, 0] > both.total[:, 1]).all()


def test_expand_pads_and_refine_snaps_back(
    verifier: PoseVerifier, scene: dict[str, torch.Tensor]
) -> None:
    hyp = verifier.expand(box_pose()[None], [1])
    C = len(verifier.objects[1].candidates)
    assert hyp.poses.shape == (1, 1 + C, 4, 4) and hyp.mask.all()
    torch.testing.assert_close(hyp.poses[0, 0], box_pose())
    # a slightly wrong pose is pulled back onto the observed surface
    nudged = box_pose()
    nudged[:3, 3] += torch.tensor([0.004, -0.003, 0.005])
    cloud, mask = verifier.observed_cloud(scene["depth"], K, scene["masks"])
    refined = verifier.refine(nudged[None, None], [1], cloud, mask)
    error = refined[0, 0, :3, 3] - box_pose()[:3, 3]
    # the model is sampled every few mm: ICP lands within that, from 7 mm off
    assert float(error.norm()) < 0.0035 and abs(float(error[2])) < 0.001


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cpu_and_cuda_agree(verifier: PoseVerifier, scene: dict[str, torch.Tensor]) -> None:
    hyps = torch.stack((box_pose(), box_pose() @ half_turn([1.0, 0, 0])))[None].double()
    args = (scene["rgb"].double(), scene["depth"].double(), K.double(), scene["masks"], [1])
    cpu = verifier.score(ImageInstances(*args), hyps)
    on_gpu = ImageInstances(*(a.cuda() if isinstance(a, torch.Tensor) else a for a in args))
    gpu = verifier.score(on_gpu, hyps.cuda())
    for f in ("depth", "silhouette", "appearance", "total"):
        torch.testing.assert_close(getattr(gpu, f).cpu(), getattr(cpu, f), atol=1e-6, rtol=0)
    torch.testing.assert_close(gpu.valid.cpu(), cpu.valid)


def test_errors(verifier: PoseVerifier, scene: dict[str, torch.Tensor]) -> None:
    hyps = box_pose()[None, None]
    with pytest.raises(ValueRangeError):
        verifier.score(ImageInstances(scene["rgb"], scene["depth"], K, scene["masks"], [7]), hyps)
    with pytest.raises(ShapeError):
        verifier.score(
            ImageInstances(scene["rgb"], scene["depth"], K, scene["masks"], [1, 1]), hyps
        )
    with pytest.raises(ShapeError):
        verifier.score(
            ImageInstances(scene["rgb"], scene["depth"][:-1], K, scene["masks"], [1]), hyps
        )
    with pytest.raises(ValueRangeError):
        verifier.score(one_box(scene), hyps, crop_size=20)
    with pytest.raises(ValueRangeError):
        PoseVerifier(config={"crop_size": 64})  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "field",
    [
        {"crop_size": 60},
        {"appearance_window": 4},
        {"significance": 0.0},
        {"depth_tolerance": -1.0},
        {"icp_distances": (0.02, 0.1)},
        {"coarse_crop_size": 128},
        {"depth_weight": 0.0, "silhouette_weight": 0.0, "appearance_weight": 0.0},
        {"num_points": True},
        {"refine_estimate": 1},
        {"search_below": True},
        {"search_below": 1.5},
        {"search_top_k": 0},
        {"expand_top_k": 0},
    ],
)
def test_config_rejects_bad_values(field: dict[str, object]) -> None:
    with pytest.raises(ValueRangeError):
        VerifierConfig(**field)  # type: ignore[arg-type]


def test_config_round_trips_and_rejects_unknown_names() -> None:
    cfg = VerifierConfig(significance=0.02, icp_distances=(0.2, 0.05))
    assert VerifierConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueRangeError):
        VerifierConfig.from_dict({"no_such_field": 1})


def test_object_without_near_symmetries_is_scored_alone() -> None:
    import open3d as o3d

    a = o3d.geometry.TriangleMesh.create_box(0.08, 0.02, 0.02)
    b = o3d.geometry.TriangleMesh.create_box(0.02, 0.05, 0.02)
    c = o3d.geometry.TriangleMesh.create_box(0.01, 0.01, 0.03).translate((0.06, 0.0, 0.02))
    part = ObjectModel.from_mesh((a + b + c).translate((-0.04, -0.025, -0.025)), num_points=64)
    v = PoseVerifier(VerifierConfig(**{**CONFIG.to_dict(), "min_self_overlap": 0.9}))
    assert len(v.prepare(2, part).candidates) == 0
    out = Renderer([part.mesh]).render(box_pose()[None], K, W, H)
    rgb = out.rgb.permute(2, 0, 1).float() / 255.0
    result = v.verify(ImageInstances(rgb, out.depth, K, out.masks_visible, [2]), box_pose()[None])
    assert result.hypotheses.shape == (1, 1, 4, 4)
    assert int(result.chosen[0]) == 0 and bool(result.valid[0])
    # not 1: the splats also cover the edge pixels whose centre lies just outside the object
    assert float(result.score.depth[0, 0]) > 0.8 and float(result.score.silhouette[0, 0]) > 0.8


def test_extra_hypotheses_compete_with_the_near_symmetric_candidates(
    verifier: PoseVerifier, scene: dict[str, torch.Tensor]
) -> None:
    true = box_pose()
    off = true.clone()
    off[:3, 3] += torch.tensor([0.03, 0.0, 0.0])  # 3 cm off: no near-symmetry turns it right
    args = (one_box(scene), off[None])

    assert not is_at(verifier.verify(*args).poses[0], true)
    out = verifier.verify(*args, extra=true[None, None], extra_mask=torch.ones(1, 1, dtype=bool))
    assert int(out.chosen[0]) != 0 and is_at(out.poses[0], true)
    padded = verifier.verify(
        *args, extra=true[None, None], extra_mask=torch.zeros(1, 1, dtype=bool)
    )
    assert not is_at(padded.poses[0], true)  # a masked-out extra hypothesis is never chosen
    with pytest.raises(ShapeError):
        verifier.verify(*args, extra=true[None])


def test_hypotheses_the_coarse_grid_cannot_tell_apart_are_scored_once(
    box: ObjectModel, scene: dict[str, torch.Tensor]
) -> None:
    true, flipped = box_pose(), box_pose() @ half_turn([1.0, 0, 0])
    nudged = true.clone()
    nudged[:3, 3] += 0.001  # 1.7 mm: far below a coarse pixel (1.2 x 0.16 m / 24 = 8 mm)
    apart = true.clone()
    apart[:3, 3] += torch.tensor([0.02, 0.0, 0.0])  # 2 cm: apart
    extra = torch.stack((true, nudged, apart, flipped))[None]  # (1, 4, 4, 4)
    scored = []

    class Recording(PoseVerifier):
        def score(self, image, hypotheses, hypothesis_mask=None, **kwargs):
            scored.append(hypothesis_mask.clone())
            return super().score(image, hypotheses, hypothesis_mask, **kwargs)

    verifier = Recording(CONFIG)
    verifier.prepare(1, box)
    image = one_box(scene)
    ranked = verifier.rank_hypotheses(image, flipped[None], extra=extra)
    assert scored[0].tolist() == [[True, True, False, True, False]]  # the coarse contest
    assert torch.equal(ranked.poses[0, 0], true)  # the first of the duplicates is kept
    out = verifier.verify(image, flipped[None], extra=extra)
    # verify expands the flipped estimate with the box's half-turns first: one of them is the
    # truth, so of the extras only the one 2 cm off is new
    assert scored[1][0, -4:].tolist() == [False, False, True, False]
    assert float(rotation_angle_error(out.poses[0, :3, :3], true[:3, :3])) < 1.0


def test_ranking_makes_the_best_hypothesis_the_estimate(
    verifier: PoseVerifier, scene: dict[str, torch.Tensor]
) -> None:
    true, flipped = box_pose(), box_pose() @ half_turn([1.0, 0, 0])
    off = box_pose(0.02)  # 2 cm off
    masks = scene["masks"].repeat(2, 1, 1)
    poses = torch.stack((flipped, flipped))
    extra = torch.stack((off, true))[None].repeat(2, 1, 1, 1)  # (2, 2, 4, 4): the truth second
    image = ImageInstances(scene["rgb"], scene["depth"], K, masks, [1, 1])
    ranked = verifier.rank_hypotheses(
        image, poses, extra=extra, estimated=torch.tensor([True, False])
    )
    assert ranked.poses.shape == (2, 3, 4, 4) and ranked.mask.tolist() == [
        [True] * 3,
        [False, True, True],
    ]
    assert torch.equal(ranked.poses[0, 0], true) and torch.equal(ranked.poses[0, 2], flipped)
    assert torch.equal(ranked.poses[1], torch.cat((poses[1:], extra[1])))  # no estimate: left
    # the incumbent a ranking keeps is the estimate verify then holds its contest around
    out = verifier.verify(image, ranked.poses[:, 0], extra=ranked.poses[:, 1:])
    assert float(rotation_angle_error(out.poses[0, :3, :3], true[:3, :3])) < 1.0
    no_extra = verifier.rank_hypotheses(image, poses, extra=extra[:, :0])
    assert torch.equal(no_extra.poses, poses[:, None]) and no_extra.mask.all()


def test_expanding_the_best_hypotheses_reaches_a_near_symmetry_of_the_second(
    box: ObjectModel, scene: dict[str, torch.Tensor]
) -> None:
    """``expand_top_k=2``: the second hypothesis's flips are candidates too.

    The estimate is 3 cm off (none of its flips is right) and the other hypothesis is the truth
    flipped end for end: only its own flip is the truth.
    """
    true, off = box_pose(), box_pose(0.03)
    flipped_true = true @ half_turn([1.0, 0, 0])
    image = one_box(scene)

    one = PoseVerifier(CONFIG)
    one.prepare(1, box)
    two = PoseVerifier(replace(CONFIG, expand_top_k=2))
    two.prepare(1, box)
    extra = flipped_true[None, None]
    assert not is_at(one.verify(image, off[None], extra=extra).poses[0], true)
    assert is_at(two.verify(image, off[None], extra=extra).poses[0], true)
    # its ranking orders every hypothesis by the coarse score, the best first
    far = box_pose(0.06)
    hyps = torch.stack((off, far, flipped_true, true))[None]  # (1, 4, 4, 4)
    ranked = two.rank_hypotheses(image, hyps[:, 0], extra=hyps[:, 1:])
    assert torch.equal(ranked.poses[0, 0], true)
    boxes = two.crop_boxes(hyps[:, 0], [1], K, image.masks)
    coarse = two.score(image, ranked.poses, boxes=boxes, crop_size=CONFIG.coarse_crop_size).total
    assert (coarse[0, :-1] >= coarse[0, 1:]).all(), coarse
    assert ranked.mask.all()


def test_instances_without_an_estimate_come_back_unverified(
    verifier: PoseVerifier, scene: dict[str, torch.Tensor]
) -> None:
    flipped = box_pose() @ half_turn([1.0, 0, 0])
    poses = torch.stack((flipped, flipped))
    masks = scene["masks"].repeat(2, 1, 1)
    args = (ImageInstances(scene["rgb"], scene["depth"], K, masks, [1, 1]), poses)
    out = verifier.verify(*args, estimated=torch.tensor([False, True]))
    alone = verifier.verify(
        ImageInstances(scene["rgb"], scene["depth"], K, masks[1:], [1]), poses[1:]
    )
    assert out.valid.tolist() == [False, True] and float(out.scores[0]) == 0.0
    assert int(out.chosen[0]) == 0 and int(out.chosen[1]) == int(alone.chosen[0]) != 0
    assert torch.equal(out.poses[0], poses[0])
    torch.testing.assert_close(out.poses[1], alone.poses[0])
    torch.testing.assert_close(out.scores[1], alone.scores[0])
    torch.testing.assert_close(out.score.total[1], alone.score.total[0])
    none = verifier.verify(*args, estimated=torch.zeros(2, dtype=torch.bool))
    assert not none.valid.any() and (none.scores == 0).all() and torch.equal(none.poses, poses)
    assert none.hypotheses.shape == (2, 1, 4, 4) and none.score.evidence.shape[:2] == (2, 1)


def test_search_finds_a_pose_turned_far_from_every_candidate(
    verifier: PoseVerifier, scene: dict[str, torch.Tensor]
) -> None:
    true = box_pose()
    turn = torch.eye(4)
    turn[:3, :3] = axis_angle_to_rotation(torch.tensor([0.3, 1.0, 0.2]), torch.tensor(2.0))
    wrong = (true @ turn)[None]
    args = (one_box(scene), wrong)
    plain = verifier.verify(*args)
    assert float(rotation_angle_error(plain.poses[0, :3, :3], true[:3, :3])) > 30
    # the turns alone (a slide of the box flipped end for end, placed to the millimetre by ICP,
    # outscores the right turn that ICP leaves 15 degrees off on this coarse a crop)
    turning = {**CONFIG.to_dict(), "search_below": 1.0, "search_slides": ()}
    searching = PoseVerifier(VerifierConfig(**turning))
    searching.objects = verifier.objects
    out = searching.verify(*args)
    H = plain.hypotheses.shape[1]
    assert out.hypotheses.shape[1] == H + CONFIG.search_top_k
    assert int(out.chosen[0]) >= H  # one of the searched turns
    torch.testing.assert_close(out.hypotheses[0, out.chosen[0]], out.poses[0])
    # ICP from the nearest turn lands in the truth's basin (the box's faces let it slide a bit)
    assert float(rotation_angle_error(out.poses[0, :3, :3], true[:3, :3])) < 20.0
    assert float(out.scores[0]) > float(plain.scores[0]) + 0.1
    # a right pose survives its own search
    kept = searching.verify(one_box(scene), true[None])
    assert int(kept.chosen[0]) < H
    assert float(rotation_angle_error(kept.poses[0, :3, :3], true[:3, :3])) < 1.0


def test_search_pads_the_instances_it_does_not_search(
    verifier: PoseVerifier, scene: dict[str, torch.Tensor]
) -> None:
    config = VerifierConfig(**{**CONFIG.to_dict(), "search_below": 1e-3})  # searches nothing
    quiet = PoseVerifier(config)
    quiet.objects = verifier.objects
    args = (one_box(scene), box_pose()[None])
    out, plain = quiet.verify(*args), verifier.verify(*args)
    H = plain.hypotheses.shape[1]
    assert out.hypotheses.shape[1] == H + 2 * config.search_top_k
    assert torch.equal(out.poses, plain.poses) and torch.equal(out.chosen, plain.chosen)
    assert not out.score.valid[:, H:].any() and torch.equal(out.score.total[:, :H],
                                                             plain.score.total)  # fmt: skip


def test_search_slides_a_bar_seen_in_part_to_where_it_is() -> None:
    import open3d as o3d

    bar = o3d.geometry.TriangleMesh.create_box(0.2, 0.03, 0.03).translate((-0.1, -0.015, -0.015))
    bar.paint_uniform_color((0.8, 0.5, 0.2))
    cover = o3d.geometry.TriangleMesh.create_box(0.12, 0.12, 0.01).translate((0.0, -0.06, 0.0))
    cover.paint_uniform_color((0.2, 0.3, 0.8))
    model = ObjectModel.from_mesh(bar, num_points=256)
    true = torch.eye(4)
    true[:3, :3] = axis_angle_to_rotation(torch.tensor([0.2, 1.0, 0.3]), torch.tensor(0.3))
    true[:3, 3] = torch.tensor([0.0, 0.0, 0.55])
    front = torch.eye(4)
    front[:3, 3] = torch.tensor([0.0, 0.0, 0.42])  # hides the bar's right half
    out = Renderer([bar, cover]).render(torch.stack((true, front)), K, W, H)
    visible = out.masks_visible[:1]
    assert 0.3 < visible.sum() / out.masks_full[0].sum() < 0.7
    image = ImageInstances(out.rgb.permute(2, 0, 1).float() / 255.0, out.depth, K, visible, [1])
    # placed centred on what is seen: a quarter of its length along its axis
    slid = true.clone()
    slid[:3, 3] -= 0.05 * true[:3, 0]
    base = {**CONFIG.to_dict(), "search_below": 1.0}
    errors = {}
    for slides in ((), (0.25, 0.5)):
        v = PoseVerifier(VerifierConfig(**{**base, "search_slides": slides}))
        v.prepare(1, model)
        pose = v.verify(image, slid[None]).poses[0]
        errors[slides] = float((pose[:3, 3] - true[:3, 3]).norm())
    assert errors[()] > 0.03  # turns and ICP leave it where it was
    assert errors[(0.25, 0.5)] < 0.01


def test_search_of_objects_with_different_turn_counts_keeps_the_invariants(
    verifier: PoseVerifier, scene: dict[str, torch.Tensor]
) -> None:
    import dataclasses

    box = verifier.objects[1]
    R = axis_angle_to_rotation(torch.tensor([1.0, 2.0, 3.0]), torch.tensor(0.5))
    turned = dataclasses.replace(  # the same box in a model frame off its principal axes
        box, points=box.points @ R.T, normals=box.normals @ R.T, centroid=box.centroid @ R.T
    )
    config = VerifierConfig(**{**CONFIG.to_dict(), "search_below": 1.0, "search_top_k": 30})
    v = PoseVerifier(config)
    v.objects = {1: box, 2: turned}
    wrong = box_pose() @ half_turn([0.0, 1.0, 0.0])
    masks = scene["masks"].repeat(2, 1, 1)
    image = ImageInstances(scene["rgb"], scene["depth"], K, masks, [1, 2])
    out = v.verify(image, torch.stack((wrong, wrong)))
    plain = verifier.verify(dataclasses.replace(image, obj_ids=[1, 1]), torch.stack((wrong, wrong)))
    H = plain.hypotheses.shape[1]
    assert out.hypotheses.shape == (2, H + 30 + 30, 4, 4)  # 30 turns, then 30 slides
    rows = torch.arange(2)
    assert torch.equal(out.poses, out.hypotheses[rows, out.chosen])
    chosen_total = out.score.total[rows, out.chosen].clamp(0, 1)
    torch.testing.assert_close(out.scores, torch.where(out.valid, chosen_total, 0.0))
    # the box has 23 turns and both have 12 slides: the rest of their columns are padding
    assert not out.score.valid[0, H + 23 : H + 30].any()
    assert not out.score.valid[:, H + 30 + 12 :].any()
    empty = v.search(
        ImageInstances(scene["rgb"], scene["depth"], K, masks[:0], []), torch.zeros(0, 4, 4)
    )
    assert empty.hypotheses.shape == (0, 61, 4, 4) and empty.poses.shape == (0, 4, 4)


def test_no_instances_give_empty_results_of_the_right_shapes(
    verifier: PoseVerifier, scene: dict[str, torch.Tensor]
) -> None:
    none = scene["masks"][:0]
    s = verifier.score(
        ImageInstances(scene["rgb"], scene["depth"], K, none, []), torch.zeros(0, 3, 4, 4)
    )
    g = (CONFIG.crop_size // CONFIG.block_size) ** 2
    assert s.total.shape == s.valid.shape == (0, 3) and s.evidence.shape == (0, 3, g)
    assert s.valid.dtype == torch.bool and len(s) == 0
    for estimated in (None, torch.zeros(0, dtype=torch.bool)):
        out = verifier.verify(
            ImageInstances(scene["rgb"], scene["depth"], K, none, []),
            torch.zeros(0, 4, 4),
            estimated=estimated,
        )
        assert out.poses.shape == (0, 4, 4) and out.scores.shape == out.valid.shape == (0,)
        assert out.chosen.dtype == torch.long and out.hypotheses.shape == (0, 1, 4, 4)
    with pytest.raises(ShapeError):  # still one id per instance
        verifier.verify(
            ImageInstances(scene["rgb"], scene["depth"], K, none, [1]), torch.zeros(0, 4, 4)
        )


def test_zero_hypotheses_per_instance_is_a_shape_error(
    verifier: PoseVerifier, scene: dict[str, torch.Tensor]
) -> None:
    with pytest.raises(ShapeError, match=r"\(1, 0, 4, 4\).*at least one hypothesis"):
        verifier.score(one_box(scene), torch.zeros(1, 0, 4, 4))
