"""Geometric encoders Φ: per-point descriptors of a point cloud's local 3D structure.

Every encoder follows :class:`GeometricEncoder`: ``encode(points, normals, mask, diameter)`` maps a
padded batch of clouds ``(B, P, 3)`` to descriptors ``(B, P, D)``; padded rows (``mask`` False)
come back as zeros. Encoders are frozen: no gradients, no training.

- :class:`FPFHEncoder`: multi-scale FPFH at radii given as fractions of the object diameter (the
  paper's two scales, 30 % and 40 %), concatenated and L2-normalised. Weight-free, the offline
  default. It runs Open3D's FPFH as a compiled CPU kernel (``poseflow.features._fpfh_cpu``, the
  default on CPU), as :func:`~poseflow.features.fpfh.compute_fpfh` in batched PyTorch (CPU or
  CUDA; re-exported here with :func:`~poseflow.features.fpfh.estimate_outward_normals`, the
  normals of :func:`open3d_normals` in PyTorch), or Open3D itself cloud by cloud.
- :class:`~poseflow.features.gedi.GeDiEncoder`: GeDi's architecture in plain PyTorch (own module).
- :class:`TorchScriptEncoder` and :class:`CallableEncoder`: adapters that plug in any per-point
  encoder (dGeDi exported to TorchScript, a user's function).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np
import torch

from poseflow._api import Hyperparameters
from poseflow._checks import check_tensor
from poseflow.errors import DegenerateInputError, MissingWeightsError, ShapeError, ValueRangeError
from poseflow.features.fpfh import check_clouds, compute_fpfh, estimate_outward_normals

__all__ = [
    "FPFH_BACKENDS",
    "CallableEncoder",
    "CheckedClouds",
    "FPFHEncoder",
    "GeometricEncoder",
    "TorchScriptEncoder",
    "check_geometric_inputs",
    "check_radius_fractions",
    "compute_fpfh",
    "encode_on_support",
    "estimate_outward_normals",
    "open3d_normals",
]


class CheckedClouds(NamedTuple):
    """A padded batch of clouds after :func:`check_geometric_inputs`, what an encoder describes.

    Attributes:
        points: clouds ``(B, P, 3)`` in metres, finite.
        normals: unit normals ``(B, P, 3)``, or None.
        mask: valid points ``(B, P)`` bool (at least 3 per cloud).
        diameter: object diameters ``(B,)`` in metres, positive, in the points' dtype.
    """

    points: torch.Tensor
    normals: torch.Tensor | None
    mask: torch.Tensor
    diameter: torch.Tensor


@runtime_checkable
class GeometricEncoder(Protocol):
    """What the pipeline needs from a geometric encoder: ``dim`` and :meth:`encode`.

    Any object with both is one. The built-in encoders also subclass it to inherit its
    :meth:`encode`, which checks the inputs and describes the :class:`CheckedClouds` with the
    subclass's ``_describe(clouds) -> (B, P, D)``.

    Attributes:
        dim: the descriptor size ``D``.
    """

    dim: int

    @torch.no_grad()
    def encode(
        self,
        points: torch.Tensor,
        normals: torch.Tensor | None,
        mask: torch.Tensor | None,
        diameter: torch.Tensor | float,
    ) -> torch.Tensor:
        """Describe every point: ``(B, P, 3)`` points → ``(B, P, D)`` descriptors.

        Args:
            points: clouds ``(B, P, 3)`` in metres.
            normals: unit normals ``(B, P, 3)`` oriented outward, or None.
            mask: valid points ``(B, P)`` bool, or None (all valid).
            diameter: object diameter(s) in metres, float or ``(B,)``.

        Returns:
            Descriptors ``(B, P, D)``, zero on padded rows.

        Raises:
            ShapeError: a shape, dtype or device mismatch.
            ValueRangeError: non-finite points or a diameter that is not positive.
            DegenerateInputError: a cloud with fewer than 3 valid points.
        """
        clouds = CheckedClouds(
            points, normals, *check_geometric_inputs(points, normals, mask, diameter)
        )
        return self._describe(clouds)  # type: ignore[attr-defined]


def check_radius_fractions(radius_fractions: Sequence[float]) -> tuple[float, ...]:
    """Multi-scale radii as fractions of the object diameter, checked: a non-empty positive tuple.

    Raises:
        ValueRangeError: none given, or one that is not positive.
    """
    if not radius_fractions or any(r <= 0 for r in radius_fractions):
        raise ValueRangeError(f"radius_fractions must be positive, got {radius_fractions}")
    return tuple(float(r) for r in radius_fractions)


def encode_on_support(
    encoder: GeometricEncoder,
    points: torch.Tensor,
    normals: torch.Tensor,
    mask: torch.Tensor | None,
    support: torch.Tensor,
    support_normals: torch.Tensor,
    support_mask: torch.Tensor | None,
    diameter: torch.Tensor | float,
) -> torch.Tensor:
    """Describe sparse points with neighbourhoods drawn from a denser cloud of the same surface.

    A descriptor such as FPFH summarises the surface within a radius; computed among a few
    dozen sampled points alone, its neighbourhoods hold a handful of points and it says little.
    Here every point is described within ``[points ; support]``, so the neighbourhoods are
    those of the support cloud (a thinned dense cloud), and the rows of ``points`` are kept (an
    encoder with an ``encode_first`` method, as :class:`FPFHEncoder`, describes only those).

    Args:
        encoder: the geometric encoder.
        points: the points to describe ``(B, N, 3)``.
        normals: their unit normals ``(B, N, 3)``.
        mask: their validity ``(B, N)``, or None.
        support: the denser cloud ``(B, M, 3)``, same frame.
        support_normals: its unit normals ``(B, M, 3)``, oriented as ``normals``.
        support_mask: its validity ``(B, M)``, or None.
        diameter: object diameter(s) in metres, float or ``(B,)``.

    Returns:
        Descriptors ``(B, N, D)``.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> surface = torch.rand(1, 400, 3, generator=g) * torch.tensor([0.1, 0.1, 0.0])
        >>> up = torch.tensor([0.0, 0.0, 1.0]).expand(1, 400, 3)
        >>> out = encode_on_support(FPFHEncoder(backend="torch"), surface[:, :8], up[:, :8], None,
        ...                         surface, up, None, 0.15)
        >>> out.shape
        torch.Size([1, 8, 66])
    """
    n = check_tensor(points, "points", ("B", "N", 3))["N"]
    check_tensor(support, "support", (points.shape[0], "M", 3))

    cloud = torch.cat([points, support.to(points)], 1)
    cloud_normals = torch.cat([normals, support_normals.to(normals)], 1)
    cloud_mask = None
    if mask is not None or support_mask is not None:
        cloud_mask = torch.cat([_all_valid(points, mask), _all_valid(support, support_mask)], 1)
    encode_first = getattr(encoder, "encode_first", None)
    if encode_first is not None:
        return encode_first(cloud, cloud_normals, cloud_mask, diameter, n)
    return encoder.encode(cloud, cloud_normals, cloud_mask, diameter)[:, :n]


def _all_valid(points: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """``mask``, or all True ``(B, P)`` when it is None."""
    if mask is not None:
        return mask
    return torch.ones(points.shape[:2], dtype=torch.bool, device=points.device)


def check_geometric_inputs(
    points: torch.Tensor,
    normals: torch.Tensor | None,
    mask: torch.Tensor | None,
    diameter: torch.Tensor | float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate the encoder inputs and return ``(mask (B, P), diameter (B,))`` filled in.

    Args:
        points: clouds, shape ``(B, P, 3)``, finite.
        normals: unit normals, shape ``(B, P, 3)``, or None.
        mask: valid points, shape ``(B, P)`` bool, or None (all valid).
        diameter: object diameter in metres, a float or a tensor of shape ``(B,)``.

    Returns:
        The mask ``(B, P)`` and the diameters ``(B,)`` on the points' device and dtype.

    Raises:
        ShapeError: on a shape, dtype or device mismatch.
        ValueRangeError: non-finite points or a diameter that is not positive.
        DegenerateInputError: a cloud with fewer than 3 valid points.

    Example:
        >>> m, d = check_geometric_inputs(torch.rand(2, 5, 3), None, None, 0.1)
        >>> m.shape, d.shape
        (torch.Size([2, 5]), torch.Size([2]))
    """
    mask, sizes = check_clouds(points, normals, mask, finite_everywhere=True)
    if isinstance(diameter, torch.Tensor):
        if diameter.dim() == 0:
            diameter = diameter.expand(sizes["B"])
        check_tensor(diameter, "diameter", ("B",), finite=True, sizes=sizes)
        diameter = diameter.to(device=points.device, dtype=points.dtype)
    else:
        diameter = torch.full(
            (sizes["B"],), float(diameter), dtype=points.dtype, device=points.device
        )
    if not bool((diameter > 0).all()):
        raise ValueRangeError(f"diameter must be positive, got {diameter.tolist()}")
    counts = mask.sum(dim=1)
    if bool((counts < 3).any()):
        raise DegenerateInputError(
            f"every cloud needs at least 3 valid points, got counts {counts.tolist()}"
        )
    return mask, diameter


