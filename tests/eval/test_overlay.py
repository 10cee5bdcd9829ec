from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch
from PIL import Image

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.eval.overlay import (
    ESTIMATE_COLOR,
    ESTIMATE_COLORS,
    GT_COLOR,
    overlay_poses,
    write_overlay,
)

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
    pic = overlay_poses(image, K, [box], _pose(), alpha=1.0, axes=False)
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


# ------------------------------------------------------------------------------ outlines, legend

BIG_K = torch.tensor([[400.0, 0, 160], [0, 400.0, 120], [0, 0, 1]])


def _big_pose(x: float = 0.0, y: float = 0.0) -> torch.Tensor:
    T = _pose(x)
    T[0, 1, 3] = y
    return T


def _grey(h: int = 240, w: int = 320) -> torch.Tensor:
    return torch.full((h, w, 3), 128, dtype=torch.uint8)


def _has(pic: torch.Tensor, colour) -> torch.Tensor:
    return (pic == torch.tensor(colour, dtype=torch.uint8)).all(-1)


def test_estimate_is_outlined_and_lightly_tinted(box):
    pic = overlay_poses(_grey(), BIG_K, [box], _big_pose(), legend=False, axes=False)
    outline = _has(pic, ESTIMATE_COLOR)
    assert int(outline.sum()) > 100
    assert not bool(outline[120, 160])  # the inside is tinted, not painted over
    inside = pic[120, 160].float()
    assert not torch.equal(inside, torch.full((3,), 128.0))  # tinted ...
    assert float((inside - 128).abs().max()) < 0.5 * float(
        (torch.tensor(ESTIMATE_COLOR) - 128).abs().max()
    )


def test_each_estimate_has_its_own_colour_and_invalid_ones_are_dashed(box):
    poses = torch.cat([_big_pose(-0.1), _big_pose(0.1)])
    pic = overlay_poses(_grey(), BIG_K, [box], poses, object_ids=[0, 0], legend=False, axes=False)
    first, second = _has(pic, ESTIMATE_COLORS[0]), _has(pic, ESTIMATE_COLORS[1])
    assert int(first[:, :160].sum()) > 100 and int(first[:, 160:].sum()) == 0
    assert int(second[:, 160:].sum()) > 100 and int(second[:, :160].sum()) == 0
    dashed = overlay_poses(
        _grey(),
        BIG_K,
        [box],
        poses,
        object_ids=[0, 0],
        valid=[True, False],
        legend=False,
        axes=False,
    )
    assert int(_has(dashed, ESTIMATE_COLORS[1]).sum()) < 0.7 * int(second.sum())  # dashes
    assert bool((dashed[120, 240] == 128).all())  # no tint inside the invalid one
    with pytest.raises(ShapeError):
        overlay_poses(_grey(), BIG_K, [box], poses, object_ids=[0, 0], scores=[0.5])
    poses[1] = float("nan")  # no estimate at all: in the legend, not drawn
    missing = overlay_poses(
        _grey(), BIG_K, [box], poses, object_ids=[0, 0], valid=[True, False], axes=False
    )
    assert int(_has(missing[:, 160:], ESTIMATE_COLORS[1]).sum()) == 0
    assert bool(_has(missing[:, :160], ESTIMATE_COLORS[0]).any())


def test_gt_outline_lies_outside_a_matching_estimate(box):
    pic = overlay_poses(
        _grey(), BIG_K, [box], _big_pose(), gt_poses=_big_pose(), legend=False, axes=False
    )
    green, blue = _has(pic, GT_COLOR), _has(pic, ESTIMATE_COLOR)
    assert int(green.sum()) > 100 and int(blue.sum()) > 100  # both visible where they agree
    assert not bool((green & blue).any())


def _legend_pixels(pic: torch.Tensor, region: tuple[slice, slice]) -> int:
    """Pixels of a region that are not the plain grey background (the legend's box and text)."""
    return int((pic[region] != 128).any(-1).sum())


