"""Dimensionality reduction of appearance features, with the scikit-learn estimator API.

The paper fits UMAP on the query features ``S_Q`` of an object only, then projects every target
instance ``S_T`` into the same low-dimensional manifold. :class:`UMAPReducer` fits with TorchDR's
GPU UMAP when the features are on CUDA and TorchDR is installed (``pip install
'poseflow[gpu]'``), as the paper does, and with umap-learn otherwise; it projects new points with
its own out-of-sample transform written in torch (CPU or CUDA, batched over instances; see
:mod:`poseflow.features.umap_transform`).

:class:`PCAReducer` and :class:`IdentityReducer` share the API for the ablation; all three derive
from the abstract :class:`Reducer`. Fitted reducers save to a directory as
``reducer.safetensors`` (arrays) plus ``reducer.json`` (class and parameters), never a pickle,
and :func:`load_reducer` brings them back on any device.

Inputs may be numpy arrays ``(N, G)`` (numpy comes back) or torch tensors ``(N, G)`` or
``(B, M, G)`` with an optional mask ``(B, M)`` (torch comes back, on the input's device and in
its dtype; padded rows are zero).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import random
from abc import ABC, abstractmethod
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any, TypeVar

import numpy as np
import torch
from torch.nn import functional as F

from poseflow._checks import check_mask, check_tensor
from poseflow.errors import (
    DegenerateInputError,
    MissingDependencyError,
    ShapeError,
    ValueRangeError,
)
from poseflow.features.umap_transform import (
    fuzzy_membership,
    nearest_training_points,
    refine_embedding,
)

__all__ = [
    "IdentityReducer",
    "PCAReducer",
    "Reducer",
    "UMAPReducer",
    "find_ab_params",
    "load_reducer",
]

_METRICS = ("cosine", "euclidean")
_FIT_BACKENDS = ("auto", "torchdr", "umap-learn")


def find_ab_params(spread: float = 1.0, min_dist: float = 0.01) -> tuple[float, float]:
    """Fit UMAP's low-dimensional kernel ``1 / (1 + a d^{2b})`` to ``spread`` and ``min_dist``.

    The kernel is fitted (least squares) to 1 below ``min_dist`` and ``exp(−(d − min_dist) /
    spread)`` above it, on ``d ∈ [0, 3 spread]``, as UMAP defines it.

    Example:
        >>> a, b = find_ab_params(1.0, 0.1)
        >>> round(a, 2), round(b, 2)
        (1.58, 0.9)
    """
    from scipy.optimize import curve_fit

    if spread <= 0 or min_dist < 0:
        raise ValueRangeError(f"need spread > 0 and min_dist >= 0, got {spread}, {min_dist}")
    x = np.linspace(0, spread * 3, 300)
    y = np.where(x < min_dist, 1.0, np.exp(-(x - min_dist) / spread))

    def curve(d: np.ndarray, a: float, b: float) -> np.ndarray:
        return 1.0 / (1.0 + a * d ** (2 * b))

    (a, b), _ = curve_fit(curve, x, y)
    return float(a), float(b)


_R = TypeVar("_R", bound="Reducer")


class Reducer(ABC):
    """Base class of the reducers: input conversion, batching with masks, save/load.

    A subclass implements :meth:`_fit` (learn from the prepared training rows) and
    :meth:`_transform` (project prepared rows) and lists, for :meth:`save` and
    :func:`load_reducer`, its fitted tensors in ``_arrays``, its constructor parameters in
    ``_params`` and its fitted scalars in ``_scalars``. Inputs reach both methods as a
    ``(N, G)`` tensor, already L2-normalised along ``G`` when ``normalize`` is set.

    Example:
        >>> class Scale(Reducer):
        ...     _params = ("factor",)
        ...     normalize = False
        ...     def __init__(self, factor: float = 2.0) -> None:
        ...         self.factor = factor
        ...     def _fit(self, x: torch.Tensor) -> None:
        ...         pass
        ...     def _transform(self, x: torch.Tensor) -> torch.Tensor:
        ...         return self.factor * x
        >>> Scale().fit_transform(torch.ones(2, 3))
        tensor([[2., 2., 2.],
                [2., 2., 2.]])
    """

    _arrays: tuple[str, ...] = ()
    _params: tuple[str, ...] = ()
    _scalars: tuple[str, ...] = ()

    normalize: bool

    def fit(self: _R, X: torch.Tensor | np.ndarray, y: None = None) -> _R:
        """Fit on the query features ``X`` ``(N, G)``; returns ``self``."""
        feats = self._prepare(_as_tensor(X, "X"))
        if feats.shape[0] < 2:
            raise DegenerateInputError(f"need at least 2 samples to fit, got {feats.shape[0]}")
        self._fit(feats)
        self.n_features_in_ = int(feats.shape[1])
        return self

    def transform(
        self, X: torch.Tensor | np.ndarray, mask: torch.Tensor | None = None
    ) -> torch.Tensor | np.ndarray:
        """Project ``X`` ``(N, G)`` or ``(B, M, G)`` (with an optional mask ``(B, M)``).

        Returns:
            The projection ``(N, D)`` or ``(B, M, D)``, numpy for numpy input, else torch on the
            input's device and dtype (padded rows zero).
        """
        self._check_fitted()
        is_numpy = isinstance(X, np.ndarray)
        x = _as_tensor(X, "X")
        batched = x.dim() == 3
        if batched:
            sizes = check_tensor(x, "X", ("B", "M", self.n_features_in_), finite=True)
            if mask is None:
                mask = torch.ones(x.shape[:2], dtype=torch.bool, device=x.device)
            check_mask(mask, "mask", ("B", "M"), sizes)
            rows = x[mask]
        else:
            check_tensor(x, "X", ("N", self.n_features_in_), finite=True)
            if mask is not None:
                raise ShapeError("mask is only accepted with batched input (B, M, G)")
            rows = x
        out_rows = self._transform(self._prepare(rows)).to(device=x.device, dtype=x.dtype)
        if batched:
            out = torch.zeros(*x.shape[:2], out_rows.shape[-1], dtype=x.dtype, device=x.device)
            out[mask] = out_rows
        else:
            out = out_rows
        return out.cpu().numpy() if is_numpy else out

    def fit_transform(
        self, X: torch.Tensor | np.ndarray, y: None = None
    ) -> torch.Tensor | np.ndarray:
        """Fit on ``X`` and project it."""
        return self.fit(X).transform(X)

    def save(self, path: str | Path) -> Path:
        """Write the fitted reducer to the directory ``path`` (created); returns it.

        Files: ``reducer.safetensors`` (the fitted arrays) and ``reducer.json`` (class name,
        hyper-parameters, fitted scalars). No pickle.
        """
        from safetensors.torch import save_file

        self._check_fitted()
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        arrays = {k: getattr(self, k).detach().cpu().contiguous() for k in self._arrays}
        save_file(arrays, str(path / "reducer.safetensors"))
        meta = {
            "class": type(self).__name__,
            "params": {k: getattr(self, k) for k in self._params},
            "fitted": {k: getattr(self, k) for k in (*self._scalars, "n_features_in_")},
        }
        (path / "reducer.json").write_text(json.dumps(meta, indent=2))
        return path

    def to(self: _R, device: str | torch.device) -> _R:
        """Move the fitted arrays to ``device`` (in place); returns ``self``."""
        for k in self._arrays:
            if hasattr(self, k):
                setattr(self, k, getattr(self, k).to(device))
        return self

    def _check_fitted(self) -> None:
        if not hasattr(self, "n_features_in_"):
            raise ValueRangeError(f"{type(self).__name__} is not fitted: call fit first")

    def _prepare(self, x: torch.Tensor) -> torch.Tensor:
        check_tensor(x, "X", ("N", "G"), finite=True)
        return F.normalize(x, dim=-1) if self.normalize else x

    @abstractmethod
    def _fit(self, x: torch.Tensor) -> None:
        """Learn from the prepared training rows ``(N, G)``, setting the fitted attributes."""

    @abstractmethod
    def _transform(self, x: torch.Tensor) -> torch.Tensor:
        """Project prepared rows ``(N, G)`` to ``(N, D)``; the caller casts to the input's dtype."""


