import dataclasses
import json

import pytest
import torch

from poseflow.assets import DEMO_CHECKPOINT
from poseflow.data import ImageInstances
from poseflow.data.objects import ObjectModel, sample_surface
from poseflow.errors import CheckpointError, MissingWeightsError, ShapeError, ValueRangeError
from poseflow.eval.predict import PoseEstimate
from poseflow.eval.timing import StageTimer
from poseflow.geometry.se3 import rotation_angle_error, transform_points, translation_error
from poseflow.models import FunFlow6D, FunFlow6DConfig
from poseflow.models.verification import rank_estimate
from poseflow.verify import PoseVerifier, VerifierConfig


def two_boxes(scene) -> ImageInstances:
    """The scene's image and its two instances, both of object 1."""
    return ImageInstances(scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 1])


def test_observe_lifts_valid_clouds_with_features(tiny_model, scene):
    obs = tiny_model.observe(two_boxes(scene))
    n = tiny_model.config.num_points
    assert obs.points.shape == (2, n, 3) and obs.valid.all()
    assert obs.geometric.shape == (2, n, tiny_model.geometric_encoder.dim)
    assert obs.appearance.shape[:2] == (2, n)
    assert torch.allclose(obs.normals[obs.mask].norm(dim=-1), torch.ones(1), atol=1e-4)
    # the cleaned cloud the N points were sampled from travels along, for the verifier's ICP
    assert obs.cloud.shape[0] == 2 and (obs.cloud_mask.sum(1) >= obs.mask.sum(1)).all()
    for b in range(2):
        a, c = obs.points[b][obs.mask[b]], obs.cloud[b][obs.cloud_mask[b]]
        d = torch.cdist(a, c, compute_mode="donot_use_mm_for_euclid_dist")
        assert d.min(dim=1).values.max() == 0  # every sampled point is one of the cloud's


def test_flow_target_is_the_observed_cloud_in_the_canonical_frame(tiny_model, scene, box):
    obs = tiny_model.observe(two_boxes(scene))
    inputs = tiny_model.flow_inputs(obs, scene["poses"])
    n = tiny_model.config.num_points
    s = inputs.scale[:, None, None]
    canonical = inputs.x_1[:, n:] * s
    back = transform_points(scene["poses"], canonical)
    assert torch.allclose(back[obs.mask], obs.points[obs.mask], atol=1e-5)
    # ...and those canonical points lie on the model's surface.
    dense, _, _ = sample_surface(box.mesh, 20000, generator=torch.Generator().manual_seed(0))
    d = torch.cdist(canonical[obs.mask], torch.from_numpy(dense).float()).min(dim=1).values
    assert d.median() < 0.01 * box.diameter
    assert torch.equal(inputs.frozen_mask[:, :n], torch.ones(2, n, dtype=torch.bool))
    assert torch.allclose(inputs.x_1[:, :n], inputs.points[:, :n])


class _Oracle(torch.nn.Module):
    """A velocity net that knows the answer: v = (x_1 - x) / (1 - t) integrates to x_1."""

    def __init__(self, x_1):
        super().__init__()
        self.x_1 = x_1

    def forward(self, x, t, *, condition, mask=None, num_query=None):
        return (self.x_1 - x) / (1 - t)[:, None, None]


@pytest.mark.parametrize("solver", ["ransac", "svd"])
@pytest.mark.parametrize("polish", [0, 4])
def test_perfect_flow_gives_the_ground_truth_pose(tiny_model, scene, solver, polish):
    verifier = dataclasses.replace(tiny_model.config.verifier, polish_levels=polish)
    model = FunFlow6D(tiny_model.config.replace(pose_solver=solver, verifier=verifier))
    model.objects = tiny_model.objects
    model.verifier.objects = tiny_model.verifier.objects
    obs = model.observe(two_boxes(scene))
    model.net.dit = _Oracle(model.flow_inputs(obs, scene["poses"]).x_1)
    est = model.estimate(scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 1])
    assert est.valid.all() and (est.scores > 0.5).all()
    # ICP's fit of the depth is finer than a pixel of the verifier's 64-pixel grid (about 3 mm
    # on these boxes), where the polish places a pose
    limit = 1.0 if polish == 0 else 2.0
    assert (rotation_angle_error(est.poses, scene["poses"]) < limit).all()
    assert (translation_error(est.poses, scene["poses"]) < 0.002).all()


