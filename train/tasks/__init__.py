"""Controller tasks: each registers itself here, one file each, as solvers do.

A task (:class:`Task`) is one control problem at one complexity level: the registered solver
it runs and the scene it builds (``SCENE``, which a run's ``scene`` config key overrides key by
key), its level (``key``: the level's name on the command line, ``levels``: the accepted
values, easiest first), its initial states, its controller network, its loss terms and its
rollout plot. :data:`TASKS` finds them; the ``control`` command, its config and the stabilised
BPTT study take the tasks, their level flags and their levels from it. A new task is one new
file in this package (plus its test).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

from adjointsim import scenes
from adjointsim.nets.mlp import MLP
from adjointsim.registry import Registry

#: every controller task, by name
TASKS = Registry("task", "adjointsim.train.tasks")


def _solver(name: str, scene: dict[str, Any], fixed: dict[str, Any]):
    """The solver of a scene, one per scene in a process: a stepper keeps nothing between
    calls, and a compiled closed loop is traced for one solver object (an ensemble resumed
    turn after turn, each turn a new run object, then compiles once)."""
    key = (name, *(tuple(sorted(d.items())) for d in (scene, fixed)))
    try:
        hash(key)
    except TypeError:  # a scene value that is not hashable (a list): built for this task alone
        return scenes.build(name, scene, fixed)
    if key not in _SOLVERS:
        _SOLVERS[key] = scenes.build(name, scene, fixed)
    return _SOLVERS[key]


_SOLVERS: dict[tuple, Any] = {}


class Task:
    """One control problem at one complexity level: scene, initial states, net, loss, plot."""

    name: ClassVar[str]
    #: the registered solver the task runs
    SOLVER: ClassVar[str]
    #: the solver's keywords, defaults of the ``scene`` config key (dt, grid, coefficients)
    SCENE: ClassVar[dict[str, Any]] = {}
    #: the level's name (its command-line flag ``--KEY``), what it is, the accepted values
    #: (easiest first)
    key: ClassVar[str]
    about: ClassVar[str]
    levels: ClassVar[tuple]
    steps: int
    #: an update costs several times a cart-pole one: the study's sizes give it fewer epochs
    costly: ClassVar[bool] = False
    #: values per state in the controller's widest layer (for the memory estimate)
    widest = 100
    #: the loss's named terms, which a weighting may balance (see :meth:`step_terms`)
    terms: tuple[str, ...] = ("loss",)

    def __init__(self, level: Any = None, scene: dict[str, Any] | None = None):
        self.level = self.level_of(level)
        fixed = self.leveled()
        for key in scene or {}:
            if key in fixed:
                raise ValueError(f"scene key {key!r} is the {self.name} task's level; pass "
                                 f"--{self.key.replace('_', '-')} instead")
        #: the scene this task's solver is built from (the defaults and ``scene``)
        self.scene = {**self.SCENE, **(scene or {})}
        self.solver = _solver(self.SOLVER, self.scene, fixed)

    @classmethod
    def level_of(cls, value: Any) -> Any:
        """The accepted level equal to ``value`` (None: the easiest), as :attr:`levels` spells
        it; another value is a ValueError naming the accepted ones."""
        if value is None:
            return cls.levels[0]
        for level in cls.levels:
            if not isinstance(value, bool) and value == level:
                return level
        shown = f"{value:g}" if isinstance(value, int | float) else repr(value)
        raise ValueError(f"{shown} is not one of {', '.join(map(str, cls.levels))} (the "
                         f"{cls.name} task's {cls.key.replace('_', ' ')})")

    def leveled(self) -> dict[str, Any]:
        """The solver keywords the level sets (not part of the scene a user may change)."""
        return {}

    def initial_states(self, rng: np.random.Generator, count: int) -> np.ndarray:
        return self.solver.random_state(rng, count)

    def control(self, out: torch.Tensor) -> torch.Tensor:
        """Network output (B, k) to the solver's control (B, *control_shape)."""
        shape = self.solver.control_shape
        # math.prod, not np.prod: under torch.compile NumPy on a tuple becomes a traced tensor,
        # and its int() would break the graph at every step of a closed loop
        if out.ndim < 1 or out[0].numel() != math.prod(shape):
            raise ValueError(
                f"{self.name}: the controller's output has shape {tuple(out.shape)}; expected "
                f"(batch, {math.prod(shape)}), one control {shape} per batch element"
            )
        return out.reshape(out.shape[0], *shape)

    def net(self) -> nn.Module:
        """The controller: an MLP from the state to the control, its last layer zero."""
        size = int(np.prod(self.solver.state_shape(1)))
        return zero_last(nn.Sequential(
            nn.Flatten(), MLP(size, int(np.prod(self.solver.control_shape)), width=100, depth=2),
        ))

    def memory(self, train: int, test: int, batch: int, itemsize: int) -> int:
        """Bytes a run needs, about: the initial states (drawn in float64), then the larger of
        a rollout over all of them at once (no tape) and one update's tape (C's doubled
        batch). The factors are measured with the paper's controllers, rounded up."""
        size = int(np.prod(self.solver.state_shape(1)))
        states = (train + test) * size * (8 + itemsize)
        rollout = max(train, test) * (4 * self.widest * itemsize + 64 * size)
        tape = batch * self.steps * 8 * self.widest * itemsize
        return states + max(rollout, tape)

    def row_loss(self, x: torch.Tensor, c: torch.Tensor, t: int) -> torch.Tensor | None:
        """Each row's loss term of the state x_{t+1} reached with control c_t (None: no
        term); rows are separate episodes, so an ensemble splits one call's rows by member."""
        raise NotImplementedError

    def step_loss(self, x: torch.Tensor, c: torch.Tensor, t: int) -> torch.Tensor | None:
        """Loss term of the state x_{t+1} reached with control c_t: the rows' mean (None: no
        term)."""
        rows = self.row_loss(x, c, t)
        return None if rows is None else rows.mean()

    def step_terms(self, x: torch.Tensor, c: torch.Tensor, t: int
                   ) -> dict[str, torch.Tensor] | None:
        """The loss's terms of the state x_{t+1} reached with control c_t, one per name of
        :attr:`terms`, summing to :meth:`step_loss` (None: no term)."""
        term = self.step_loss(x, c, t)
        return None if term is None else {"loss": term}

    def total(self, terms: list[torch.Tensor]) -> torch.Tensor:
        return torch.stack(terms).sum()

    def draw(self, fig: Any, ax: Any, states: np.ndarray, t: np.ndarray) -> None:
        """One controlled rollout into ``ax``: ``states`` (steps + 1, C, *grid) at times
        ``t``."""
        raise NotImplementedError


def zero_last(net: nn.Sequential) -> nn.Sequential:
    """``net`` with its last linear layer zero: the control is 0 at the start (as in the
    reference runs)."""
    last = [m for m in net.modules() if isinstance(m, nn.Linear)][-1]
    nn.init.zeros_(last.weight)
    nn.init.zeros_(last.bias)
    return net


def get_task(name: str, level: Any = None, scene: dict[str, Any] | None = None) -> Task:
    """The task ``name`` at ``level`` (None: its easiest) in ``scene`` (None: its own)."""
    return TASKS.get(name)(level, scene)
