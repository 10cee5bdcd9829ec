"""What ``valid`` means: a calibrated decision that a pose is within the BOP tolerance.

An estimator's score ranks poses, but a score says nothing by itself about whether a pose is
right: the same 0.5 is a sure pose of one object and a coin toss for another. A
:class:`ValidityRule` turns it into a decision with a stated precision. It is fitted on images
with ground truth that the estimator never saw (the onboarding's calibration renders of the
user's own objects, ``poseflow calibrate``): per object, the lowest score above which at least
``precision`` of the calibration poses were within ``tolerance`` (MSSD below that fraction of
the diameter, BOP's tightest useful threshold). An object no threshold makes that precise is
never marked valid. The rule is stored per estimator in ``MODEL/validity.json``
(:func:`write_validity`, :func:`read_validity`) and applied by ``poseflow estimate``.

:func:`estimate_errors` gives each estimate of a results file its MSSD error,
:func:`validity_report` the precision and recall of a rule's decisions, and
:func:`plot_reliability` the picture of score against error.

Shape letters: ``E`` estimates.
"""

from __future__ import annotations

import json
import math
import os
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from poseflow.errors import CheckpointError, MissingDependencyError, ValueRangeError

if TYPE_CHECKING:
    from poseflow.eval.frame import FramePoses

__all__ = [
    "VALIDITY_FILE",
    "ValidityRule",
    "apply_validity",
    "estimate_errors",
    "mesh_key",
    "plot_reliability",
    "read_validity",
    "validity_report",
    "write_validity",
]

#: The rules of a model folder, one per estimator.
VALIDITY_FILE = "validity.json"


