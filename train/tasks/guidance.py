"""Guidance (Schnell & Thuerey 2024): 2 drivers herd 4 evaders to the origin; 60 steps of
Δt = 4/60, loss the mean over steps of mean_e |x_e|² + r_c mean(c²), the control weight r_c the
level. Two terms, ``tracking`` and ``control`` (r_c included), that a weighting may balance."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from . import TASKS, Task


@TASKS.register
class Guidance(Task):
    name, SOLVER, steps = "guidance", "guidance", 60
    SCENE = {"drivers": 2, "evaders": 4, "dt": 4.0 / 60}
    key, about, levels = "control_weight", "the weight of the control cost", \
        (1.0, 0.1, 0.01, 0.001)
    terms = ("tracking", "control")

    def _costs(self, x: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Each row's mean_e |x_e|² and mean(c²)."""
        return ((x[:, :2, self.solver.drivers:] ** 2).sum(dim=1).mean(dim=1),
                (c**2).flatten(1).mean(dim=1))

    def row_loss(self, x: torch.Tensor, c: torch.Tensor, t: int) -> torch.Tensor | None:
        track, effort = self._costs(x, c)
        return (track + self.level * effort) / self.steps

    def step_terms(self, x: torch.Tensor, c: torch.Tensor, t: int
                   ) -> dict[str, torch.Tensor] | None:
        track, effort = self._costs(x, c)
        return {"tracking": track.mean() / self.steps,
                "control": self.level * effort.mean() / self.steps}

    def draw(self, fig: Any, ax: Any, states: np.ndarray, t: np.ndarray) -> None:
        """The drivers' and evaders' paths."""
        nd = self.solver.drivers
        for i in range(states.shape[2]):
            color = "C3" if i < nd else "C0"
            ax.plot(states[:, 0, i], states[:, 1, i], color=color, lw=1)
            ax.plot(states[0, 0, i], states[0, 1, i], "o", color=color, ms=3)
        ax.plot([], [], color="C3", label="drivers")
        ax.plot([], [], color="C0", label="evaders")
        ax.plot(0, 0, "k+", ms=10)
        # the scene of the start (drivers r ≤ 4) and the evaders: far-flung drivers leave it
        r = max(float(np.abs(states[0, :2]).max()), float(np.abs(states[:, :2, nd:]).max())) \
            + 0.5
        ax.set_xlim(-r, r)
        ax.set_ylim(-r, r)
        ax.set_aspect("equal")
        ax.legend(fontsize=8)