def test_untrained_model_returns_finite_flagged_poses(tiny_model, scene):
    est = tiny_model.estimate(
        scene["rgb"],
        scene["depth"],
        scene["K"],
        scene["masks"],
        torch.tensor([1, 1]),
        generator=torch.Generator().manual_seed(0),
    )
    assert est.poses.shape == (2, 4, 4) and torch.isfinite(est.poses).all()
    assert ((est.scores >= 0) & (est.scores <= 1)).all()


def test_bad_input(tiny_model, scene):
    with pytest.raises(ValueRangeError, match="not prepared"):
        tiny_model.observe(
            ImageInstances(scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 7])
        )
    with pytest.raises(ShapeError):
        tiny_model.observe(
            ImageInstances(scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1])
        )
    empty = torch.zeros_like(scene["masks"])
    est = tiny_model.estimate(scene["rgb"], scene["depth"], scene["K"], empty, [1, 1])
    assert not est.valid.any() and torch.isfinite(est.poses).all()


def test_intrinsics_as_lists_or_arrays_and_their_shape(tiny_model, scene):
    args = (scene["rgb"], scene["depth"])
    masks, ids = scene["masks"], [1, 1]

    def estimate(K):
        return tiny_model.estimate(*args, K, masks, ids, generator=torch.Generator().manual_seed(0))

    ref = estimate(scene["K"])
    for K in (scene["K"].tolist(), scene["K"].double().numpy(), scene["K"].reshape(9).tolist()):
        est = estimate(K)
        assert torch.equal(est.poses, ref.poses) and torch.equal(est.valid, ref.valid)
        obs = tiny_model.observe(ImageInstances(*args, K, masks, ids))
        assert obs.points.shape == (2, tiny_model.config.num_points, 3)
    for bad in (torch.eye(2), [[300.0, 0], [0, 300.0]], "K", [[1, 2, 3]] * 3 + [[4, 5, 6]]):
        with pytest.raises(ShapeError, match="K must be 9 numbers"):
            tiny_model.estimate(*args, bad, masks, ids)
        with pytest.raises(ShapeError, match="K must be 9 numbers"):
            tiny_model.observe(ImageInstances(*args, bad, masks, ids))
    with pytest.raises(ValueRangeError, match="transposed"):
        tiny_model.estimate(*args, scene["K"].T, masks, ids)


def test_no_masks_give_an_empty_estimate(tiny_model, scene):
    none = scene["masks"][:0]
    for K in (scene["K"], scene["K"].tolist()):
        est = tiny_model.estimate(scene["rgb"], scene["depth"], K, none, [])
        assert est.poses.shape == (0, 4, 4) and est.scores.shape == (0,)
        assert est.valid.shape == (0,) and est.valid.dtype == torch.bool
    obs = tiny_model.observe(
        ImageInstances(scene["rgb"], scene["depth"], scene["K"], none, torch.tensor([]))
    )
    n = tiny_model.config.num_points
    assert obs.points.shape == (0, n, 3) and obs.mask.shape == (0, n) and obs.valid.shape == (0,)
    assert obs.geometric.shape == (0, n, tiny_model.geometric_encoder.dim)
    assert obs.appearance.shape == (0, n, tiny_model.appearance_encoder.dim)


@pytest.mark.parametrize("verification", [False, True])
def test_a_pose_behind_the_camera_is_never_valid(tiny_model, scene, monkeypatch, verification):
    import poseflow.models.proposals as proposals
    import poseflow.models.verification as verification_module

    behind = torch.eye(4).repeat(2, 1, 1)
    behind[:, 2, 3] = torch.tensor([0.5, -0.5])
    flagged = PoseEstimate(behind, torch.full((2,), 0.9), torch.ones(2, dtype=torch.bool))
    if verification:
        monkeypatch.setattr(verification_module, "verify_estimate", lambda *a, **k: flagged)
    else:
        monkeypatch.setattr(proposals, "select_hypotheses", lambda *a, **k: flagged)
    config = tiny_model.config if verification else tiny_model.config.replace(verifier=None)
    model = FunFlow6D(config)
    model.objects, model.verifier = tiny_model.objects, tiny_model.verifier
    est = model.estimate(scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 1])
    assert est.valid.tolist() == [True, False] and est.scores.tolist() == pytest.approx([0.9, 0])


