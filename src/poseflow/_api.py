"""The class half of poseflow's function + class pairs, written once.

poseflow follows Kornia: an operation is a function (``icp``) and a class (``ICP``) with the same
docstring. The class's ``__init__`` takes the function's keyword-only hyper-parameters, checks
them and stores each one as the attribute of the same name; calling the class runs the function
with them. :class:`Hyperparameters` reads them back from the signature of ``__init__`` (for the
``repr``), and :class:`Solver` adds the call, so that no class lists them a second time.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from typing import Any, ClassVar, Generic, TypeVar

__all__ = ["Hyperparameters", "Solver"]

#: What the function of a :class:`Solver` returns.
R = TypeVar("R")


class Hyperparameters:
    """Mixin: ``repr`` and :meth:`hyperparameters` from the keyword-only arguments of ``__init__``.

    A subclass's ``__init__`` must store every keyword-only argument as the attribute of the same
    name; positional arguments (data, a network) are not hyper-parameters and are left out.

    Example:
        >>> class Blur(Hyperparameters):
        ...     def __init__(self, *, sigma: float = 1.0, border: str = "reflect") -> None:
        ...         self.sigma = float(sigma)
        ...         self.border = border
        >>> Blur(sigma=2)
        Blur(sigma=2.0, border='reflect')
        >>> Blur().hyperparameters()
        {'sigma': 1.0, 'border': 'reflect'}
    """

    def hyperparameters(self) -> dict[str, Any]:
        """The keyword-only arguments of ``__init__`` by name, as this instance stores them."""
        return {name: getattr(self, name) for name in _keyword_only(type(self))}

    def __repr__(self) -> str:
        arguments = ", ".join(f"{name}={value!r}" for name, value in self.hyperparameters().items())
        return f"{type(self).__name__}({arguments})"


class Solver(Hyperparameters, Generic[R]):
    """Base of the class form of a function: ``Cls(**hyper)(*data) == function(*data, **hyper)``.

    A subclass sets :attr:`function` and checks and stores the function's keyword-only
    hyper-parameters in its ``__init__``, so that a bad value fails when the solver is built.

    Example:
        >>> def shift(x: float, *, by: float = 1.0) -> float:
        ...     return x + by
        >>> class Shift(Solver[float]):
        ...     function = staticmethod(shift)
        ...     def __init__(self, *, by: float = 1.0) -> None:
        ...         self.by = by
        >>> Shift(by=2.0)(1.0), shift(1.0, by=2.0)
        (3.0, 3.0)
    """

    #: The function of the pair, called with the data and the stored hyper-parameters.
    function: ClassVar[Callable[..., Any]]

    def __call__(self, *args: Any, **kwargs: Any) -> R:
        """Call :attr:`function` on the arguments and the stored hyper-parameters."""
        return type(self).function(*args, **kwargs, **self.hyperparameters())


@functools.cache
def _keyword_only(cls: type) -> tuple[str, ...]:
    """Names of the keyword-only parameters of ``cls.__init__``, in signature order."""
    parameters = inspect.signature(cls.__init__).parameters.values()
    return tuple(p.name for p in parameters if p.kind is inspect.Parameter.KEYWORD_ONLY)
