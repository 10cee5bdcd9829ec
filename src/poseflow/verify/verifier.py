"""The pose verifier: a contest of each instance's hypotheses, to verify, search and rank.

One contest (``PoseVerifier._contest``) serves all three: the hypotheses of each instance
are scored on a coarse grid of the crop their first places, the first and the best others are
kept, refined by ICP and scored on the full grid. :meth:`~PoseVerifier.verify` and
:meth:`~PoseVerifier.search` then keep the first unless another beats it significantly,
:meth:`~PoseVerifier.rank_hypotheses` takes the best. :meth:`~PoseVerifier.verify` finally
polishes its choice (:meth:`~poseflow.verify.PoseScorer.polish`).

Every method takes the instances of one image as an :class:`~poseflow.data.ImageInstances`.

Shape letters: B instances of one image, H hypotheses per instance, E more hypotheses, M observed
points, Hi x Wi the image.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace

import torch

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.data.frame import ImageInstances
from poseflow.geometry.se3 import rotation_angle_error
from poseflow.verify.results import Hypotheses, Verification
from poseflow.verify.score import VerifierScore
from poseflow.verify.scorer import PoseScorer
from poseflow.verify.symmetry import box_slides, box_turns

__all__ = ["PoseVerifier"]

#: Observed clouds ``(B, M, 3)`` and their valid points ``(B, M)`` bool (None: all valid).
ObservedClouds = tuple[torch.Tensor, torch.Tensor | None]


@dataclass(frozen=True)
class _Image(ImageInstances):
    """The inputs of one image's contest: its instances and their observed clouds.

    Attributes:
        K: intrinsics ``(3, 3)`` in the hypotheses' dtype.
        observed: the observed clouds ``(B, M, 3)`` that ICP registers, or None (lifted from
            the depth when needed).
        observed_mask: ``(B, M)`` bool, or None.
    """

    observed: torch.Tensor | None = None
    observed_mask: torch.Tensor | None = None

    @classmethod
    def of(
        cls, image: ImageInstances, dtype: torch.dtype, observed: ObservedClouds | None
    ) -> _Image:
        """``image`` with its ``K`` in ``dtype`` and the observed clouds, if given."""
        rgb, depth, K, masks, obj_ids = image
        return cls(rgb, depth, K.to(dtype), masks, obj_ids, *(observed or ()))

    def take(self, rows: torch.Tensor, *more: torch.Tensor | None) -> tuple:
        """The instances ``rows`` ``(B',)`` of this image, then those rows of ``more``.

        A None in ``more`` stays None.
        """
        picked = [
            None if t is None else t[rows] for t in (self.observed, self.observed_mask, *more)
        ]
        ids = torch.as_tensor(self.obj_ids).reshape(-1)[rows.cpu()]
        image = replace(
            self, masks=self.masks[rows], obj_ids=ids, observed=picked[0], observed_mask=picked[1]
        )
        return (image, *picked[2:])


@dataclass(frozen=True)
class _Contest:
    """What a contest of ``B x H`` hypotheses kept: the first and the best ``k`` others.

    Attributes:
        image: the image, with the observed clouds the contest lifted.
        index: ``(B, 1 + k)`` int64, the kept hypotheses' columns.
        poses: the kept hypotheses ``(B, 1 + k, 4, 4)``, ICP-refined.
        mask: ``(B, 1 + k)`` bool, those that are real and scored on the full grid.
        coarse: the scores of all ``(B, H)`` on the coarse grid.
        full: the scores of the kept ones on the full grid; None where none was kept to score.
    """

    image: _Image
    index: torch.Tensor
    poses: torch.Tensor
    mask: torch.Tensor
    coarse: VerifierScore
    full: VerifierScore | None

    def verification(self, significance: float) -> Verification:
        """The first kept unless another beats it significantly (the rule of verify and search)."""
        return Verification.select(self.poses, self.full, significance=significance)

    def best(self) -> torch.Tensor:
        """``(B,)`` the column of the best hypothesis: the ranking's rule.

        The best on the full grid, or on the coarse grid where the full grid saw none.
        """
        best = torch.where(self.coarse.valid, self.coarse.total, -torch.inf).argmax(1)
        if self.full is None:
            return best
        full = torch.where(self.full.valid[:, 1:], self.full.total[:, 1:], -torch.inf)
        full_best = self.index[:, 1:].gather(1, full.argmax(1, keepdim=True))[:, 0]
        return torch.where(torch.isfinite(full).any(1), full_best, best)


class PoseVerifier(PoseScorer):
    """Render-and-compare verification of 6D pose hypotheses with near-symmetry candidates.

    Built once, with :class:`~poseflow.verify.PoseScorer`'s arguments; :meth:`prepare` caches what
    each object needs (surface points with normals and albedo, its near-symmetries). For the
    instances of one image, :meth:`verify` runs the whole stage: :meth:`expand` each estimate with
    its near-symmetric candidates and holds a contest of them: all are scored on a coarse grid
    (:meth:`score`), the best ``refine_top_k`` candidates (and, with ``refine_estimate``, the
    estimate) refined by ICP of the observed cloud onto the model (:meth:`refine`) and scored again
    on the full grid, and the estimate is kept unless a candidate beats it by more than the score's
    own spread (:func:`~poseflow.verify.select_significant`); a chosen pose that still scores below
    ``search_below`` is then searched over all orientations by the same contest (:meth:`search`),
    and the chosen poses are polished on the full grid's score (:meth:`polish`).
    :meth:`rank_hypotheses` runs it to rank an estimator's hypotheses. Each step is a public method
    of :class:`~poseflow.verify.PoseScorer`, so the verifier also scores hypotheses from anywhere.

    Example:
        >>> import open3d as o3d
        >>> from poseflow.data import ImageInstances, ObjectModel
        >>> from poseflow.render import Renderer
        >>> from poseflow.verify import VerifierConfig
        >>> box = o3d.geometry.TriangleMesh.create_box(0.1, 0.06, 0.03)
        >>> model = ObjectModel.from_mesh(box.translate((-0.05, -0.03, -0.015)), num_points=64)
        >>> verifier = PoseVerifier(VerifierConfig(num_points=1024, crop_size=32,
        ...                                        min_self_overlap=0.9))
        >>> verifier.prepare(1, model).candidates.shape  # the box's three half-turns
        torch.Size([3, 4, 4])
        >>> K = torch.tensor([[300.0, 0, 80], [0, 300.0, 60], [0, 0, 1]])
        >>> pose = torch.eye(4); pose[2, 3] = 0.4
        >>> out = Renderer([model.mesh]).render(pose[None], K, 160, 120)
        >>> image = ImageInstances(None, out.depth, K, out.masks_full, [1])  # no colour
        >>> result = verifier.verify(image, pose[None])
        >>> result.hypotheses.shape  # the estimate, 2 candidates, 4 turns and 4 slides searched
        torch.Size([1, 11, 4, 4])
        >>> int(result.chosen[0]), bool(result.valid[0])  # the estimate is kept
        (0, True)
    """

    def verify(
        self,
        image: ImageInstances,
        poses: torch.Tensor,
        observed: ObservedClouds | None = None,
        *,
        extra: torch.Tensor | None = None,
        extra_mask: torch.Tensor | None = None,
        estimated: torch.Tensor | None = None,
    ) -> Verification:
        """Check each estimate against its near-symmetric candidates, keep the best, polish it.

        Args:
            image: the colour image ``(3, Hi, Wi)`` (or None: depth and silhouette only), depth
                in metres ``(Hi, Wi)``, intrinsics ``(3, 3)``, and the ``B`` instances' masks
                ``(B, Hi, Wi)`` bool and object ids ``(B,)``, all prepared.
            poses: the estimates ``(B, 4, 4)``.
            observed: the observed clouds ``(B, M, 3)`` (camera frame) that ICP registers and
                their valid points ``(B, M)`` bool (or None: all), as :meth:`observed_cloud`
                gives them; lifted from the image's depth and masks when None.
            extra: more hypotheses of each instance ``(B, E, 4, 4)`` (e.g. the estimator's
                other solutions), candidates like the near-symmetric ones: scored, the best
                refined, and chosen only where they beat the estimate.
            extra_mask: ``(B, E)`` bool, False for padding of ``extra``.
            estimated: ``(B,)`` bool, False for instances the estimator found no pose for: they
                are not verified and come back unchanged, with score 0 and ``valid`` False.

        Returns:
            A :class:`~poseflow.verify.Verification`; without instances (``B = 0``) an empty
            one, whose ``hypotheses`` are ``(0, 1, 4, 4)``.

        Raises:
            ShapeError: wrong shapes, devices or dtypes.
            ValueRangeError: an object that was not prepared.
        """
        sizes = check_tensor(poses, "poses", ("B", 4, 4), finite=True)
        check_mask(image.masks, "masks", ("B", None, None), sizes)
        if extra is not None:
            check_tensor(extra, "extra", ("B", "E", 4, 4), sizes=sizes, finite=True)
            check_same(("poses", poses), ("extra", extra))
            if extra_mask is not None:
                check_mask(extra_mask, "extra_mask", ("B", "E"), sizes)
        B = sizes["B"]
        if B == 0:
            self._objects(image.obj_ids, 0)
            return self._unscored(poses[:, None])
        contested = _Image.of(image, poses.dtype, observed)
        if estimated is None:
            return self._verified(contested, poses, extra, extra_mask)
        check_mask(estimated, "estimated", ("B",), sizes)
        rows = estimated.nonzero()[:, 0]
        if len(rows) == B:
            return self._verified(contested, poses, extra, extra_mask)
        if not len(rows):  # one hypothesis each, the estimate, unscored
            return self._unscored(poses[:, None])
        part = self._verified(*contested.take(rows, poses, extra, extra_mask))
        out = self._unscored(poses[:, None].expand(B, part.hypotheses.shape[1], 4, 4))
        out.scatter(rows, part)
        return out

    def search(
        self,
        image: ImageInstances,
        poses: torch.Tensor,
        observed: ObservedClouds | None = None,
    ) -> Verification:
        """Search every orientation for poses that explain the image poorly.

        Each pose is turned by the :func:`~poseflow.verify.box_turns` of its object (the
        flips and quarter turns about its own and its principal axes, and the turns about the
        boxes' diagonals) and slid along its principal axes by ``search_slides`` of its extent
        (:func:`~poseflow.verify.box_slides`); these are scored on the coarse grid, the best
        ``search_top_k`` turns and as many slides refined by ICP, scored on the full grid and
        tested against the pose as :meth:`verify`'s candidates are. A pose upside down, which
        no near-symmetry or hypothesis of the estimator reaches, is then found by ICP from the
        turn nearest to the truth; an object seen only in part and placed centred on what is
        seen, by a slide.
        :meth:`verify` runs this on its chosen poses that score below ``search_below``.

        Args:
            image: the colour image ``(3, Hi, Wi)`` (or None: depth and silhouette only), depth
                in metres ``(Hi, Wi)``, intrinsics ``(3, 3)``, and the ``B`` instances' masks
                ``(B, Hi, Wi)`` bool and object ids ``(B,)``, all prepared.
            poses: the poses searched around ``(B, 4, 4)`` (already refined: they are
                compared as they are).
            observed: the observed clouds ``(B, M, 3)`` that ICP registers and their valid
                points ``(B, M)`` (or None), as in :meth:`verify`; lifted when None.

        Returns:
            A :class:`~poseflow.verify.Verification` whose hypotheses are the pose, then
            ``search_top_k`` refined turns (invalid where the object has fewer) and, with
            ``search_slides``, ``search_top_k`` refined slides. The crops are centred on
            ``poses``.
        """
        check_tensor(poses, "poses", ("B", 4, 4), finite=True)
        if poses.shape[0] == 0:
            return self._unscored(poses[:, None].expand(0, 1 + self._search_width(), 4, 4))
        return self._searched(_Image.of(image, poses.dtype, observed), poses)

    def rank_hypotheses(
        self,
        image: ImageInstances,
        poses: torch.Tensor,
        *,
        extra: torch.Tensor,
        extra_mask: torch.Tensor | None = None,
        estimated: torch.Tensor | None = None,
    ) -> Hypotheses:
        """Make each instance's best hypothesis by the verifier's score its estimate.

        An estimator's own score (geometric agreement of a few points) ranks hypotheses that
        differ by a near-symmetry poorly; the verifier's depth, silhouette and appearance terms
        rank them on what the image shows: all on the coarse grid of :meth:`verify`'s contest
        and, where ``config.rank_top_k`` is above 1, the best ``rank_top_k`` of them again on
        the full grid, which resolves thin parts (a handle) that decide between turns of a
        nearly symmetric object. The best is then the incumbent of :meth:`verify`.

        Args:
            image: the colour image ``(3, Hi, Wi)`` (or None: depth and silhouette only), depth
                in metres ``(Hi, Wi)``, intrinsics ``(3, 3)``, and the ``B`` instances' masks
                ``(B, Hi, Wi)`` bool and object ids ``(B,)``, all prepared.
            poses: the estimator's choice ``(B, 4, 4)``.
            extra: its other hypotheses ``(B, E, 4, 4)``.
            extra_mask: ``(B, E)`` bool, False for padding of ``extra``.
            estimated: ``(B,)`` bool, False for instances without an estimate: they are left
                as they are.

        Returns:
            :class:`~poseflow.verify.Hypotheses` ``(B, 1 + E, 4, 4)``: the estimate, then
            ``extra``, with each instance's best swapped with its estimate (mask likewise: the
            estimate's entry is ``estimated``).

        Raises:
            ShapeError: wrong shapes, devices or dtypes.
            ValueRangeError: an object that was not prepared.
        """
        sizes = check_tensor(poses, "poses", ("B", 4, 4))
        check_tensor(extra, "extra", ("B", "E", 4, 4), sizes=sizes)
        B, E = extra.shape[:2]
        valid = (
            torch.ones_like(poses[:, 0, 0], dtype=torch.bool) if estimated is None else estimated
        )
        more = (
            torch.ones_like(extra[..., 0, 0], dtype=torch.bool)
            if extra_mask is None
            else extra_mask
        )
        hyp = torch.cat((poses[:, None], extra), dim=1)  # (B, 1 + E, 4, 4)
        mask = torch.cat((valid[:, None], more), dim=1)
        if B == 0 or E == 0:
            return Hypotheses(hyp, mask)
        top = min(self.config.rank_top_k, 1 + E)
        contest = self._contest(
            _Image.of(image, poses.dtype, None), hyp, mask, k=top if top > 1 else 0, ranking=True
        )
        best = torch.where(valid, contest.best(), 0)
        rows = torch.arange(B, device=hyp.device)
        if self.config.expand_top_k > 1:  # all of them by their score, the best first
            ranked = torch.where(contest.coarse.valid, contest.coarse.total, -torch.inf)
            ranked[rows, best] = torch.inf
            order = ranked.argsort(dim=1, descending=True, stable=True)
            order = torch.where(valid[:, None], order, torch.arange(1 + E, device=hyp.device))
            return Hypotheses(
                hyp.gather(1, order[..., None, None].expand(-1, -1, 4, 4)), mask.gather(1, order)
            )
        swapped, flags = hyp.clone(), mask.clone()
        swapped[rows, 0], swapped[rows, best] = hyp[rows, best], hyp[rows, 0]
        flags[rows, 0], flags[rows, best] = mask[rows, best], mask[rows, 0]
        return Hypotheses(swapped, flags)

    def _contest(
        self,
        image: _Image,
        hypotheses: torch.Tensor,
        mask: torch.Tensor,
        *,
        k: int,
        groups: tuple[int, ...] = (),
        refine_first: bool = False,
        ranking: bool = False,
    ) -> _Contest:
        """The contest of hypotheses ``(B, H, 4, 4)``: the six steps of verify, search, ranking.

        On the crop the first hypothesis places (1), all are scored on the coarse grid (2); the
        observed clouds are lifted where needed (3); the first and the best ``k`` others are
        kept and refined by ICP (4) and scored on the full grid (5). The choice (6) is the
        caller's: :meth:`_Contest.verification` or :meth:`_Contest.best`.

        Args:
            image: the image.
            hypotheses: ``(B, H, 4, 4)``, the incumbent first.
            mask: ``(B, H)`` bool, False for padding.
            k: other hypotheses kept, ``k < H``.
            groups: the sizes of consecutive groups of the other hypotheses (summing to
                ``H - 1``), each of which contributes its best ``k`` (so that one kind of
                start cannot crowd out another); empty: one group.
            refine_first: refine the incumbent by ICP too.
            ranking: rank them all: the best ``k`` of all hypotheses, the incumbent included,
                are kept behind it (it leads unscored: the full grid's tolerances are scaled by
                its depth, as the coarse grid's), and none is refined; with ``k = 0`` nothing
                is scored on the full grid.
        """
        cfg = self.config
        boxes = self.crop_boxes(hypotheses[:, 0], image.obj_ids, image.K, image.masks)
        # the grid that decides: the full one where a ranking re-scores its best k unrefined
        grid = cfg.crop_size if ranking and k else cfg.coarse_crop_size
        mask = mask & self._distinct(hypotheses, mask, image.obj_ids, grid)
        coarse = self.score(image, hypotheses, mask, boxes=boxes, crop_size=cfg.coarse_crop_size)
        if not ranking and image.observed is None and (k or refine_first):
            lifted = self.observed_cloud(image.depth, image.K, image.masks)
            image = replace(image, observed=lifted[0], observed_mask=lifted[1])
        start = 0 if ranking else 1
        bounds = list(itertools.accumulate(groups or (hypotheses.shape[1] - start,), initial=start))
        index = torch.zeros(
            len(hypotheses), 1 + k * (len(bounds) - 1), dtype=torch.long, device=hypotheses.device
        )
        if k:
            ranked = torch.where(coarse.valid, coarse.total, -torch.inf)
            index[:, 1:] = torch.cat([
                ranked[:, a:b].topk(k, dim=-1).indices + a for a, b in itertools.pairwise(bounds)
            ], dim=1)  # fmt: skip
        poses = hypotheses.gather(1, index[..., None, None].expand(-1, -1, 4, 4))
        kept = mask.gather(1, index)
        kept[:, 1:] &= coarse.valid.gather(1, index[:, 1:])
        if ranking:
            kept[:, 0] = False
        elif image.observed is not None and image.observed.shape[1] >= 3:
            first = 0 if refine_first else 1
            if poses.shape[1] > first:
                refined = self.refine(
                    poses[:, first:], image.obj_ids, image.observed.to(poses.dtype),
                    image.observed_mask,
                )  # fmt: skip
                poses = torch.cat((poses[:, :first], refined), dim=1)
        full = None
        if k or not ranking:
            full = self.score(image, poses, kept, boxes=boxes)
        return _Contest(image, index, poses, kept, coarse, full)

    def _distinct(
        self, hypotheses: torch.Tensor, mask: torch.Tensor, obj_ids: object, grid: int
    ) -> torch.Tensor:
        """``(B, H)`` bool: False where a crop of ``grid`` pixels shows an earlier hypothesis again.

        Two poses of an object look the same on the grid when no surface point moves by one of
        its pixels between them (``crop_margin`` times the diameter over ``grid``): bounded by
        ``angle * r + |Δt|``, ``r`` the farthest surface point from the model's origin. The
        first of such a group (the incumbent first) stays.
        """
        cfg = self.config
        objects = self._objects(obj_ids, hypotheses.shape[0])
        kw = {"dtype": hypotheses.dtype, "device": hypotheses.device}
        radius = torch.stack([o.points.norm(dim=-1).max() for o in objects]).to(**kw)
        pixel = torch.tensor([o.diameter for o in objects], **kw) * (cfg.crop_margin / grid)
        B, H = mask.shape
        pairs = (B, H, H, 4, 4)
        angle = rotation_angle_error(
            hypotheses[:, :, None].expand(pairs), hypotheses[:, None].expand(pairs), degrees=False
        )
        t = hypotheses[..., :3, 3]
        shift = (t[:, :, None] - t[:, None]).norm(dim=-1)
        close = angle * radius[:, None, None] + shift <= pixel[:, None, None]
        keep = mask.clone()
        for j in range(1, H):
            keep[:, j] &= ~(close[:, :j, j] & keep[:, :j]).any(1)
        return keep

    def _unscored(self, hypotheses: torch.Tensor) -> Verification:
        """The verification of unscored hypotheses ``(B, H, 4, 4)`` on the full grid."""
        blocks = (self.config.crop_size // self.config.block_size) ** 2
        return Verification.unscored(hypotheses, blocks)

    def _verified(
        self,
        image: _Image,
        poses: torch.Tensor,
        extra: torch.Tensor | None,
        extra_mask: torch.Tensor | None,
    ) -> Verification:
        """:meth:`verify` of instances that all have an estimate ``(B, 4, 4)``."""
        cfg = self.config
        B = poses.shape[0]
        if extra is None:
            extra = poses.new_zeros(B, 0, 4, 4)
        more = torch.ones_like(extra[..., 0, 0], dtype=torch.bool)
        if extra_mask is not None:
            more = extra_mask.bool()
        # the estimate and the first m others, each with its near-symmetric candidates, in one call
        m = min(cfg.expand_top_k - 1, extra.shape[1])
        ids = torch.as_tensor(image.obj_ids).reshape(-1).repeat_interleave(1 + m)
        grown = self.expand(torch.cat((poses[:, None], extra[:, :m]), 1).reshape(-1, 4, 4), ids)
        C = grown.poses.shape[1]
        kept = grown.mask.reshape(B, 1 + m, C)
        kept[:, 1:] &= more[:, :m, None]
        hyp = Hypotheses(
            torch.cat((grown.poses.reshape(B, (1 + m) * C, 4, 4), extra[:, m:]), dim=1),
            torch.cat((kept.reshape(B, (1 + m) * C), more[:, m:]), dim=1),
        )
        k = min(cfg.refine_top_k, hyp.poses.shape[1] - 1)
        contest = self._contest(image, hyp.poses, hyp.mask, k=k, refine_first=cfg.refine_estimate)
        out = contest.verification(cfg.significance)
        if cfg.search_below > 0:
            # the instances still scoring low are searched; their turns and slides follow as
            # more columns (invalid, the pose repeated, where an instance was not searched),
            # scored on a crop centred on the pose searched around, their statistics against it
            H = out.hypotheses.shape[1]
            searched = out.widened(self._search_width())
            rows = (out.valid & (out.scores < cfg.search_below)).nonzero()[:, 0]
            if len(rows):
                found = self._searched(*contest.image.take(rows, out.poses))
                # the others keep their pose and its score on the first crop
                searched.scatter(rows, found, column=H, skip=1, where=found.chosen > 0)
            out = searched
        rows = out.valid.nonzero()[:, 0]
        if cfg.polish_levels and len(rows):
            polished, total = self.polish(*contest.image.take(rows, out.poses))
            out.poses[rows] = polished
            out.scores[rows] = total.clamp(0, 1)
        return out

    def _searched(self, image: _Image, poses: torch.Tensor) -> Verification:
        """:meth:`search` of ``B > 0`` poses ``(B, 4, 4)``."""
        k = self.config.search_top_k
        objects = self._objects(image.obj_ids, poses.shape[0])
        turns_of = {id(o): box_turns(o.points).to(poses) for o in objects}
        count = torch.tensor([len(turns_of[id(o)]) for o in objects], device=poses.device)
        width = max(int(count.max()), k)
        eye = torch.eye(4, dtype=poses.dtype, device=poses.device)
        turns = torch.stack([  # (B, width, 4, 4), padded with the identity
            torch.cat((t, eye.expand(width - len(t), 4, 4)))
            for t in (turns_of[id(o)] for o in objects)
        ])  # fmt: skip
        padded = torch.arange(width, device=poses.device) >= count[:, None]
        hyp = [poses[:, None], poses[:, None] @ turns]
        hyp_mask = [torch.ones_like(padded[:, :1]), ~padded]
        groups: tuple[int, ...] = ()
        if self.config.search_slides:  # (B, S, 4, 4), as many for every object
            slides = torch.stack([box_slides(o.points, self.config.search_slides) for o in objects])
            S = slides.shape[1]
            slides = torch.cat((slides.to(poses), eye.expand(len(poses), max(k - S, 0), 4, 4)), 1)
            hyp.append(poses[:, None] @ slides)
            hyp_mask.append(
                torch.arange(slides.shape[1], device=poses.device).expand(len(poses), -1) < S
            )
            groups = (width, slides.shape[1])
        contest = self._contest(
            image, torch.cat(hyp, dim=1), torch.cat(hyp_mask, dim=1), k=k, groups=groups
        )
        return contest.verification(self.config.significance)

    def _search_width(self) -> int:
        """The columns :meth:`search` adds: the best turns, then the best slides."""
        return self.config.search_top_k * (2 if self.config.search_slides else 1)