def test_save_load_round_trip(tiny_model, tmp_path):
    tiny_model.save(tmp_path / "ckpt")
    loaded = FunFlow6D.load(tmp_path / "ckpt")
    assert loaded.config == tiny_model.config
    for a, b in zip(tiny_model.net.state_dict().values(), loaded.net.state_dict().values()):
        assert torch.equal(a, b)
    with pytest.raises(MissingWeightsError):
        FunFlow6D.load(tmp_path / "nothing")


def test_a_damaged_checkpoint_is_a_checkpoint_error_naming_the_file(tiny_model, tmp_path):
    folder = tiny_model.save(tmp_path / "ckpt")
    weights = folder / "model.safetensors"
    whole = weights.read_bytes()
    for damaged in (whole[: len(whole) // 2], whole[:-1], b"\xff" * 64, b""):
        weights.write_bytes(damaged)
        with pytest.raises(CheckpointError, match=r"model\.safetensors is truncated") as err:
            FunFlow6D.load(folder)
        assert str(weights) in str(err.value)
    weights.write_bytes(whole)
    config = json.loads((folder / "config.json").read_text())
    for text in ("{", "[1, 2]", json.dumps({**config, "num_points": "many"})):
        (folder / "config.json").write_text(text)
        with pytest.raises(CheckpointError, match=r"config\.json"):
            FunFlow6D.load(folder)
    # weights of another network than the configuration describes
    (folder / "config.json").write_text(json.dumps(config))
    assert FunFlow6D.load(folder).config == tiny_model.config
    other = FunFlow6D(tiny_model.config.replace(feature_dim=16))
    other.save(tmp_path / "other")
    weights.write_bytes((tmp_path / "other" / "model.safetensors").read_bytes())
    with pytest.raises(CheckpointError, match=r"does not fit its config\.json"):
        FunFlow6D.load(folder)


def test_prepared_objects_are_cached(tiny_model, box, tmp_path):
    model = FunFlow6D(tiny_model.config)
    model.prepare_objects({1: box}, cache_dir=tmp_path, progress=False)
    again = FunFlow6D(tiny_model.config)
    again.prepare_objects({1: box}, cache_dir=tmp_path, progress=False)
    a, b = model.objects[1], again.objects[1]
    assert torch.equal(a.points, b.points) and torch.allclose(a.geometric, b.geometric)
    x = a.bank.pooled()
    assert torch.allclose(a.reducer.transform(x), b.reducer.transform(x), atol=1e-4)
    # the verifier's preparation sits beside the object's, in its own entry, and is read back
    (verifier_entry,) = (tmp_path / "obj_000001").glob("*/verifier.json")
    (object_entry,) = (tmp_path / "obj_000001").glob("*/object.json")
    assert verifier_entry.parent != object_entry.parent
    va, vb = model.verifier.objects[1], again.verifier.objects[1]
    assert torch.equal(va.points, vb.points) and torch.equal(va.candidates, vb.candidates)


def test_preparing_another_mesh_under_the_same_id_replaces_it_everywhere(tiny_model, box, tmp_path):
    larger = ObjectModel.from_mesh(box.mesh.scaled(1.5), num_points=1000)
    model = FunFlow6D(tiny_model.config)
    model.prepare_objects({1: box}, cache_dir=tmp_path, progress=False)
    model.prepare_objects({1: larger}, cache_dir=tmp_path, progress=False)
    assert model.objects[1].diameter == pytest.approx(larger.diameter)
    assert model.verifier.objects[1].diameter == pytest.approx(larger.diameter)
    folder = tmp_path / "obj_000001"
    assert len(list(folder.glob("*/object.json"))) == len(list(folder.glob("*/verifier.json"))) == 2
    # both meshes read their own entries back, the verifier's too
    again = FunFlow6D(tiny_model.config)
    again.prepare_objects({1: box}, cache_dir=tmp_path, progress=False)
    assert again.verifier.objects[1].diameter == pytest.approx(box.diameter)
    assert torch.equal(again.verifier.objects[1].points, tiny_model.verifier.objects[1].points)
    assert len(list(folder.glob("*/verifier.json"))) == 2


def test_noise_conditioning_can_be_switched_off(tiny_model, scene):
    obs = tiny_model.observe(two_boxes(scene))
    inputs = tiny_model.flow_inputs(obs, scene["poses"])
    x = torch.randn_like(inputs.x_1)
    net_inputs = inputs.net_kwargs()
    off = FunFlow6D(tiny_model.config.replace(noise_conditioning=False))
    off.load_state_dict(tiny_model.state_dict())
    off.eval()
    for p in off.net.dit.parameters():  # leave the zero initialisation so outputs vary
        torch.nn.init.normal_(p, std=0.05)
    a = off(x=x, t=torch.rand(2), x_0=torch.randn_like(x), **net_inputs)
    b = off(x=x, t=torch.rand(2).fill_(0.5), x_0=torch.randn_like(x), **net_inputs)
    c = off(x=x, t=torch.full((2,), 0.5), x_0=torch.zeros_like(x), **net_inputs)
    assert torch.allclose(b, c, atol=1e-6) and not torch.allclose(a, b, atol=1e-4)


def test_estimate_reports_stages_to_the_active_timer_only(tiny_model, scene):
    args = (scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 1])
    timer = StageTimer(synchronize=False)
    with timer.active():
        tiny_model.estimate(*args, generator=torch.Generator().manual_seed(0))
    expected = {
        "lifting", "geometric_encoder", "appearance_encoder", "flow_inputs", "reducer", "fusion",
        "integration", "flow_net", "ransac", "icp", "verification",
    }  # fmt: skip
    assert set(timer.counts) == expected
    assert timer.counts["flow_net"] == tiny_model.config.steps
    before = dict(timer.counts)
    tiny_model.estimate(*args, generator=torch.Generator().manual_seed(0))
    assert timer.counts == before


def _perfect_flow_to(model, scene, poses):
    """Make ``model``'s velocity net carry the observed clouds to where ``poses`` put them."""
    obs = model.observe(two_boxes(scene))
    model.net.dit = _Oracle(model.flow_inputs(obs, poses).x_1)


def test_verification_turns_a_flipped_pose_back_and_scores_it(tiny_model, scene):
    """The flow's answer is the box turned end for end: depth cannot tell, the print can."""
    model = FunFlow6D(tiny_model.config)
    model.objects, model.verifier = tiny_model.objects, tiny_model.verifier
    flips = model.verifier.objects[1].candidates
    flip = flips[rotation_angle_error(torch.eye(3), flips[:, :3, :3]).argmax()]  # a half-turn
    _perfect_flow_to(model, scene, scene["poses"] @ flip)
    args = (scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 1])
    timer = StageTimer(synchronize=False)
    with timer.active():
        on = model.estimate(*args)
    assert timer.counts["verification"] == 1
    model.config = model.config.replace(verifier=None)
    off = model.estimate(*args)
    assert off.valid.all() and on.valid.all()
    assert (rotation_angle_error(off.poses, scene["poses"]) > 150).all()  # the flip
    assert (rotation_angle_error(on.poses, scene["poses"]) < 3).all()
    assert (translation_error(on.poses, scene["poses"]) < 0.003).all()
    # every hypothesis is the flip: all agree with the unverified pose, none with the verified
    assert off.agreement.tolist() == [1.0, 1.0] and on.agreement.tolist() == [0.0, 0.0]
    # the scores are the verifier's, not RANSAC fitness times surface agreement
    assert ((on.scores > 0) & (on.scores <= 1)).all()
    assert (on.scores - off.scores).abs().min() > 1e-3


