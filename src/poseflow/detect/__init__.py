"""Finding the user's objects in RGB-D images: instance masks, object ids and scores.

A small RGB-D U-Net (:class:`InstanceSegmenter`) predicts every pixel's object, a centre heatmap
per object and each pixel's offset to its instance's centre; :func:`group_instances` turns them
into instances (two of one object apart by their centres). :class:`Detector` runs both on an
image at any camera, :func:`detect_dataset` over a BOP split, writing BOP detections with COCO-RLE
masks. :func:`train_detector` learns it from renders of the objects (the recipe's synth images):
``poseflow train-detector``.
"""

from poseflow.detect.detector import (
    DETECTOR_FORMAT,
    DetectedObjects,
    Detector,
    DetectorConfig,
    detect_dataset,
    mask_box,
)
from poseflow.detect.grouping import Instances, group_instances, head_to_image
from poseflow.detect.network import (
    INPUT_CHANNELS,
    InstanceSegmenter,
    detector_inputs,
    resample_to_focal,
)
from poseflow.detect.training import (
    DetectorImages,
    DetectorTargets,
    detector_images,
    detector_loss,
    detector_targets,
    train_detector,
    training_batch,
)

__all__ = [
    "DETECTOR_FORMAT",
    "INPUT_CHANNELS",
    "DetectedObjects",
    "Detector",
    "DetectorConfig",
    "DetectorImages",
    "DetectorTargets",
    "InstanceSegmenter",
    "Instances",
    "detect_dataset",
    "detector_images",
    "detector_inputs",
    "detector_loss",
    "detector_targets",
    "group_instances",
    "head_to_image",
    "mask_box",
    "resample_to_focal",
    "train_detector",
    "training_batch",
]