@dataclass(frozen=True)
class ValidityRule:
    """Per object, the score from which an estimator's poses are marked valid.

    Attributes:
        method: the estimator it was fitted for (``funflow6d``, ``baseline``, ``hybrid``).
        tolerance: a pose is right when its MSSD is below this fraction of the diameter.
        precision: the share of right poses among the valid ones it was fitted to reach.
        thresholds: ``{obj_id: score}``; ``inf`` where no score reached ``precision``.
        mesh_keys: ``{obj_id: key}`` of the meshes it was fitted on (:func:`mesh_key`; empty:
            not recorded).
        counts: ``{obj_id: (poses, right)}`` of the calibration.
        agreements: ``{obj_id: share}``: a pose is valid only where at least this share of
            the estimator's hypotheses agree with it (:class:`~poseflow.eval.PoseEstimate`'s
            ``agreement``); 0 or absent: no such condition.
    """

    method: str
    tolerance: float
    precision: float
    thresholds: dict[int, float]
    mesh_keys: dict[int, str] = field(default_factory=dict)
    counts: dict[int, tuple[int, int]] = field(default_factory=dict)
    agreements: dict[int, float] = field(default_factory=dict)

    @classmethod
    def fit(
        cls,
        method: str,
        scores: torch.Tensor | Sequence[float],
        errors: torch.Tensor | Sequence[float],
        obj_ids: torch.Tensor | Sequence[int],
        *,
        precision: float = 0.95,
        tolerance: float = 0.1,
        mesh_keys: Mapping[int, str] | None = None,
        agreement: torch.Tensor | Sequence[float] | None = None,
    ) -> ValidityRule:
        """Fit the thresholds on calibration poses: per object, the lowest precise enough.

        For each object, the poses are taken in order of falling score; the threshold is the
        lowest score at which the poses at or above it are right in at least ``precision`` of
        cases, estimated as ``(right + 1/2) / (poses + 1)`` (Jeffreys' prior, so that a handful
        of right poses does not make an object trusted at any score). An object without such a
        score gets ``inf``.
        With ``agreement``, each of the object's agreements is tried as a second condition;
        one is kept where it marks at least a tenth of the object's right poses more valid
        than the score alone (the least such agreement among those marking the most), so that
        a condition fitted to one or two poses does not stay.

        Args:
            method: the estimator's name.
            scores: ``(E,)`` the poses' scores.
            errors: ``(E,)`` their MSSD errors as fractions of the diameter (``inf``: no pose
                of a present object was found there, :func:`estimate_errors`).
            obj_ids: ``(E,)`` their objects.
            precision: the share of right poses to reach, in ``(0, 1)``.
            tolerance: the MSSD fraction below which a pose is right, ``> 0``.
            mesh_keys: the objects' :func:`mesh_key`, recorded with the rule.
            agreement: ``(E,)`` the share of the estimator's hypotheses agreeing with each
                pose; None: the score alone decides.

        Returns:
            The rule.

        Raises:
            ValueRangeError: ``precision`` or ``tolerance`` out of range, or columns of
                different lengths.

        Example:
            >>> rule = ValidityRule.fit("funflow6d", [0.9, 0.8, 0.7, 0.6, 0.5] * 8,
            ...                         [0.01, 0.02, 0.03, 0.5, 0.04] * 8, [1] * 40)
            >>> rule.thresholds  # below 0.7, a fifth of the poses are wrong
            {1: 0.7}
        """
        if not 0 < precision < 1:
            raise ValueRangeError(f"precision must lie in (0, 1), got {precision}")
        if not tolerance > 0:
            raise ValueRangeError(f"tolerance must be positive, got {tolerance}")
        s, e = (torch.as_tensor(x, dtype=torch.float64).reshape(-1) for x in (scores, errors))
        o = torch.as_tensor(obj_ids).reshape(-1).long()
        if not len(s) == len(e) == len(o):
            raise ValueRangeError(
                f"scores, errors and obj_ids differ in length: {len(s)}, {len(e)}, {len(o)}"
            )
        a = torch.zeros_like(s) if agreement is None else torch.as_tensor(agreement).double()
        if len(a) != len(s):
            raise ValueRangeError(f"agreement has {len(a)} entries for {len(s)} poses")
        thresholds, counts, agreements = {}, {}, {}
        for obj in sorted({int(x) for x in o.tolist()}):
            rows = o == obj
            right = e[rows] < tolerance
            counts[obj] = (int(rows.sum()), int(right.sum()))
            best = (-1, 0.0, math.inf)  # (right poses marked valid, agreement, score)
            gain = 0  # what an agreement condition must add: a tenth of the right poses
            for least in sorted({0.0, *a[rows].tolist()}):
                kept = a[rows] >= least
                cut = _lowest_precise_score(s[rows][kept], right[kept], precision)
                marked = int((right & kept & (s[rows] >= cut)).sum())
                if marked > best[0] + gain:
                    best = (marked, least, cut)
                gain = max(1, math.ceil(0.1 * int(right.sum())))
            thresholds[obj], agreements[obj] = best[2], best[1] if math.isfinite(best[2]) else 0.0
        return cls(
            method, tolerance, precision, thresholds, dict(mesh_keys or {}), counts,
            {k: v for k, v in agreements.items() if v > 0},
        )  # fmt: skip

    def decide(
        self,
        scores: torch.Tensor,
        obj_ids: torch.Tensor | Sequence[int],
        mesh_keys: Mapping[int, str] | None = None,
        agreement: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, list[str]]:
        """Which poses are valid, and a note for each one that is not.

        Args:
            scores: ``(E,)`` the poses' scores.
            obj_ids: ``(E,)`` their objects.
            mesh_keys: ``{obj_id: mesh_key}`` of the meshes the poses are of; an object
                whose mesh differs from the calibration's is not valid (the rule does not know
                it). None: not checked.
            agreement: ``(E,)`` the poses' agreements, for objects with an agreement
                threshold (without it, those objects are not valid).

        Returns:
            ``(valid (E,) bool, notes)``, the note empty where valid.

        Example:
            >>> rule = ValidityRule("funflow6d", 0.1, 0.95, {1: 0.5, 2: math.inf})
            >>> valid, notes = rule.decide(torch.tensor([0.6, 0.4, 0.9]), [1, 1, 2])
            >>> valid.tolist(), notes[1][:26]
            ([True, False, False], 'score 0.400 below 0.500, f')
        """
        ids = [int(x) for x in torch.as_tensor(obj_ids).reshape(-1).tolist()]
        valid = torch.zeros(len(ids), dtype=torch.bool)
        notes = []
        shares = [None] * len(ids) if agreement is None else agreement.reshape(-1).tolist()
        for i, (obj, score) in enumerate(zip(ids, scores.reshape(-1).tolist())):
            note = ""
            known = self.mesh_keys.get(obj)
            least = self.agreements.get(obj, 0.0)
            if obj not in self.thresholds:
                note = f"obj {obj} was not calibrated (`poseflow calibrate`)"
            elif mesh_keys is not None and known and mesh_keys.get(obj) != known:
                note = f"obj {obj}'s mesh is not the one calibrated (`poseflow calibrate`)"
            elif math.isinf(self.thresholds[obj]):
                note = (
                    f"no score made poses of obj {obj} right in {self.precision:.0%} of the "
                    "calibration renders"
                )
            elif score < self.thresholds[obj]:
                note = (
                    f"score {score:.3f} below {self.thresholds[obj]:.3f}, from which poses of "
                    f"obj {obj} were right in {self.precision:.0%} of the calibration renders"
                )
            elif least > 0 and (shares[i] is None or shares[i] < least):
                agreed = "unknown" if shares[i] is None else f"{shares[i]:.0%}"
                note = (
                    f"the estimator's hypotheses agree with the pose too little ({agreed}; "
                    f"obj {obj} needs {least:.0%} to be right in {self.precision:.0%} of the "
                    "calibration renders)"
                )
            valid[i] = not note
            notes.append(note)
        return valid, notes

    def to_json(self) -> dict[str, Any]:
        """The rule as JSON (``inf`` thresholds as null)."""
        return {
            "tolerance": self.tolerance,
            "precision": self.precision,
            "objects": {
                str(o): {
                    "threshold": None if math.isinf(t) else t,
                    "agreement": self.agreements.get(o, 0.0),
                    "mesh_key": self.mesh_keys.get(o, ""),
                    "poses": self.counts.get(o, (0, 0))[0],
                    "right": self.counts.get(o, (0, 0))[1],
                }
                for o, t in sorted(self.thresholds.items())
            },
        }

    @classmethod
    def from_json(cls, method: str, data: Mapping[str, Any]) -> ValidityRule:
        """The rule of :meth:`to_json`."""
        objects = {int(o): v for o, v in data["objects"].items()}
        return cls(
            method,
            float(data["tolerance"]),
            float(data["precision"]),
            {o: _threshold(v["threshold"]) for o, v in objects.items()},
            {o: v["mesh_key"] for o, v in objects.items() if v.get("mesh_key")},
            {o: (int(v["poses"]), int(v["right"])) for o, v in objects.items()},
            {o: float(v["agreement"]) for o, v in objects.items() if v.get("agreement", 0) > 0},
        )


