"""GeDi: generalisable and distinctive 3D local descriptors, in plain PyTorch.

GeDi (Poiesi and Boscaini, TPAMI 2022) describes a point by the patch of points within a radius
``r`` around it: the patch is expressed in a local reference frame (LRF) and scaled by ``1/r``,
so the descriptor is invariant to rotations and translations, then a PointNet++ network (a
quaternion network that refines the orientation, three set-abstraction layers, an MLP) maps it to a
unit 32-d vector. This module re-implements that architecture without custom CUDA ops
(farthest-point sampling and ball query are written with torch tensors), with parameter names that
match the public checkpoint, so its ``state_dict`` loads as is.

Shape letters: K patches, L points per patch, S sampled centres, C channels.

Weights: the public GeDi checkpoint (trained on 3DMatch) is distributed by the authors' repository,
github.com/fabiopoiesi/gedi (``download_data.py`` puts it in ``data/chkpts/3dmatch/chkpt.tar``).
Load it with :meth:`GeDiEncoder.from_checkpoint`; nothing is downloaded here. The network was
trained with ``r_lrf = 0.5`` m on 3DMatch scans voxelised at 1 cm, i.e. about 50 voxels per
radius; for objects the radius is a fraction of the object diameter (the paper's distilled dGeDi
uses 30 % and 40 %), and the cloud should be sampled densely enough that a patch holds a few hundred
points. dGeDi (the distilled, faster network the paper uses) plugs in through
:class:`~poseflow.features.geometric.TorchScriptEncoder`.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from pathlib import Path

import torch
from torch import nn
from torch.nn import functional as F

from poseflow._api import Hyperparameters
from poseflow.errors import MissingWeightsError, ShapeError, ValueRangeError
from poseflow.features.geometric import CheckedClouds, GeometricEncoder, check_radius_fractions
from poseflow.geometry.pointcloud import farthest_point_sample
from poseflow.geometry.se3 import quaternion_to_rotation

__all__ = [
    "GeDiEncoder",
    "GeDiNet",
    "ball_query",
    "local_reference_frame",
]


def local_reference_frame(
    centres: torch.Tensor,
    neighbours: torch.Tensor,
    mask: torch.Tensor,
    radius: torch.Tensor | float,
) -> torch.Tensor:
    """GeDi's local reference frame of each patch.

    ``z`` is the eigenvector of the smallest eigenvalue of the patch covariance (about the centre),
    signed so that ``Σ z·(p − p_i) ≥ 0``; ``x`` is the sum of the neighbours' offsets projected on
    the plane ``⊥ z``, weighted by ``(r − |p_i − p|)²`` and ``(z·(p_i − p))²``; the frame's columns
    are ``[x, x × z, z]`` exactly as in the public GeDi code (a reflection, kept so that the public
    weights apply; the descriptor is still invariant to rotations). When the weighted sum vanishes
    (a planar patch) ``x`` falls back to the direction of largest spread.

    Args:
        centres: patch centres ``p``, shape ``(K, 3)``.
        neighbours: patch points ``p_i``, shape ``(K, L, 3)``.
        mask: which neighbours are real, shape ``(K, L)`` bool.
        radius: the patch radius ``r`` (float or ``(K,)``).

    Returns:
        Frames of shape ``(K, 3, 3)`` (columns x, y, z), in the centres' dtype.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> nb = torch.randn(4, 50, 3, generator=g) * torch.tensor([1.0, 0.5, 0.1])
        >>> ok = torch.ones(4, 50, dtype=torch.bool)
        >>> lrf = local_reference_frame(torch.zeros(4, 3), nb, ok, 3.0)
        >>> bool(torch.allclose(lrf.transpose(1, 2) @ lrf, torch.eye(3).expand(4, 3, 3), atol=1e-5))
        True
    """
    dtype = centres.dtype
    c = centres.double()[:, None, :]
    d = neighbours.double() - c  # p_i - p
    w = mask.to(torch.float64)[..., None]
    count = w.sum(dim=1).clamp_min(1.0)
    cov = (d * w).transpose(1, 2) @ d / count[..., None]
    _, vecs = torch.linalg.eigh(cov)
    z = vecs[..., 0]
    sign = torch.where((d * w).sum(dim=1).mul(z).sum(-1) > 0, -1.0, 1.0)  # Σ z·(p − p_i) ≥ 0
    z = z * sign[:, None]
    proj = (d * z[:, None, :]).sum(-1, keepdim=True)
    v = d - proj * z[:, None, :]
    if isinstance(radius, torch.Tensor):
        r = radius.double().reshape(-1, 1, 1)
    else:
        r = torch.tensor(float(radius), dtype=torch.float64)
    alpha = (r - d.norm(dim=-1, keepdim=True)) ** 2
    x = (alpha * proj**2 * v * w).sum(dim=1)
    spread = vecs[..., 2]
    spread = spread * torch.where((v * w).sum(dim=1).mul(spread).sum(-1) < 0, -1.0, 1.0)[:, None]
    norm = x.norm(dim=-1, keepdim=True)
    x = torch.where(norm > 1e-12, x / norm.clamp_min(1e-300), spread)
    y = torch.linalg.cross(x, z, dim=-1)
    return torch.stack((x, y, z), dim=-1).to(dtype)


def ball_query(
    xyz: torch.Tensor, centres: torch.Tensor, radius: float, nsample: int
) -> torch.Tensor:
    """The first ``nsample`` points (in index order) within ``radius`` of each centre.

    Groups with fewer points are padded with their first point, as PointNet++'s ball query does.

    Args:
        xyz: points, shape ``(K, L, 3)``.
        centres: centres, shape ``(K, S, 3)``; each must have a point within ``radius``.
        radius: ball radius.
        nsample: group size.

    Returns:
        Indices into ``xyz`` of shape ``(K, S, nsample)``.

    Example:
        >>> pts = torch.tensor([[[0.0, 0, 0], [0.1, 0, 0], [5.0, 0, 0]]])
        >>> ball_query(pts, pts[:, :1], 0.5, 3)
        tensor([[[0, 1, 0]]])
    """
    L = xyz.shape[1]
    inside = torch.cdist(centres, xyz) < radius
    order = torch.arange(L, device=xyz.device).expand_as(inside)
    key = torch.where(inside, order, order + L)
    k = min(nsample, L)
    first = key.topk(k, dim=-1, largest=False).values
    valid = first < L
    idx = torch.where(valid, first, first[..., :1])
    if k < nsample:
        idx = torch.cat([idx, idx[..., :1].expand(*idx.shape[:-1], nsample - k)], dim=-1)
    return idx


def _shared_mlp(spec: Sequence[int], conv: type[nn.Module], bn: type[nn.Module]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for c_in, c_out in itertools.pairwise(spec):
        layers += [conv(c_in, c_out, kernel_size=1, bias=False), bn(c_out), nn.ReLU(True)]
    return nn.Sequential(*layers)


class _SetAbstraction(nn.Module):
    """PointNet++ set abstraction: sample centres, group balls, shared MLP, max-pool."""

    def __init__(self, mlp: Sequence[int], npoint: int | None, radius: float, nsample: int) -> None:
        super().__init__()
        self.npoint = npoint
        self.radius = radius
        self.nsample = nsample
        self.mlps = nn.ModuleList([_shared_mlp(mlp, nn.Conv2d, nn.BatchNorm2d)])

    def forward(
        self, xyz: torch.Tensor, features: torch.Tensor | None
    ) -> tuple[torch.Tensor | None, torch.Tensor]:
        K = xyz.shape[0]
        if self.npoint is None:
            grouped = xyz.transpose(1, 2)[:, :, None, :]  # (K, 3, 1, L)
            if features is not None:
                grouped = torch.cat([grouped, features[:, :, None, :]], dim=1)
            new_xyz = None
        else:
            centre_idx = farthest_point_sample(xyz.detach(), self.npoint)[0]
            rows = torch.arange(K, device=xyz.device)[:, None]
            new_xyz = xyz[rows, centre_idx]  # (K, S, 3)
            group = ball_query(xyz, new_xyz, self.radius, self.nsample)  # (K, S, n)
            rows3 = rows[..., None]
            grouped = (xyz[rows3, group] - new_xyz[:, :, None, :]).permute(0, 3, 1, 2)
            if features is not None:
                feats = features.transpose(1, 2)[rows3, group].permute(0, 3, 1, 2)
                grouped = torch.cat([grouped, feats], dim=1)
        out = self.mlps[0](grouped).amax(dim=-1)  # (K, C, S)
        return new_xyz, out


class _QuaternionNet(nn.Module):
    """PointNet that predicts a rotation (as a unit quaternion) refining the LRF."""

    def __init__(self, width: float) -> None:
        super().__init__()
        c = [max(1, round(w * width)) for w in (256, 512, 1024, 512, 256)]
        self.conv1 = nn.Sequential(
            nn.Conv1d(3, c[0], 1, bias=False), nn.BatchNorm1d(c[0]), nn.ReLU()
        )
        self.conv2 = nn.Sequential(
            nn.Conv1d(c[0], c[1], 1, bias=False), nn.BatchNorm1d(c[1]), nn.ReLU()
        )
        self.conv3 = nn.Sequential(nn.Conv1d(c[1], c[2], 1, bias=False), nn.BatchNorm1d(c[2]))
        self.fc1 = nn.Sequential(nn.Linear(c[2], c[3], bias=False), nn.BatchNorm1d(c[3]), nn.ReLU())
        self.fc2 = nn.Sequential(nn.Linear(c[3], c[4], bias=False), nn.BatchNorm1d(c[4]), nn.ReLU())
        self.fc3 = nn.Linear(c[4], 4)
        nn.init.zeros_(self.fc3.bias)

    def forward(self, pc: torch.Tensor) -> torch.Tensor:
        x = self.conv3(self.conv2(self.conv1(pc))).amax(dim=2)
        q = self.fc3(self.fc2(self.fc1(x)))
        identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=q.dtype, device=q.device)
        return F.normalize(q + identity, dim=1)


class GeDiNet(nn.Module):
    """GeDi's network: quaternion refinement, three set abstractions, MLP head, unit output.

    Parameter names follow the public checkpoint (``qnet``, ``samodule1..3``, ``fc_layer``).

    Args:
        dim: descriptor size (32 for the public weights).
        width: channel multiplier (1.0 for the public weights; smaller values give a light
            network of the same structure, e.g. for tests).

    Example:
        >>> net = GeDiNet(width=1 / 16).eval()
        >>> patches = torch.rand(2, 3, 128, generator=torch.Generator().manual_seed(0)) - 0.5
        >>> net(patches).shape
        torch.Size([2, 32])
    """

    def __init__(self, dim: int = 32, *, width: float = 1.0) -> None:
        super().__init__()

        def ch(c: int) -> int:
            return max(1, round(c * width))

        self.dim = dim
        self.qnet = _QuaternionNet(width)
        self.samodule1 = _SetAbstraction([3, ch(128), ch(128), ch(128)], 128, 0.2, 32)
        self.samodule2 = _SetAbstraction([ch(128) + 3, ch(256), ch(256), ch(256)], 64, 0.4, 16)
        self.samodule3 = _SetAbstraction([ch(256) + 3, ch(512), ch(512), ch(1024)], None, 0.0, 0)
        self.fc_layer = nn.Sequential(
            nn.Linear(ch(1024), ch(512), bias=False),
            nn.BatchNorm1d(ch(512)),
            nn.ReLU(True),
            nn.Linear(ch(512), ch(256), bias=False),
            nn.BatchNorm1d(ch(256)),
            nn.ReLU(True),
            nn.Dropout(0.3),
            nn.Linear(ch(256), dim),
        )

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        """Describe canonical patches ``(K, 3, L)`` (``L ≥ 128``) as unit vectors ``(K, dim)``."""
        if patches.dim() != 3 or patches.shape[1] != 3 or patches.shape[2] < 128:
            raise ShapeError(f"patches must have shape (K, 3, L>=128), got {tuple(patches.shape)}")
        R = quaternion_to_rotation(self.qnet(patches))
        pc = R @ patches
        xyz = pc.transpose(1, 2).contiguous()
        xyz, feat = self.samodule1(xyz, None)
        xyz, feat = self.samodule2(xyz, feat)
        _, feat = self.samodule3(xyz, feat)
        return F.normalize(self.fc_layer(feat.squeeze(-1)), dim=1)


class GeDiEncoder(Hyperparameters, GeometricEncoder):
    """Multi-scale GeDi descriptors behind the geometric-encoder protocol.

    For every valid point and every radius ``r = fraction * diameter``: the valid points within
    ``r`` form the patch; all of them define the LRF, ``samples_per_patch`` of them (drawn at
    random, with replicas when the patch is smaller) are expressed in the LRF, divided by ``r`` and
    described by the network. The per-scale 32-d unit descriptors are concatenated and
    L2-normalised (two scales give the paper's ``D = 64``).

    Args:
        net: a :class:`GeDiNet` (put in eval mode here).
        radius_fractions: patch radii as fractions of the object diameter.
        samples_per_patch: points per patch fed to the network (512 in GeDi; at least 128).
        patch_batch: patches per forward pass (bounds memory).
        seed: seed of the patch sampling, so that descriptors are reproducible.

    Example:
        >>> enc = GeDiEncoder(GeDiNet(width=1 / 16), samples_per_patch=128)
        >>> pts = torch.rand(1, 40, 3, generator=torch.Generator().manual_seed(0))
        >>> enc.encode(pts, None, None, 1.0).shape
        torch.Size([1, 40, 64])
    """

    def __init__(
        self,
        net: GeDiNet,
        *,
        radius_fractions: Sequence[float] = (0.30, 0.40),
        samples_per_patch: int = 512,
        patch_batch: int = 128,
        seed: int = 0,
    ) -> None:
        if samples_per_patch < 128:
            raise ValueRangeError(
                f"samples_per_patch must be at least 128, got {samples_per_patch}"
            )
        self.net = net.eval()
        self.radius_fractions = check_radius_fractions(radius_fractions)
        self.samples_per_patch = int(samples_per_patch)
        self.patch_batch = int(patch_batch)
        self.seed = int(seed)
        self.dim = net.dim * len(self.radius_fractions)

    @classmethod
    def from_checkpoint(
        cls,
        path: str | Path,
        *,
        map_location: str | torch.device = "cpu",
        **kwargs: object,
    ) -> GeDiEncoder:
        """Build the encoder from the public GeDi weights.

        Accepts a ``.safetensors`` file, or a torch checkpoint (``chkpt.tar``) read with
        ``weights_only=True`` whose state dict is the file itself or its ``pnet_model_state_dict``
        entry (a ``module.`` prefix from DataParallel is dropped).

        Args:
            path: the weights file.
            map_location: device to load onto.
            **kwargs: forwarded to :class:`GeDiEncoder` (radii, samples, ...).

        Raises:
            MissingWeightsError: the file does not exist.
        """
        path = Path(path)
        if not path.is_file():
            raise MissingWeightsError(
                f"no GeDi checkpoint at {path}: get chkpt.tar from github.com/fabiopoiesi/gedi "
                "(python download_data.py, then data/chkpts/3dmatch/chkpt.tar) and pass its path"
            )
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path), device=str(map_location))
        else:
            state = torch.load(str(path), map_location=map_location, weights_only=True)
            if "pnet_model_state_dict" in state:
                state = state["pnet_model_state_dict"]
        state = {k.removeprefix("module."): v for k, v in state.items()}
        dim = state["fc_layer.7.weight"].shape[0]
        net = GeDiNet(dim)
        net.load_state_dict(state)
        return cls(net.to(map_location), **kwargs)  # type: ignore[arg-type]

    def _describe(self, clouds: CheckedClouds) -> torch.Tensor:
        """Unit-norm descriptors ``(B, P, D)`` (:meth:`~GeometricEncoder.encode`), zero on padding.

        In the points' dtype, computed on the network's device; the normals are not used (the LRF
        replaces them).
        """
        points, mask, diameter = clouds.points, clouds.mask, clouds.diameter
        param = next(self.net.parameters())
        out = torch.zeros(*points.shape[:2], self.dim, dtype=points.dtype, device=points.device)
        for b in range(points.shape[0]):
            cloud = points[b][mask[b]].to(device=param.device, dtype=param.dtype)
            gen = torch.Generator(device=param.device).manual_seed(self.seed)
            scales = [
                self._encode_cloud(cloud, fraction * float(diameter[b]), gen)
                for fraction in self.radius_fractions
            ]
            feat = F.normalize(torch.cat(scales, dim=1), dim=1)
            out[b, mask[b]] = feat.to(device=points.device, dtype=points.dtype)
        return out

    def _encode_cloud(
        self, cloud: torch.Tensor, radius: float, gen: torch.Generator
    ) -> torch.Tensor:
        n, L = cloud.shape[0], self.samples_per_patch
        feats = []
        for start in range(0, n, self.patch_batch):
            centres = cloud[start : start + self.patch_batch]
            inside = torch.cdist(centres, cloud) <= radius  # (k, n), the centre is inside
            lrf = local_reference_frame(
                centres, cloud[None].expand(len(centres), -1, -1), inside, radius
            )
            keys = torch.rand(inside.shape, generator=gen, device=cloud.device, dtype=cloud.dtype)
            keys = torch.where(inside, keys, keys + 2.0)
            take = min(L, n)
            order = keys.topk(take, dim=1, largest=False).indices
            count = inside.sum(dim=1, keepdim=True)
            slot = torch.arange(L, device=cloud.device)[None] % count.clamp_max(take)
            idx = order.gather(1, slot)
            local = (cloud[idx] - centres[:, None, :]) / radius  # (k, L, 3)
            patches = (local @ lrf).transpose(1, 2)  # coordinates in the LRF, (k, 3, L)
            feats.append(self.net(patches.contiguous()))
        return torch.cat(feats, dim=0)