def _as_tensor(X: torch.Tensor | np.ndarray, name: str) -> torch.Tensor:
    if isinstance(X, torch.Tensor):
        return X
    if isinstance(X, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(X))
    raise ShapeError(f"{name} must be a torch.Tensor or numpy array, got {type(X).__name__}")


class IdentityReducer(Reducer):
    """No projection (the ablation's "none"), optionally L2-normalising each feature.

    Example:
        >>> IdentityReducer(normalize=True).fit_transform(torch.tensor([[3.0, 4.0], [1.0, 0.0]]))
        tensor([[0.6000, 0.8000],
                [1.0000, 0.0000]])
    """

    _params = ("normalize",)

    def __init__(self, *, normalize: bool = False) -> None:
        self.normalize = normalize

    def __repr__(self) -> str:
        return f"IdentityReducer(normalize={self.normalize})"

    def _fit(self, x: torch.Tensor) -> None:
        return None

    def _transform(self, x: torch.Tensor) -> torch.Tensor:
        return x


class PCAReducer(Reducer):
    """Principal component analysis (SVD in float64), fit on the query features.

    Args:
        n_components: output size ``D``.
        normalize: L2-normalise the input features before fitting and projecting.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> x = torch.randn(100, 2, generator=g) @ torch.tensor([[3.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        >>> pca = PCAReducer(2, normalize=False).fit(x)
        >>> pca.transform(x).shape, bool(pca.explained_variance_[0] > pca.explained_variance_[1])
        (torch.Size([100, 2]), True)
    """

    _arrays = ("mean_", "components_", "explained_variance_")
    _params = ("n_components", "normalize")

    def __init__(self, n_components: int = 64, *, normalize: bool = True) -> None:
        if n_components < 1:
            raise ValueRangeError(f"n_components must be positive, got {n_components}")
        self.n_components = n_components
        self.normalize = normalize

    def __repr__(self) -> str:
        return f"PCAReducer(n_components={self.n_components}, normalize={self.normalize})"

    def _fit(self, x: torch.Tensor) -> None:
        n, g = x.shape
        if self.n_components > min(n, g):
            raise ValueRangeError(
                f"n_components={self.n_components} exceeds min(samples, features)={min(n, g)}"
            )
        x64 = x.double()
        mean = x64.mean(dim=0)
        _, s, vh = torch.linalg.svd(x64 - mean, full_matrices=False)
        comps = vh[: self.n_components]
        # fix the sign of every component (largest-magnitude entry positive) for reproducibility
        sign = torch.sign(comps.gather(1, comps.abs().argmax(dim=1, keepdim=True)))
        self.mean_ = mean.to(x.dtype)
        self.components_ = (comps * sign).to(x.dtype)
        self.explained_variance_ = (s[: self.n_components] ** 2 / max(n - 1, 1)).to(x.dtype)

    def _transform(self, x: torch.Tensor) -> torch.Tensor:
        mean = self.mean_.to(device=x.device, dtype=x.dtype)
        return (x - mean) @ self.components_.to(device=x.device, dtype=x.dtype).T