def mesh_key(model: Any) -> str:
    """A key of an object's mesh in metres (vertices and triangles): which mesh a rule knows.

    Unlike :meth:`~poseflow.data.ObjectModel.content_key` it leaves out the sampled surface, so
    the same mesh file read by any command (any sample size) has the same key.

    Example:
        >>> import open3d as o3d
        >>> from poseflow.data import ObjectModel
        >>> box = o3d.geometry.TriangleMesh.create_box(0.1, 0.2, 0.3)
        >>> mesh_key(ObjectModel.from_mesh(box, num_points=16)) == mesh_key(
        ...     ObjectModel.from_mesh(box, num_points=32))
        True
    """
    from poseflow._cache import arrays_key

    return arrays_key({"vertices": model.mesh.vertices, "triangles": model.mesh.triangles})


def _threshold(value: float | None) -> float:
    return math.inf if value is None else float(value)


def _lowest_precise_score(scores: torch.Tensor, right: torch.Tensor, precision: float) -> float:
    """The lowest score from which the poses are right in ``precision`` of cases.

    The share of right poses is estimated by its posterior mean under Jeffreys' prior,
    ``(right + 1/2) / (poses + 1)``, so that a few poses, all right, do not make an object
    trusted (at 95 %, nine right poses are needed).
    """
    order = torch.argsort(scores, descending=True, stable=True)
    s, r = scores[order], right[order].double()
    kept = torch.arange(1, len(s) + 1, dtype=torch.float64)
    share = (r.cumsum(0) + 0.5) / (kept + 1)
    # only cut between different scores: equal scores are all in or all out
    ends = torch.ones(len(s), dtype=torch.bool)
    ends[:-1] = s[:-1] != s[1:]
    good = (share >= precision) & ends
    if not bool(good.any()):
        return math.inf
    return float(s[int(good.nonzero()[-1])])


