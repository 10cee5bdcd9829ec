"""Dataset-level BOP 2019 evaluation: results file in, Average Recall report out.

:func:`evaluate_bop` reproduces the BOP toolkit's ``eval_bop19_pose.py`` for the 6D localisation
task without depending on it:

- targets from ``test_targets_bop19.json`` (or, when absent, every object with an instance of
  visible fraction >= 0.1, see :func:`poseflow.eval.recall.targets_from_gt`);
- the top ``inst_count`` estimates of each target by score, each compared with every GT instance
  of its object in its image (:func:`poseflow.eval.recall.assign`);
- errors on the evaluation models (``models_eval/``: vertices, diameter, symmetries of
  ``models_info.json``, continuous symmetries sampled with ``max_sym_disc_step = 0.01``):
  VSD with ``delta = 15 mm`` and ``tau = 0.05 ... 0.5`` diameters (depth rendered with
  :class:`poseflow.render.Renderer`, missing measured depth counted as visible), MSSD divided by the
  diameter, MSPD scaled to a 640-pixel-wide image; as in the toolkit, MSSD is infinite when the
  two model centres are a diameter or more apart and VSD is 1 when the projections of the two
  bounding spheres do not overlap;
- greedy matching, recall pooled over all targets for every threshold (0.05 ... 0.5 for VSD and
  MSSD, 5 ... 50 px for MSPD) and every ``tau``, and
  ``AR = (AR_VSD + AR_MSSD + AR_MSPD) / 3``.

Everything is vectorised per object (MSSD, MSPD) or cropped to the pixels the object can cover
(VSD), so a thousand estimates on 640x480 images take seconds.
"""

from __future__ import annotations

import os
import warnings
from collections import defaultdict
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from poseflow._progress import progress as progress_loop
from poseflow.data.bop import BOPDataset, BOPDataWarning, ModelInfo
from poseflow.data.objects import load_mesh
from poseflow.errors import ValueRangeError
from poseflow.eval.errors import (
    MSPD_THRESHOLDS,
    MSSD_THRESHOLDS,
    VSD_DELTA,
    VSD_TAUS,
    VSD_THRESHOLDS,
    mspd,
    mssd,
    vsd_from_depth,
)
from poseflow.eval.recall import Assignment, Recall, Target, assign, match, targets_from_gt
from poseflow.eval.results import PoseResults, read_results
from poseflow.eval.symmetry import MAX_SYM_DISC_STEP, symmetry_transforms
from poseflow.render.mesh import TexturedMesh
from poseflow.render.raycast import Renderer, box_window

__all__ = [
    "METRICS",
    "EvalModel",
    "closest_results",
    "evaluate_bop",
    "gt_results",
    "load_eval_models",
]

#: The three BOP 2019 error functions, in the order of the report.
METRICS: tuple[str, ...] = ("vsd", "mssd", "mspd")

#: Image width the MSPD thresholds refer to.
MSPD_REFERENCE_WIDTH = 640.0


class EvalModel:
    """What evaluation needs of one object: mesh, vertices, diameter and symmetry set (metres).

    Args:
        mesh: the evaluation mesh (``models_eval/obj_XXXXXX.ply``) in metres.
        diameter: the diameter of ``models_info.json`` in metres.
        symmetries: the symmetry set, ``(S, 4, 4)`` float64.
    """

    def __init__(self, mesh: TexturedMesh, diameter: float, symmetries: torch.Tensor) -> None:
        if not diameter > 0:
            raise ValueRangeError(f"an object's diameter must be positive, got {diameter}")
        self.mesh = mesh
        self.vertices = torch.from_numpy(np.ascontiguousarray(mesh.vertices, dtype=np.float64))
        self.diameter = float(diameter)
        self.symmetries = symmetries.to(torch.float64)
        self.corners = mesh.bounding_box_corners()