class UMAPReducer(Reducer):
    """UMAP fitted with umap-learn, with a fast batched torch out-of-sample transform.

    Args:
        n_components: output size ``D`` (paper: 64).
        n_neighbors: neighbourhood size ``k`` (paper: 30).
        min_dist: minimum distance of the embedding (paper: 0.01).
        metric: ``"cosine"`` (paper) or ``"euclidean"``.
        normalize: L2-normalise the input features before fitting and projecting.
        random_state: seed of the fit and of the transform's negative sampling.
        n_epochs: fitting epochs (None: umap-learn's default, 500 up to 10,000 samples and 200
            above; TorchDR takes as many full-gradient iterations).
        fit_backend: who fits the embedding: ``"auto"`` (TorchDR when the features are on CUDA
            and TorchDR imports, else umap-learn), ``"torchdr"`` (always TorchDR, on the
            features' device, CPU included) or ``"umap-learn"`` (always umap-learn, on the CPU).
            Both fit the same fuzzy graph (TorchDR is given ``a`` and ``b`` of
            :func:`find_ab_params` and, for the cosine metric, squared distances between the
            L2-normalised features, which are twice the cosine distances and give the same
            memberships); their optimisers differ, so the embeddings do too.
        transform_epochs: optimisation epochs of the torch transform after the membership-weighted
            initialisation. Default 0: on the feature benchmark (mutual-NN inliers) the
            initialisation alone matches or beats umap-learn's ``transform``, while the layout
            optimisation pulls a point onto single neighbours, which costs mutual matches
            (``benchmarks/LOG.md``).
        negative_sample_rate: repulsive samples per unit of membership, as in umap-learn.
        learning_rate: initial step of the transform's optimisation (decays linearly to 0).
        optimize_neighbors: strongest edges per new point kept in the optimisation (all
            ``n_neighbors`` edges set the initial position).
        negative_draws: random training points drawn per new point and epoch to estimate the
            repulsion.
        chunk_size: new points per kNN block (bounds memory to ``chunk_size × N`` distances).

    Attributes:
        train_: the (prepared) training features ``(N, G)``.
        embedding_: their embedding ``(N, D)``, on the training features' device and dtype.
        a_, b_: the low-dimensional kernel's parameters.
        fit_backend_: ``"torchdr"`` or ``"umap-learn"``, who fitted in this process (not saved).
        umap_model_: umap-learn's estimator, after a umap-learn fit in this process (not saved).

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> train, emb = torch.randn(200, 16, generator=g), torch.randn(200, 4, generator=g)
        >>> red = UMAPReducer.from_embedding(train, emb, n_neighbors=10)
        >>> red.transform(train[:5] + 0.01 * torch.randn(5, 16, generator=g)).shape
        torch.Size([5, 4])
    """

    _arrays = ("train_", "embedding_")
    _params = (
        "n_components",
        "n_neighbors",
        "min_dist",
        "metric",
        "normalize",
        "random_state",
        "n_epochs",
        "fit_backend",
        "transform_epochs",
        "negative_sample_rate",
        "learning_rate",
        "optimize_neighbors",
        "negative_draws",
        "chunk_size",
    )
    _scalars = ("a_", "b_")

    def __init__(
        self,
        n_components: int = 64,
        *,
        n_neighbors: int = 30,
        min_dist: float = 0.01,
        metric: str = "cosine",
        normalize: bool = True,
        random_state: int | None = 0,
        n_epochs: int | None = None,
        fit_backend: str = "auto",
        transform_epochs: int = 0,
        negative_sample_rate: int = 5,
        learning_rate: float = 0.5,
        optimize_neighbors: int = 10,
        negative_draws: int = 5,
        chunk_size: int = 4096,
    ) -> None:
        if metric not in _METRICS:
            raise ValueRangeError(f"metric must be one of {_METRICS}, got {metric!r}")
        if fit_backend not in _FIT_BACKENDS:
            raise ValueRangeError(
                f"fit_backend must be one of {_FIT_BACKENDS}, got {fit_backend!r}"
            )
        if n_components < 1 or n_neighbors < 2 or transform_epochs < 0 or chunk_size < 1:
            raise ValueRangeError(
                "need n_components >= 1, n_neighbors >= 2, transform_epochs >= 0, chunk_size >= 1"
            )
        self.n_components = n_components
        self.n_neighbors = n_neighbors
        self.min_dist = min_dist
        self.metric = metric
        self.normalize = normalize
        self.random_state = random_state
        self.n_epochs = n_epochs
        self.fit_backend = fit_backend
        self.transform_epochs = transform_epochs
        self.negative_sample_rate = negative_sample_rate
        self.learning_rate = learning_rate
        self.optimize_neighbors = optimize_neighbors
        self.negative_draws = negative_draws
        self.chunk_size = chunk_size

    def __repr__(self) -> str:
        return (
            f"UMAPReducer(n_components={self.n_components}, n_neighbors={self.n_neighbors}, "
            f"min_dist={self.min_dist}, metric={self.metric!r}, normalize={self.normalize})"
        )

    @classmethod
    def from_embedding(
        cls, train: torch.Tensor, embedding: torch.Tensor, **params: Any
    ) -> UMAPReducer:
        """Build a fitted reducer from training features and their embedding (any UMAP fit).

        Useful with an embedding computed elsewhere (TorchDR on a GPU, a previous run). ``a`` and
        ``b`` come from ``min_dist`` with :func:`find_ab_params`.

        Args:
            train: training features ``(N, G)`` (normalised here if ``normalize``).
            embedding: their embedding ``(N, D)``.
            **params: constructor parameters (``n_components`` is taken from ``embedding``).
        """
        sizes = check_tensor(train, "train", ("N", "G"), finite=True)
        check_tensor(embedding, "embedding", ("N", "D"), finite=True, sizes=sizes)
        red = cls(n_components=int(embedding.shape[1]), **params)
        red.train_ = red._prepare(train)
        red.embedding_ = embedding.to(device=train.device, dtype=train.dtype)
        red.a_, red.b_ = find_ab_params(1.0, red.min_dist)
        red.n_features_in_ = int(train.shape[1])
        return red

    def resolve_fit_backend(self, device: str | torch.device) -> str:
        """Name who fits features on ``device``: ``"torchdr"`` or ``"umap-learn"``.

        Args:
            device: the device of the features to fit.

        Returns:
            ``fit_backend`` when it names one; for ``"auto"``, ``"torchdr"`` on a CUDA device
            when TorchDR imports, else ``"umap-learn"``.

        Raises:
            MissingDependencyError: ``fit_backend="torchdr"`` and TorchDR does not import.

        Example:
            >>> UMAPReducer().resolve_fit_backend("cpu")
            'umap-learn'
        """
        if self.fit_backend == "torchdr":
            _import_torchdr()
            return "torchdr"
        if self.fit_backend == "auto" and torch.device(device).type == "cuda":
            with contextlib.suppress(MissingDependencyError):
                _import_torchdr()
                return "torchdr"
        return "umap-learn"

    def _fit(self, x: torch.Tensor) -> None:
        if x.shape[0] <= self.n_neighbors:
            raise DegenerateInputError(
                f"UMAP needs more than n_neighbors={self.n_neighbors} samples, got {x.shape[0]}"
            )
        self.fit_backend_ = self.resolve_fit_backend(x.device)
        if hasattr(self, "umap_model_"):
            del self.umap_model_  # from an earlier umap-learn fit: it would describe old data
        self.train_ = x.detach().clone()
        if self.fit_backend_ == "torchdr":
            emb = self._fit_torchdr(x.detach())
        else:
            emb = self._fit_umap_learn(x.detach())
        self.embedding_ = emb.to(device=x.device, dtype=x.dtype)

    def _epochs(self, n: int) -> int:
        if self.n_epochs is not None:
            return self.n_epochs
        return 500 if n <= 10_000 else 200

    def _umap_settings(self) -> dict[str, Any]:
        """The settings that TorchDR's and umap-learn's ``UMAP`` take by the same names."""
        return {
            "n_components": self.n_components,
            "n_neighbors": self.n_neighbors,
            "min_dist": self.min_dist,
            "random_state": self.random_state,
        }

    def _fit_torchdr(self, x: torch.Tensor) -> torch.Tensor:
        """Fit with TorchDR's UMAP on ``x``'s device; returns the embedding ``(N, D)``."""
        torchdr = _import_torchdr()
        self.a_, self.b_ = find_ab_params(1.0, self.min_dist)
        if self.metric == "cosine":
            x, metric = F.normalize(x, dim=-1), "sqeuclidean"
        else:
            metric = "euclidean"
        with _restored_global_state():  # TorchDR seeds every global RNG when given a seed
            model = torchdr.UMAP(
                **self._umap_settings(),
                a=self.a_,
                b=self.b_,
                metric=metric,
                max_iter=self._epochs(x.shape[0]),
                backend=None,  # TorchDR's default, faiss, is not a dependency
                distributed=False,  # never join a torchrun process group from here
                verbose=False,
            )
            return torch.as_tensor(model.fit_transform(x)).detach()

    def _fit_umap_learn(self, x: torch.Tensor) -> torch.Tensor:
        """Fit with umap-learn on the CPU; returns the embedding ``(N, D)`` (float32, CPU)."""
        try:
            import umap
        except ImportError as err:
            raise MissingDependencyError("umap-learn", "umap", "UMAPReducer.fit") from err
        model = umap.UMAP(**self._umap_settings(), metric=self.metric, n_epochs=self.n_epochs)
        data = x.cpu().numpy().astype(np.float32)
        threads = torch.get_num_threads()
        emb = model.fit_transform(data)
        torch.set_num_threads(threads)  # umap-learn's numba/threadpool set-up changes it
        self.umap_model_ = model
        self.a_, self.b_ = float(model._a), float(model._b)
        return torch.from_numpy(np.asarray(emb))

    def transform_umap_learn(self, X: np.ndarray) -> np.ndarray:
        """Project with umap-learn's own ``transform`` (the reference; needs the in-memory fit).

        Args:
            X: features ``(N, G)``.

        Returns:
            The projection ``(N, D)``, float32 numpy.
        """
        if not hasattr(self, "umap_model_"):
            raise ValueRangeError(
                "umap-learn's transform needs a reducer fitted with umap-learn in this process"
            )
        x = self._prepare(_as_tensor(X, "X")).detach().cpu().numpy().astype(np.float32)
        return self.umap_model_.transform(x)

    def _transform(self, x: torch.Tensor) -> torch.Tensor:
        train = self.train_.to(device=x.device, dtype=x.dtype)
        emb = self.embedding_.to(device=x.device, dtype=x.dtype)
        dist, idx = nearest_training_points(
            x, train, self.n_neighbors, self.metric, self.chunk_size
        )
        weights = fuzzy_membership(dist, math.log2(self.n_neighbors))
        y = (weights[..., None] * emb[idx]).sum(dim=1) / weights.sum(dim=1, keepdim=True)
        if self.transform_epochs == 0:
            return y
        return refine_embedding(
            y,
            emb,
            idx,
            weights,
            a=self.a_,
            b=self.b_,
            epochs=self.transform_epochs,
            learning_rate=self.learning_rate,
            negative_sample_rate=self.negative_sample_rate,
            negative_draws=self.negative_draws,
            optimize_neighbors=self.optimize_neighbors,
            seed=0 if self.random_state is None else int(self.random_state),
        )


