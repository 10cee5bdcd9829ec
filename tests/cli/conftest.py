"""Fixtures of the command-line tests."""

from __future__ import annotations

import open3d as o3d
import pytest

from poseflow.data.bop import BOPDataset
from poseflow.data.synthetic import generate_dataset


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    """A generated frame of one box: the paths ``estimate`` takes, and its ground truth."""
    box = o3d.geometry.TriangleMesh.create_box(0.1, 0.07, 0.05).translate((-0.05, -0.035, -0.025))
    root = generate_dataset(
        tmp_path_factory.mktemp("frame") / "ds", [box], num_train_images=0, num_test_images=1,
        objects_per_image=1, distractors_per_image=0, width=160, height=120, progress=False,
        seed=3,
    )  # fmt: skip
    scene = root / "test" / "000000"
    gt = BOPDataset(root, "test").scene(0).gt_of(0)[0]
    return {
        "root": root,
        "rgb": scene / "rgb" / "000000.png",
        "depth": scene / "depth" / "000000.png",
        "camera": scene / "scene_camera.json",
        "mask": scene / "mask_visib" / "000000_000000.png",
        "mesh": root / "models" / "obj_000001.ply",  # in mm, as BOP models are
        "pose": gt.pose,
    }
