from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch
from PIL import Image

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.eval.overlay import ESTIMATE_COLOR, GT_COLOR, overlay_poses, write_overlay

K = torch.tensor([[120.0, 0, 40], [0, 120.0, 30], [0, 0, 1]])


@pytest.fixture(scope="module")
def box():
    return o3d.geometry.TriangleMesh.create_box(0.1, 0.1, 0.1).translate((-0.05, -0.05, -0.05))


def _pose(x: float = 0.0) -> torch.Tensor:
    T = torch.eye(4)[None].clone()
    T[0, 0, 3] = x
    T[0, 2, 3] = 0.6
    return T


def test_png_has_the_image_size(box, tmp_path):
    image = torch.randint(
        0, 256, (60, 80, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(0)
    )
    path = tmp_path / "000001.png"
    pic = write_overlay(path, image, K, [box], _pose(), gt_poses=_pose(0.05))
    with Image.open(path) as im:
        assert im.size == (80, 60) and im.mode == "RGB"
        assert torch.equal(torch.from_numpy(np.array(im)), pic)


def test_background_turns_grey_and_models_are_coloured(box):
    image = torch.zeros(60, 80, 3, dtype=torch.uint8)
    image[..., 0] = 255  # pure red
    pic = overlay_poses(image, K, [box], _pose(), alpha=1.0)
    corner = pic[0, 0].tolist()
    assert corner[0] == corner[1] == corner[2] == round(0.299 * 255)
    centre = pic[30, 40].float()
    # The front face looks straight at the camera: full shading, the estimate colour.
    torch.testing.assert_close(
        centre, torch.tensor(ESTIMATE_COLOR, dtype=torch.float32), atol=1, rtol=0
    )


def test_gt_outline_in_second_colour(box):
    image = torch.full((60, 80, 3), 128, dtype=torch.uint8)
    pic = overlay_poses(image, K, [box], torch.zeros(0, 4, 4), gt_poses=_pose())
    green = (pic == torch.tensor(GT_COLOR, dtype=torch.uint8)).all(-1)
    assert int(green.sum()) > 0
    assert not bool(green[30, 40])  # only the outline, not the inside
    assert bool((pic[0, 0] == 128).all())


def test_channels_first_float_image(box):
    image = torch.full((3, 60, 80), 0.5)
    pic = overlay_poses(image, K, [box], _pose())
    assert pic.shape == (60, 80, 3) and pic.dtype == torch.uint8


def test_bad_arguments(box):
    with pytest.raises(ValueRangeError):
        overlay_poses(torch.zeros(60, 80, 3, dtype=torch.uint8), K, [box], _pose(), alpha=1.5)
    with pytest.raises(ShapeError):
        overlay_poses(torch.zeros(60, 80, 5, dtype=torch.uint8), K, [box], _pose())
    with pytest.raises(ShapeError):
        overlay_poses(torch.zeros(60, 80, 3, dtype=torch.int32), K, [box], _pose())