def _import_torchdr() -> ModuleType:
    """Import TorchDR, the GPU UMAP of the ``gpu`` extra.

    Returns:
        The ``torchdr`` module.

    Raises:
        MissingDependencyError: TorchDR, or a package it imports without declaring it
            (matplotlib), is not installed; the message names ``pip install 'poseflow[gpu]'``.
    """
    try:
        import torchdr
    except ImportError as err:
        missing = err.name or "torchdr"
        purpose = "UMAP on the GPU" if missing == "torchdr" else "TorchDR, which imports it"
        raise MissingDependencyError(missing, "gpu", purpose) from err
    return torchdr


@contextlib.contextmanager
def _restored_global_state() -> Iterator[None]:
    """Restore the global RNGs, ``PYTHONHASHSEED`` and cuDNN's flags on exit.

    TorchDR's estimators call its ``seed_everything`` when given a seed: it reseeds Python's,
    NumPy's and torch's global generators (CPU and every GPU), sets ``PYTHONHASHSEED`` and turns
    on ``cudnn.benchmark``; none of that may leak into the caller.
    """
    py_state = random.getstate()
    np_state = np.random.get_state()  # noqa: NPY002 (the legacy global state is what TorchDR seeds)
    hash_seed = os.environ.get("PYTHONHASHSEED")
    cudnn = torch.backends.cudnn.benchmark, torch.backends.cudnn.deterministic
    gpus = list(range(torch.cuda.device_count())) if torch.cuda.is_available() else []
    try:
        with torch.random.fork_rng(devices=gpus):
            yield
    finally:
        random.setstate(py_state)
        np.random.set_state(np_state)  # noqa: NPY002
        if hash_seed is None:
            os.environ.pop("PYTHONHASHSEED", None)
        else:
            os.environ["PYTHONHASHSEED"] = hash_seed
        torch.backends.cudnn.benchmark, torch.backends.cudnn.deterministic = cudnn