def load_eval_models(
    dataset: BOPDataset,
    obj_ids: Sequence[int],
    *,
    max_sym_disc_step: float = MAX_SYM_DISC_STEP,
) -> dict[int, EvalModel]:
    """Load the evaluation models of ``obj_ids`` (``models_eval/``, else ``models/``).

    Raises:
        MissingFileError: a model or ``models_info.json`` is missing.
        ValueRangeError: an object has no ``models_info.json`` entry.
    """
    eval_dir = (dataset.root / "models_eval" / "models_info.json").is_file()
    infos = dataset.models_info(eval_models=eval_dir)
    out = {}
    for obj_id in sorted(set(int(o) for o in obj_ids)):
        if obj_id not in infos:
            raise ValueRangeError(f"object {obj_id} has no entry in models_info.json")
        info: ModelInfo = infos[obj_id]
        mesh = load_mesh(dataset.model_path(obj_id, eval_models=eval_dir), scale=1e-3)
        disc = (
            torch.from_numpy(np.stack(info.symmetries_discrete))
            if info.symmetries_discrete
            else None
        )
        cont = [
            (torch.from_numpy(np.asarray(c.axis)), torch.from_numpy(np.asarray(c.offset)))
            for c in info.symmetries_continuous
        ]
        syms = symmetry_transforms(disc, cont, max_sym_disc_step=max_sym_disc_step)
        out[obj_id] = EvalModel(mesh, info.diameter, syms)
    return out


def _image_size(scene: Any, im_id: int) -> tuple[int, int]:
    """(width, height) of an image, read from the depth or colour file header."""
    from PIL import Image

    try:
        path = scene.depth_path(im_id)
    except FileNotFoundError:
        path = scene.rgb_path(im_id)
    with Image.open(path) as im:
        return int(im.size[0]), int(im.size[1])


def _sphere_projections_overlap(radius: float, t1: np.ndarray, t2: np.ndarray) -> bool:
    """The toolkit's approximate test of whether two bounding spheres' silhouettes overlap."""
    if t1[2] == 0 or t2[2] == 0:
        return False
    dist = float(np.linalg.norm(t1[:2] / t1[2] - t2[:2] / t2[2]))
    return dist < radius * (1.0 / t1[2] + 1.0 / t2[2])


class _Scene:
    """Per-image data of the evaluation: GT poses, intrinsics, image size."""

    def __init__(self, dataset: BOPDataset, keys: Sequence[tuple[int, int]]) -> None:
        self.dataset = dataset
        self.gt_poses: dict[tuple[int, int], np.ndarray] = {}
        self.gt_objs: dict[tuple[int, int], list[tuple[int, float]]] = {}
        self.K: dict[tuple[int, int], np.ndarray] = {}
        self.size: dict[tuple[int, int], tuple[int, int]] = {}
        for s, i in keys:
            scene = dataset.scene(s)
            gts = scene.gt_of(i)
            infos = scene.gt_info.get(i, [])
            visib = [g.visib_fract for g in infos] if infos else [1.0] * len(gts)
            self.gt_objs[(s, i)] = [(g.obj_id, v) for g, v in zip(gts, visib)]
            self.gt_poses[(s, i)] = np.stack([g.pose for g in gts]) if gts else np.zeros((0, 4, 4))
            if i not in scene.camera:
                raise ValueRangeError(f"scene {s} has no camera for image {i}")
            self.K[(s, i)] = np.asarray(scene.camera[i].K, dtype=np.float64)
            self.size[(s, i)] = _image_size(scene, i)


