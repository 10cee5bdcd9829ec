"""Verification of pose hypotheses by rendering and comparing, with near-symmetry candidates.

A pose that fits the depth can still show the wrong side of the object's print: a labelled box
flipped end for end, a can turned about its axis. :class:`PoseVerifier` renders every hypothesis
(a z-buffered projection of the model's coloured surface points, batched over instances and
hypotheses) and scores it against the image by depth agreement (as in VSD), silhouette IoU with
the instance mask and a lighting-robust appearance agreement. It expands each estimate with the
object's near-symmetries, found once per object from its geometry, refines them by ICP, and
replaces the estimate only when a candidate beats it by more than the score's own spread. A pose
that still scores low (``search_below``) is searched over every orientation
(:meth:`PoseVerifier.search`): turned by the flips and quarter turns of the object's box
(:func:`box_turns`) and slid along its axes (:func:`box_slides`, for an object seen only in
part), the best of these refined by ICP and tested in the same way. The chosen pose is
finally polished by a pattern search of its score (:meth:`PoseScorer.polish`), which places
what ICP on the depth leaves a few pixels off: a thin part, a print, a handle.

The parts: :func:`prepare_verifier_object` prepares what the verifier keeps per object
(:class:`VerifierObject`, cached on disk by :func:`cached_verifier_object`); :class:`PoseScorer`
expands, refines and scores hypotheses; :class:`PoseVerifier` runs those steps as one contest to
verify, search and rank hypotheses (:meth:`PoseVerifier.rank_hypotheses`) and returns
:class:`Hypotheses` and :class:`Verification`; :func:`score_renderings` and
:func:`select_significant` are the scoring rule and the test of a candidate, :func:`render_points`
the renderer, :func:`near_symmetries` the search for near-symmetries.

Used on its own, with a user's hypotheses::

    import torch
    from poseflow.data import ImageInstances, ObjectModel
    from poseflow.verify import PoseVerifier, VerifierConfig

    model = ObjectModel.from_file("obj_000001.ply", scale=0.001)  # BOP mesh in mm
    verifier = PoseVerifier(VerifierConfig())
    verifier.prepare(1, model)  # once per object: surface samples, near-symmetries

    # rgb (3, H, W) in [0, 1], depth (H, W) in metres, K (3, 3), masks (B, H, W) bool,
    # hypotheses (B, H', 4, 4) model-to-camera poses of the B instances
    image = ImageInstances(rgb, depth, K, masks, [1] * len(masks))
    score = verifier.score(image, hypotheses)
    best = score.total.argmax(-1)  # per-term scores: score.depth, .silhouette, .appearance

    # or the whole stage for one estimate per instance: candidates, ICP, scores, the choice
    result = verifier.verify(image, poses)
    result.poses, result.scores, result.chosen  # (B, 4, 4), (B,), (B,) 0 = estimate kept

``examples/verify_your_poses.py`` runs this on a rendered scene. ``FunFlow6D`` and
``ClassicBaseline`` run :meth:`PoseVerifier.verify` after choosing their poses (unless their
configuration's ``verifier`` is None), with their own lifted clouds as ICP's source.
"""

from poseflow.verify.config import VerifierConfig
from poseflow.verify.objects import (
    VerifierObject,
    cached_verifier_object,
    prepare_verifier_object,
    verifier_fingerprint,
)
from poseflow.verify.render import (
    ObservedCrops,
    PointRendering,
    box_sum,
    crop_intrinsics,
    crop_observation,
    render_points,
)
from poseflow.verify.results import Hypotheses, Verification
from poseflow.verify.score import (
    VerifierScore,
    appearance_agreement,
    balance_colors,
    depth_agreement,
    score_renderings,
    select_significant,
    silhouette_agreement,
    visible_rendering,
)
from poseflow.verify.scorer import PoseScorer
from poseflow.verify.symmetry import (
    NearSymmetries,
    box_slides,
    box_turns,
    near_symmetries,
    revolution_axis,
)
from poseflow.verify.verifier import PoseVerifier

__all__ = [
    "Hypotheses",
    "NearSymmetries",
    "ObservedCrops",
    "PointRendering",
    "PoseScorer",
    "PoseVerifier",
    "Verification",
    "VerifierConfig",
    "VerifierObject",
    "VerifierScore",
    "appearance_agreement",
    "balance_colors",
    "box_slides",
    "box_sum",
    "box_turns",
    "cached_verifier_object",
    "crop_intrinsics",
    "crop_observation",
    "depth_agreement",
    "near_symmetries",
    "prepare_verifier_object",
    "render_points",
    "revolution_axis",
    "score_renderings",
    "select_significant",
    "silhouette_agreement",
    "verifier_fingerprint",
    "visible_rendering",
]
