"""The learning problems of List et al.: what the reference and coarse solvers are, which scene
parameters the train and test splits use, how trajectories start and what the network is told.

A problem is a family of scenes indexed by one scalar parameter (the KS domain factor, the
Kolmogorov Reynolds number). The network sees ``condition(param)`` as a constant extra channel.
Each problem is one file in :mod:`adjointsim.train.steppers` that registers its class with
:data:`STEPPERS`; its :attr:`Problem.SCENE` names the solver keys a user may set (``adjointsim
data --scene KEY=VALUE`` or the ``[scene]`` table of ``--config``), checked by the solvers' own
validation. :data:`PROBLEMS` holds every problem at its default scene.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any, ClassVar

import numpy as np

from adjointsim import Stepper
from adjointsim.errors import UserError
from adjointsim.registry import Registry

#: the neural-stepper problems, one file each in adjointsim.train.steppers
STEPPERS = Registry("problem", "adjointsim.train.steppers")


class Problem:
    """One problem at one scene: subclass it in a file of :mod:`adjointsim.train.steppers`,
    set the class attributes and the four methods, and register it with :data:`STEPPERS`."""

    name: ClassVar[str]
    dims: ClassVar[int]
    #: parameter values of the training split and of the named test splits
    train_params: ClassVar[tuple[float, ...]]
    test_params: ClassVar[dict[str, tuple[float, ...]]]
    #: frames discarded before a trajectory is stored (transients)
    warmup_frames: ClassVar[int]
    #: reference solver steps per stored frame (one coarse step spans one frame)
    substeps: ClassVar[int]
    #: knobs of the scaled-down versions ("quick": the README's study)
    sizes: ClassVar[dict[str, dict]]
    #: the scene keys a user may set, with the paper's values
    SCENE: ClassVar[dict[str, Any]] = {}
    #: state channels (the network sees them and the condition, and returns as many)
    channels: ClassVar[int] = 1
    #: the networks' padding: circular on periodic domains, else zeros or replicate
    padding: ClassVar[str] = "circular"

    def __init__(self, scene: dict[str, Any] | None = None):
        given = dict(scene or {})
        unknown = [k for k in given if k not in self.SCENE]
        if unknown:
            raise UserError(f"scene key {unknown[0]!r} is not one of the {self.name} problem's "
                            f"({', '.join(self.SCENE)})")
        self.scene = {**self.SCENE, **given}
        if given:  # the solvers' own validation, one line naming the key
            try:
                for param in self.train_params[:1]:
                    self.reference(param)
                    self.coarse(param)
            except (TypeError, ValueError) as e:
                raise UserError(f"scene of the {self.name} problem: {e}") from None

    # Each problem overrides these four.
    def reference(self, param: float) -> Stepper:
        raise NotImplementedError

    def coarse(self, param: float) -> Stepper:
        raise NotImplementedError

    def initial_states(
        self, rng: np.random.Generator, param: float, count: int, split: str
    ) -> np.ndarray:
        raise NotImplementedError

    def condition(self, param: float) -> float:
        raise NotImplementedError

    def to_coarse(self, u: np.ndarray) -> np.ndarray:
        """Reference-grid states → coarse grid (identity when the grids agree)."""
        return u

    @property
    def splits(self) -> dict[str, tuple[float, ...]]:
        return {"train": self.train_params, **self.test_params}


class _Defaults(Mapping):
    """Every registered problem at its default scene, by name (loaded on first use)."""

    def __init__(self) -> None:
        self._made: dict[str, Problem] = {}

    def __getitem__(self, name: str) -> Problem:
        if name not in STEPPERS.names():
            raise KeyError(name)
        if name not in self._made:
            self._made[name] = STEPPERS.get(name)()
        return self._made[name]

    def __iter__(self) -> Iterator[str]:
        return iter(STEPPERS.names())

    def __len__(self) -> int:
        return len(STEPPERS.names())


PROBLEMS: Mapping[str, Problem] = _Defaults()


def get_problem(name: str, scene: dict[str, Any] | None = None) -> Problem:
    """The problem ``name`` at ``scene`` (its default scene where a key is not given)."""
    if name not in PROBLEMS:
        raise UserError(f"unknown problem {name!r}; choose from {sorted(PROBLEMS)}")
    return STEPPERS.get(name)(scene) if scene else PROBLEMS[name]
