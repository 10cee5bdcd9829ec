"""RANSAC over minimal Procrustes solves, batched over instances and hypotheses.

The hypotheses of all instances are solved together (one batched SVD per chunk of hypotheses,
over the instances that have not yet reached the confidence) and scored with one matrix multiply:
the squared residual of pair ``n`` under hypothesis ``(R, t)``,

    |R s + t - d|^2 = |s|^2 + |d|^2 + |t|^2 + 2 (R^T t).s - 2 <R, d s^T> - 2 t.d,

is linear in per-pair features ``[d s^T, d, s, |s|^2 + |d|^2, 1]`` (17 numbers) with
per-hypothesis coefficients, so a ``(H, 17) @ (17, N)`` product yields every residual. On CPU the
solver's tensor ops run on the calling thread (see
:func:`poseflow.registration._threads.serial_cpu_ops`).
"""

from __future__ import annotations

import math

import torch

from poseflow._api import Solver
from poseflow.errors import ValueRangeError
from poseflow.geometry.se3 import from_Rt
from poseflow.registration._threads import serial_cpu_ops
from poseflow.registration.procrustes import check_pairs, solve_procrustes
from poseflow.registration.result import RegistrationResult

__all__ = ["RANSACProcrustes", "ransac_procrustes"]

#: Residual-matrix entries scored at once (bounds memory; results do not depend on it).
_CHUNK_ELEMENTS = 1 << 21
#: Hypotheses in the first chunk; later chunks double up to the memory bound.
_FIRST_CHUNK = 64
#: Rounds of refitting on the inliers of the current estimate, at most.
_MAX_REFITS = 10


def ransac_procrustes(
    source: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    generator: torch.Generator | None = None,
    max_correspondence_distance: float,
    max_iterations: int = 1000,
    sample_size: int = 3,
    confidence: float = 0.999,
) -> RegistrationResult:
    """Robustly fit the rigid transform mapping ``source`` onto ``target`` from putative pairs.

    Each hypothesis is the Procrustes solution of ``sample_size`` distinct valid pairs drawn at
    random (samples whose points are collinear in the source or the target are rejected, not
    solved); it scores the number of pairs whose residual ``|R s + t - d|`` is below
    ``max_correspondence_distance``. Each chunk of hypotheses is solved in one batched SVD and
    scored in one matrix multiply, over the instances still drawing. With ``confidence < 1`` an
    instance stops after the first hypothesis ``h`` for which
    ``h >= log(1 - confidence) / log(1 - w^s)``, ``w`` being the best inlier ratio so far
    (Open3D's rule); ``confidence = 1`` draws all ``max_iterations``. The best hypothesis
    (first among ties) is then refitted on its inliers, and again on the refit's inliers, until
    the inlier set stops changing (at most 10 rounds; each round lowers
    ``sum min(r^2, threshold^2)``).

    An instance's result depends only on its own data and the generator's draws, not on the rest
    of the batch: registering instances one by one with the same seed gives the same results.

    Args:
        source: source points, shape ``(B, N, 3)``.
        target: corresponding target points, shape ``(B, N, 3)``: pair ``n`` is
            ``(source[:, n], target[:, n])``.
        mask: optional ``(B, N)`` bool, True for pairs to use; masked pairs may hold NaN.
        generator: optional seeded ``torch.Generator`` for reproducible samples.
        max_correspondence_distance: inlier threshold on the residual, in the points' unit.
        max_iterations: hypotheses per instance, at most.
        sample_size: pairs per minimal sample, at least 3.
        confidence: early-stopping confidence in ``(0, 1]``.

    Returns:
        A :class:`~poseflow.registration.result.RegistrationResult`; ``num_iterations`` counts
        the hypotheses each instance drew. Instances with fewer than ``sample_size`` valid
        pairs, only degenerate samples, or fewer than ``sample_size`` inliers get
        ``valid = False`` and the identity.

    Raises:
        ShapeError: wrong shapes, mismatched devices or dtypes, a non-bool mask.
        ValueRangeError: NaN/inf at valid pairs, or a hyper-parameter out of range.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> src = torch.randn(1, 100, 3, generator=g)
        >>> dst = src @ torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]).T + 2.0
        >>> dst[:, :30] = torch.randn(1, 30, 3, generator=g)  # 30% outliers
        >>> result = ransac_procrustes(src, dst, max_correspondence_distance=0.01, generator=g)
        >>> result.transformation[0, :3].round(decimals=3).abs()  # abs: no -0. in the output
        tensor([[0., 1., 0., 2.],
                [1., 0., 0., 2.],
                [0., 0., 1., 2.]])
        >>> round(result.fitness.item(), 2)
        0.7
    """
    distance, confidence = _check_hyperparameters(
        max_correspondence_distance, max_iterations, sample_size, confidence
    )
    with serial_cpu_ops(source):
        return _register(
            source, target, mask, generator, distance, max_iterations, sample_size, confidence
        )


