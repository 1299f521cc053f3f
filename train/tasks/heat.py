"""Heat control: a source term holds the heat equation at a target profile.

u_t = ν u_xx + c(t, x) on [0, 1] with u = 0 at both ends (``diffusion1d-crank-nicolson``, 32
interior points, ν = 0.1, Δt = 0.01, 50 steps): from a random smooth profile
Σ_{j ≤ 3} a_j sin(jπx), a_j ~ U(−1, 1)/j, the controller sets the source c_t(x) at every step
so that the last state is the target sin(kπx), the wavenumber k (1..3) the level: diffusion
damps the target's mode as e^{−νk²π²t}, so a higher k needs a stronger source. Loss: the
tracking error mean (u_T − u*)² at the last step plus r mean over steps of mean(c²), r = 10⁻³:
two terms, ``tracking`` and ``control``, that a weighting may balance. The optimal control of
the heat equation by a distributed source is the classic example of PDE-constrained control
(Lions 1971; Tröltzsch 2010, ch. 3), and a benchmark of controllers trained through
differentiable solvers (Holl, Koltun & Thuerey 2020).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from . import TASKS, Task

#: r, the weight of the control cost
EFFORT = 1e-3


@TASKS.register
class Heat(Task):
    name, SOLVER, steps = "heat", "diffusion1d-crank-nicolson", 50
    SCENE = {"n": 32, "length": 1.0, "nu": 0.1, "dt": 0.01, "bc": "dirichlet"}
    key, about, levels = "wavenumber", "the target profile's wavenumber k of sin(kπx)", \
        (1, 2, 3)
    terms = ("tracking", "control")

    def __init__(self, level=None, scene=None):
        super().__init__(level, scene)
        self.x = (np.arange(self.solver.grid_shape[0]) + 1) * self.solver.h
        self.target = np.sin(self.level * np.pi * self.x / self.solver.length)[None]
        self._target = None

    def initial_states(self, rng: np.random.Generator, count: int) -> np.ndarray:
        a = rng.uniform(-1.0, 1.0, (count, 3)) / np.arange(1, 4)
        modes = np.sin(np.pi * np.arange(1, 4)[:, None] * self.x / self.solver.length)
        return (a @ modes)[:, None]

    def _costs(self, x: torch.Tensor, c: torch.Tensor, t: int
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """Each row's tracking term (zero before the last step) and control term."""
        track = torch.zeros(len(x), dtype=x.dtype)
        if t == self.steps - 1:
            if self._target is None or self._target.dtype != x.dtype:
                self._target = torch.tensor(self.target, dtype=x.dtype)
            track = ((x - self._target) ** 2).flatten(1).mean(dim=1)
        return track, EFFORT * (c**2).flatten(1).mean(dim=1) / self.steps

    def row_loss(self, x: torch.Tensor, c: torch.Tensor, t: int) -> torch.Tensor | None:
        track, effort = self._costs(x, c, t)
        return track + effort

    def step_terms(self, x: torch.Tensor, c: torch.Tensor, t: int
                   ) -> dict[str, torch.Tensor] | None:
        track, effort = self._costs(x, c, t)
        return {"tracking": track.mean(), "control": effort.mean()}

    def draw(self, fig: Any, ax: Any, states: np.ndarray, t: np.ndarray) -> None:
        """The profile at the start and the end, and the target."""
        ax.plot(self.x, states[0, 0], color="C0", lw=1, label="t = 0")
        ax.plot(self.x, states[-1, 0], color="C3", label=f"t = {t[-1]:g}")
        ax.plot(self.x, self.target[0], "k--", lw=1, label="target")
        ax.set_xlabel("x")
        ax.set_ylabel("u")
        ax.legend(fontsize=8)