def evaluate_bop(
    dataset: str | os.PathLike[str] | BOPDataset,
    results: str | os.PathLike[str] | PoseResults,
    *,
    split: str = "test",
    targets: str | os.PathLike[str] | Sequence[Target] | None = None,
    metrics: Sequence[str] = METRICS,
    vsd_delta: float = VSD_DELTA,
    vsd_taus: Sequence[float] = VSD_TAUS,
    max_sym_disc_step: float = MAX_SYM_DISC_STEP,
    progress: bool = False,
) -> dict[str, Any]:
    """Evaluate pose estimates on a BOP dataset with the BOP 2019 Average Recall.

    Args:
        dataset: the dataset folder (holding ``models_eval/`` and the split) or a
            :class:`~poseflow.data.bop.BOPDataset`.
        results: a BOP 2019 CSV results file or :class:`~poseflow.eval.results.PoseResults`.
        split: the split folder, when ``dataset`` is a path.
        targets: a targets JSON file or a list of targets; default the dataset's
            ``test_targets_bop19.json`` when present, else targets derived from visibility.
        metrics: which of ``"vsd"``, ``"mssd"``, ``"mspd"`` to compute (VSD needs depth images);
            AR is the mean over those computed.
        vsd_delta: VSD visibility tolerance in metres.
        vsd_taus: VSD misalignment tolerances (fractions of the diameter).
        max_sym_disc_step: discretisation step of continuous symmetries.
        progress: show a progress bar over images while computing VSD.

    Returns:
        A JSON-serialisable report: ``AR``, ``AR_VSD``, ``AR_MSSD``, ``AR_MSPD`` (those computed),
        ``per_object`` (``{obj_id: {"AR", "AR_VSD", ..., "num_targets"}}``), ``per_threshold``
        (``{metric: {"thresholds", "recall"}}``; VSD also ``"taus"``, its recall one row per
        tau), ``num_targets``, ``num_estimates`` (in the results), ``num_evaluated`` (kept as
        top-``inst_count``), ``average_time`` (seconds per image, -1 if unknown) and ``metrics``.

    Raises:
        ValueRangeError: an unknown metric, a target naming an image without ground truth, or a
            malformed results file (see :func:`~poseflow.eval.results.read_results`).
        MissingFileError: missing dataset or results files.

    Warns:
        BOPDataWarning: results rows name objects without a model or images the split does not
            hold (they cannot count: the count and the first examples are given), or the
            translations look like metres where BOP files hold millimetres.

    Example:
        >>> import tempfile, open3d as o3d
        >>> from poseflow.data.synthetic import generate_dataset
        >>> box = o3d.geometry.TriangleMesh.create_box(0.08, 0.06, 0.04)
        >>> root = generate_dataset(tempfile.mkdtemp(), [box], num_train_images=0,
        ...     num_test_images=1, objects_per_image=1, width=64, height=48, progress=False)
        >>> report = evaluate_bop(root, gt_results(root))
        >>> report["AR"], report["AR_VSD"], report["num_targets"]
        (1.0, 1.0, 1)
    """
    unknown = [m for m in metrics if m not in METRICS]
    if unknown or not metrics:
        raise ValueRangeError(f"metrics must be a non-empty subset of {METRICS}, got {metrics}")
    ds = dataset if isinstance(dataset, BOPDataset) else _open(dataset, split)
    res = results if isinstance(results, PoseResults) else read_results(results)
    tgts = _load_targets(ds, targets)
    _warn_unknown_rows(ds, res)
    scenes = _Scene(ds, sorted({(t.scene_id, t.im_id) for t in tgts}))
    _warn_metre_translations(res, scenes)
    a = assign(tgts, scenes.gt_objs, res.scene_ids, res.im_ids, res.obj_ids, res.scores)
    models = load_eval_models(ds, [t.obj_id for t in tgts], max_sym_disc_step=max_sym_disc_step)
    pairs = _Pairs(a, res, scenes)

    recalls: dict[str, Recall] = {}
    if "mssd" in metrics:
        recalls["mssd"] = match(a, _mssd_errors(pairs, models), MSSD_THRESHOLDS)
    if "mspd" in metrics:
        recalls["mspd"] = match(a, _mspd_errors(pairs, models, scenes), MSPD_THRESHOLDS)
    if "vsd" in metrics:
        errs = _vsd_errors(pairs, models, scenes, ds, vsd_delta, vsd_taus, progress)
        recalls["vsd"] = match(a, errs, VSD_THRESHOLDS)
    return _report(recalls, a, res, [m for m in METRICS if m in metrics], vsd_taus)


