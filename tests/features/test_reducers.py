from __future__ import annotations

import builtins
import math
import os
import random
import sys
import types

import numpy as np
import pytest
import torch

import poseflow.features
from poseflow.errors import (
    DegenerateInputError,
    MissingDependencyError,
    ShapeError,
    ValueRangeError,
)
from poseflow.features.reducers import (
    IdentityReducer,
    PCAReducer,
    Reducer,
    UMAPReducer,
    find_ab_params,
    load_reducer,
)
from poseflow.features.umap_transform import fuzzy_membership


def _clusters(n: int, g: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    centres = torch.randn(8, g, generator=gen, dtype=torch.float64) * 3
    label = torch.arange(n) % 8
    return centres[label] + 0.3 * torch.randn(n, g, generator=gen, dtype=torch.float64), label


def test_pca_matches_numpy_svd(dtype: torch.dtype) -> None:
    x, _ = _clusters(200, 12, 0)
    x = x.to(dtype)
    pca = PCAReducer(4, normalize=False).fit(x)
    xn = x.double().numpy()
    _, s, vt = np.linalg.svd(xn - xn.mean(0), full_matrices=False)
    got = pca.transform(x).double().numpy()
    want = (xn - xn.mean(0)) @ vt[:4].T
    assert np.allclose(np.abs(got), np.abs(want), atol=1e-3 if dtype == torch.float32 else 1e-9)
    assert np.allclose(pca.explained_variance_.double().numpy(), s[:4] ** 2 / 199, rtol=1e-4)
    assert pca.transform(x).dtype == dtype


def test_numpy_in_numpy_out_and_batched_mask(device: torch.device) -> None:
    x, _ = _clusters(100, 6, 1)
    pca = PCAReducer(3).fit(x.numpy())
    assert isinstance(pca.transform(x.numpy()), np.ndarray)
    batch = torch.stack([x[:50], x[50:]]).to(device)
    mask = torch.ones(2, 50, dtype=torch.bool, device=device)
    mask[1, 40:] = False
    pca.to(device)
    out = pca.transform(batch, mask)
    assert out.shape == (2, 50, 3) and out.device.type == device.type
    assert torch.allclose(out[1, :40], pca.transform(x[50:90].to(device)))
    assert bool((out[1, 40:] == 0).all())


def test_identity_and_errors() -> None:
    x = torch.tensor([[3.0, 4.0], [0.0, 2.0], [1.0, 1.0]])
    assert torch.allclose(IdentityReducer().fit_transform(x), x)
    assert torch.allclose(
        IdentityReducer(normalize=True).fit_transform(x).norm(dim=1), torch.ones(3)
    )
    with pytest.raises(ValueRangeError):
        PCAReducer(3).transform(x)  # not fitted
    with pytest.raises(ValueRangeError):
        PCAReducer(5).fit(x)
    with pytest.raises(ShapeError):
        PCAReducer(1).fit(x).transform(torch.zeros(2, 3))
    with pytest.raises(DegenerateInputError):
        PCAReducer(1).fit(x[:1])
    with pytest.raises(ValueRangeError):
        UMAPReducer(metric="manhattan")


def test_save_load_roundtrip(tmp_path, device: torch.device) -> None:
    x, _ = _clusters(120, 10, 2)
    emb = torch.randn(120, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    for red in (IdentityReducer(normalize=True).fit(x), PCAReducer(4).fit(x),
                UMAPReducer.from_embedding(x, emb, n_neighbors=10)):  # fmt: skip
        path = red.save(tmp_path / type(red).__name__)
        assert not list(path.glob("*.pkl"))
        back = load_reducer(path, device=device)
        assert type(back) is type(red)
        assert torch.allclose(back.transform(x.to(device)).cpu(), red.transform(x), atol=1e-10)


class _Shift(Reducer):
    """A minimal subclass: subtracts the fitted mean (one array, one parameter)."""

    _arrays = ("mean_",)
    _params = ("normalize",)

    def __init__(self, *, normalize: bool = False) -> None:
        self.normalize = normalize

    def _fit(self, x: torch.Tensor) -> None:
        self.mean_ = x.mean(dim=0)

    def _transform(self, x: torch.Tensor) -> torch.Tensor:
        return x - self.mean_.to(x)


def test_reducer_is_an_abstract_base_exported_by_features() -> None:
    assert poseflow.features.Reducer is Reducer
    assert "Reducer" in poseflow.features.__all__
    with pytest.raises(TypeError, match="abstract"):
        Reducer()  # type: ignore[abstract]

    class OnlyFit(Reducer):
        def _fit(self, x: torch.Tensor) -> None:
            pass

    with pytest.raises(TypeError, match="_transform"):
        OnlyFit()  # type: ignore[abstract]
    for cls in (IdentityReducer, PCAReducer, UMAPReducer):
        assert issubclass(cls, Reducer)


def test_reducer_subclass_gets_fit_transform_batching_and_validation() -> None:
    x = torch.tensor([[1.0, 2.0], [3.0, 6.0], [5.0, 4.0]])
    red = _Shift()
    assert red.fit(x) is red and red.n_features_in_ == 2
    assert torch.equal(red.transform(x), x - torch.tensor([3.0, 4.0]))
    batch = torch.stack([x, 2 * x])
    mask = torch.tensor([[True, True, False], [True, False, True]])
    out = red.transform(batch, mask)
    assert torch.equal(out[1, 2], 2 * x[2] - torch.tensor([3.0, 4.0]))
    assert bool((out[0, 2] == 0).all() and (out[1, 1] == 0).all())
    assert isinstance(red.transform(x.numpy()), np.ndarray)
    with pytest.raises(ShapeError):
        red.transform(torch.zeros(2, 5))
    with pytest.raises(ValueRangeError, match="not fitted"):
        _Shift().transform(x)


def test_load_reducer_returns_the_saved_reducer_type(tmp_path) -> None:
    x, _ = _clusters(60, 6, 9)
    back = load_reducer(PCAReducer(2).fit(x).save(tmp_path / "pca"))
    assert isinstance(back, Reducer) and type(back) is PCAReducer
    assert load_reducer.__annotations__["return"] == "Reducer"
    (tmp_path / "odd").mkdir()
    (tmp_path / "odd" / "reducer.json").write_text('{"class": "_Shift", "params": {}}')
    with pytest.raises(ValueRangeError, match="unknown reducer class"):
        load_reducer(tmp_path / "odd")


def test_find_ab_params_matches_umap_defaults() -> None:
    a, b = find_ab_params(1.0, 0.1)  # umap-learn's defaults give a = 1.577, b = 0.895
    assert abs(a - 1.577) < 0.01 and abs(b - 0.895) < 0.01


def test_membership_sums_to_log2_k() -> None:
    d = torch.rand(50, 30, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    d, _ = d.sort(dim=1)
    w = fuzzy_membership(d, math.log2(30))
    assert torch.allclose(w.sum(dim=1), torch.full((50,), math.log2(30), dtype=torch.float64))
    assert bool((w[:, :-1] >= w[:, 1:]).all())  # closer neighbours weigh more


def test_torch_transform_places_points_by_their_neighbours(dtype: torch.dtype) -> None:
    # a 2-d embedding that separates the clusters: new points must land in their cluster
    x, label = _clusters(400, 16, 3)
    gen = torch.Generator().manual_seed(4)
    angle = label.double() * (2 * math.pi / 8)
    emb = 5 * torch.stack([angle.cos(), angle.sin()], dim=1)
    emb = emb + 0.2 * torch.randn(400, 2, generator=gen, dtype=torch.float64)
    red = UMAPReducer.from_embedding(x.to(dtype), emb.to(dtype), n_neighbors=15, metric="euclidean")
    new, new_label = _clusters(200, 16, 3)
    new = new + 0.1 * torch.randn(200, 16, generator=gen, dtype=torch.float64)
    y = red.transform(new.to(dtype))
    assert y.dtype == dtype and y.shape == (200, 2)
    ang = torch.arange(8, dtype=torch.float64) * (2 * math.pi / 8)
    centres = 5 * torch.stack([ang.cos(), ang.sin()], dim=1)  # (8, 2)
    assert bool((torch.cdist(y.double(), centres).argmin(dim=1) == new_label).all())
    red.transform_epochs = 0
    y0 = red.transform(new.to(dtype))
    assert bool((torch.cdist(y0.double(), centres).argmin(dim=1) == new_label).all())


def test_torch_transform_batched_equals_flat(device: torch.device) -> None:
    x, _ = _clusters(300, 8, 5)
    emb = torch.randn(300, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    red = UMAPReducer.from_embedding(x, emb, n_neighbors=10, transform_epochs=0).to(device)
    batch = torch.stack([x[:100], x[100:200]]).to(device)
    out = red.transform(batch)
    assert torch.allclose(out[1], red.transform(x[100:200].to(device)))


@pytest.mark.slow
def test_umap_fit_and_transform_match_umap_learn() -> None:
    from poseflow.eval.inliers import mutual_nearest_neighbors

    x, _ = _clusters(600, 32, 6)
    x = x.float()
    red = UMAPReducer(16, n_neighbors=15).fit(x)
    assert red.embedding_.shape == (600, 16)
    gen = torch.Generator().manual_seed(7)
    pick = torch.randperm(600, generator=gen)[:200]
    new = x[pick] + 0.05 * torch.randn(200, 32, generator=gen)
    ours = red.transform(new)
    ref = torch.from_numpy(red.transform_umap_learn(new.numpy()))
    match_ours = mutual_nearest_neighbors(red.embedding_[None], ours[None])[0]
    match_ref = mutual_nearest_neighbors(red.embedding_[None], ref[None])[0]
    correct_ours = int((match_ours == pick).sum())
    correct_ref = int((match_ref == pick).sum())
    # near-duplicates of training points favour umap-learn's SGD, which snaps a point onto its
    # nearest neighbour (measured 69 vs 109 of 200 here); on real features the weighted-mean
    # transform finds more inliers than umap-learn's (benchmarks/features.py)
    assert correct_ours >= 0.5 * correct_ref
    assert correct_ours > 40


def test_fit_backend_names_are_checked() -> None:
    with pytest.raises(ValueRangeError, match="fit_backend"):
        UMAPReducer(fit_backend="cuml")


def test_fit_backend_dispatch_with_torchdr_importable(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "torchdr", types.ModuleType("torchdr"))
    assert UMAPReducer().resolve_fit_backend("cpu") == "umap-learn"
    assert UMAPReducer().resolve_fit_backend(torch.device("cuda", 0)) == "torchdr"
    assert UMAPReducer(fit_backend="torchdr").resolve_fit_backend("cpu") == "torchdr"
    assert UMAPReducer(fit_backend="umap-learn").resolve_fit_backend("cuda") == "umap-learn"


def test_fit_backend_dispatch_without_torchdr(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "torchdr", None)  # makes `import torchdr` fail
    assert UMAPReducer().resolve_fit_backend("cuda") == "umap-learn"
    with pytest.raises(MissingDependencyError, match=r"torchdr .*pip install 'poseflow\[gpu\]'"):
        UMAPReducer(fit_backend="torchdr").resolve_fit_backend("cpu")
    with pytest.raises(ImportError):  # also an ImportError, for code that catches those
        UMAPReducer(fit_backend="torchdr", n_neighbors=5).fit(torch.rand(20, 4))


def test_fit_backend_names_an_undeclared_torchdr_dependency(monkeypatch) -> None:
    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name == "torchdr":
            raise ModuleNotFoundError("No module named 'matplotlib'", name="matplotlib")
        return real_import(name, *args, **kwargs)

    monkeypatch.delitem(sys.modules, "torchdr", raising=False)
    monkeypatch.setattr(builtins, "__import__", fake_import)
    with pytest.raises(MissingDependencyError, match=r"matplotlib .*TorchDR.*poseflow\[gpu\]"):
        UMAPReducer(fit_backend="torchdr").resolve_fit_backend("cpu")


def test_torchdr_fit_on_cpu(tmp_path, dtype: torch.dtype) -> None:
    pytest.importorskip("torchdr")
    x, label = _clusters(160, 16, 10)
    x = x.to(dtype)
    params = {"n_neighbors": 10, "n_epochs": 60, "fit_backend": "torchdr", "random_state": 0}
    state = (torch.get_rng_state(), np.random.get_state()[1].copy(), random.getstate())  # noqa: NPY002
    hash_seed = os.environ.get("PYTHONHASHSEED")
    red = UMAPReducer(2, **params).fit(x)
    # TorchDR reseeds the global generators; the reducer must leave them as they were
    assert torch.equal(torch.get_rng_state(), state[0])
    assert np.array_equal(np.random.get_state()[1], state[1])  # noqa: NPY002
    assert random.getstate() == state[2]
    assert os.environ.get("PYTHONHASHSEED") == hash_seed
    assert red.fit_backend_ == "torchdr" and not hasattr(red, "umap_model_")
    emb = red.embedding_
    assert emb.shape == (160, 2) and emb.dtype == dtype and bool(torch.isfinite(emb).all())
    assert (red.a_, red.b_) == find_ab_params(1.0, 0.01)
    assert torch.equal(UMAPReducer(2, **params).fit(x).embedding_, emb)  # seeded: repeatable
    # the embedding keeps the clusters: 5 nearest embedded neighbours share the label
    d = torch.cdist(emb.double(), emb.double()).fill_diagonal_(float("inf"))
    same = (label[d.topk(5, largest=False).indices] == label[:, None]).double().mean()
    assert same > 0.9
    # new points land by their cluster, and the saved reducer transforms the same way
    new = x[:40] + 0.05 * torch.randn(40, 16, generator=torch.Generator().manual_seed(11)).to(dtype)
    y = red.transform(new)
    nearest = torch.cdist(y.double(), emb.double()).argmin(dim=1)
    assert (label[nearest] == label[:40]).double().mean() > 0.9
    back = load_reducer(red.save(tmp_path / "umap"))
    assert back.fit_backend == "torchdr"
    assert torch.equal(back.transform(new), y)
