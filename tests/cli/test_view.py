"""``poseflow view``: recordings and GLB scenes of a results CSV on a tiny generated dataset."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from poseflow.cli import main
from poseflow.data.object_folder import load_object_models
from poseflow.data.synthetic import generate_dataset
from poseflow.eval import GLTF_FROM_CAMERA, PoseResults, gt_results, write_results

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("rerun")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    box = o3d.geometry.TriangleMesh.create_box(0.08, 0.06, 0.04).translate((-0.04, -0.03, -0.02))
    root = tmp_path_factory.mktemp("bop")
    generate_dataset(
        root, [box], num_train_images=0, num_test_images=2, objects_per_image=1,
        distractors_per_image=0, width=96, height=72, progress=False,
    )  # fmt: skip
    return root


@pytest.fixture(scope="module")
def results(dataset, tmp_path_factory):
    """The ground truth moved by 1 cm along x: an estimate that is visibly off."""
    gt = gt_results(dataset)
    poses = gt.poses.clone()
    poses[:, 0, 3] += 0.01
    moved = PoseResults(gt.scene_ids, gt.im_ids, gt.obj_ids, gt.scores * 0.5, poses, gt.times)
    path = tmp_path_factory.mktemp("res") / "mymethod_synth-test.csv"
    write_results(path, moved)
    return path, moved


def test_view_writes_a_recording_and_a_glb_per_image(dataset, results, tmp_path, capsys):
    csv, moved = results
    out = tmp_path / "view"
    assert main(["view", str(csv), str(dataset), "--out", str(out), "--stride", "3"]) == 0
    text = capsys.readouterr().out
    assert "rerun FILE.rrd" in text
    keys = sorted(set(zip(moved.scene_ids.tolist(), moved.im_ids.tolist())))
    assert len(keys) == 2
    assert sorted(p.name for p in out.iterdir()) == sorted(
        f"{s:06d}_{i:06d}.{ext}" for s, i in keys for ext in ("glb", "rrd")
    )
    mesh = load_object_models(dataset)[1].mesh
    s, i = keys[0]
    row = int(((moved.scene_ids == s) & (moved.im_ids == i)).nonzero()[0, 0])
    T = moved.poses[row].numpy()  # as read back from the CSV, millimetres to metres
    scene = trimesh.load(out / f"{s:06d}_{i:06d}.glb", process=False)
    transform, geom = scene.graph["est_0_obj_000001"]
    np.testing.assert_allclose(transform, GLTF_FROM_CAMERA)
    vertices = scene.geometry[geom].vertices
    np.testing.assert_allclose(vertices, mesh.vertices @ T[:3, :3].T + T[:3, 3], atol=2e-6)
    assert "gt_0_obj_000001" in scene.graph.nodes_geometry
    assert "observed" in scene.graph.nodes_geometry

    from rerun.chunk import RrdReader

    entities = {}
    for chunk in RrdReader(out / f"{s:06d}_{i:06d}.rrd").stream():
        batch = chunk.to_record_batch()
        entities.setdefault(chunk.entity_path, {}).update(
            {n: batch.column(n).to_pylist() for n in batch.schema.names}
        )
    est = entities["/world/estimates/est_0_obj_000001"]
    assert est["valid"][0] == [True]
    assert est["score"][0][0] == pytest.approx(float(moved.scores[row]), abs=1e-6)
    label = entities["/world/estimates/est_0_obj_000001/label"]["Points3D:labels"][0][0]
    assert label.startswith("obj 1: score")
    assert "mymethod" in entities["/description"]["TextDocument:text"][0][0]
    assert "/world/ground_truth/gt_0_obj_000001" in entities
    assert len(entities["/world/observed"]["Points3D:positions"][0]) > 0


def test_view_selects_images_formats_and_accepts_either_order(dataset, results, tmp_path):
    csv, moved = results
    s, i = int(moved.scene_ids[-1]), int(moved.im_ids[-1])
    out = tmp_path / "one"
    argv = ["view", str(dataset), str(csv), "--out", str(out), "--scene", str(s)]
    argv += ["--im-id", str(i), "--format", "ply", "--no-gt", "-q"]
    assert main(argv) == 0
    stem = f"{s:06d}_{i:06d}"
    assert sorted(p.name for p in out.iterdir()) == [f"{stem}.ply", f"{stem}_cloud.ply"]
    merged = trimesh.load(out / f"{stem}.ply", process=False)
    mesh = load_object_models(dataset)[1].mesh
    assert len(merged.vertices) == mesh.num_vertices  # one estimate, no ground truth
    out2 = tmp_path / "limited"
    assert main(["view", str(csv), str(dataset), "--out", str(out2), "--max-images", "1"]) == 0
    assert len(list(out2.glob("*.rrd"))) == 1


def test_view_errors(dataset, results, tmp_path, capsys):
    csv, _ = results
    out = str(tmp_path / "x")
    assert main(["view", str(csv), str(dataset), "--out", out, "--format", "obj"]) == 2
    assert main(["view", str(csv), str(dataset), "--out", out, "--scene", "99"]) == 2
    assert main(["view", str(tmp_path / "none.csv"), str(dataset), "--out", out]) == 1
    assert main(["view", str(csv), str(tmp_path), "--out", out]) == 1  # not a BOP dataset
    err = capsys.readouterr().err
    assert "--format takes a subset of rrd,glb,ply" in err and "holds no estimate" in err
    assert "does not exist" in err and "not a BOP dataset" in err


def test_view_without_rerun_names_the_extra(dataset, results, tmp_path, capsys, monkeypatch):
    import importlib.util

    csv, _ = results
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "rerun" else real(name, *a)
    )
    assert main(["view", str(csv), str(dataset), "--out", str(tmp_path / "y")]) == 1
    assert "pip install 'poseflow[viz]'" in capsys.readouterr().err
    assert not (tmp_path / "y").exists()  # stopped before any work