def _check_hyperparameters(
    max_correspondence_distance: float, max_iterations: int, sample_size: int, confidence: float
) -> tuple[float, float]:
    """Check RANSAC's hyper-parameters; the distance and the confidence as floats."""
    if not (math.isfinite(max_correspondence_distance) and max_correspondence_distance > 0):
        raise ValueRangeError(
            f"max_correspondence_distance must be finite and > 0, got {max_correspondence_distance}"
        )
    if isinstance(max_iterations, bool) or not isinstance(max_iterations, int):
        raise ValueRangeError(f"max_iterations must be an int, got {max_iterations!r}")
    if max_iterations < 1:
        raise ValueRangeError(f"max_iterations must be >= 1, got {max_iterations}")
    if isinstance(sample_size, bool) or not isinstance(sample_size, int) or sample_size < 3:
        raise ValueRangeError(f"sample_size must be an int >= 3, got {sample_size!r}")
    if not 0 < confidence <= 1:
        raise ValueRangeError(f"confidence must be in (0, 1], got {confidence}")
    return float(max_correspondence_distance), float(confidence)


def _register(
    source: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None,
    generator: torch.Generator | None,
    max_correspondence_distance: float,
    max_iterations: int,
    sample_size: int,
    confidence: float,
) -> RegistrationResult:
    """:func:`ransac_procrustes` with checked hyper-parameters."""
    source, target, w = check_pairs(source, target, None, mask)
    valid = w > 0
    B, N = source.shape[:2]
    dtype = source.dtype
    s, H = sample_size, max_iterations
    tau2 = max_correspondence_distance**2
    n_valid = valid.sum(-1)
    possible = n_valid >= s
    if not bool(possible.any()):
        return _invalid(B, N, dtype, source.device)

    # Centre both clouds (on their valid points) so the expanded residuals keep precision.
    wn = (w / n_valid.clamp_min(1).to(dtype).unsqueeze(-1)).unsqueeze(-1)
    centre_s, centre_d = (wn * source).sum(1), (wn * target).sum(1)  # (B, 3)
    src = (source - centre_s.unsqueeze(1)) * w.unsqueeze(-1)
    dst = (target - centre_d.unsqueeze(1)) * w.unsqueeze(-1)
    samples = _minimal_samples(valid, n_valid, H, s, generator)
    counts, stop = _draw_hypotheses(src, dst, valid, samples, tau2, possible, confidence)

    drawn = torch.arange(H, device=source.device).expand(B, H)
    best = torch.where(drawn < stop[:, None], counts, -1).argmax(1)  # first of the maxima
    best_samples = samples.gather(1, best.view(B, 1, 1).expand(B, 1, s))
    R, t, ok = _hypotheses(src, dst, best_samples)
    found = possible & ok[:, 0] & (counts.gather(1, best[:, None])[:, 0] >= s)
    T, inliers, res2 = _refit(src, dst, from_Rt(R[:, 0], t[:, 0]), valid, tau2, found)
    found &= inliers.sum(-1) >= s
    # Undo the centring: x -> T (x - c_s) + c_d.
    R, t = T[:, :3, :3], T[:, :3, 3]
    t = t + centre_d - (R @ centre_s.unsqueeze(-1)).squeeze(-1)
    return _finish(from_Rt(R, t), inliers, res2, n_valid, stop, found)


