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


T = TypeVar("T", bound=type)


class UnknownNameError(KeyError):
    """A name nobody registered (a user error: the CLI prints it on one line)."""

    def __str__(self) -> str:
        return str(self.args[0])


class Registry:
    """Classes that register themselves under their ``name``, one file each in ``package``
    (imported on first use): the solvers' mechanism, for the training layer's problems
    (controller tasks, neural-stepper problems, PINN and HIG problems)."""

    def __init__(self, kind: str, package: str):
        self.kind, self.package = kind, package
        self._classes: dict[str, type] = {}
        self._loaded = False

    def register(self, cls: T) -> T:
        """Class decorator: add ``cls`` under ``cls.name``."""
        name = cls.name
        if name in self._classes and self._classes[name] is not cls:
            raise ValueError(f"{self.kind} name {name!r} is registered twice")
        self._classes[name] = cls
        return cls

    def _load(self) -> None:
        import importlib
        import pkgutil

        pkg = importlib.import_module(self.package)
        for info in pkgutil.iter_modules(pkg.__path__):
            if not info.name.startswith("_"):
                importlib.import_module(f"{self.package}.{info.name}")

    def names(self) -> list[str]:
        """The registered names, in registration order (files in alphabetical order)."""
        if not self._loaded:
            self._loaded = True
            self._load()
        return list(self._classes)

    def get(self, name: str) -> type:
        """The class registered under ``name``."""
        if name not in self.names():
            raise UnknownNameError(f"unknown {self.kind} {name!r}; choose from "
                                   f"{', '.join(self.names())}")
        return self._classes[name]

    def items(self) -> list[tuple[str, type]]:
        return [(n, self._classes[n]) for n in self.names()]