def apply_validity(
    poses: FramePoses, rule: ValidityRule | None, mesh_keys: Mapping[int, str] | None = None
) -> tuple[FramePoses, str]:
    """A frame's poses with ``valid`` decided by ``rule``, and what ``valid`` means there.

    A pose stays valid only where it was (found and plausible) and the rule marks it valid;
    the rule's note says why it is not. Without a rule the poses come back unchanged.

    Args:
        poses: the frame's :class:`~poseflow.eval.frame.FramePoses`.
        rule: the model's rule for the estimator (:func:`read_validity`), or None.
        mesh_keys: ``{obj_id: mesh_key}`` of the meshes estimated (:func:`mesh_key`).

    Returns:
        ``(poses, meaning)``, the meaning one sentence for the output's metadata.
    """
    if rule is None:
        return poses, (
            "a pose was found and is plausible; not calibrated (no validity.json for this "
            "estimator: run `poseflow calibrate`), so it says nothing of its accuracy"
        )
    valid, notes = rule.decide(poses.scores, poses.obj_ids, mesh_keys, poses.agreement)
    keep = poses.valid & valid
    merged = [old or new for old, new in zip(_padded(poses.notes, len(poses)), notes)]
    meaning = (
        f"the pose is within MSSD < {rule.tolerance:g} diameter with a precision of "
        f"{rule.precision:.0%} on the calibration renders (its score, and where its object "
        "needs one its agreement, at least its object's thresholds in validity.json)"
    )
    return replace(poses, valid=keep, notes=merged), meaning


def _padded(notes: Sequence[str], n: int) -> list[str]:
    return [*notes, *[""] * (n - len(notes))][:n]


def estimate_errors(
    dataset: str | os.PathLike[str] | Any,
    results: str | os.PathLike[str] | Any,
    *,
    split: str = "test",
) -> torch.Tensor:
    """Each estimate's MSSD error: to the nearest ground-truth instance of its object.

    Args:
        dataset: the dataset folder or a :class:`~poseflow.data.bop.BOPDataset`.
        results: a results CSV or :class:`~poseflow.eval.results.PoseResults`.
        split: the split folder, when ``dataset`` is a path.

    Returns:
        ``(E,)`` float64: the symmetry-aware MSSD divided by the diameter (the smallest over the
        image's instances of the object); ``inf`` where the image holds none.

    Example:
        >>> import tempfile, open3d as o3d
        >>> from poseflow.data.synthetic import generate_dataset
        >>> from poseflow.eval.evaluate import gt_results
        >>> box = o3d.geometry.TriangleMesh.create_box(0.08, 0.06, 0.04)
        >>> root = generate_dataset(tempfile.mkdtemp(), [box], num_train_images=0,
        ...     num_test_images=1, objects_per_image=1, width=64, height=48, progress=False)
        >>> estimate_errors(root, gt_results(root)).tolist()
        [0.0]
    """
    from poseflow.eval.errors import mssd
    from poseflow.eval.evaluate import _open, load_eval_models
    from poseflow.eval.results import read_results

    ds = dataset if not isinstance(dataset, (str, os.PathLike)) else _open(dataset, split)
    res = results if not isinstance(results, (str, os.PathLike)) else read_results(results)
    errors = torch.full((len(res.scores),), math.inf, dtype=torch.float64)
    rows: dict[int, list[int]] = defaultdict(list)
    for e, obj in enumerate(res.obj_ids.tolist()):
        rows[int(obj)].append(e)
    if not rows:
        return errors
    models = load_eval_models(ds, list(rows))
    poses = res.poses.to(torch.float64)
    gts: dict[tuple[int, int], list[Any]] = {}
    for obj, idx in rows.items():
        # every (estimate, instance of its object in its image) pair, in one call per object
        pairs, truth = [], []
        for e in idx:
            key = (int(res.scene_ids[e]), int(res.im_ids[e]))
            if key not in gts:
                gts[key] = ds.scene(key[0]).gt_of(key[1])
            for g in gts[key]:
                if g.obj_id == obj:
                    pairs.append(e)
                    truth.append(g.pose)
        if not pairs:
            continue
        m, at = models[obj], torch.tensor(pairs)
        T_gt = torch.from_numpy(np.stack(truth)).to(torch.float64)
        err = mssd(poses[at], T_gt, m.vertices, m.symmetries) / m.diameter
        errors.scatter_reduce_(0, at, err, reduce="amin")
    return errors