def test_other_hypotheses_reach_the_verifier(tiny_model, scene):
    """Two hypotheses per instance: the selection keeps one, the other is a candidate."""
    model = FunFlow6D(tiny_model.config.replace(num_hypotheses=2))
    model.objects, model.verifier = tiny_model.objects, tiny_model.verifier
    seen = {}
    verify = model.verifier.verify

    def spy(*args, **kwargs):
        seen.update(kwargs)
        return verify(*args, **kwargs)

    model.verifier.verify = spy
    try:
        model.estimate(scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 1])
        assert seen["extra"].shape == (2, 1, 4, 4) and seen["extra_mask"].shape == (2, 1)
        seen.clear()
        model.config = model.config.with_inference({"verifier.rank_hypotheses": False})
        model.verifier.config = model.config.verifier  # no prepared object depends on it
        model.estimate(scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 1])
        assert seen["extra"] is None
    finally:
        del model.verifier.verify
        model.verifier.config = tiny_model.config.verifier


def test_the_verifier_ranks_the_hypotheses_before_expanding_the_best(tiny_model, scene):
    """The estimator's pick is 3 cm off; the true pose among the others becomes the estimate."""
    verifier = tiny_model.verifier
    truth = scene["poses"]
    off = truth.clone()
    off[:, 0, 3] += 0.03
    turned = truth.clone()
    turned[:, 1, 3] -= 0.02
    extra = torch.stack((turned, truth), dim=1)  # (2, 2, 4, 4): the truth second
    extra_mask = torch.tensor([[True, True], [True, False]])  # instance 1: the truth is padding
    estimate = PoseEstimate(off, torch.tensor([0.9, 0.8]), torch.tensor([True, True]))
    image = two_boxes(scene)
    ranked, rest, rest_mask = rank_estimate(verifier, estimate, extra, extra_mask, image)
    assert torch.equal(ranked.poses[0], truth[0])  # swapped in
    assert torch.equal(rest[0, 1], off[0]) and rest_mask[0].all()  # the pick is a candidate
    assert not torch.equal(ranked.poses[1], truth[1])  # padding never wins
    assert torch.equal(ranked.valid, estimate.valid) and torch.equal(ranked.scores, estimate.scores)
    # the set of hypotheses is the same, in another order
    before = torch.cat((off[:, None], extra), 1).flatten(-2).sort(1).values
    after = torch.cat((ranked.poses[:, None], rest), 1).flatten(-2).sort(1).values
    assert torch.equal(before, after)
    invalid = PoseEstimate(off, estimate.scores, torch.tensor([False, True]))
    kept, _, _ = rank_estimate(verifier, invalid, extra, extra_mask, image)
    assert torch.equal(kept.poses[0], off[0])  # an instance without an estimate is left alone