def gt_results(
    dataset: str | os.PathLike[str] | BOPDataset, *, split: str = "test", score: float = 1.0
) -> PoseResults:
    """Results holding every ground-truth pose of a split: a perfect method, for checks.

    Args:
        dataset: the dataset folder or a :class:`~poseflow.data.bop.BOPDataset`.
        split: the split folder, when ``dataset`` is a path.
        score: the score given to every estimate.

    Returns:
        :class:`~poseflow.eval.results.PoseResults` with one estimate per GT instance (time -1).
    """
    ds = dataset if isinstance(dataset, BOPDataset) else _open(dataset, split)
    cols: dict[str, list] = defaultdict(list)
    for s in ds.scene_ids:
        scene = ds.scene(s)
        for i in scene.im_ids:
            for g in scene.gt_of(i):
                for key, value in (("s", s), ("i", i), ("o", g.obj_id), ("p", g.pose)):
                    cols[key].append(value)
    if not cols:
        return PoseResults.empty()
    poses = torch.from_numpy(np.stack(cols["p"]))
    return PoseResults.from_columns(cols["s"], cols["i"], cols["o"], [score] * len(poses), poses)


def closest_results(
    dataset: str | os.PathLike[str] | BOPDataset,
    results: Sequence[str | os.PathLike[str] | PoseResults],
    *,
    split: str = "test",
    targets: str | os.PathLike[str] | Sequence[Target] | None = None,
    max_sym_disc_step: float = MAX_SYM_DISC_STEP,
) -> tuple[PoseResults, list[int]]:
    """Per image and object, the estimates of whichever results come closest to the truth.

    The oracle choice among several estimators (or settings): its AR is what a selector that
    picks one of them per target could reach at best, to be read next to each one's own AR and
    the selector's. Closeness is the mean MSSD (a fraction of the diameter, capped at 1) of the
    targets of an image and object, the estimates assigned to them as :func:`evaluate_bop`
    assigns them, a target without an estimate counting 1; a tie goes to the earlier results.

    Args:
        dataset: the dataset folder or a :class:`~poseflow.data.bop.BOPDataset`.
        results: two or more CSV files or :class:`~poseflow.eval.results.PoseResults`.
        split: the split folder, when ``dataset`` is a path.
        targets: as in :func:`evaluate_bop`.
        max_sym_disc_step: discretisation step of continuous symmetries.

    Returns:
        ``(chosen, counts)``: the chosen rows of every image and target object (times -1: they
        mix runs), and how many image-object groups each of ``results`` gave.

    Raises:
        ValueRangeError: fewer than two results, or as :func:`evaluate_bop`.

    Example:
        >>> import tempfile, open3d as o3d
        >>> from poseflow.data.synthetic import generate_dataset
        >>> box = o3d.geometry.TriangleMesh.create_box(0.08, 0.06, 0.04)
        >>> root = generate_dataset(tempfile.mkdtemp(), [box], num_train_images=0,
        ...     num_test_images=1, objects_per_image=1, width=64, height=48, progress=False)
        >>> truth = gt_results(root)
        >>> off = PoseResults.from_columns(truth.scene_ids, truth.im_ids, truth.obj_ids,
        ...                                truth.scores, truth.poses * 2)
        >>> chosen, counts = closest_results(root, [off, truth])
        >>> counts, evaluate_bop(root, chosen)["AR"]
        ([0, 1], 1.0)
    """
    if len(results) < 2:
        raise ValueRangeError(f"closest_results needs two or more results, got {len(results)}")
    ds = dataset if isinstance(dataset, BOPDataset) else _open(dataset, split)
    sets = [r if isinstance(r, PoseResults) else read_results(r) for r in results]
    tgts = _load_targets(ds, targets)
    scenes = _Scene(ds, sorted({(t.scene_id, t.im_id) for t in tgts}))
    models = load_eval_models(ds, [t.obj_id for t in tgts], max_sym_disc_step=max_sym_disc_step)
    count: dict[tuple[int, int, int], int] = defaultdict(int)
    for t in tgts:
        count[(t.scene_id, t.im_id, t.obj_id)] += t.inst_count
    group = {key: g for g, key in enumerate(count)}
    # every target a miss (1) until an assigned estimate replaces its 1 by its capped MSSD
    error = torch.tensor(list(count.values()), dtype=torch.float64).repeat(len(sets), 1)
    for j, res in enumerate(sets):
        a = assign(tgts, scenes.gt_objs, res.scene_ids, res.im_ids, res.obj_ids, res.scores)
        pairs = _Pairs(a, res, scenes)
        errs = _mssd_errors(pairs, models).clamp(max=1.0)
        for (s, i), o, e in zip(pairs.image, pairs.obj.tolist(), errs.tolist()):
            error[j, group[(s, i, o)]] += e - 1.0
    best = error.argmin(0).tolist()  # the first of equal minima
    rows_of: list[dict[tuple[int, int, int], list[int]]] = [defaultdict(list) for _ in sets]
    for j, r in enumerate(sets):
        keys = zip(r.scene_ids.tolist(), r.im_ids.tolist(), r.obj_ids.tolist())
        for e, key in enumerate(keys):
            rows_of[j][key].append(e)
    parts = []
    for key, j in zip(count, best):
        r, rows = sets[j], torch.tensor(rows_of[j].get(key, []), dtype=torch.long)
        columns = (r.scene_ids, r.im_ids, r.obj_ids, r.scores, r.poses)
        parts.append(PoseResults.from_columns(*(c[rows] for c in columns)))
    counts = [best.count(j) for j in range(len(sets))]
    return PoseResults.concat(parts), counts


