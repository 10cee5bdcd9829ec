"""Symmetry sets of object models, discretised as the BOP toolkit does.

An object's symmetry set holds every rigid transform ``S`` (model frame to model frame) under which
the model looks the same, so that a pose ``T_gt @ S`` is as correct as ``T_gt``. BOP describes it
in ``models_info.json`` by *discrete* symmetries (row-major 4x4 matrices) and *continuous* ones (a
rotation axis through a point ``offset``). MSSD and MSPD take the minimum error over the set, with
each continuous symmetry sampled at ``ceil(pi / max_sym_disc_step)`` equally spaced angles, so that
the model vertex furthest from the axis moves by at most ``max_sym_disc_step`` diameters between
two samples (the toolkit's ``max_sym_disc_step = 0.01``). The set always contains the identity and
is the product "continuous sample after discrete symmetry".

Transforms here are in metres, like everything inside poseflow; :func:`symmetries_from_model_info`
converts the millimetres of ``models_info.json``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch

from poseflow._checks import check_tensor
from poseflow.errors import ShapeError, ValueRangeError
from poseflow.geometry.se3 import axis_angle_to_rotation

__all__ = [
    "MAX_SYM_DISC_STEP",
    "discretize_continuous_symmetry",
    "symmetries_from_model_info",
    "symmetry_transforms",
]

#: The BOP toolkit's maximum step (fraction of the diameter) between sampled continuous symmetries.
MAX_SYM_DISC_STEP = 0.01


def discretize_continuous_symmetry(
    axis: torch.Tensor,
    offset: torch.Tensor,
    *,
    max_sym_disc_step: float = MAX_SYM_DISC_STEP,
) -> torch.Tensor:
    """Sample a continuous rotational symmetry at equally spaced angles, the toolkit's way.

    The axis passes through ``offset``; sample ``i`` rotates by ``i * 2 pi / n`` with
    ``n = ceil(pi / max_sym_disc_step)``, and maps ``x`` to ``R x - R offset + offset``.

    Args:
        axis: direction of the axis, shape ``(3,)``.
        offset: a point on the axis in metres, shape ``(3,)``.
        max_sym_disc_step: largest step between samples as a fraction of the diameter.

    Returns:
        Transforms of shape ``(n, 4, 4)``; the first is the identity.

    Example:
        >>> S = discretize_continuous_symmetry(torch.tensor([0.0, 0.0, 1.0]), torch.zeros(3))
        >>> S.shape
        torch.Size([315, 4, 4])
    """
    if not max_sym_disc_step > 0:
        raise ValueRangeError(f"max_sym_disc_step must be positive, got {max_sym_disc_step}")
    check_tensor(offset, "offset", (3,), finite=True)
    dtype = offset.dtype if offset.is_floating_point() else torch.float64
    n = math.ceil(math.pi / max_sym_disc_step)
    angles = torch.arange(n, dtype=torch.float64, device=offset.device) * (2 * math.pi / n)
    check_tensor(axis, "axis", (3,), finite=True)
    if float(axis.norm()) == 0.0:
        raise ValueRangeError("a symmetry axis must have non-zero length")
    R = axis_angle_to_rotation(axis.to(torch.float64), angles)
    o = offset.to(torch.float64)
    T = torch.zeros(n, 4, 4, dtype=torch.float64, device=offset.device)
    T[:, :3, :3] = R
    T[:, :3, 3] = o - R @ o
    T[:, 3, 3] = 1
    return T.to(dtype)


def symmetry_transforms(
    discrete: torch.Tensor | None = None,
    continuous: Sequence[tuple[torch.Tensor, torch.Tensor]] = (),
    *,
    max_sym_disc_step: float = MAX_SYM_DISC_STEP,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """The full symmetry set of an object: identity, discrete symmetries, sampled continuous ones.

    Follows the BOP toolkit: the discrete set is the identity plus ``discrete``; without continuous
    symmetries that is the result, otherwise every sample ``C`` of every continuous symmetry is
    composed after every discrete ``D`` as ``C @ D``.

    Args:
        discrete: discrete symmetry transforms in metres, shape ``(D, 4, 4)``, or None. An identity
            among them is kept (it only duplicates an entry).
        continuous: ``(axis, offset)`` pairs, each of shape ``(3,)``, offset in metres.
        max_sym_disc_step: see :func:`discretize_continuous_symmetry`.
        dtype: output dtype.
        device: output device.

    Returns:
        Transforms of shape ``(S, 4, 4)``; ``S = 1 + D`` without continuous symmetries, else
        ``(1 + D) * sum_c n_c``.

    Example:
        >>> flip = torch.diag(torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=torch.float64))
        >>> symmetry_transforms(flip[None]).shape
        torch.Size([2, 4, 4])
    """
    eye = torch.eye(4, dtype=torch.float64, device=device)[None]
    if discrete is None or discrete.numel() == 0:
        disc = eye
    else:
        check_tensor(discrete, "discrete", ("D", 4, 4), finite=True)
        disc = torch.cat((eye, discrete.to(device=eye.device, dtype=torch.float64)), 0)
    conts = [
        discretize_continuous_symmetry(
            torch.as_tensor(axis, dtype=torch.float64, device=eye.device),
            torch.as_tensor(offset, dtype=torch.float64, device=eye.device),
            max_sym_disc_step=max_sym_disc_step,
        )
        for axis, offset in continuous
    ]
    if not conts:
        return disc.to(dtype)
    cont = torch.cat(conts, 0)
    # Row d * C + c holds C_c @ D_d, the toolkit's order (discrete outer, continuous inner).
    out = (cont[None, :, :, :] @ disc[:, None, :, :]).reshape(-1, 4, 4)
    return out.to(dtype)


def symmetries_from_model_info(
    info: Mapping[str, Any],
    *,
    max_sym_disc_step: float = MAX_SYM_DISC_STEP,
    unit_scale: float = 1e-3,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """The symmetry set of one entry of a BOP ``models_info.json``.

    Args:
        info: the object's entry, with optional ``symmetries_discrete`` (row-major 4x4 lists,
            translation in the file's unit) and ``symmetries_continuous`` (dicts with ``axis`` and
            ``offset``).
        max_sym_disc_step: see :func:`discretize_continuous_symmetry`.
        unit_scale: metres per file unit (BOP files are in millimetres).
        dtype: output dtype.
        device: output device.

    Returns:
        Transforms in metres, shape ``(S, 4, 4)``.

    Raises:
        ShapeError: a discrete symmetry does not have 16 entries.

    Example:
        >>> info = {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}
        >>> symmetries_from_model_info(info).shape
        torch.Size([315, 4, 4])
    """
    discrete = None
    entries = info.get("symmetries_discrete") or []
    if entries:
        mats = []
        for i, entry in enumerate(entries):
            m = torch.as_tensor(entry, dtype=torch.float64).reshape(-1)
            if m.numel() != 16:
                raise ShapeError(f"symmetries_discrete[{i}] must have 16 entries, got {m.numel()}")
            m = m.reshape(4, 4).clone()
            m[:3, 3] *= unit_scale
            mats.append(m)
        discrete = torch.stack(mats)
    continuous = [
        (
            torch.as_tensor(c["axis"], dtype=torch.float64),
            torch.as_tensor(c["offset"], dtype=torch.float64) * unit_scale,
        )
        for c in info.get("symmetries_continuous") or []
    ]
    return symmetry_transforms(
        discrete, continuous, max_sym_disc_step=max_sym_disc_step, dtype=dtype, device=device
    )
