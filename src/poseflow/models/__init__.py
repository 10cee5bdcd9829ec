"""FunFlow6D: the model class, its configuration and its trainable network."""

from poseflow.assets import DEMO_CHECKPOINT
from poseflow.models.config import ABLATIONS, INFERENCE_FIELDS, FunFlow6DConfig
from poseflow.models.funflow6d import FunFlow6D, Observation, PreparedObject
from poseflow.models.network import FunFlow6DNet, NetConfig
from poseflow.models.training import FlowTrainingSet, augment, build_training_set, train

__all__ = [
    "ABLATIONS",
    "DEMO_CHECKPOINT",
    "INFERENCE_FIELDS",
    "FlowTrainingSet",
    "FunFlow6D",
    "FunFlow6DConfig",
    "FunFlow6DNet",
    "NetConfig",
    "Observation",
    "PreparedObject",
    "augment",
    "build_training_set",
    "train",
]