def open3d_normals(points: np.ndarray, radius: float, *, max_nn: int = 30) -> np.ndarray:
    """Estimate unit normals with Open3D, oriented away from the cloud's centroid.

    Orienting away from the centroid gives a query model and an observed partial view the same
    (outward) convention, which FPFH needs: its angles change when a normal flips.

    Args:
        points: one cloud, shape ``(P, 3)``, float64.
        radius: neighbourhood radius in metres.
        max_nn: neighbours used at most.

    Returns:
        Normals of shape ``(P, 3)``, float64.

    Example:
        >>> import numpy as np
        >>> pts = np.random.default_rng(0).normal(size=(200, 3))
        >>> pts /= np.linalg.norm(pts, axis=1, keepdims=True)
        >>> n = open3d_normals(pts, 0.5)
        >>> bool((np.sum(n * pts, axis=1) > 0.9).mean() > 0.9)
        True
    """
    from poseflow.render.backend import import_open3d

    o3d = import_open3d("Open3D's normals and FPFH")

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
    normals = np.asarray(pcd.normals).copy()
    outward = points - points.mean(axis=0, keepdims=True)
    flip = np.sum(normals * outward, axis=1) < 0
    normals[flip] *= -1
    return normals


#: :class:`FPFHEncoder`'s backends.
FPFH_BACKENDS = ("auto", "numba", "torch", "open3d")