def test_legend_names_the_method_and_avoids_the_objects(box):
    top_left = (slice(0, 60), slice(0, 120))
    plain = overlay_poses(_grey(), BIG_K, [box], _big_pose(), legend=False, axes=False)
    assert _legend_pixels(plain, top_left) == 0
    pic = overlay_poses(
        _grey(), BIG_K, [box], _big_pose(), method="FunFlow6D", scores=[0.87],
        mesh_names=["obj 1"], gt_poses=_big_pose(),
    )  # fmt: skip
    assert _legend_pixels(pic, top_left) > 500  # the box and its lines, in the free corner
    assert bool(_has(pic[top_left], ESTIMATE_COLOR).any())  # the estimate's swatch
    assert bool(_has(pic[top_left], GT_COLOR).any())  # the ground truth's swatch
    assert bool((pic[top_left].float().mean(-1) > 200).any())  # white text
    # a longer method name makes a wider box
    longer = overlay_poses(
        _grey(), BIG_K, [box], _big_pose(), method="FunFlow6D with a much longer name"
    )
    cols = lambda p: int((p[:60] != 128).any(-1).any(0)[:200].sum())  # noqa: E731
    assert cols(longer) > cols(pic)
    # an object in the top-left corner moves the legend to another corner
    moved = overlay_poses(_grey(), BIG_K, [box], _big_pose(-0.13, -0.09), method="FunFlow6D")
    assert _legend_pixels(moved, (slice(0, 60), slice(200, 320))) > 500


def test_a_turn_that_keeps_the_silhouette_shows_in_the_axes(box):
    turned = _big_pose().clone()
    turned[0, :3, :3] = torch.diag(torch.tensor([-1.0, -1.0, 1.0]))  # 180 deg about the view axis
    same = [overlay_poses(_grey(), BIG_K, [box], T, legend=False, axes=False)
            for T in (_big_pose(), turned)]  # fmt: skip
    assert torch.equal(same[0], same[1])  # the box's silhouette and shading cannot tell
    shown = [overlay_poses(_grey(), BIG_K, [box], T, legend=False) for T in (_big_pose(), turned)]
    differ = (shown[0] != shown[1]).any(-1)
    assert int(differ.sum()) > 50
    red = (shown[0].int() - torch.tensor([235, 40, 40])).abs().sum(-1) < 30
    assert red[:, 160:].sum() > red[:, :160].sum()  # x points right, turned left


def test_a_turn_of_a_labelled_object_shows_where_the_label_is(box):
    """A box printed dark on its right half: turned 180 degrees about the view axis, the same
    silhouette, but the print moves to the left half, and the picture shows it."""
    printed = o3d.geometry.TriangleMesh(box).subdivide_midpoint(number_of_iterations=4)
    x = np.asarray(printed.vertices)[:, 0]
    printed.vertex_colors = o3d.utility.Vector3dVector(
        np.where(x[:, None] > 0.02, 0.1, 0.9).repeat(3, axis=1)
    )
    turned = _big_pose().clone()
    turned[0, :3, :3] = torch.diag(torch.tensor([-1.0, -1.0, 1.0]))
    pics = [overlay_poses(_grey(), BIG_K, [printed], T, legend=False, axes=False)
            for T in (_big_pose(), turned)]  # fmt: skip
    # the front face spans columns 127-193; the print x > 2 cm, columns 173-193 (or mirrored)
    lum = [p[100:140].float().mean(-1) for p in pics]
    left, right = slice(130, 144), slice(176, 190)
    assert float(lum[0][:, right].mean()) < float(lum[0][:, left].mean()) - 20  # print right
    assert float(lum[1][:, left].mean()) < float(lum[1][:, right].mean()) - 20  # turned: left


def test_the_legend_never_disappears(box):
    name = "FunFlow6D (a/very/long/path/to/a/model/folder/that/fills/the/picture/model)"
    small_k = torch.tensor([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
    pic = overlay_poses(_grey(120, 160), small_k, [box], _big_pose(), method=name, scores=[0.9])
    plain = overlay_poses(_grey(120, 160), small_k, [box], _big_pose(), legend=False)
    assert int((pic != plain).any(-1).sum()) > 100  # drawn, in a smaller font and shortened
