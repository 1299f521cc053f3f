"""The solver registry: every stepper class registers itself once, with a small default scene.

The gradient checker, the property tests and the benchmarks iterate over this registry; nothing
else keeps a list of solvers.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, TypeVar

if TYPE_CHECKING:
    from .stepper import Stepper

_REGISTRY: dict[str, type[Stepper]] = {}
S = TypeVar("S", bound="type[Stepper]")


class UnknownSolverError(KeyError):
    """A solver name nobody registered (a user error: the CLI prints it on one line)."""


def register(cls: S) -> S:
    """Class decorator: add a stepper class under its ``name``."""
    name = cls.name
    if name in _REGISTRY and _REGISTRY[name] is not cls:
        raise ValueError(f"solver name {name!r} is registered twice")
    _REGISTRY[name] = cls
    return cls


def _load_builtin() -> None:
    # Importing the solver modules runs their @register decorators.
    from . import solvers  # noqa: F401


def names() -> list[str]:
    """Registered solver names, sorted."""
    _load_builtin()
    return sorted(_REGISTRY)


def get(name: str) -> type[Stepper]:
    """The stepper class registered under ``name``."""
    _load_builtin()
    try:
        return _REGISTRY[name]
    except KeyError:
        raise UnknownSolverError(
            f"unknown solver {name!r}; registered solvers are: {', '.join(sorted(_REGISTRY))}"
        ) from None


def all_classes() -> list[type[Stepper]]:
    """Every registered stepper class, sorted by name."""
    return [get(n) for n in names()]