class FPFHEncoder(Hyperparameters, GeometricEncoder):
    """Multi-scale FPFH descriptors, concatenated and L2-normalised.

    Each scale is Open3D's 33-bin FPFH histogram with a hybrid search of radius
    ``fraction * diameter`` and at most ``max_nn`` neighbours; the scales are concatenated
    (``D = 33 * len(radius_fractions)``) and each row is L2-normalised. The backends give the
    same descriptors to float64 rounding, except where Open3D's own result hangs on rounding
    (neighbours at exactly equal distances, as a point and its copy in a support cloud are;
    two neighbours whose normals are equal up to rounding, as estimated normals on a flat face
    can be):

    - ``"numba"``: a compiled kernel, cloud by cloud, on the CPU in float64; the scales share
      one neighbour search and each pair's feature is computed once. With :meth:`encode_first`
      it builds the histograms of the described points and their neighbours only.
    - ``"torch"``: :func:`compute_fpfh`, the whole padded batch at once on the input's device
      (CPU or CUDA), float64 inside; the scales share one neighbour search. Needs no Open3D.
    - ``"open3d"``: Open3D's ``compute_fpfh_feature``, cloud by cloud, on the CPU in float64.
    - ``"auto"`` (default): ``"numba"`` for CPU inputs, ``"torch"`` for any other device. On
      one CPU thread the compiled kernel is the fastest on FunFlow6D's clouds (hundreds of
      points); its neighbour search is brute force, quadratic in the points, so Open3D's k-d
      tree can be faster on clouds of thousands (``benchmarks/features.py`` prints the ratios).

    The descriptors have the input's device and dtype, unit norm on valid rows (a point with an
    empty neighbourhood gets a zero histogram) and zero on padded rows.

    Args:
        radius_fractions: FPFH radii as fractions of the object diameter (paper: 0.30 and 0.40).
        max_nn: neighbours per FPFH query at most (bounds the cost on dense clouds).
        normal_radius_fraction: normal-estimation radius as a fraction of the diameter, used when
            ``encode`` gets no normals (at most 30 neighbours, turned away from the centroid:
            :func:`estimate_outward_normals`, or :func:`open3d_normals` with ``"open3d"``).
        backend: one of :data:`FPFH_BACKENDS`.

    Example:
        >>> enc = FPFHEncoder()
        >>> pts = torch.rand(2, 300, 3, generator=torch.Generator().manual_seed(0)) * 0.1
        >>> f = enc.encode(pts, None, None, 0.17)
        >>> f.shape, enc.dim
        (torch.Size([2, 300, 66]), 66)
        >>> bool(torch.allclose(f.norm(dim=-1), torch.ones(2, 300), atol=1e-5))
        True
    """

    def __init__(
        self,
        *,
        radius_fractions: Sequence[float] = (0.30, 0.40),
        max_nn: int = 100,
        normal_radius_fraction: float = 0.05,
        backend: str = "auto",
    ) -> None:
        if max_nn < 3:
            raise ValueRangeError(f"max_nn must be at least 3, got {max_nn}")
        if backend not in FPFH_BACKENDS:
            raise ValueRangeError(
                f"backend must be one of {', '.join(map(repr, FPFH_BACKENDS))}, got {backend!r}"
            )
        self.radius_fractions = check_radius_fractions(radius_fractions)
        self.max_nn = int(max_nn)
        self.normal_radius_fraction = float(normal_radius_fraction)
        self.backend = backend
        self.dim = 33 * len(self.radius_fractions)

    def _describe(self, clouds: CheckedClouds) -> torch.Tensor:
        """Unit-norm descriptors ``(B, P, D)`` (:meth:`~GeometricEncoder.encode`)."""
        return self._describe_first(clouds, clouds.points.shape[1])

    @torch.no_grad()
    def encode_first(
        self,
        points: torch.Tensor,
        normals: torch.Tensor | None,
        mask: torch.Tensor | None,
        diameter: torch.Tensor | float,
        count: int,
    ) -> torch.Tensor:
        """:meth:`encode`'s descriptors of the first ``count`` points only ``(B, count, D)``.

        Their neighbourhoods are drawn from all the points. The compiled kernel and Open3D then
        compute the histograms of those points and their neighbours only (about half the time
        of :meth:`encode` on a support cloud ten times larger); the torch backend describes
        every point and slices.
        """
        clouds = CheckedClouds(
            points, normals, *check_geometric_inputs(points, normals, mask, diameter)
        )
        if not 0 <= count <= points.shape[1]:
            raise ValueRangeError(f"count must lie in [0, {points.shape[1]}], got {count}")
        return self._describe_first(clouds, count)

    def _describe_first(self, clouds: CheckedClouds, count: int) -> torch.Tensor:
        """Unit-norm descriptors of the first ``count`` points, in the points' device and dtype."""
        points = clouds.points
        backend = self.backend
        if backend == "auto":
            backend = "numba" if points.device.type == "cpu" else "torch"
        if backend == "torch":
            out = self._encode_torch(clouds)[:, :count]
        elif backend == "numba":
            out = self._encode_numba(clouds, count)
        else:
            out = self._encode_open3d(clouds, count)
        out = torch.nn.functional.normalize(out, dim=-1)
        return out.to(device=points.device, dtype=points.dtype)

    def _normals64(self, clouds: CheckedClouds) -> torch.Tensor:
        """The clouds' float64 normals, estimated (:func:`estimate_outward_normals`) if absent."""
        if clouds.normals is not None:
            return clouds.normals.to(torch.float64)
        radius = self.normal_radius_fraction * clouds.diameter.to(torch.float64)
        pts = clouds.points.to(torch.float64)
        return estimate_outward_normals(pts, clouds.mask, radius=radius, max_nn=30)

    def _encode_torch(self, clouds: CheckedClouds) -> torch.Tensor:
        """Raw float64 histograms ``(B, P, D)`` by :func:`compute_fpfh`."""
        pts = clouds.points.to(torch.float64)
        diameter = clouds.diameter.to(torch.float64)
        nrm = self._normals64(clouds)
        fractions = torch.tensor(self.radius_fractions, dtype=torch.float64, device=pts.device)
        return compute_fpfh(
            pts, nrm, clouds.mask, radius=diameter[:, None] * fractions, max_nn=self.max_nn
        )

    def _encode_numba(self, clouds: CheckedClouds, count: int) -> torch.Tensor:
        """Raw float64 CPU histograms of the first ``count`` points ``(B, count, D)``, compiled."""
        from poseflow.features._fpfh_cpu import fpfh_first_kernel

        points = clouds.points.detach().cpu().double()
        normals = self._normals64(clouds).detach().cpu()
        mask = clouds.mask.cpu()
        out = torch.zeros(points.shape[0], count, self.dim, dtype=torch.float64)
        for b in range(points.shape[0]):
            valid = mask[b]
            described = valid[:count]
            if not bool(described.any()):
                continue
            d = float(clouds.diameter[b])
            bounds = np.array([(fraction * d) ** 2 for fraction in self.radius_fractions])
            order = valid.nonzero()[:, 0]  # the described points come first
            histograms = fpfh_first_kernel(
                points[b, order].numpy(),
                normals[b, order].numpy(),
                int(described.sum()),
                bounds,
                self.max_nn,
            )
            out[b, described] = torch.from_numpy(histograms)
        return out

    def _encode_open3d(self, clouds: CheckedClouds, count: int) -> torch.Tensor:
        """Raw float64 CPU histograms of the first ``count`` points ``(B, count, D)``, by Open3D."""
        from poseflow.render.backend import import_open3d

        o3d = import_open3d("Open3D's normals and FPFH")

        points, normals, diameter = clouds.points, clouds.normals, clouds.diameter
        out = torch.zeros(points.shape[0], count, self.dim, dtype=torch.float64)
        pts_np = points.detach().cpu().double().numpy()
        nrm_np = None if normals is None else normals.detach().cpu().double().numpy()
        mask_np = clouds.mask.cpu().numpy()
        for b in range(points.shape[0]):
            valid = mask_np[b]
            described = valid[:count]
            if not described.any():
                continue
            pts = np.ascontiguousarray(pts_np[b][valid])
            d = float(diameter[b])
            if nrm_np is None:
                nrm = open3d_normals(pts, self.normal_radius_fraction * d)
            else:
                nrm = np.ascontiguousarray(nrm_np[b][valid])
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
            pcd.normals = o3d.utility.Vector3dVector(nrm)
            rows = (np.cumsum(valid) - 1)[:count][described]  # their rows among the valid points
            scales = []
            for fraction in self.radius_fractions:
                param = o3d.geometry.KDTreeSearchParamHybrid(
                    radius=fraction * d, max_nn=self.max_nn
                )
                fpfh = o3d.pipelines.registration.compute_fpfh_feature(pcd, param, rows.tolist())
                scales.append(np.asarray(fpfh.data).T)
            out[b, torch.from_numpy(described)] = torch.from_numpy(np.concatenate(scales, axis=1))
        return out


