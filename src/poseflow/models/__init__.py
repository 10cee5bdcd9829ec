"""FunFlow6D: the model class, its configuration, its trainable network and its parts by job.

- :mod:`~poseflow.models.objects`: :class:`PreparedObject`, prepared once per object and cached;
- :mod:`~poseflow.models.observe`: :class:`Observation`, the target clouds of an RGBD image;
- :mod:`~poseflow.models.inputs`: :class:`FlowInputs`, the query and target clouds paired;
- :mod:`~poseflow.models.config`: :class:`FunFlow6DConfig` and its typed parts, the named
  :data:`RECIPES` and :func:`apply_overrides` (dotted keys, merged into nested configurations);
- :mod:`~poseflow.models.network`: :class:`FunFlow6DNet`, fusion + positional encoder + DiT;
- :mod:`~poseflow.models.pose`: :func:`solve_pose` and :func:`agreement_score`;
- :mod:`~poseflow.models.verification`: :func:`verify_estimate`, render-and-compare checking;
- :mod:`~poseflow.models.funflow6d`: :class:`FunFlow6D`, which composes them;
- :mod:`~poseflow.models.hybrid`: :class:`Hybrid`, FunFlow6D's and the classic baseline's poses
  chosen among by one verification, and :func:`full_grid_ranking`, its verifier setting.
"""

from poseflow.models.config import (
    ABLATIONS,
    INFERENCE_FIELDS,
    RECIPES,
    DiTOverrides,
    FunFlow6DConfig,
    NetConfig,
    NetOptions,
    apply_overrides,
)
from poseflow.models.funflow6d import FunFlow6D
from poseflow.models.hybrid import Hybrid, full_grid_ranking
from poseflow.models.inputs import TRAINING_FIELDS, FlowInputs, reduce_appearance
from poseflow.models.network import FunFlow6DNet, NetInputs
from poseflow.models.objects import (
    PreparedObject,
    load_prepared_object,
    object_fingerprint,
    prepare_objects,
)
from poseflow.models.observe import Observation, observe
from poseflow.models.pose import agreement_score, solve_pose
from poseflow.models.training import FlowTrainingSet, augment, build_training_set, train
from poseflow.models.verification import (
    Proposals,
    keep_better,
    other_hypotheses,
    prepare_verification,
    verify_estimate,
    verify_proposals,
)

__all__ = [
    "ABLATIONS",
    "INFERENCE_FIELDS",
    "RECIPES",
    "TRAINING_FIELDS",
    "DiTOverrides",
    "FlowInputs",
    "FlowTrainingSet",
    "FunFlow6D",
    "FunFlow6DConfig",
    "FunFlow6DNet",
    "Hybrid",
    "NetConfig",
    "NetInputs",
    "NetOptions",
    "Observation",
    "PreparedObject",
    "Proposals",
    "agreement_score",
    "apply_overrides",
    "augment",
    "build_training_set",
    "full_grid_ranking",
    "keep_better",
    "load_prepared_object",
    "object_fingerprint",
    "observe",
    "other_hypotheses",
    "prepare_objects",
    "prepare_verification",
    "reduce_appearance",
    "solve_pose",
    "train",
    "verify_estimate",
    "verify_proposals",
]