@pytest.mark.parametrize("top", [0, 1, 2, 4])
def test_the_ranking_rescores_its_coarse_best_on_the_full_grid(tiny_model, scene, top):
    """rank_top_k = 0 ranks by the coarse score; k > 0 by the full score among the coarse top k."""
    verifier = PoseVerifier(dataclasses.replace(tiny_model.verifier.config, rank_top_k=top))
    verifier.objects = tiny_model.verifier.objects
    truth = scene["poses"]
    shifts = torch.tensor([0.012, 0.004, -0.008, 0.002, 0.0])  # metres along x
    poses = truth[:, None].repeat(1, len(shifts), 1, 1)
    poses[..., 0, 3] += shifts
    mask = torch.ones(2, len(shifts), dtype=torch.bool)
    image = two_boxes(scene)
    estimate = PoseEstimate(poses[:, 0], torch.ones(2), torch.ones(2, dtype=torch.bool))
    ranked, _, _ = rank_estimate(verifier, estimate, poses[:, 1:], mask[:, 1:], image)
    boxes = verifier.crop_boxes(poses[:, 0], [1, 1], scene["K"], scene["masks"])
    coarse = verifier.score(image, poses, mask, boxes=boxes,
                            crop_size=verifier.config.coarse_crop_size).total  # fmt: skip
    full = verifier.score(image, poses, mask, boxes=boxes).total
    # a shift within one pixel of the deciding grid of an earlier one is its duplicate
    cfg = verifier.config
    grid = cfg.crop_size if top > 1 else cfg.coarse_crop_size
    pixel = cfg.crop_margin * verifier.objects[1].diameter / grid
    kept: list[float] = []
    for s in shifts.tolist():
        if all(abs(s - k) > pixel for k in kept):
            kept.append(s)
    distinct = torch.tensor([s in kept for s in shifts.tolist()])
    coarse = torch.where(distinct, coarse, -torch.inf)
    if top == 0:
        expected = coarse.argmax(1)
    else:
        idx = coarse.topk(top, dim=1).indices
        expected = idx.gather(1, full.gather(1, idx).argmax(1, keepdim=True))[:, 0]
    assert torch.equal(ranked.poses, poses[torch.arange(2), expected])