class CallableEncoder(GeometricEncoder):
    """Adapt any function ``f(points, normals, mask, diameter) -> (B, P, D)`` to the protocol.

    The output is checked (shape, finiteness), padded rows are zeroed, and the result is moved to
    the input's device and dtype, so a user's encoder behaves like the built-in ones.

    Args:
        fn: the per-point encoder.
        dim: its descriptor size ``D``.
        normalize: L2-normalise every descriptor.

    Example:
        >>> fn = lambda p, n, m, d: torch.cat([p, p.norm(dim=-1, keepdim=True)], -1)
        >>> enc = CallableEncoder(fn, 4)
        >>> enc.encode(torch.rand(1, 10, 3), None, None, 1.0).shape
        torch.Size([1, 10, 4])
    """

    def __init__(
        self,
        fn: Callable[..., torch.Tensor],
        dim: int,
        *,
        normalize: bool = False,
    ) -> None:
        if dim <= 0:
            raise ValueRangeError(f"dim must be positive, got {dim}")
        self.fn = fn
        self.dim = int(dim)
        self.normalize = normalize

    def _describe(self, clouds: CheckedClouds) -> torch.Tensor:
        """Run the wrapped encoder (:meth:`~GeometricEncoder.encode`).

        Raises:
            ShapeError: the wrapped encoder returned the wrong shape.
            ValueRangeError: it returned NaN or inf on a valid point.
        """
        points, mask = clouds.points, clouds.mask
        out = self.fn(*clouds)
        if not isinstance(out, torch.Tensor) or tuple(out.shape) != (*points.shape[:2], self.dim):
            got = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
            raise ShapeError(f"encoder returned {got}, expected {(*points.shape[:2], self.dim)}")
        out = out.to(device=points.device, dtype=points.dtype)
        out = torch.where(mask[..., None], out, torch.zeros((), dtype=out.dtype, device=out.device))
        if not bool(torch.isfinite(out).all()):
            raise ValueRangeError("encoder returned NaN or inf descriptors")
        if self.normalize:
            out = torch.nn.functional.normalize(out, dim=-1)
        return out