def _minimal_samples(
    valid: torch.Tensor,
    n_valid: torch.Tensor,
    H: int,
    s: int,
    generator: torch.Generator | None,
) -> torch.Tensor:
    """``H`` samples of ``s`` distinct valid pairs per instance, ``(B, H, s)`` indices into ``N``.

    The same uniform draws for every instance, mapped to distinct ranks among that instance's
    valid points, so an instance's result does not depend on the batch.
    """
    B, device = valid.shape[0], valid.device
    gen_device = generator.device if generator is not None else device
    u = torch.rand(H, s, generator=generator, dtype=torch.float64, device=gen_device)
    ranks = _distinct_ranks(u.to(device), n_valid.clamp_min(s))  # (B, H, s)
    order = torch.argsort((~valid).to(torch.uint8), dim=1, stable=True)  # valid points first
    return order.gather(1, ranks.reshape(B, H * s)).reshape(B, H, s)


def _residual_features(src: torch.Tensor, dst: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """The 17 residual features of every pair ``(B, 17, N)`` (see the module docstring).

    Invalid pairs get a huge ``|s|^2 + |d|^2`` so that no hypothesis counts them as inliers.
    """
    B, N = valid.shape
    norms = src.square().sum(-1) + dst.square().sum(-1)
    big = torch.finfo(src.dtype).max / 64  # never an inlier, no overflow in a 17-term sum
    return torch.cat(
        (
            (dst.unsqueeze(-1) * src.unsqueeze(-2)).reshape(B, N, 9),
            dst,
            src,
            torch.where(valid, norms, big).unsqueeze(-1),
            torch.ones(B, N, 1, dtype=src.dtype, device=src.device),
        ),
        -1,
    ).transpose(1, 2)


def _draw_hypotheses(
    src: torch.Tensor,
    dst: torch.Tensor,
    valid: torch.Tensor,
    samples: torch.Tensor,
    tau2: float,
    possible: torch.Tensor,
    confidence: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Inlier counts ``(B, H)`` of the samples' hypotheses and how many each instance drew ``(B,)``.

    Hypotheses are solved and scored in chunks that double in size, over the instances that have
    not reached ``confidence``; counts not drawn are -1.
    """
    (B, H, s), N = samples.shape, valid.shape[1]
    n_valid = valid.sum(-1)
    features = _residual_features(src, dst, valid)
    counts = torch.full((B, H), -1, dtype=torch.int32, device=src.device)
    stop = torch.where(possible, H, 0)
    done, chunk = 0, min(_FIRST_CHUNK, H)
    max_chunk = max(_FIRST_CHUNK, _CHUNK_ELEMENTS // max(1, B * N))
    drawing = possible.nonzero()[:, 0]  # instances that still draw hypotheses
    while done < H and len(drawing):
        hc = min(chunk, H - done)
        counts[drawing, done : done + hc] = _count_inliers(
            src[drawing], dst[drawing], features[drawing], samples[drawing, done : done + hc], tau2
        )
        done += hc
        chunk = min(2 * chunk, max_chunk)
        if confidence < 1:
            stop = _stopping_points(counts[:, :done], n_valid, s, confidence, possible, H)
            drawing = (stop > done).nonzero()[:, 0]
    return counts, stop


def _refit(
    src: torch.Tensor,
    dst: torch.Tensor,
    T: torch.Tensor,
    valid: torch.Tensor,
    tau2: float,
    found: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Refit the ``found`` instances' ``T`` on their inliers until the inlier sets stop changing.

    Each round lowers the truncated cost ``sum_n min(r_n^2, tau^2)``, so this settles (a few
    rounds) on a least-squares optimum. Returns ``T`` ``(B, 4, 4)``, the inliers ``(B, N)`` and
    the squared residuals ``(B, N)``.
    """
    inliers, res2 = _inliers(src, dst, T, valid, tau2)
    active = found.clone()
    for _ in range(_MAX_REFITS):
        T_new, ok_new = solve_procrustes(src, dst, inliers.to(src.dtype))
        inliers_new, res2_new = _inliers(src, dst, T_new, valid, tau2)
        accept = active & ok_new
        T = torch.where(accept[:, None, None], T_new, T)
        active = accept & (inliers_new != inliers).any(-1)
        inliers = torch.where(accept[:, None], inliers_new, inliers)
        res2 = torch.where(accept[:, None], res2_new, res2)
        if not bool(active.any()):
            break
    return T, inliers, res2


class RANSACProcrustes(Solver[RegistrationResult]):
    """RANSAC-Procrustes solver: stores the hyper-parameters, registers when called.

    ``RANSACProcrustes(**hyper)(source, target, mask, generator=...)`` is
    :func:`ransac_procrustes` with those hyper-parameters; see it for the algorithm, arguments
    and result.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> src = torch.randn(2, 50, 3, generator=g)
        >>> solver = RANSACProcrustes(max_correspondence_distance=0.05, max_iterations=100)
        >>> result = solver(src, src + 1.0, generator=g)
        >>> result.valid.tolist(), result.fitness.tolist()
        ([True, True], [1.0, 1.0])
    """

    function = staticmethod(ransac_procrustes)

    def __init__(
        self,
        *,
        max_correspondence_distance: float,
        max_iterations: int = 1000,
        sample_size: int = 3,
        confidence: float = 0.999,
    ) -> None:
        self.max_correspondence_distance, self.confidence = _check_hyperparameters(
            max_correspondence_distance, max_iterations, sample_size, confidence
        )
        self.max_iterations = max_iterations
        self.sample_size = sample_size


def _distinct_ranks(u: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """Map uniform draws ``(H, s)`` to ``s`` distinct ranks in ``[0, n_b)`` per instance.

    Returns ``(B, H, s)`` int64. Draw ``j`` picks uniformly among the ``n_b - j`` ranks not yet
    taken (then steps over the taken ones in increasing order).
    """
    s = u.shape[1]
    picks: list[torch.Tensor] = []
    for j in range(s):
        size = (n - j).to(torch.float64).unsqueeze(-1)  # (B, 1)
        r = (u[:, j] * size).floor().long()  # (B, H)
        r = torch.minimum(r, (n - j - 1).unsqueeze(-1))
        if picks:
            taken = torch.stack(picks, -1).sort(-1).values
            for m in range(j):
                r = r + (r >= taken[..., m]).long()
        picks.append(r)
    return torch.stack(picks, -1)


def _hypotheses(
    src: torch.Tensor, dst: torch.Tensor, samples: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Procrustes on minimal samples ``(B, H, s)``.

    Returns rotations ``(B, H, 3, 3)``, translations ``(B, H, 3)`` and ``ok`` ``(B, H)``, False
    for degenerate samples.
    """
    B, H, s = samples.shape
    flat = samples.reshape(B, H * s, 1).expand(B, H * s, 3)
    ps = src.gather(1, flat).reshape(B * H, s, 3)
    pd = dst.gather(1, flat).reshape(B * H, s, 3)
    T, ok = solve_procrustes(ps, pd, torch.ones(B * H, s, dtype=src.dtype, device=src.device))
    return T[:, :3, :3].reshape(B, H, 3, 3), T[:, :3, 3].reshape(B, H, 3), ok.reshape(B, H)


def _count_inliers(
    src: torch.Tensor, dst: torch.Tensor, features: torch.Tensor, samples: torch.Tensor, tau2: float
) -> torch.Tensor:
    """Inlier counts ``(B, H)`` int32 of the hypotheses of minimal samples ``(B, H, s)``.

    ``features`` ``(B, 17, N)`` are the pairs' residual features (see the module docstring);
    degenerate samples count -1.
    """
    B, hc = samples.shape[:2]
    R, t, ok = _hypotheses(src, dst, samples)
    coeffs = torch.cat(
        (
            -2 * R.reshape(B, hc, 9),
            -2 * t,
            2 * (R.transpose(-1, -2) @ t.unsqueeze(-1)).squeeze(-1),
            torch.ones(B, hc, 1, dtype=src.dtype, device=src.device),
            t.square().sum(-1, keepdim=True),
        ),
        -1,
    )  # (B, hc, 17)
    residual2 = coeffs @ features  # (B, hc, N)
    count = (residual2 < tau2).sum(-1, dtype=torch.int32)
    return torch.where(ok, count, -1)


def _stopping_points(
    counts: torch.Tensor,
    n_valid: torch.Tensor,
    s: int,
    confidence: float,
    possible: torch.Tensor,
    H: int,
) -> torch.Tensor:
    """Hypotheses each instance draws before the confidence is reached (``H`` if not yet)."""
    best = counts.cummax(1).values.clamp_min(0).to(torch.float64)
    ratio = best / n_valid.clamp_min(1).to(torch.float64).unsqueeze(-1)
    p_good = ratio.pow(s).clamp_max(1.0)  # probability that a sample is all inliers
    needed = math.log(1 - confidence) / torch.log1p(-p_good)  # inf when p_good = 1 -> use below
    needed = torch.where(p_good >= 1, 0.0, needed)
    drawn = torch.arange(1, counts.shape[1] + 1, device=counts.device, dtype=torch.float64)
    reached = drawn >= needed
    first = torch.where(reached.any(1), reached.to(torch.uint8).argmax(1) + 1, H)
    return torch.where(possible, first, 0)


def _inliers(
    src: torch.Tensor, dst: torch.Tensor, T: torch.Tensor, valid: torch.Tensor, tau2: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Inlier mask ``(B, N)`` and squared residuals ``(B, N)`` of pairs under ``T``."""
    moved = src @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]
    res2 = (moved - dst).square().sum(-1)
    return (res2 < tau2) & valid, res2


def _finish(
    T: torch.Tensor,
    inliers: torch.Tensor,
    res2: torch.Tensor,
    n_valid: torch.Tensor,
    iterations: torch.Tensor,
    found: torch.Tensor,
) -> RegistrationResult:
    """Assemble the result; instances not ``found`` get the identity and no inliers."""
    B = T.shape[0]
    dtype = T.dtype
    inliers = inliers & found[:, None]
    n_in = inliers.sum(-1)
    fitness = n_in.to(dtype) / n_valid.clamp_min(1).to(dtype)
    rmse = ((res2 * inliers).sum(-1) / n_in.clamp_min(1).to(dtype)).sqrt()
    eye = torch.eye(4, dtype=dtype, device=T.device).expand(B, 4, 4)
    return RegistrationResult(
        transformation=torch.where(found[:, None, None], T, eye),
        fitness=fitness,
        inlier_rmse=torch.where(found, rmse, 0),
        inliers=inliers,
        num_iterations=iterations.to(torch.int64),
        valid=found,
    )


def _invalid(B: int, N: int, dtype: torch.dtype, device: torch.device) -> RegistrationResult:
    zeros = torch.zeros(B, dtype=dtype, device=device)
    return RegistrationResult(
        transformation=torch.eye(4, dtype=dtype, device=device).expand(B, 4, 4).clone(),
        fitness=zeros,
        inlier_rmse=zeros.clone(),
        inliers=torch.zeros(B, N, dtype=torch.bool, device=device),
        num_iterations=torch.zeros(B, dtype=torch.int64, device=device),
        valid=torch.zeros(B, dtype=torch.bool, device=device),
    )