def _examples(items: Sequence[Any], limit: int = 3) -> str:
    shown = ", ".join(str(x) for x in items[:limit])
    return shown + (", ..." if len(items) > limit else "")


def _warn_unknown_rows(ds: BOPDataset, res: PoseResults) -> None:
    """Warn about results rows that cannot count: unknown objects, scenes or images."""
    if not len(res):
        return
    infos = ds.models_info()
    objs = res.obj_ids.tolist()
    unknown_objs = sorted({o for o in objs if o not in infos})
    if unknown_objs:
        n = sum(o in set(unknown_objs) for o in objs)
        warnings.warn(
            f"{n} results rows name objects that {ds.root}/models does not hold "
            f"({_examples(unknown_objs)}); they are ignored",
            BOPDataWarning,
            stacklevel=3,
        )
    known_scenes = set(ds.scene_ids)
    images = {(s, i) for s, i in zip(res.scene_ids.tolist(), res.im_ids.tolist())}
    known = {
        (s, i) for s in sorted({s for s, _ in images} & known_scenes) for i in ds.scene(s).im_ids
    }
    missing = sorted(images - known)
    if missing:
        n = sum((s, i) in set(missing) for s, i in zip(res.scene_ids.tolist(), res.im_ids.tolist()))
        names = [f"scene {s} image {i}" for s, i in missing]
        warnings.warn(
            f"{n} results rows name images that the split {ds.split_path} does not hold "
            f"({_examples(names)}); they are ignored: is this the right dataset and --split?",
            BOPDataWarning,
            stacklevel=3,
        )


def _warn_metre_translations(res: PoseResults, scenes: _Scene) -> None:
    """Warn when the estimates' distances are about a thousandth of the ground truth's."""
    est = res.poses[:, 2, 3].abs()
    gt = [p[:, 2, 3] for p in scenes.gt_poses.values() if len(p)]
    if not len(est) or not gt:
        return
    est_z = float(est.median())
    gt_z = float(np.median(np.abs(np.concatenate(gt))))
    if gt_z > 0 and est_z < 0.01 * gt_z:
        warnings.warn(
            f"the estimated translations are {1000 * est_z:.3g} mm from the camera (median), the "
            f"ground truth {1000 * gt_z:.3g} mm: was t written in metres? BOP results files "
            "hold t in millimetres",
            BOPDataWarning,
            stacklevel=3,
        )


def _open(root: str | os.PathLike[str], split: str) -> BOPDataset:
    return BOPDataset(root, split, load_rgb=False, load_masks=False)


