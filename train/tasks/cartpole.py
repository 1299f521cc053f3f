"""Cart-pole swing-up (Schnell & Thuerey 2024): 1–4 poles hanging from a cart, swung upright
by a force on the cart; 100 steps of Δt = 0.01, loss 1 − mean_i cos θ_i at the last step."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch

from . import TASKS, Task

if TYPE_CHECKING:
    import numpy as np


@TASKS.register
class CartPole(Task):
    name, SOLVER, steps = "cartpole", "cartpole", 100
    SCENE = {"dt": 0.01}
    key, about, levels = "poles", "the number of poles", (1, 2, 3, 4)

    def leveled(self) -> dict[str, Any]:
        return {"poles": self.level}

    def row_loss(self, x: torch.Tensor, c: torch.Tensor, t: int) -> torch.Tensor | None:
        if t < self.steps - 1:
            return None
        return 1.0 - torch.cos(x[:, 0, 1:]).mean(dim=1)

    def draw(self, fig: Any, ax: Any, states: np.ndarray, t: np.ndarray) -> None:
        """The pole angles over time (0 = upright)."""
        for i in range(1, states.shape[2]):
            ax.plot(t, states[:, 0, i], label=f"θ_{i}")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel("t")
        ax.set_ylabel("pole angle (0 = upright)")
        ax.legend(fontsize=8)