def validity_report(
    valid: torch.Tensor,
    errors: torch.Tensor,
    obj_ids: torch.Tensor | Sequence[int],
    *,
    tolerance: float = 0.1,
) -> dict[str, Any]:
    """The precision and recall of ``valid`` decisions against the truth.

    Args:
        valid: ``(E,)`` bool, the poses marked valid.
        errors: ``(E,)`` their MSSD fractions (:func:`estimate_errors`).
        obj_ids: ``(E,)`` their objects.
        tolerance: a pose is right below this MSSD fraction.

    Returns:
        ``{"precision", "recall", "poses", "right", "valid", "valid_right", "per_object"}``:
        precision = right among valid (1 when none is valid), recall = valid among right
        (1 when none is right); ``per_object`` the same per object id (string keys).

    Example:
        >>> r = validity_report(torch.tensor([True, True, False, False]),
        ...                     torch.tensor([0.02, 0.5, 0.03, 0.4]), [1, 1, 1, 1])
        >>> r["precision"], r["recall"]
        (0.5, 0.5)
    """
    v = torch.as_tensor(valid).reshape(-1).bool()
    ok = torch.as_tensor(errors).reshape(-1) < tolerance
    o = torch.as_tensor(obj_ids).reshape(-1)

    def counts(rows: torch.Tensor) -> dict[str, Any]:
        n_valid, n_right = int((v & rows).sum()), int((ok & rows).sum())
        both = int((v & ok & rows).sum())
        return {
            "precision": both / n_valid if n_valid else 1.0,
            "recall": both / n_right if n_right else 1.0,
            "poses": int(rows.sum()),
            "right": n_right,
            "valid": n_valid,
            "valid_right": both,
        }

    report = counts(torch.ones_like(v))
    report["per_object"] = {str(int(x)): counts(o == x) for x in torch.unique(o).tolist()}
    return report


def write_validity(folder: str | os.PathLike[str], rule: ValidityRule) -> Path:
    """Add (or replace) ``rule`` in ``FOLDER/validity.json``; returns the file."""
    from poseflow._cache import atomic_write

    path = Path(folder) / VALIDITY_FILE
    data = _read(path) if path.is_file() else {"methods": {}}
    data["methods"][rule.method] = rule.to_json()
    text = json.dumps(data, indent=1)
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))
    return path


def read_validity(folder: str | os.PathLike[str], method: str) -> ValidityRule | None:
    """The rule of ``method`` in ``FOLDER/validity.json``; None when there is none.

    Raises:
        CheckpointError: the file is not a rules file.
    """
    path = Path(folder) / VALIDITY_FILE
    if not path.is_file():
        return None
    entry = _read(path)["methods"].get(method)
    return None if entry is None else ValidityRule.from_json(method, entry)


def _read(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
        if not isinstance(data.get("methods"), dict):
            raise ValueError("no 'methods' object")
        return data
    except (ValueError, AttributeError) as exc:
        raise CheckpointError(f"{path} is not a validity file: {exc}") from None


def plot_reliability(
    path: str | os.PathLike[str],
    panels: Mapping[str, tuple[torch.Tensor, torch.Tensor, torch.Tensor, ValidityRule | None]],
) -> Path:
    """Score against MSSD error, one panel per estimator, each object's threshold drawn.

    Args:
        path: the PNG to write.
        panels: ``{title: (scores (E,), errors (E,), obj_ids (E,), rule or None)}``.

    Returns:
        The written path.

    Raises:
        MissingDependencyError: matplotlib (the ``viz`` extra) is not installed.
    """
    try:
        import matplotlib
    except ImportError as exc:
        raise MissingDependencyError("matplotlib", "viz", "reliability plots") from exc

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.8), squeeze=False)
    colours = plt.get_cmap("tab10")
    for ax, (title, (scores, errors, obj_ids, rule)) in zip(axes[0], panels.items()):
        o = torch.as_tensor(obj_ids).reshape(-1)
        e = torch.as_tensor(errors).reshape(-1).clamp(max=1.0)
        s = torch.as_tensor(scores).reshape(-1)
        for k, obj in enumerate(torch.unique(o).tolist()):
            rows = o == obj
            ax.scatter(s[rows], e[rows], s=12, color=colours(k % 10), label=f"obj {obj}", alpha=0.8)
            t = None if rule is None else rule.thresholds.get(obj)
            if t is not None and math.isfinite(t):
                ax.axvline(t, color=colours(k % 10), linestyle=":", linewidth=1)
        tol = 0.1 if rule is None else rule.tolerance
        ax.axhline(tol, color="black", linewidth=0.8)
        ax.set(title=title, xlabel="score", ylabel="MSSD / diameter (capped at 1)", ylim=(0, 1.02))
        ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
