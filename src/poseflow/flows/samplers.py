"""ODE samplers that integrate a velocity model from noise (``t = 0``) to data (``t = 1``).

Each solver takes ``steps`` uniform steps of size ``dt = 1 / steps`` and calls the model as
``model(x=x_t, t=t, **cond)`` with ``t`` of shape ``(B,)`` (see
:class:`~poseflow.flows.protocols.VelocityModel`); conditioning keywords are passed through.
Each is an explicit Runge-Kutta method, given by its :class:`ButcherTableau`.

=========================  =====  ======================  ============================
solver                     order  model calls per step    note
=========================  =====  ======================  ============================
:class:`EulerSampler`      1      1                       the paper (``K = 50``)
:class:`MidpointSampler`   2      2                       explicit midpoint (RK2)
:class:`HeunSampler`       2      2                       trapezoidal predictor-corrector
:class:`RK4Sampler`        4      4                       classic Runge-Kutta
=========================  =====  ======================  ============================

Frozen points (anchors)
-----------------------
The velocity of every point under ``frozen_mask`` is set to zero at every model evaluation, so
frozen points never move: they end exactly where they start. Where they start is explicit:

- ``x_frozen=None`` (default): frozen points keep their value in ``x_0``. With ``x_0`` fresh
  Gaussian noise this is the paper's inference read literally ("starting from a fresh Gaussian
  sample ... the velocity components corresponding to [the anchor's] points are zeroed out at
  every step"): the anchor stays at its noise sample, and its canonical coordinates reach the
  network only through the conditioning (FunFlow6D's positional encoding of ``Q``). Note that in
  the paper's training the anchor moves along the path like every other point.
- ``x_frozen=X`` (``(B, L, C)``, e.g. ``X(1)`` with ``Q`` at the anchor rows): frozen points are
  placed at ``X`` before the first step, so the anchor sits at its canonical coordinates for the
  whole integration ("``Q`` ... is never transformed"). Train such a model with the anchor pinned
  too, ``LinearPath().sample(x_0, x_1, t, frozen_mask=...)`` (``CFMObjective(pin_frozen=True)``),
  so that it sees the anchor at ``Q`` at every ``t`` in both phases, as in Rectified Point Flow.

``x_0`` itself is never modified, so a model conditioned on the noise (FunFlow6D's positional
encoder reads each point's ``X(0)``) still gets the true noise.

Sampling runs under ``torch.no_grad`` unless ``enable_grad=True``. The sampler does not switch
the model between train and eval mode: call ``model.eval()`` first.
"""

from __future__ import annotations

import abc
import functools
import operator
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import torch

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.errors import ShapeError, ValueRangeError
from poseflow.flows.protocols import VelocityModel

__all__ = [
    "SAMPLERS",
    "ButcherTableau",
    "EulerSampler",
    "HeunSampler",
    "MidpointSampler",
    "ODESampler",
    "RK4Sampler",
    "get_sampler",
    "initial_noise",
    "sample",
]

Field = Callable[[torch.Tensor, float], torch.Tensor]