def _load_targets(
    ds: BOPDataset, targets: str | os.PathLike[str] | Sequence[Target] | None
) -> list[Target]:
    if targets is None:
        if (ds.root / "test_targets_bop19.json").is_file():
            raw: Sequence[Any] = ds.test_targets()
        else:
            gts = {}
            for s in ds.scene_ids:
                scene = ds.scene(s)
                for i in scene.im_ids:
                    gt, infos = scene.gt_of(i), scene.gt_info.get(i, [])
                    visib = [x.visib_fract for x in infos] if infos else [1.0] * len(gt)
                    gts[(s, i)] = [(g.obj_id, v) for g, v in zip(gt, visib)]
            return targets_from_gt(gts)
    elif isinstance(targets, (str, os.PathLike)):
        from poseflow.data.bop import read_test_targets

        raw = read_test_targets(targets)
    else:
        raw = targets
    return [Target(int(t.scene_id), int(t.im_id), int(t.obj_id), int(t.inst_count)) for t in raw]


class _Pairs:
    """The (estimate, GT) pairs to score, with their poses and objects, grouped for batching."""

    def __init__(self, a: Assignment, res: PoseResults, scenes: _Scene) -> None:
        row, _, _, est, gt = a.pairs()
        self.count = int(row.numel())
        self.obj = torch.tensor([a.targets[r].obj_id for r in row.tolist()], dtype=torch.long)
        self.image = [(a.targets[r].scene_id, a.targets[r].im_id) for r in row.tolist()]
        self.gt_id = gt.tolist()
        self.est = est.tolist()
        self.T_est = res.poses[est].to(torch.float64)
        if self.count:
            self.T_gt = torch.from_numpy(
                np.stack([scenes.gt_poses[k][g] for k, g in zip(self.image, self.gt_id)])
            )
        else:
            self.T_gt = torch.zeros(0, 4, 4, dtype=torch.float64)

    def by_object(self) -> dict[int, torch.Tensor]:
        groups: dict[int, list[int]] = defaultdict(list)
        for p, o in enumerate(self.obj.tolist()):
            groups[o].append(p)
        return {o: torch.tensor(idx, dtype=torch.long) for o, idx in groups.items()}


def _mssd_errors(pairs: _Pairs, models: Mapping[int, EvalModel]) -> torch.Tensor:
    out = torch.full((pairs.count,), float("inf"), dtype=torch.float64)
    for o, idx in pairs.by_object().items():
        m = models[o]
        T_e, T_g = pairs.T_est[idx], pairs.T_gt[idx]
        e = mssd(T_e, T_g, m.vertices, m.symmetries) / m.diameter
        far = (T_e[:, :3, 3] - T_g[:, :3, 3]).norm(dim=-1) >= m.diameter
        out[idx] = torch.where(far, torch.full_like(e, float("inf")), e)
    return out


def _mspd_errors(pairs: _Pairs, models: Mapping[int, EvalModel], scenes: _Scene) -> torch.Tensor:
    out = torch.full((pairs.count,), float("inf"), dtype=torch.float64)
    if not pairs.count:
        return out
    K = torch.from_numpy(np.stack([scenes.K[k] for k in pairs.image]))
    scale = torch.tensor(
        [MSPD_REFERENCE_WIDTH / scenes.size[k][0] for k in pairs.image], dtype=torch.float64
    )
    for o, idx in pairs.by_object().items():
        m = models[o]
        e = mspd(pairs.T_est[idx], pairs.T_gt[idx], K[idx], m.vertices, m.symmetries)
        out[idx] = e * scale[idx]
    return out


