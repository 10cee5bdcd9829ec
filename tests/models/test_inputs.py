"""FlowInputs: the shapes of every field, and the names a training set is stored under."""

import dataclasses

import pytest
import torch

from poseflow.data import ImageInstances
from poseflow.errors import ValueRangeError
from poseflow.models import TRAINING_FIELDS, FlowInputs, FlowTrainingSet, FunFlow6D, NetInputs


@pytest.fixture(scope="module")
def inputs(tiny_model, scene):
    image = ImageInstances(scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 1])
    obs = tiny_model.observe(image, generator=torch.Generator().manual_seed(0))
    return tiny_model.flow_inputs(obs, scene["poses"])


def test_every_field_has_its_documented_shape(tiny_model, inputs):
    B, n = 2, tiny_model.config.num_points
    net = tiny_model.net.config
    shapes = {
        "geometric": (B, 2 * n, net.geometric_dim),
        "semantic": (B, 2 * n, net.semantic_dim),
        "points": (B, 2 * n, 3),
        "normals": (B, 2 * n, 3),
        "mask": (B, 2 * n),
        "frozen_mask": (B, 2 * n),
        "anchor": (B, 2 * n, 3),
        "scale": (B,),
        "centroid": (B, 3),
        "obj_ids": (B,),
        "x_1": (B, 2 * n, 3),
    }
    assert [f.name for f in dataclasses.fields(FlowInputs)] == list(shapes)
    for name, shape in shapes.items():
        assert getattr(inputs, name).shape == shape, name
    assert inputs.mask.dtype == inputs.frozen_mask.dtype == torch.bool
    assert torch.equal(inputs.anchor[:, :n], inputs.points[:, :n])
    assert (inputs.anchor[:, n:] == 0).all()


def test_training_fields_are_the_stored_names(inputs, tmp_path):
    # A training set on disk is keyed by these names: they must not change.
    names = ("x_1", "frozen_mask", "geometric", "semantic", "points", "normals", "mask")
    assert TRAINING_FIELDS == names
    assert set(NetInputs.field_names()) < set(TRAINING_FIELDS)
    data = FlowTrainingSet({k: getattr(inputs, k) for k in TRAINING_FIELDS})
    back = FlowTrainingSet.load(data.save(tmp_path / "set.safetensors"))
    assert sorted(back.tensors) == sorted(names)
    item = back[1]
    assert torch.equal(item["x_1"], inputs.x_1[1])
    with pytest.raises(ValueRangeError, match="lack"):
        FlowTrainingSet({k: getattr(inputs, k) for k in TRAINING_FIELDS[1:]})


def test_repeat_interleave_repeats_every_tensor(inputs):
    rep = inputs.repeat_interleave(3)
    for f in dataclasses.fields(FlowInputs):
        a, b = getattr(inputs, f.name), getattr(rep, f.name)
        assert b.shape[0] == 3 * a.shape[0] and torch.equal(b[3:6], a[1:2].expand_as(b[3:6]))
    without = dataclasses.replace(inputs, x_1=None).repeat_interleave(2)
    assert without.x_1 is None and without.points.shape[0] == 4


def test_net_inputs_from_keyword_tensors(inputs):
    kwargs = inputs.net_kwargs()
    assert tuple(kwargs) == NetInputs.field_names()
    back = NetInputs.from_kwargs(kwargs)
    assert type(back) is NetInputs and torch.equal(back.points, inputs.points)
    assert NetInputs.from_kwargs({k: v for k, v in kwargs.items() if k != "mask"}).mask is None
    with pytest.raises(ValueRangeError, match="unknown"):
        NetInputs.from_kwargs({**kwargs, "x_1": inputs.x_1})
    with pytest.raises(ValueRangeError, match="missing"):
        NetInputs.from_kwargs({k: v for k, v in kwargs.items() if k != "points"})


@pytest.mark.parametrize("missing", ["geometric_encoder", "appearance_encoder"])
def test_a_stream_without_an_encoder_is_fed_the_other(tiny_model, box, scene, missing):
    model = FunFlow6D(tiny_model.config.replace(**{missing: "none"}))
    model.prepare_objects({1: box}, progress=False)
    obs = model.observe(
        ImageInstances(scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 1])
    )
    inputs = model.flow_inputs(obs)
    assert torch.equal(inputs.geometric, inputs.semantic) and inputs.x_1 is None
    est = model.estimate(scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 1])
    assert est.poses.shape == (2, 4, 4) and torch.isfinite(est.poses).all()


def test_a_symmetric_pose_gives_an_end_state_among_the_equivalents(tiny_model, scene):
    from poseflow.flows import apply_equivalents
    from poseflow.models.inputs import equivalent_maps

    image = ImageInstances(scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 1])
    obs = tiny_model.observe(image, generator=torch.Generator().manual_seed(0))
    half_turn = torch.diag(torch.tensor([-1.0, -1.0, 1.0, 1.0]))
    half_turn[:2, 3] = torch.tensor([0.01, -0.02])  # about an axis off the origin
    symmetries = torch.stack([torch.eye(4), half_turn])
    plain = tiny_model.flow_inputs(obs, scene["poses"])
    turned = tiny_model.flow_inputs(obs, scene["poses"] @ half_turn)
    scale = tiny_model.objects[1].diameter / 2
    maps = equivalent_maps(symmetries, scale).expand(2, -1, -1, -1)
    every = apply_equivalents(plain.x_1, maps, plain.frozen_mask)
    assert torch.allclose(every[:, 1], turned.x_1, atol=1e-5)
    assert torch.equal(every[:, 0], plain.x_1)
    assert not torch.allclose(plain.x_1, turned.x_1, atol=1e-3)
