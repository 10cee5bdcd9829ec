"""Conditional flow matching over point sets: path, loss, samplers, trainer.

The generative core of FunFlow6D as a general-purpose package: it knows nothing of poses. Train
a velocity model ``model(x=x_t, t=t, **cond)`` with :class:`CFMTrainer` and integrate it from
noise with :func:`sample` (Euler, midpoint, Heun or RK4), anchors held fixed by ``frozen_mask``.
:class:`PointDiT` is a velocity net over point tokens and :class:`PointPositionalEncoder` the
per-point positional encoding of its condition.
"""

from poseflow._precision import (
    PRECISIONS,
    autocast_dtype,
    native_bfloat16,
    precision_autocast,
)
from poseflow.flows.checkpoint import (
    atomic_write,
    flatten_optimizer_state,
    latest_checkpoint,
    load_checkpoint,
    prune_checkpoints,
    save_checkpoint,
    unflatten_optimizer_state,
)
from poseflow.flows.distributed import (
    DistributedContext,
    all_reduce_mean,
    barrier,
    destroy_distributed,
    init_distributed,
    main_rank_succeeded,
)
from poseflow.flows.dit import (
    PRESETS,
    DiTBlock,
    PointDiT,
    PointDiTConfig,
    sinusoidal_time_embedding,
)
from poseflow.flows.ema import EMA
from poseflow.flows.equivalents import (
    apply_equivalents,
    identity_maps,
    nearest_equivalent,
    pad_maps,
)
from poseflow.flows.loss import cfm_loss
from poseflow.flows.objective import CFMObjective, DistillationObjective, FlowBatch, StepRandom
from poseflow.flows.path import LinearPath, PathSample
from poseflow.flows.positional import PointPositionalEncoder, nerf_embedding
from poseflow.flows.protocols import VelocityModel
from poseflow.flows.samplers import (
    SAMPLERS,
    ButcherTableau,
    EulerSampler,
    HeunSampler,
    MidpointSampler,
    ODESampler,
    RK4Sampler,
    get_sampler,
    initial_noise,
    sample,
)
from poseflow.flows.schedule import warmup_cosine_lr
from poseflow.flows.timesteps import (
    TIME_SAMPLERS,
    sample_time,
    uniform_time,
)
from poseflow.flows.trainer import CFMTrainer, Objective, TrainConfig, ValidateHook

__all__ = [
    "EMA",
    "PRECISIONS",
    "PRESETS",
    "SAMPLERS",
    "TIME_SAMPLERS",
    "ButcherTableau",
    "CFMObjective",
    "CFMTrainer",
    "DiTBlock",
    "DistillationObjective",
    "DistributedContext",
    "EulerSampler",
    "FlowBatch",
    "HeunSampler",
    "LinearPath",
    "MidpointSampler",
    "ODESampler",
    "Objective",
    "PathSample",
    "PointDiT",
    "PointDiTConfig",
    "PointPositionalEncoder",
    "RK4Sampler",
    "StepRandom",
    "TrainConfig",
    "ValidateHook",
    "VelocityModel",
    "all_reduce_mean",
    "apply_equivalents",
    "atomic_write",
    "autocast_dtype",
    "barrier",
    "cfm_loss",
    "destroy_distributed",
    "flatten_optimizer_state",
    "get_sampler",
    "identity_maps",
    "init_distributed",
    "initial_noise",
    "latest_checkpoint",
    "load_checkpoint",
    "main_rank_succeeded",
    "native_bfloat16",
    "nearest_equivalent",
    "nerf_embedding",
    "pad_maps",
    "precision_autocast",
    "prune_checkpoints",
    "sample",
    "sample_time",
    "save_checkpoint",
    "sinusoidal_time_embedding",
    "unflatten_optimizer_state",
    "uniform_time",
    "warmup_cosine_lr",
]
