"""Evaluation: BOP 2019 Average Recall, results files, the inlier metric, timing and pictures.

- pose errors :func:`vsd_from_depth`, :func:`mssd`, :func:`mspd` (vectorised over estimates) and
  symmetry sets discretised as the BOP toolkit does (:func:`symmetry_transforms`);
- the recall protocol (:func:`assign`, :func:`match`) and the dataset-level
  :func:`evaluate_bop` returning AR, AR_VSD, AR_MSSD, AR_MSPD, per object and per threshold, and
  :func:`closest_results`, the oracle choice among several results per target;
- :func:`predict_dataset`, the loop that runs any estimator over a BOP split (ground-truth or
  detected masks) into results (:func:`predict_seeded`: reseeding its generator per image, the
  estimators' ``predict``), and :func:`estimate_frame` for one frame, written by
  :func:`write_poses_json`; a pose behind the camera is never valid
  (:func:`invalidate_implausible`);
- the same loop split over the processes of a ``torchrun`` job (:func:`join_ranks`,
  :class:`Ranks`, :func:`shard_images`, :func:`merge_parts`), merged into one process's results;
- what `valid` means: a per-object score threshold fitted on calibration renders
  (:class:`ValidityRule`, :func:`estimate_errors`, :func:`validity_report`,
  :func:`plot_reliability`), stored in a model folder (:func:`write_validity`);
- BOP 2019 results CSV files (:func:`read_results`, :func:`write_results`);
- the paper's correspondence-inlier metric (:func:`correspondence_inliers`);
- the per-image stage breakdown (:class:`StageTimer`, reported to through :func:`stage` and
  :func:`timed` while a timer is active) and qualitative overlays with a legend
  (:func:`overlay_poses`, :func:`write_overlay`, :func:`write_result_overlays`);
- 3D scenes of one image for viewers (:func:`build_scene`: the observed cloud and the posed
  meshes), written as a Rerun recording (:func:`write_recording`) or a GLB/PLY scene
  (:func:`export_scene`).
"""

from poseflow.eval.detection import score_detections
from poseflow.eval.distributed import (
    PredictionPart,
    Ranks,
    image_seed,
    join_ranks,
    merge_parts,
    merge_results,
    merge_timers,
    shard_images,
)
from poseflow.eval.errors import (
    MSPD_THRESHOLDS,
    MSSD_THRESHOLDS,
    VSD_DELTA,
    VSD_TAUS,
    VSD_THRESHOLDS,
    depth_to_distance,
    mspd,
    mssd,
    project_points,
    vsd_from_depth,
)
from poseflow.eval.evaluate import (
    METRICS,
    EvalModel,
    closest_results,
    evaluate_bop,
    gt_results,
    load_eval_models,
)
from poseflow.eval.frame import FramePoses, estimate_frame, write_poses_json
from poseflow.eval.inliers import InlierResult, correspondence_inliers, mutual_nearest_neighbors
from poseflow.eval.overlay import (
    ESTIMATE_COLOR,
    ESTIMATE_COLORS,
    GT_COLOR,
    as_uint8_image,
    overlay_poses,
    write_overlay,
    write_result_overlays,
)
from poseflow.eval.predict import (
    Estimator,
    PoseEstimate,
    invalidate_implausible,
    on_device,
    predict_dataset,
    predict_seeded,
    seeded_estimator,
)
from poseflow.eval.recall import Assignment, Recall, Target, assign, match, targets_from_gt
from poseflow.eval.results import HEADER, PoseResults, read_results, write_results
from poseflow.eval.scene import (
    GLTF_FROM_CAMERA,
    ObservedCloud,
    PosedMesh,
    SceneView,
    backproject_rgbd,
    build_scene,
    export_scene,
    place_mesh,
    write_recording,
)
from poseflow.eval.symmetry import (
    MAX_SYM_DISC_STEP,
    discretize_continuous_symmetry,
    symmetries_from_model_info,
    symmetry_transforms,
)
from poseflow.eval.timing import (
    EXCLUDED_STAGES,
    STAGES,
    StageTimer,
    active_timer,
    stage,
    timed,
)
from poseflow.eval.validity import (
    VALIDITY_FILE,
    ValidityRule,
    apply_validity,
    estimate_errors,
    mesh_key,
    plot_reliability,
    read_validity,
    validity_report,
    write_validity,
)

__all__ = [
    "ESTIMATE_COLOR",
    "ESTIMATE_COLORS",
    "EXCLUDED_STAGES",
    "GLTF_FROM_CAMERA",
    "GT_COLOR",
    "HEADER",
    "MAX_SYM_DISC_STEP",
    "METRICS",
    "MSPD_THRESHOLDS",
    "MSSD_THRESHOLDS",
    "STAGES",
    "VALIDITY_FILE",
    "VSD_DELTA",
    "VSD_TAUS",
    "VSD_THRESHOLDS",
    "Assignment",
    "Estimator",
    "EvalModel",
    "FramePoses",
    "InlierResult",
    "ObservedCloud",
    "PoseEstimate",
    "PoseResults",
    "PosedMesh",
    "PredictionPart",
    "Ranks",
    "Recall",
    "SceneView",
    "StageTimer",
    "Target",
    "ValidityRule",
    "active_timer",
    "apply_validity",
    "as_uint8_image",
    "assign",
    "backproject_rgbd",
    "build_scene",
    "closest_results",
    "correspondence_inliers",
    "depth_to_distance",
    "discretize_continuous_symmetry",
    "estimate_errors",
    "estimate_frame",
    "evaluate_bop",
    "export_scene",
    "gt_results",
    "image_seed",
    "invalidate_implausible",
    "join_ranks",
    "load_eval_models",
    "match",
    "merge_parts",
    "merge_results",
    "merge_timers",
    "mesh_key",
    "mspd",
    "mssd",
    "mutual_nearest_neighbors",
    "on_device",
    "overlay_poses",
    "place_mesh",
    "plot_reliability",
    "predict_dataset",
    "predict_seeded",
    "project_points",
    "read_results",
    "read_validity",
    "score_detections",
    "seeded_estimator",
    "shard_images",
    "stage",
    "symmetries_from_model_info",
    "symmetry_transforms",
    "targets_from_gt",
    "timed",
    "validity_report",
    "vsd_from_depth",
    "write_overlay",
    "write_poses_json",
    "write_recording",
    "write_result_overlays",
    "write_results",
    "write_validity",
]