class TorchScriptEncoder(CallableEncoder):
    """Load a TorchScript per-point encoder (e.g. dGeDi exported with ``torch.jit.save``).

    The scripted module is called as ``module(points, normals, mask, diameter)`` with
    ``normals`` replaced by zeros when None, and must return ``(B, P, D)``; it runs on the device of
    the points it receives (``map_location`` picks where it is loaded).

    What loads what: this is the one place in poseflow that reads a file other than safetensors,
    JSON, images and meshes. ``torch.jit.load`` unpickles the archive's constants and runs the
    TorchScript code it holds, which can do anything the file's author wrote, so it is opt-in:
    pass ``trust=True`` only for a file you exported yourself or trust like code you would run.
    Everything else poseflow loads (checkpoints, prepared objects, reducers, GeDi's
    ``.safetensors`` weights) is safetensors plus JSON; a GeDi ``chkpt.tar`` is read by
    ``torch.load(weights_only=True)``, which unpickles tensors only.

    Args:
        path: the ``.pt`` file written by ``torch.jit.save``.
        dim: the descriptor size ``D``.
        normalize: L2-normalise every descriptor.
        map_location: device to load the module on.
        trust: load and run the file's code (required: see above).

    Raises:
        MissingWeightsError: ``path`` does not exist.
        ValueRangeError: ``trust`` is not True (nothing is read).

    Example:
        >>> import tempfile, os
        >>> class Toy(torch.nn.Module):
        ...     def forward(self, p, n, m, d):
        ...         return torch.cat([p, n], -1)
        >>> path = os.path.join(tempfile.mkdtemp(), "toy.pt")
        >>> torch.jit.save(torch.jit.script(Toy()), path)
        >>> TorchScriptEncoder(path, 6, trust=True).encode(torch.rand(1, 8, 3), None, None, 1).shape
        torch.Size([1, 8, 6])
    """

    def __init__(
        self,
        path: str | Path,
        dim: int,
        *,
        normalize: bool = False,
        map_location: str | torch.device = "cpu",
        trust: bool = False,
    ) -> None:
        path = Path(path)
        if not path.is_file():
            raise MissingWeightsError(
                f"no TorchScript encoder at {path}: export one with "
                "torch.jit.save(torch.jit.script(model), path) and pass that path"
            )
        if trust is not True:
            raise ValueRangeError(
                f"loading the TorchScript file {path} runs the code it holds (torch.jit.load "
                "unpickles it): pass trust=True if you exported it yourself or trust it as code; "
                "poseflow's own weights are safetensors and never need this"
            )
        self.module = torch.jit.load(str(path), map_location=map_location).eval()

        def call(points, normals, mask, diameter):
            if normals is None:
                normals = torch.zeros_like(points)
            return self.module(points, normals, mask, diameter)

        super().__init__(call, dim, normalize=normalize)
