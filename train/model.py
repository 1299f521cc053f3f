"""Neural time-steppers in the prediction and correction setups of List et al.

* prediction:            û_{t+1} = f(û_t)
* correction, parallel:  û_{t+1} = S(û_t) + Δt · f(û_t)
* correction, sequential: ũ = S(û_t);  û_{t+1} = ũ + f(ũ)

S is the coarse solver, run through :mod:`adjointsim.train.bridge`, one scene per problem
parameter (the batch is split by parameter). The network also sees the problem's conditioning
value as a constant extra channel. Whether gradients flow through S is decided by the caller:
a detached state gives a solver call with no tape and no adjoint (NOG), an attached one runs
the hand-written adjoint in the backward pass (WIG).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from adjointsim import Stepper

from . import bridge

if TYPE_CHECKING:
    from .unroll import GradientFlow

SETUPS = ("prediction", "correction")
CORRECTIONS = ("parallel", "sequential")


class NeuralStepper(nn.Module):
    def __init__(
        self,
        net: nn.Module,
        setup: str,
        solver: Callable[[float], Stepper] | None = None,
        correction: str = "parallel",
    ):
        super().__init__()
        if setup not in SETUPS:
            raise ValueError(f"unknown setup {setup!r}; choose from {SETUPS}")
        if correction not in CORRECTIONS:
            raise ValueError(f"unknown correction form {correction!r}; choose from {CORRECTIONS}")
        if setup == "correction" and solver is None:
            raise ValueError("the correction setup needs a coarse solver")
        self.net, self.setup, self.correction = net, setup, correction
        self._make_solver = solver
        self._solvers: dict[float, Stepper] = {}

    def solver(self, param: float) -> Stepper:
        if param not in self._solvers:
            self._solvers[param] = self._make_solver(param)
        return self._solvers[param]

    # Which solver advances which rows depends on the parameters' values: under torch.compile
    # this runs eager (a graph break per step), as no graph can hold a choice of solvers.
    @torch.compiler.disable
    def groups(self, params: torch.Tensor) -> list[tuple[Stepper, np.ndarray | slice]]:
        """The coarse solver of each scene parameter in the batch, with the rows it advances."""
        values = params.numpy()
        unique = np.unique(values)
        if len(unique) == 1:
            return [(self.solver(float(unique[0])), slice(None))]
        return [(self.solver(float(p)), np.flatnonzero(values == p)) for p in unique]

    def solve(
        self,
        u: torch.Tensor,
        params: torch.Tensor,
        groups: list[tuple[Stepper, np.ndarray | slice]] | None = None,
    ) -> torch.Tensor:
        """One coarse-solver step of every batch element, each with its scene parameter."""
        return bridge.rollout_grouped(groups or self.groups(params), u.contiguous(), 1)

    def _f(self, u: torch.Tensor, conditions: torch.Tensor) -> torch.Tensor:
        shape = (u.shape[0], 1, *u.shape[2:])
        c = conditions.to(u.dtype).reshape(-1, *([1] * (u.ndim - 1))).expand(shape)
        return self.net(torch.cat([u, c], dim=1))

    def forward(
        self,
        u: torch.Tensor,
        params: torch.Tensor,
        conditions: torch.Tensor,
        flow: GradientFlow | None = None,
    ) -> torch.Tensor:
        """One step; ``flow`` (a :class:`adjointsim.train.unroll.GradientFlow`) stops gradients
        on the state fed into the network (``flow.net``) and into the solver (``flow.phys``)."""
        if flow is None:
            net, phys, control = _same, _same, _call
        else:
            net, phys, control = flow.net, flow.phys, flow.control
        if self.setup == "prediction":
            return control(self._f, net(u), net(conditions))
        if self.correction == "parallel":
            groups = self.groups(params)
            steps = {stepper.dt for stepper, _ in groups}
            if len(steps) > 1:
                raise ValueError(f"the parallel correction needs one Δt per batch, got {steps}")
            return (self.solve(phys(u), params, groups)
                    + steps.pop() * control(self._f, net(u), net(conditions)))
        v = self.solve(phys(u), params)
        return v + control(self._f, net(v), net(conditions))


def _same(x: torch.Tensor) -> torch.Tensor:
    return x


def _call(fn, *inputs: torch.Tensor) -> torch.Tensor:
    return fn(*inputs)
