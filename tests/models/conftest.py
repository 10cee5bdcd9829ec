"""A tiny rendered scene and a tiny prepared model shared by the model tests."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from poseflow.data.demo_objects import demo_objects
from poseflow.geometry.se3 import from_Rt, random_rotation
from poseflow.models import FunFlow6D, FunFlow6DConfig, NetOptions
from poseflow.render import Renderer

TINY = FunFlow6DConfig(
    num_points=48,
    crop_size=32,
    query_views=2,
    dit_preset="tiny",
    steps=4,
    ransac_iterations=200,
    net=NetOptions(fusion_heads=2, posenc_dim=16, posenc_frequencies=2),
)


@pytest.fixture(scope="session")
def box():
    return demo_objects(num_points=1000, names=["labelled_box"])[0]


@pytest.fixture(scope="session")
def tiny_model(box):
    torch.manual_seed(0)
    model = FunFlow6D(TINY)
    model.prepare_objects({1: box}, progress=False)
    return model


@pytest.fixture(scope="session")
def scene(box):
    """One image with two instances of object 1 at known poses (metres)."""
    g = torch.Generator().manual_seed(3)
    R = random_rotation(2, generator=g, dtype=torch.float64)
    t = torch.tensor([[-0.06, 0.0, 0.5], [0.07, 0.02, 0.55]], dtype=torch.float64)
    poses = from_Rt(R, t)
    K = torch.tensor([[300.0, 0, 79.5], [0, 300.0, 59.5], [0, 0, 1]], dtype=torch.float64)
    out = Renderer([box.mesh]).render(
        poses.numpy(), K.numpy(), 160, 120, object_ids=[0, 0], background=(90, 90, 90)
    )
    depth = torch.as_tensor(np.asarray(out.depth), dtype=torch.float32)
    instance = torch.as_tensor(np.asarray(out.instance))
    masks = torch.stack([instance == 0, instance == 1])
    rgb = torch.as_tensor(np.asarray(out.rgb)).permute(2, 0, 1).contiguous()
    return {"rgb": rgb, "depth": depth, "K": K.float(), "masks": masks, "poses": poses.float()}