_CLASSES: dict[str, type[Reducer]] = {
    c.__name__: c for c in (IdentityReducer, PCAReducer, UMAPReducer)
}


def load_reducer(path: str | Path, *, device: str | torch.device = "cpu") -> Reducer:
    """Load a reducer written by ``save`` onto ``device``.

    Args:
        path: the directory holding ``reducer.json`` and ``reducer.safetensors``.
        device: where the fitted arrays go.

    Returns:
        The fitted reducer (its ``transform`` works; umap-learn's own transform does not, as the
        umap-learn object is not saved).

    Example:
        >>> import tempfile
        >>> pca = PCAReducer(2).fit(torch.rand(20, 5))
        >>> back = load_reducer(pca.save(tempfile.mkdtemp()))
        >>> bool(torch.allclose(back.transform(torch.ones(1, 5)), pca.transform(torch.ones(1, 5))))
        True
    """
    from safetensors.torch import load_file

    path = Path(path)
    meta = json.loads((path / "reducer.json").read_text())
    cls = _CLASSES.get(meta.get("class", ""))
    if cls is None:
        raise ValueRangeError(f"unknown reducer class {meta.get('class')!r} in {path}")
    red = cls(**meta["params"])
    for k, v in meta["fitted"].items():
        setattr(red, k, v)
    for k, v in load_file(str(path / "reducer.safetensors"), device=str(device)).items():
        setattr(red, k, v)
    return red
