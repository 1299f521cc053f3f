"""The problems of ``adjointsim hig``, one file each, registered by name like the solvers.

A problem is a subclass of :class:`HigProblem` decorated with ``@PROBLEMS.register``: it names
itself, its solver and the scene it builds (``SCENE``, the paper's, which a run's ``scene``
config key overrides key by key), its default time budget, its data set sizes, and per
optimiser the batch, learning rate and (HIG, GN) τ. It makes its network, its physics (the
solver, or a torch function, between the network's output and the loss), its loss and its
data. ``adjointsim hig --help``, the config's accepted values, the study and the docs find it
through :data:`PROBLEMS`; adding a problem is one new file here (and its test). See
:mod:`adjointsim.train.hig_problems` for the training run.

The settings are those of Schnell, Holl & Thuerey (ICLR 2022) and their reference code; each
problem's file says where it deviates.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import torch

from adjointsim import scenes
from adjointsim.registry import Registry
from adjointsim.stepper import NonFiniteInputError, NonFiniteStateError, Stepper

from ..hig import SolverPhysics, TorchPhysics

#: every HIG problem, by name (one module of this package each)
PROBLEMS = Registry("HIG problem", "adjointsim.train.higs")
OPTIMIZERS = ("adam", "gn", "hig")
#: data set sizes: "tiny" shrinks them (tests, the study's smoke size); "quick" is "full"
SIZES = ("tiny", "quick", "full")
DTYPE = torch.float64
Batch = tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # network input, physics context, target


class HigProblem:
    """What the training run asks of a problem: the network (:meth:`model`), the physics
    between its output and :meth:`loss` (``physics``, built in ``__init__`` from the scene),
    training batches (:meth:`sample`, from ``train`` unless overridden) and the test batch
    ``test``."""

    #: the problem's name on the command line and in configs
    name: ClassVar[str] = ""
    #: the solver class and its keywords (the defaults of the ``scene`` config key)
    SOLVER: ClassVar[type[Stepper]]
    SCENE: ClassVar[dict[str, Any]] = {}
    #: solver keywords the problem's physics relies on: not part of the scene a user changes
    FIXED: ClassVar[dict[str, Any]] = {}
    #: the default time budget (s of update time)
    BUDGET: ClassVar[float] = 600.0
    #: per optimiser: batch, lr and (HIG/GN) tau
    SETTINGS: ClassVar[dict[str, dict[str, float]]] = {}
    #: the size of the data sets ("tiny"; "full" also for "quick")
    DATA: ClassVar[dict[str, int]] = {"tiny": 256, "full": 4096}

    physics: SolverPhysics | TorchPhysics
    train: Batch
    test: Batch

    def __init__(self, seed: int, size: str = "full", scene: dict[str, Any] | None = None):
        if size not in SIZES:
            raise ValueError(f"size must be one of {', '.join(SIZES)}, not {size!r}")
        self.seed = seed
        #: the number of samples of each data set
        self.count = self.DATA["tiny" if size == "tiny" else "full"]
        #: the scene this problem's solver is built from (the defaults and ``scene``)
        self.scene = {**self.SCENE, **(scene or {})}
        self.solver = self.build_solver(scene)

    @classmethod
    def build_solver(cls, scene: dict[str, Any] | None = None) -> Stepper:
        """The solver of the scene ``SCENE`` with ``scene`` over it key by key; a key the
        solver does not take, or one the problem fixes, is a ValueError naming it, and so is a
        value the solver's own checks refuse."""
        return scenes.build(cls.SOLVER, {**cls.SCENE, **(scene or {})}, cls.FIXED)

    @property
    def settings(self) -> dict[str, dict[str, float]]:
        return self.SETTINGS

    def model(self) -> torch.nn.Module:
        raise NotImplementedError

    def loss(self, y: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """The per-sample loss of the physics' output ``y``."""
        return ((y - target) ** 2).sum(dim=1)

    def sample(self, gen: torch.Generator, batch: int) -> Batch:
        """A training batch of ``batch`` samples drawn from ``gen``."""
        x, c, t = self.train
        idx = torch.randperm(x.shape[0], generator=gen)[:batch]
        return x[idx], c[idx], t[idx]

    def state_dict(self) -> dict[str, Any]:
        """What a resumed run needs of the data beside the generator (fields drawn ahead)."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""

    def test_loss(self, model: torch.nn.Module) -> float:
        """Mean per-sample loss on the test set; inf when the physics blows up."""
        x, c, t = self.test
        with torch.no_grad():
            try:
                value = float(self.loss(self.physics(model(x), c), t).mean())
            except (NonFiniteStateError, NonFiniteInputError):
                return math.inf
        return value if math.isfinite(value) else math.inf


def make_problem(name: str, seed: int, size: str = "full",
                 scene: dict[str, Any] | None = None) -> HigProblem:
    """Problem ``name`` with data drawn from ``seed`` in its scene with ``scene`` over it;
    ``size="tiny"`` shrinks the data sets (tests and the study's smoke size), nothing else."""
    return PROBLEMS.get(name)(seed, size, scene)