def _vsd_errors(
    pairs: _Pairs,
    models: Mapping[int, EvalModel],
    scenes: _Scene,
    ds: BOPDataset,
    delta: float,
    taus: Sequence[float],
    progress: bool,
) -> torch.Tensor:
    out = torch.ones(pairs.count, len(taus), dtype=torch.float64)
    if not pairs.count:
        return out
    obj_ids = sorted(models)
    mesh_index = {o: i for i, o in enumerate(obj_ids)}
    renderer = Renderer([models[o].mesh for o in obj_ids])
    by_image: dict[tuple[int, int], list[int]] = defaultdict(list)
    for p, key in enumerate(pairs.image):
        by_image[key].append(p)
    keys = sorted(by_image)
    for key in progress_loop(keys, total=len(keys), desc="VSD", enabled=progress):
        K = scenes.K[key]
        width, height = scenes.size[key]
        depth = ds.scene(key[0]).load_depth_image(key[1]).to(torch.float64)
        # Every pose is rendered once, alone, inside its own window (an estimate is usually
        # compared with several GT instances of its object, a GT instance with several estimates).
        cache: dict[tuple[str, int], tuple[tuple[int, int, int, int] | None, torch.Tensor]] = {}
        for p in by_image[key]:
            o = int(pairs.obj[p])
            m = models[o]
            T_e, T_g = pairs.T_est[p].numpy(), pairs.T_gt[p].numpy()
            if not _sphere_projections_overlap(0.5 * m.diameter, T_e[:3, 3], T_g[:3, 3]):
                continue  # the toolkit's shortcut: error 1 for every tau
            views = []
            for ck, T in ((("est", pairs.est[p]), T_e), (("gt", pairs.gt_id[p]), T_g)):
                if ck not in cache:
                    w = box_window(m.corners, T, K, width, height)
                    d = _render_depth(renderer, mesh_index[o], T, K, w) if w is not None else None
                    cache[ck] = (w, torch.zeros(0, 0) if d is None else d)
                views.append(cache[ck])
            wins = [w for w, _ in views if w is not None]
            if not wins:
                continue  # nothing rendered in either pose: empty union, error 1
            u0, v0 = min(w[0] for w in wins), min(w[2] for w in wins)
            u1, v1 = max(w[1] for w in wins), max(w[3] for w in wins)
            d_est, d_gt = (torch.zeros(v1 - v0, u1 - u0, dtype=torch.float64) for _ in range(2))
            for (w, d), canvas in zip(views, (d_est, d_gt)):
                if w is not None:
                    canvas[w[2] - v0 : w[3] - v0, w[0] - u0 : w[1] - u0] = d
            Kc = torch.from_numpy(K.copy())
            Kc[0, 2] -= u0
            Kc[1, 2] -= v0
            out[p] = vsd_from_depth(
                d_est[None], d_gt[None], depth[v0:v1, u0:u1], Kc, m.diameter, delta=delta, taus=taus
            )[0]
    return out


def _render_depth(
    renderer: Renderer, mesh: int, T: np.ndarray, K: np.ndarray, window: tuple[int, int, int, int]
) -> torch.Tensor:
    """Depth of one object rendered alone inside a pixel window (the intrinsics shifted to it)."""
    u0, u1, v0, v1 = window
    Kc = K.copy()
    Kc[0, 2] -= u0
    Kc[1, 2] -= v0
    out = renderer.render(T[None], Kc, u1 - u0, v1 - v0, object_ids=[mesh], rgb=False)
    return out.depth.to(torch.float64)


def _report(
    recalls: Mapping[str, Recall],
    a: Assignment,
    res: PoseResults,
    metrics: Sequence[str],
    taus: Sequence[float],
) -> dict[str, Any]:
    names = {"vsd": "AR_VSD", "mssd": "AR_MSSD", "mspd": "AR_MSPD"}
    report: dict[str, Any] = {}
    for m in metrics:
        report[names[m]] = recalls[m].average
    report["AR"] = float(np.mean([recalls[m].average for m in metrics]))
    per_object: dict[str, dict[str, Any]] = {}
    first = recalls[metrics[0]]
    for o in sorted(first.per_object):
        entry: dict[str, Any] = {names[m]: recalls[m].object_average(o) for m in metrics}
        entry["AR"] = float(np.mean([entry[names[m]] for m in metrics]))
        entry["num_targets"] = first.per_object_targets[o]
        per_object[str(o)] = entry
    report["per_object"] = per_object
    per_threshold: dict[str, Any] = {}
    for m in metrics:
        r = recalls[m]
        d: dict[str, Any] = {"thresholds": r.thresholds.tolist()}
        if m == "vsd":
            d["taus"] = [float(t) for t in taus]
            d["recall"] = r.recall.tolist()
        else:
            d["recall"] = r.recall[0].tolist()
        per_threshold[m] = d
    report["per_threshold"] = per_threshold
    report["num_targets"] = first.num_targets
    report["num_estimates"] = len(res)
    report["num_evaluated"] = int((a.est_index >= 0).sum())
    report["average_time"] = res.average_time()
    report["metrics"] = list(metrics)
    return report