def test_verification_needs_the_objects_prepared_for_it(tiny_model, box, scene):
    args = (scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 1])
    model = FunFlow6D(tiny_model.config.replace(verifier=None))
    model.prepare_objects({1: box}, progress=False)
    assert model.verifier.objects == {}  # nothing prepared while verification is off
    model.config = model.config.replace(verifier=tiny_model.config.verifier)
    with pytest.raises(ValueRangeError, match="not prepared for verification"):
        model.estimate(*args)
    model.config = model.config.replace(verifier={"crop_size": 48})
    with pytest.raises(ValueRangeError, match="call prepare_objects again"):
        model.estimate(*args)
    model.verifier = tiny_model.verifier
    model.config = model.config.replace(verifier=tiny_model.verifier.config)
    assert model.estimate(*args).poses.shape == (2, 4, 4)


def test_checkpoints_from_before_verification_load_without_it(tiny_model, tmp_path):
    folder = tiny_model.save(tmp_path / "ckpt")
    raw = json.loads((folder / "config.json").read_text())
    assert raw["verifier"] == tiny_model.config.verifier.to_dict()
    del raw["verifier"]
    (folder / "config.json").write_text(json.dumps(raw))
    assert FunFlow6D.load(folder).config.verifier is None  # as it was saved
    # a configuration file that is not a checkpoint takes the default of new configurations
    assert FunFlow6DConfig.from_dict(raw).verifier == VerifierConfig()
    # the shipped demo checkpoint verifies
    assert FunFlow6D.load(DEMO_CHECKPOINT).config.verifier == VerifierConfig()


def test_checkpoints_from_before_the_descriptor_support_describe_the_sampled_points(
    tiny_model, tmp_path
):
    from poseflow.models import object_fingerprint

    folder = tiny_model.save(tmp_path / "ckpt")
    raw = json.loads((folder / "config.json").read_text())
    assert raw["geometric_support_voxel"] == 0.04
    del raw["geometric_support_voxel"]
    (folder / "config.json").write_text(json.dumps(raw))
    old = FunFlow6D.load(folder).config
    assert old.geometric_support_voxel == 0.0
    # caches of objects prepared before the field keep their key; new ones get another
    assert "geometric_support_voxel" not in object_fingerprint(old)
    assert object_fingerprint(tiny_model.config)["geometric_support_voxel"] == 0.04
    with pytest.raises(ValueRangeError, match="geometric_support_voxel"):
        old.replace(geometric_support_voxel=0.5)


@pytest.mark.parametrize("name", ["flow_precision", "appearance_precision"])
def test_checkpoints_from_before_a_precision_field_compute_in_float32(tiny_model, tmp_path, name):
    folder = tiny_model.save(tmp_path / "ckpt")
    raw = json.loads((folder / "config.json").read_text())
    assert raw[name] == getattr(tiny_model.config, name) == "auto"
    del raw[name]
    (folder / "config.json").write_text(json.dumps(raw))
    assert getattr(FunFlow6D.load(folder).config, name) == "fp32"


def test_the_descriptor_support_changes_the_geometric_features_only(tiny_model, scene):
    image = two_boxes(scene)
    config = tiny_model.config
    try:
        tiny_model.config = config.replace(geometric_support_voxel=0.0)
        sparse = tiny_model.observe(image, generator=torch.Generator().manual_seed(4))
    finally:
        tiny_model.config = config
    dense = tiny_model.observe(image, generator=torch.Generator().manual_seed(4))
    assert torch.equal(sparse.points, dense.points) and torch.equal(sparse.normals, dense.normals)
    rows = dense.mask
    assert torch.isfinite(dense.geometric).all()
    assert torch.allclose(dense.geometric[rows].norm(dim=-1), torch.ones(int(rows.sum())))
    assert not torch.allclose(sparse.geometric[rows], dense.geometric[rows], atol=1e-2)