def initial_noise(
    shape: Sequence[int],
    *,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Draw the initial state ``X(0)``: every entry i.i.d. standard normal, as in the paper.

    Args:
        shape: the state shape, e.g. ``(B, L, 3)``.
        generator: optional random generator; its device is the default ``device``.
        device: output device.
        dtype: floating output dtype (default: torch's default dtype).

    Returns:
        A tensor of the given shape.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> torch.equal(initial_noise((2, 5, 3), generator=g),
        ...             initial_noise((2, 5, 3), generator=torch.Generator().manual_seed(0)))
        True
    """
    if device is None and generator is not None:
        device = generator.device
    return torch.randn(tuple(shape), generator=generator, device=device, dtype=dtype)


@dataclass(frozen=True)
class ButcherTableau:
    """An explicit Runge-Kutta method: its stages and how they combine into one step.

    Stage ``i`` evaluates the velocity ``k_i = v(x + dt * sum_j coupling[i][j] k_j, t +
    nodes[i] dt)`` (``j < i``; zero couplings are skipped); the step is ``x + (dt / divisor) *
    sum_i weights[i] k_i`` (zero weights skipped). The weights are kept as integers over a common
    ``divisor`` so that each solver computes exactly the arithmetic of its textbook formula.

    Args:
        order: global order of accuracy.
        nodes: the stage times as fractions of ``dt``, one per stage (the first 0).
        coupling: per stage, the factors of the earlier stages' velocities in its state.
        weights: per stage, the factor of its velocity in the step, times ``divisor``.
        divisor: the common denominator of ``weights``.

    Example:
        >>> RK4Sampler.tableau.weights, RK4Sampler.tableau.divisor, RK4Sampler.stages
        ((1, 2, 2, 1), 6, 4)
    """

    order: int
    nodes: tuple[float, ...]
    coupling: tuple[tuple[float, ...], ...]
    weights: tuple[int, ...]
    divisor: int = 1


class ODESampler(abc.ABC):
    """Base class of the fixed-step solvers; subclasses give their :class:`ButcherTableau`.

    Args:
        steps: number of uniform steps K (>= 1); the paper uses K = 50 with Euler.
    """

    #: The solver's name in :data:`SAMPLERS`.
    name: ClassVar[str]
    #: The solver's explicit Runge-Kutta method.
    tableau: ClassVar[ButcherTableau]
    #: Global order of accuracy: halving ``dt`` divides the error by ``2**order``.
    order: ClassVar[int]
    #: Model evaluations per step.
    stages: ClassVar[int]

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "tableau" in cls.__dict__:
            cls.order, cls.stages = cls.tableau.order, len(cls.tableau.nodes)

    def __init__(self, *, steps: int = 50) -> None:
        if int(steps) != steps or steps < 1:
            raise ValueRangeError(f"steps must be a positive integer, got {steps}")
        self.steps = int(steps)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(steps={self.steps})"

    @property
    def nfe(self) -> int:
        """Number of model evaluations of one :meth:`sample` call."""
        return self.steps * self.stages

    def sample(
        self,
        model: VelocityModel,
        x_0: torch.Tensor,
        *,
        frozen_mask: torch.Tensor | None = None,
        x_frozen: torch.Tensor | None = None,
        return_trajectory: bool = False,
        enable_grad: bool = False,
        **cond: Any,
    ) -> torch.Tensor:
        """Integrate ``dx/dt = model(x, t | cond)`` from ``x_0`` at ``t = 0`` to ``t = 1``.

        Args:
            model: the velocity model, called as ``model(x=x_t, t=t, **cond)``.
            x_0: the initial state, shape ``(B, L, C)``; not modified.
            frozen_mask: optional ``(B, L)`` bool, True at points whose velocity is zeroed.
            x_frozen: optional ``(B, L, C)`` start values of the frozen points (needs
                ``frozen_mask``); by default they keep their ``x_0`` values (module docstring).
            return_trajectory: return all ``K + 1`` states instead of the last one.
            enable_grad: record autograd through the integration (default: ``torch.no_grad``).
            **cond: conditioning keywords passed to every model call.

        Returns:
            The state at ``t = 1``, shape ``(B, L, C)``; with ``return_trajectory`` the states at
            ``t = 0, dt, ..., 1``, shape ``(K + 1, B, L, C)``.

        Raises:
            ShapeError: bad shapes or devices, or a model output not shaped like ``x``.
            ValueRangeError: the integration produced NaN or inf.

        Example:
            >>> def drift(*, x, t):
            ...     return torch.ones_like(x)
            >>> x_0 = torch.zeros(1, 2, 3)
            >>> EulerSampler(steps=5).sample(drift, x_0)[0, 0]
            tensor([1., 1., 1.])
            >>> frozen = torch.tensor([[True, False]])
            >>> EulerSampler(steps=5).sample(drift, x_0, frozen_mask=frozen)[0, :, 0]
            tensor([0., 1.])
        """
        sizes = check_tensor(x_0, "x_0", ("B", "L", "C"))
        x = x_0
        frozen = None
        if frozen_mask is not None:
            check_mask(frozen_mask, "frozen_mask", ("B", "L"), sizes)
            check_same(("x_0", x_0), ("frozen_mask", frozen_mask), dtype=False)
            frozen = frozen_mask.unsqueeze(-1)
        if x_frozen is not None:
            if frozen is None:
                raise ShapeError("x_frozen needs frozen_mask to say which points it pins")
            check_tensor(x_frozen, "x_frozen", ("B", "L", "C"), sizes=sizes)
            check_same(("x_0", x_0), ("x_frozen", x_frozen))
            x = torch.where(frozen, x_frozen, x_0)
        field = _field(model, cond, frozen, x_0.shape)
        dt = 1.0 / self.steps
        with torch.set_grad_enabled(enable_grad):
            states = [x]
            for k in range(self.steps):
                x = self.step(field, x, k * dt, dt)
                if return_trajectory:
                    states.append(x)
            out = torch.stack(states) if return_trajectory else x
        if not bool(torch.isfinite(x).all()):
            raise ValueRangeError(
                f"{type(self).__name__} produced NaN or inf: the velocity model returned "
                "non-finite values or the integration diverged"
            )
        return out

    def generate(
        self,
        model: VelocityModel,
        shape: Sequence[int],
        *,
        generator: torch.Generator | None = None,
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
        **options: Any,
    ) -> torch.Tensor:
        """Draw ``x_0`` with :func:`initial_noise` from ``generator``, then :meth:`sample`.

        Args:
            model: the velocity model.
            shape: the state shape ``(B, L, C)``.
            generator: optional random generator for the initial noise.
            device: device of the noise (default: the generator's).
            dtype: dtype of the noise.
            **options: the keywords of :meth:`sample` (``frozen_mask``, ``x_frozen``,
                ``return_trajectory``, ``enable_grad``) and the conditioning keywords.

        Returns:
            As :meth:`sample`.

        Example:
            >>> def pull(*, x, t):
            ...     return -x
            >>> rk4 = RK4Sampler(steps=4)
            >>> a = rk4.generate(pull, (2, 3, 3), generator=torch.Generator().manual_seed(1))
            >>> b = rk4.generate(pull, (2, 3, 3), generator=torch.Generator().manual_seed(1))
            >>> torch.equal(a, b)
            True
        """
        x_0 = initial_noise(shape, generator=generator, device=device, dtype=dtype)
        return self.sample(model, x_0, **options)

    def step(self, field: Field, x: torch.Tensor, t: float, dt: float) -> torch.Tensor:
        """Advance the state ``x`` at time ``t`` by ``dt`` using the (anchor-zeroed) ``field``."""
        method = self.tableau
        slopes: list[torch.Tensor] = []
        for node, coupling in zip(method.nodes, method.coupling):
            x_stage = x
            for factor, slope in zip(coupling, slopes):
                if factor:
                    x_stage = x_stage + (factor * dt) * slope
            slopes.append(field(x_stage, t + node * dt))
        terms = [k if w == 1 else w * k for w, k in zip(method.weights, slopes) if w]
        return x + (dt / method.divisor) * functools.reduce(operator.add, terms)


class EulerSampler(ODESampler):
    """Forward Euler, ``x <- x + dt v(x, t)``: the paper's sampler (K = 50 by default).

    Example:
        >>> EulerSampler().nfe
        50
    """

    name = "euler"
    tableau = ButcherTableau(order=1, nodes=(0.0,), coupling=((),), weights=(1,))


class MidpointSampler(ODESampler):
    """Explicit midpoint rule: evaluate at ``t + dt/2`` after a half Euler step.

    Example:
        >>> MidpointSampler(steps=10).nfe
        20
    """

    name = "midpoint"
    tableau = ButcherTableau(order=2, nodes=(0.0, 0.5), coupling=((), (0.5,)), weights=(0, 1))


class HeunSampler(ODESampler):
    """Heun's method: average the velocities at the start and at an Euler predictor.

    Example:
        >>> HeunSampler(steps=10).order
        2
    """

    name = "heun"
    tableau = ButcherTableau(
        order=2, nodes=(0.0, 1.0), coupling=((), (1.0,)), weights=(1, 1), divisor=2
    )


class RK4Sampler(ODESampler):
    """The classic fourth-order Runge-Kutta method.

    Example:
        >>> RK4Sampler(steps=5).nfe
        20
    """

    name = "rk4"
    tableau = ButcherTableau(
        order=4,
        nodes=(0.0, 0.5, 0.5, 1.0),
        coupling=((), (0.5,), (0.0, 0.5), (0.0, 0.0, 1.0)),
        weights=(1, 2, 2, 1),
        divisor=6,
    )


#: The solvers by name.
SAMPLERS: dict[str, type[ODESampler]] = {
    cls.name: cls for cls in (EulerSampler, MidpointSampler, HeunSampler, RK4Sampler)
}


def get_sampler(method: str = "euler", *, steps: int = 50) -> ODESampler:
    """Build the solver called ``method`` (a key of :data:`SAMPLERS`) with ``steps`` steps.

    Example:
        >>> get_sampler("rk4", steps=8)
        RK4Sampler(steps=8)
    """
    if method not in SAMPLERS:
        raise ValueRangeError(f"unknown sampler {method!r}; choose from {sorted(SAMPLERS)}")
    return SAMPLERS[method](steps=steps)


def sample(
    model: VelocityModel,
    x_0: torch.Tensor,
    *,
    steps: int = 50,
    method: str = "euler",
    **options: Any,
) -> torch.Tensor:
    """Integrate a velocity model from ``x_0`` to ``t = 1``; see :meth:`ODESampler.sample`.

    Args:
        model: the velocity model, called as ``model(x=x_t, t=t, **cond)``.
        x_0: the initial state, shape ``(B, L, C)`` (draw it with :func:`initial_noise`).
        steps: number of uniform steps K (the paper: 50).
        method: ``"euler"`` (the paper), ``"midpoint"``, ``"heun"`` or ``"rk4"``.
        **options: the keywords of :meth:`ODESampler.sample`: ``frozen_mask`` (``(B, L)``
            bool, True at points whose velocity is zeroed), ``x_frozen`` (their ``(B, L, C)``
            start values), ``return_trajectory`` (return the ``(K + 1, B, L, C)`` states),
            ``enable_grad`` (record autograd), and the conditioning keywords of every model call.

    Returns:
        The state at ``t = 1`` ``(B, L, C)``, or the trajectory ``(K + 1, B, L, C)``.

    Example:
        >>> import math
        >>> def spin(*, x, t):  # rotation about z at unit angular speed
        ...     return torch.stack([-x[..., 1], x[..., 0], torch.zeros_like(x[..., 2])], -1)
        >>> x_0 = torch.tensor([[[1.0, 0.0, 0.0]]], dtype=torch.float64)
        >>> x_1 = sample(spin, x_0, steps=20, method="rk4")
        >>> exact = torch.tensor([math.cos(1.0), math.sin(1.0), 0.0], dtype=torch.float64)
        >>> bool((x_1[0, 0] - exact).abs().max() < 1e-7)
        True
    """
    return get_sampler(method, steps=steps).sample(model, x_0, **options)


def _field(
    model: VelocityModel,
    cond: dict[str, Any],
    frozen: torch.Tensor | None,
    shape: torch.Size,
) -> Field:
    """Wrap the model as ``f(x, t) -> v`` with ``t`` broadcast to ``(B,)`` and anchors zeroed."""

    def f(x: torch.Tensor, t: float) -> torch.Tensor:
        tt = torch.full((shape[0],), t, dtype=x.dtype, device=x.device)
        v = model(x=x, t=tt, **cond)
        if not isinstance(v, torch.Tensor) or v.shape != shape:
            got = tuple(v.shape) if isinstance(v, torch.Tensor) else type(v).__name__
            raise ShapeError(
                f"the velocity model must return a tensor of shape {tuple(shape)}, got {got}"
            )
        return v if frozen is None else v.masked_fill(frozen, 0)

    return f
