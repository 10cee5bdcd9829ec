"""FunFlow6D: the model class that composes poseflow's parts into the paper's method.

Shape letters: ``B`` instances, ``N`` points per cloud, ``H`` hypotheses per instance, ``Dg`` /
``Ds`` geometric / semantic channels, ``G`` raw appearance channels.

Coordinates. Every cloud enters the flow divided by its object's half diameter ``s = d / 2``:
the query ``Q`` in its canonical frame, the observed target ``T`` centred on its barycentre
``c``. The flow carries ``(T - c) / s`` to ``T̂ / s`` with ``T̂ ≈ Tʳ = Rᵀ (T - t)`` and the pose
solvers work in the same unit, so one threshold (a fraction of the diameter) serves all objects.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from poseflow._checks import check_tensor
from poseflow.data.objects import ObjectModel
from poseflow.errors import MissingWeightsError, ShapeError, ValueRangeError
from poseflow.eval.predict import PoseEstimate, predict_dataset
from poseflow.features import (
    QueryFeatureBank,
    lift_query_features,
    lift_target_features,
    load_reducer,
)
from poseflow.flows import get_sampler, initial_noise
from poseflow.geometry.neighbors import nearest_neighbors
from poseflow.geometry.pointcloud import (
    backproject_depth,
    estimate_normals,
    farthest_point_sample,
    remove_statistical_outliers,
)
from poseflow.geometry.se3 import from_Rt, inverse_transform, transform_points
from poseflow.models.components import (
    build_appearance_encoder,
    build_geometric_encoder,
    build_reducer,
)
from poseflow.models.config import FunFlow6DConfig
from poseflow.models.network import FunFlow6DNet
from poseflow.registration import multi_scale_icp, procrustes, ransac_procrustes

__all__ = ["FunFlow6D", "Observation", "PreparedObject"]

_MIN_POINTS = 16


@dataclass
class PreparedObject:
    """What inference needs of one object, computed once by :meth:`FunFlow6D.prepare_objects`.

    Attributes:
        points: the query cloud ``Q`` ``(N, 3)``, canonical frame, metres.
        normals: its unit normals ``(N, 3)``.
        dense_points: a denser surface sample ``(Nd, 3)``, the ICP target.
        diameter: the object's diameter, metres.
        geometric: ``Φ(Q)`` ``(N, Dg)``, or None without a geometric encoder.
        bank: the multi-view appearance bank of ``Q``, or None without an appearance encoder.
        reducer: the reducer fitted on the query's appearance features, or None.
    """

    points: torch.Tensor
    normals: torch.Tensor
    dense_points: torch.Tensor
    diameter: float
    geometric: torch.Tensor | None
    bank: QueryFeatureBank | None
    reducer: Any


@dataclass
class Observation:
    """Target clouds lifted from an RGBD image, with their frozen features.

    Attributes:
        obj_ids: object of each instance ``(B,)``.
        points: target clouds ``(B, N, 3)``, camera frame, metres (padded rows repeat a point).
        normals: unit normals ``(B, N, 3)`` facing the camera.
        mask: valid points ``(B, N)``.
        valid: instances with enough points ``(B,)``; the others are padding only.
        geometric: ``Φ(T)`` ``(B, N, Dg)`` or None.
        appearance: raw lifted appearance features ``(B, N, G)`` or None.
    """

    obj_ids: torch.Tensor
    points: torch.Tensor
    normals: torch.Tensor
    mask: torch.Tensor
    valid: torch.Tensor
    geometric: torch.Tensor | None
    appearance: torch.Tensor | None


class FunFlow6D(nn.Module):
    """Model-based 6D pose estimation by conditional flow matching on fused frozen features.

    Args:
        config: the configuration (default: the offline defaults, FPFH + dense SIFT + PCA,
            gated fusion, ``small`` DiT).

    Example:
        >>> model = FunFlow6D(FunFlow6DConfig(num_points=32, dit_preset="tiny", crop_size=48))
        >>> sum(p.numel() for p in model.parameters()) > 0
        True
    """

    def __init__(self, config: FunFlow6DConfig | None = None) -> None:
        super().__init__()
        self.config = cfg = FunFlow6DConfig() if config is None else config
        self.geometric_encoder = build_geometric_encoder(
            cfg.geometric_encoder, radii=cfg.geometric_radii
        )
        self.appearance_encoder = build_appearance_encoder(
            cfg.appearance_encoder, crop_size=cfg.crop_size
        )
        gdim = self.geometric_encoder.dim if self.geometric_encoder is not None else None
        sdim = self._semantic_dim()
        self.net = FunFlow6DNet(
            cfg.net_config(
                geometric_dim=gdim if gdim is not None else sdim,
                semantic_dim=sdim if sdim is not None else gdim,
            )
        )
        self.objects: dict[int, PreparedObject] = {}

    def _semantic_dim(self) -> int | None:
        enc = self.appearance_encoder
        if enc is None:
            return None
        return enc.dim if self.config.reducer == "identity" else self.config.feature_dim

    # ------------------------------------------------------------------ objects

    def prepare_objects(
        self,
        models: Mapping[int, ObjectModel],
        *,
        cache_dir: str | Path | None = None,
        progress: bool = True,
    ) -> None:
        """Compute, per object, the query cloud, its features and the fitted reducer.

        Args:
            models: ``{obj_id: ObjectModel}`` (metres, textured meshes for appearance).
            cache_dir: where prepared objects are stored and looked up (safetensors + JSON);
                None computes everything in memory.
            progress: show a progress bar.
        """
        from tqdm.auto import tqdm

        items = sorted(models.items())
        for obj_id, model in tqdm(items, desc="prepare objects", disable=not progress):
            folder = None if cache_dir is None else Path(cache_dir) / f"obj_{obj_id:06d}"
            prepared = self._load_prepared(folder) if folder is not None else None
            if prepared is None:
                prepared = self._prepare(model)
                if folder is not None:
                    self._save_prepared(folder, prepared)
            self.objects[int(obj_id)] = prepared

    def _prepare(self, model: ObjectModel) -> PreparedObject:
        cfg = self.config
        dense = model.points.detach().cpu().float()
        dense_normals = model.normals.detach().cpu().float()
        g = torch.Generator().manual_seed(0)
        idx, _ = farthest_point_sample(dense[None], cfg.num_points, generator=g)
        points, normals = dense[idx[0]], dense_normals[idx[0]]
        geometric = None
        if self.geometric_encoder is not None:
            geometric = self.geometric_encoder.encode(
                points[None], normals[None], None, model.diameter
            )[0]
        bank, reducer = None, None
        if self.appearance_encoder is not None:
            bank = lift_query_features(
                self.appearance_encoder, model, points, model.diameter, num_views=cfg.query_views
            )
            reducer = build_reducer(cfg.reducer, n_components=cfg.feature_dim)
            reducer.fit(_bank_rows(bank, max_rows=4096))
        return PreparedObject(
            points=points,
            normals=normals,
            dense_points=dense,
            diameter=float(model.diameter),
            geometric=geometric,
            bank=bank,
            reducer=reducer,
        )

    def _save_prepared(self, folder: Path, obj: PreparedObject) -> None:
        from safetensors.torch import save_file

        folder.mkdir(parents=True, exist_ok=True)
        tensors = {
            "points": obj.points,
            "normals": obj.normals,
            "dense_points": obj.dense_points,
        }
        if obj.geometric is not None:
            tensors["geometric"] = obj.geometric
        if obj.bank is not None:
            tensors.update({f"bank.{k}": v for k, v in obj.bank.state().items()})
        if obj.reducer is not None:
            obj.reducer.save(folder / "reducer")
        tmp = folder / "object.safetensors.tmp"
        save_file({k: v.contiguous() for k, v in tensors.items()}, str(tmp))
        tmp.replace(folder / "object.safetensors")
        meta = {"diameter": obj.diameter, "config": self._object_fingerprint()}
        (folder / "object.json").write_text(json.dumps(meta, indent=1))

    def _load_prepared(self, folder: Path) -> PreparedObject | None:
        from safetensors.torch import load_file

        meta_path = folder / "object.json"
        if not meta_path.is_file():
            return None
        meta = json.loads(meta_path.read_text())
        if meta.get("config") != self._object_fingerprint():
            return None
        t = load_file(str(folder / "object.safetensors"))
        bank_state = {k[5:]: v for k, v in t.items() if k.startswith("bank.")}
        return PreparedObject(
            points=t["points"],
            normals=t["normals"],
            dense_points=t["dense_points"],
            diameter=float(meta["diameter"]),
            geometric=t.get("geometric"),
            bank=QueryFeatureBank.from_state(bank_state) if bank_state else None,
            reducer=load_reducer(folder / "reducer") if (folder / "reducer").exists() else None,
        )

    def _object_fingerprint(self) -> dict[str, Any]:
        cfg = self.config
        return {
            "num_points": cfg.num_points,
            "geometric_encoder": cfg.geometric_encoder,
            "geometric_radii": list(cfg.geometric_radii),
            "appearance_encoder": cfg.appearance_encoder,
            "crop_size": cfg.crop_size,
            "query_views": cfg.query_views,
            "reducer": cfg.reducer,
            "feature_dim": cfg.feature_dim,
        }

    def _object(self, obj_id: int) -> PreparedObject:
        try:
            return self.objects[int(obj_id)]
        except KeyError:
            raise ValueRangeError(
                f"object {int(obj_id)} is not prepared; call prepare_objects first "
                f"(prepared: {sorted(self.objects)})"
            ) from None

    # ------------------------------------------------------------------ observation

    @torch.no_grad()
    def observe(
        self,
        rgb: torch.Tensor,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: torch.Tensor | Sequence[int],
        *,
        generator: torch.Generator | None = None,
        timer: Any = None,
        crop_jitter: float = 0.0,
    ) -> Observation:
        """Lift the masked depth of each instance to a cloud of ``N`` points with its features.

        Args:
            rgb: the image ``(3, H, W)`` in ``[0, 1]`` (float) or ``[0, 255]`` (uint8).
            depth: depth ``(H, W)`` in metres (0 or NaN where missing).
            K: intrinsics ``(3, 3)``.
            masks: instance masks ``(B, H, W)`` bool.
            obj_ids: object id of each mask ``(B,)``.
            generator: seeds the start of the farthest-point sampling.
            timer: optional :class:`~poseflow.eval.timing.StageTimer`.
            crop_jitter: training augmentation of the appearance crop (see
                :func:`~poseflow.features.lifting.jitter_boxes`); 0 at inference.

        Returns:
            The :class:`Observation`; instances with fewer than 16 valid points are flagged
            invalid (their features are computed on padding and ignored downstream).
        """
        stage = _stages(timer)
        obj_ids = torch.as_tensor(obj_ids, dtype=torch.long).reshape(-1)
        sizes = check_tensor(masks, "masks", ("B", "H", "W"), floating=False)
        check_tensor(depth, "depth", ("H", "W"), sizes=sizes, floating=False)
        check_tensor(rgb, "rgb", (3, "H", "W"), sizes=sizes, floating=False)
        if len(obj_ids) != sizes["B"]:
            raise ShapeError(f"got {sizes['B']} masks but {len(obj_ids)} object ids")
        B, n = sizes["B"], self.config.num_points
        image = rgb.float() / 255.0 if not rgb.is_floating_point() else rgb.float()
        depth = torch.nan_to_num(depth.float(), nan=0.0, posinf=0.0)
        K = K.float()
        with stage("other"):
            cloud = backproject_depth(depth.expand(B, *depth.shape), K, masks.bool())
            cloud_points, cloud_pixels, keep = cloud.points, cloud.pixels, cloud.mask
            if cloud_points.shape[1] == 0:  # every mask empty: one padded point each
                cloud_points = K.new_zeros(B, 1, 3)
                cloud_pixels = torch.zeros(B, 1, 2, dtype=torch.long, device=K.device)
                keep = torch.zeros(B, 1, dtype=torch.bool, device=K.device)
            if cloud_points.shape[1] > self.config.dense_points:
                cloud_points, cloud_pixels, keep = _random_subset(
                    cloud_points, cloud_pixels, keep, self.config.dense_points, generator
                )
            if cloud_points.shape[1] >= 20:
                keep = remove_statistical_outliers(cloud_points, keep, k=20)
            idx, valid_pts = farthest_point_sample(cloud_points, n, keep, generator=generator)
            points = torch.gather(cloud_points, 1, idx[..., None].expand(-1, -1, 3))
            pixels = torch.gather(cloud_pixels, 1, idx[..., None].expand(-1, -1, 2))
            valid = valid_pts.sum(dim=1) >= _MIN_POINTS
            normals = estimate_normals(points, valid_pts, k=min(16, n))
        diameters = torch.tensor(
            [self._object(i).diameter for i in obj_ids.tolist()], device=points.device
        )
        geometric = appearance = None
        v = valid  # encoders see only instances with enough points; the others stay zero
        if self.geometric_encoder is not None:
            with stage("geometric_encoder"):
                geometric = points.new_zeros(B, n, self.geometric_encoder.dim)
                if bool(v.any()):
                    geometric[v] = self.geometric_encoder.encode(
                        points[v], normals[v], valid_pts[v], diameters[v]
                    )
        if self.appearance_encoder is not None:
            with stage("appearance_encoder"):
                appearance = points.new_zeros(B, n, self.appearance_encoder.dim)
                if bool(v.any()):
                    appearance[v] = lift_target_features(
                        self.appearance_encoder,
                        image.expand(int(v.sum()), *image.shape),
                        points[v],
                        K,
                        valid_pts[v],
                        pixels=pixels[v].to(points.dtype),
                        jitter=crop_jitter,
                        generator=generator if crop_jitter > 0 else None,
                    )
        return Observation(obj_ids, points, normals, valid_pts, valid, geometric, appearance)

    # ------------------------------------------------------------------ flow inputs

    def flow_inputs(
        self,
        obs: Observation,
        poses: torch.Tensor | None = None,
        *,
        timer: Any = None,
    ) -> dict[str, torch.Tensor]:
        """The network's inputs for ``[Q ; T]``, and ``x_1 = [Q ; Tʳ]`` when poses are given.

        Args:
            obs: the observation.
            poses: ground-truth model-to-camera poses ``(B, 4, 4)`` (training only).
            timer: optional stage timer.

        Returns:
            A dict with ``geometric``, ``semantic``, ``points``, ``normals``, ``mask``,
            ``frozen_mask``, ``anchor`` (``[Q ; 0]``), ``scale`` ``(B,)``, ``centroid``
            ``(B, 3)``, ``obj_ids`` and, with poses, ``x_1``; all normalised as the module
            docstring says.
        """
        stage = _stages(timer)
        objs = [self._object(i) for i in obs.obj_ids.tolist()]
        B, n = obs.points.shape[:2]
        dev, dt = obs.points.device, obs.points.dtype
        scale = torch.tensor([o.diameter / 2 for o in objs], dtype=dt, device=dev)
        mask_t = obs.mask & obs.valid[:, None]
        w = mask_t.to(dt)[..., None]
        centroid = (obs.points * w).sum(1) / w.sum(1).clamp_min(1.0)
        q_pts = torch.stack([o.points for o in objs]).to(dev, dt)
        q_nrm = torch.stack([o.normals for o in objs]).to(dev, dt)
        t_pts = (obs.points - centroid[:, None]) / scale[:, None, None]
        q_n = q_pts / scale[:, None, None]
        semantic_q = semantic_t = None
        if obs.appearance is not None:
            with stage("reducer"):
                semantic_q, semantic_t = self._semantic(objs, obs.appearance, mask_t)
        geometric_q = geometric_t = None
        if obs.geometric is not None:
            geometric_q = torch.stack([o.geometric for o in objs]).to(dev, dt)
            geometric_t = obs.geometric
        if geometric_q is None:
            geometric_q, geometric_t = semantic_q, semantic_t
        if semantic_q is None:
            semantic_q, semantic_t = geometric_q, geometric_t
        ones = torch.ones(B, n, dtype=torch.bool, device=dev)
        out = {
            "geometric": torch.cat([geometric_q, geometric_t], 1),
            "semantic": torch.cat([semantic_q, semantic_t], 1),
            "points": torch.cat([q_n, t_pts], 1),
            "normals": torch.cat([q_nrm, obs.normals], 1),
            "mask": torch.cat([ones, mask_t], 1),
            "frozen_mask": torch.cat([ones, ~ones], 1),
            "anchor": torch.cat([q_n, torch.zeros_like(t_pts)], 1),
            "scale": scale,
            "centroid": centroid,
            "obj_ids": obs.obj_ids.to(dev),
        }
        if poses is not None:
            check_tensor(poses, "poses", (B, 4, 4))
            R, t = poses[:, :3, :3].to(dt), poses[:, :3, 3].to(dt)
            t_canon = (obs.points - t[:, None]) @ R  # Rᵀ (T - t), row-vector form
            out["x_1"] = torch.cat([q_n, t_canon / scale[:, None, None]], 1)
        return out

    def _semantic(
        self, objs: list[PreparedObject], appearance: torch.Tensor, mask: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Reduced appearance features of the query and the target of every instance.

        Instances of the same object go through its bank and reducer together.
        """
        select = getattr(self.appearance_encoder, "query_pooling", "mean") == "select"
        mask = mask | ~mask.any(dim=1, keepdim=True)  # an instance without points: use them all
        sem_q = sem_t = None
        for obj in {id(o): o for o in objs}.values():
            rows = [b for b, o in enumerate(objs) if o is obj]
            idx = torch.tensor(rows, device=appearance.device)
            feats_t, m = appearance[idx], mask[idx]
            if select:
                feats_q = obj.bank.select(feats_t, m)
            else:
                feats_q = obj.bank.pooled().to(feats_t).expand(len(rows), -1, -1)
            q = obj.reducer.transform(feats_q.to(feats_t))
            t = obj.reducer.transform(feats_t, m)
            if sem_q is None:
                sem_q = q.new_zeros(len(objs), *q.shape[1:])
                sem_t = t.new_zeros(len(objs), *t.shape[1:])
            sem_q[idx], sem_t[idx] = q, t  # type: ignore[index]
        return sem_q, sem_t  # type: ignore[return-value]

    # ------------------------------------------------------------------ training and inference

    def velocity(self, *, x: torch.Tensor, t: torch.Tensor, **inputs: torch.Tensor) -> torch.Tensor:
        """The velocity-model call used in training: ``Ψ(t, X(t) | C)`` ``(B, 2N, 3)``."""
        keys = ("geometric", "semantic", "points", "normals", "mask")
        return self.net(
            x=x, t=t, x_0=self._noise_condition(inputs["x_0"]), **{k: inputs[k] for k in keys}
        )

    def _noise_condition(self, x_0: torch.Tensor) -> torch.Tensor:
        """``X(0)`` as the positional encoder sees it (zeros without noise conditioning)."""
        return x_0 if self.config.noise_conditioning else torch.zeros_like(x_0)

    def forward(self, **kwargs: Any) -> torch.Tensor:
        """Same as :meth:`velocity`, so the model plugs into :class:`~poseflow.flows.CFMTrainer`."""
        return self.velocity(**kwargs)

    @torch.no_grad()
    def estimate(
        self,
        rgb: torch.Tensor,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: torch.Tensor | Sequence[int],
        *,
        generator: torch.Generator | None = None,
        timer: Any = None,
    ) -> PoseEstimate:
        """Estimate the pose of every masked instance of one RGBD image, in one batch.

        Args:
            rgb: the image ``(3, H, W)``, uint8 or float in ``[0, 1]``.
            depth: depth ``(H, W)`` in metres.
            K: intrinsics ``(3, 3)``.
            masks: instance masks ``(B, H, W)`` bool.
            obj_ids: object id of each mask ``(B,)``; every id must be prepared.
            generator: seeds the noise, the sampling of the clouds and RANSAC.
            timer: optional :class:`~poseflow.eval.timing.StageTimer` for the paper's breakdown.

        Returns:
            A :class:`PoseEstimate`.
        """
        cfg = self.config
        stage = _stages(timer)
        was_training = self.training
        self.eval()
        try:
            obs = self.observe(rgb, depth, K, masks, obj_ids, generator=generator, timer=timer)
            inputs = self.flow_inputs(obs, timer=timer)
            H = cfg.num_hypotheses
            rep = {k: v.repeat_interleave(H, dim=0) for k, v in inputs.items()}
            B, L = inputs["points"].shape[:2]
            n = L // 2
            dev, dt = rep["points"].device, rep["points"].dtype
            x_0 = initial_noise((B * H, L, 3), generator=generator, device=dev, dtype=dt)
            with stage("fusion"):
                cond = self.net.condition(
                    geometric=rep["geometric"],
                    semantic=rep["semantic"],
                    points=rep["points"],
                    normals=rep["normals"],
                    x_0=self._noise_condition(x_0),
                    mask=rep["mask"],
                )
            dit = _timed(self.net.dit, timer)
            with stage("integration"):
                x_1 = get_sampler(cfg.solver, steps=cfg.steps).sample(
                    dit,
                    x_0,
                    frozen_mask=rep["frozen_mask"],
                    x_frozen=rep["anchor"] if cfg.anchor == "pinned" else None,
                    condition=cond,
                    mask=rep["mask"],
                    num_query=n,
                )
            transform, score, ok = self._solve_pose(rep, x_1[:, n:], generator, stage)
            best = score.reshape(B, H).argmax(dim=1) + torch.arange(B, device=dev) * H
            transform, score, ok = transform[best], score[best], ok[best]
            ok = ok & obs.valid.to(dev)
            poses = inverse_transform(transform)
            eye = torch.eye(4, dtype=dt, device=dev).expand(B, 4, 4)
            poses = torch.where(ok[:, None, None], poses, eye)
            return PoseEstimate(poses, torch.where(ok, score, torch.zeros_like(score)), ok)
        finally:
            self.train(was_training)

    def predict(
        self,
        dataset: str | Path | Any,
        *,
        split: str = "test",
        targets: Sequence[Any] | None = None,
        detections: Sequence[Any] | None = None,
        max_images: int | None = None,
        seed: int = 0,
        timer: Any = None,
        progress: bool = False,
    ) -> Any:
        """Estimate every target instance of a BOP split; see :func:`poseflow.eval.predict_dataset`.

        Args:
            dataset: the dataset folder or a :class:`~poseflow.data.bop.BOPDataset`.
            split: the split folder.
            targets: :class:`~poseflow.eval.recall.Target` records to estimate (default: the
                split's ``test_targets_bop19.json`` when present, else every instance).
            detections: masks from a BOP segmentation file instead of the ground truth.
            max_images: stop after this many images.
            seed: seeds the noise, sampling and RANSAC of every image.
            timer: optional :class:`~poseflow.eval.timing.StageTimer`.
            progress: show a progress bar.

        Returns:
            :class:`~poseflow.eval.results.PoseResults`, one row per valid estimate.
        """
        device = next(self.net.parameters()).device
        g = torch.Generator(device=device).manual_seed(seed)

        def estimator(rgb, depth, K, masks, obj_ids):
            return self.estimate(
                rgb.to(device), depth.to(device), K.to(device), masks.to(device), obj_ids,
                generator=g, timer=timer,
            )  # fmt: skip

        return predict_dataset(
            estimator,
            dataset,
            split=split,
            object_ids=sorted(self.objects),
            targets=targets,
            detections=detections,
            max_images=max_images,
            timer=timer,
            progress=progress,
        )

    def _solve_pose(
        self,
        inputs: dict[str, torch.Tensor],
        predicted: torch.Tensor,
        generator: torch.Generator | None,
        stage: Any,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Camera-to-canonical transforms ``(B, 4, 4)`` in metres, scores and validity."""
        cfg = self.config
        n = predicted.shape[1]
        source = inputs["points"][:, n:]
        mask = inputs["mask"][:, n:]
        scale, centroid = inputs["scale"], inputs["centroid"]
        # Distances in normalised units: a fraction f of the diameter is 2f there (s = d / 2).
        with stage("ransac"):
            if cfg.pose_solver == "ransac":
                rr = ransac_procrustes(
                    source,
                    predicted,
                    mask,
                    max_correspondence_distance=2 * cfg.ransac_threshold,
                    max_iterations=cfg.ransac_iterations,
                    generator=generator,
                )
                T, score, ok = rr.transformation, rr.fitness, rr.valid
            else:
                T = procrustes(source, predicted, mask=mask)
                score = torch.ones(len(T), dtype=T.dtype, device=T.device)
                ok = mask.sum(1) >= 3
        dense, dense_mask = self._dense_targets(inputs, scale)
        if cfg.icp_thresholds:
            with stage("icp"):
                ir = multi_scale_icp(
                    source,
                    dense,
                    T,
                    max_correspondence_distances=[2 * f for f in cfg.icp_thresholds],
                    max_iterations=cfg.icp_iterations,
                    source_mask=mask,
                    target_mask=dense_mask,
                )
                T = torch.where(ir.valid[:, None, None], ir.transformation, T)
        score = score * self._agreement(source, mask, T, dense, dense_mask)
        # Undo the normalisation: canonical = R (x - c) + s t'  =>  t = s t' - R c.
        R, t = T[:, :3, :3], T[:, :3, 3]
        t = scale[:, None] * t - (R @ centroid[..., None]).squeeze(-1)
        return from_Rt(R, t), score, ok

    def _agreement(
        self,
        source: torch.Tensor,
        mask: torch.Tensor,
        transform: torch.Tensor,
        dense: torch.Tensor,
        dense_mask: torch.Tensor,
    ) -> torch.Tensor:
        """Fraction of valid target points within ``ransac_threshold`` of the model surface."""
        moved = transform_points(transform, source)
        dist, _ = nearest_neighbors(moved, dense, k=1, reference_mask=dense_mask)
        close = (dist[..., 0] <= 2 * self.config.ransac_threshold) & mask
        return close.sum(1) / mask.sum(1).clamp_min(1)

    def _dense_targets(
        self, inputs: dict[str, torch.Tensor], scale: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The ICP targets: each instance's dense model cloud, normalised and padded."""
        dev, dt = scale.device, scale.dtype
        clouds = [self._object(i).dense_points for i in inputs["obj_ids"].tolist()]
        size = max(len(c) for c in clouds)
        dense = torch.zeros(len(clouds), size, 3, dtype=dt, device=dev)
        dense_mask = torch.zeros(len(clouds), size, dtype=torch.bool, device=dev)
        for b, c in enumerate(clouds):
            dense[b, : len(c)] = c.to(dev, dt) / scale[b]
            dense_mask[b, : len(c)] = True
        return dense, dense_mask

    # ------------------------------------------------------------------ save and load

    def save(self, folder: str | Path) -> Path:
        """Write ``config.json`` and ``model.safetensors`` (trainable weights only)."""
        from safetensors.torch import save_file

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        state = {k: v.detach().cpu().contiguous() for k, v in self.net.state_dict().items()}
        tmp = folder / "model.safetensors.tmp"
        save_file(state, str(tmp), metadata={"format": "poseflow.FunFlow6D/1"})
        tmp.replace(folder / "model.safetensors")
        (folder / "config.json").write_text(json.dumps(self.config.to_json(), indent=1))
        return folder

    @classmethod
    def load(cls, folder: str | Path, *, device: str | torch.device = "cpu") -> FunFlow6D:
        """Load a model written by :meth:`save` (no pickle is ever read)."""
        from safetensors.torch import load_file

        folder = Path(folder)
        weights = folder / "model.safetensors"
        if not weights.is_file() or not (folder / "config.json").is_file():
            raise MissingWeightsError(
                f"{folder} holds no FunFlow6D checkpoint (config.json + model.safetensors); "
                "train one with `poseflow train`"
            )
        model = cls(FunFlow6DConfig.from_json(folder / "config.json"))
        model.net.load_state_dict(load_file(str(weights)))
        return model.to(device)


def _random_subset(
    points: torch.Tensor,
    pixels: torch.Tensor,
    mask: torch.Tensor,
    size: int,
    generator: torch.Generator | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A uniform random subset of at most ``size`` valid points per cloud.

    Args:
        points: clouds ``(B, P, 3)``.
        pixels: their pixels ``(B, P, 2)``.
        mask: validity ``(B, P)`` bool.
        size: points kept, ``< P``.
        generator: seeds the draw (None: a fixed seed, so that repeated calls agree).

    Returns:
        ``(points, pixels, mask)`` with ``size`` columns; clouds with fewer valid points keep
        them all (and padding).
    """
    if generator is None:
        generator = torch.Generator(device=mask.device).manual_seed(0)
    keys = torch.rand(mask.shape, generator=generator, device=mask.device)
    keys = torch.where(mask, keys, 2.0)  # valid points first, in random order
    idx = keys.topk(size, dim=1, largest=False).indices
    take = lambda t: torch.gather(t, 1, idx[..., None].expand(-1, -1, t.shape[-1]))  # noqa: E731
    return take(points), take(pixels), torch.gather(mask, 1, idx)


def _bank_rows(bank: QueryFeatureBank, *, max_rows: int) -> torch.Tensor:
    """Visible per-view features of a bank, evenly subsampled to at most ``max_rows`` rows."""
    rows = bank.features[bank.visible].float()
    if len(rows) > max_rows:
        rows = rows[torch.linspace(0, len(rows) - 1, max_rows).round().long()]
    return rows


def _stages(timer: Any) -> Any:
    """``timer.stage`` or a no-op context factory."""
    if timer is None:
        return lambda name: contextlib.nullcontext()
    return timer.stage


def _timed(dit: nn.Module, timer: Any) -> Any:
    """Wrap the DiT so that each call is charged to the ``flow_net`` stage."""
    if timer is None:
        return dit

    def call(**kwargs: Any) -> torch.Tensor:
        with timer.stage("flow_net"):
            return dit(**kwargs)

    return call