def test_predict_gives_an_image_the_same_poses_whatever_came_before(tiny_model, tmp_path):
    from poseflow.data.bop import BOPDataset
    from poseflow.data.synthetic import generate_dataset
    from poseflow.eval.recall import Target

    root = generate_dataset(
        tmp_path / "ds", num_train_images=0, num_test_images=2, width=160, height=120,
        seed=5, progress=False,
    )  # fmt: skip
    ds = BOPDataset(root, "test")
    scene_id = ds.scene_ids[-1]
    scene = ds.scene(scene_id)
    last = max(scene.im_ids)
    count = sum(gt.obj_id == 1 for gt in scene.gt_of(last))
    assert count > 0
    config = tiny_model.config
    try:
        tiny_model.config = config.replace(verifier=None, pose_solver="svd")
        both = tiny_model.predict(root, seed=3)
        target = Target(scene_id, last, 1, count)
        alone = tiny_model.predict(root, seed=3, targets=[target])
    finally:
        tiny_model.config = config
    rows = (both.scene_ids == scene_id) & (both.im_ids == last)
    assert bool((~rows).any()) and len(alone) == int(rows.sum()) > 0
    assert torch.equal(alone.poses, both.poses[rows])


def test_appearance_precision_applies_to_network_encoders_only(tiny_model, scene):
    """bfloat16 features close to float32 for a network encoder; dense SIFT stays float32."""
    from poseflow.features import DenseSIFTEncoder
    from poseflow.features.learned import LearnedAppearanceEncoder
    from poseflow.models.observe import observe

    learned = LearnedAppearanceEncoder()  # the shipped descriptor
    image = two_boxes(scene)

    def features(encoder, precision):
        return observe(
            *image, [0.1, 0.1], num_points=32, dense_points=512, appearance_encoder=encoder,
            generator=torch.Generator().manual_seed(0), appearance_precision=precision,
        ).appearance  # fmt: skip

    full, half = features(learned, "fp32"), features(learned, "bf16")
    assert full.dtype == half.dtype == torch.float32 and not torch.equal(full, half)
    assert float((half - full).norm() / full.norm()) < 0.05  # bfloat16: 8 bits of mantissa
    sift = DenseSIFTEncoder(input_size=32)
    assert torch.equal(features(sift, "bf16"), features(sift, "fp32"))
    assert learned.autocast and not getattr(sift, "autocast", False)


@pytest.mark.parametrize(
    "device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
        not torch.cuda.is_available(), reason="no CUDA device"))],
)  # fmt: skip
def test_the_encoders_networks_follow_the_model(device, tmp_path):
    cfg = FunFlow6DConfig(
        num_points=32, dit_preset="tiny", crop_size=48, appearance_encoder="learned"
    )
    model = FunFlow6D(cfg)
    encoder_net = model.appearance_encoder.net
    # frozen and kept in their own folder: not trained, not in the training checkpoints or EMA
    trained = {id(p) for p in model.parameters()}
    assert not any(id(p) in trained for p in encoder_net.parameters())
    assert all(k.startswith("net.") for k in model.state_dict())
    model.train()
    assert not encoder_net.training and model.net.training
    model.to(device=device, dtype=torch.float64)
    assert {p.dtype for p in encoder_net.parameters()} == {torch.float64}
    assert {p.device.type for p in encoder_net.parameters()} == {device}
    model.save(tmp_path / "m")
    loaded = FunFlow6D.load(tmp_path / "m", device=device)
    assert {p.device.type for p in loaded.appearance_encoder.net.parameters()} == {device}


def test_an_encoder_folder_given_relative_to_the_working_directory_is_found_from_anywhere(
    tmp_path, monkeypatch
):
    from poseflow.features.learned import DescriptorNet, save_descriptor

    monkeypatch.chdir(tmp_path)
    save_descriptor(DescriptorNet(widths=(8, 16), dim=8, out_stride=2), "desc", input_size=32)
    cfg = FunFlow6DConfig(num_points=32, dit_preset="tiny", crop_size=48,
                          appearance_encoder="learned:desc", feature_dim=4)  # fmt: skip
    FunFlow6D(cfg).save(tmp_path / "runs" / "m")
    monkeypatch.chdir(tmp_path / "runs")  # another working directory
    loaded = FunFlow6D.load("m")
    assert loaded.appearance_encoder.source == str(tmp_path / "desc")
