"""Quantum state transfer (Schnell & Thuerey 2024): ``schrodinger1d-cn`` with m = 1/2, 32
interior points, Δt = 0.0625, 128 steps; a superposition of the two lowest eigenstates driven
to eigenstate n (the level, 3..5) by a dipole field, loss Σ_t (1 − |⟨ψ_n|ψ_t⟩|²)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

from . import TASKS, Task, zero_last


@TASKS.register
class Quantum(Task):
    name, SOLVER, steps = "quantum", "schrodinger1d-cn", 128
    SCENE = {"n": 32, "length": 2.0, "dt": 0.0625, "mass": 0.5}
    key, about, levels = "target", "the eigenstate to reach", (3, 4, 5)
    costly = True
    widest = 60 * 16  # the first convolution's channels × points

    def __init__(self, level=None, scene=None):
        super().__init__(level, scene)
        n = self.solver.n
        j = np.arange(1, n + 1)
        self.eigen = [np.sin(k * np.pi * j / (n + 1)) for k in range(1, max(self.levels) + 1)]
        # made here, not on the first call: a compiled loop then sees one state of the task
        self._target = {dtype: torch.tensor(self.eigen[self.level - 1], dtype=dtype)
                        for dtype in (torch.float32, torch.float64)}

    def initial_states(self, rng: np.random.Generator, count: int) -> np.ndarray:
        """(c1 e^{i p1} ψ1 + c2 e^{i p2} ψ2)/norm, c ~ N(0, 1), p ~ U(0, 2π)."""
        c = rng.standard_normal((count, 2))
        p = rng.uniform(0.0, 2.0 * np.pi, (count, 2))
        psi = (c[:, :1] * np.exp(1j * p[:, :1]) * self.eigen[0]
               + c[:, 1:] * np.exp(1j * p[:, 1:]) * self.eigen[1])
        psi /= np.sqrt(self.solver.h * np.sum(np.abs(psi) ** 2, axis=1, keepdims=True))
        return np.stack([psi.real, psi.imag], axis=1)

    def net(self) -> nn.Module:
        """Two strided convolutions and a linear layer (the paper's controller)."""
        n = self.solver.n
        points = (((n - 1) // 2) // 2) + 1  # after two stride-2 convolutions
        return zero_last(nn.Sequential(
            nn.Conv1d(2, 60, 3, stride=2, padding=1), nn.Tanh(),
            nn.Conv1d(60, 60, 3, stride=2, padding=1), nn.Tanh(),
            nn.Flatten(), nn.Linear(60 * points, 1),
        ))

    def row_loss(self, x: torch.Tensor, c: torch.Tensor, t: int) -> torch.Tensor | None:
        # ⟨ψ_n|ψ⟩ = h Σ ψ_n ψ (ψ_n real, both normalised as h Σ|ψ|² = 1)
        overlap = self.solver.h * (x @ self._target[x.dtype])  # (B, 2): real and imaginary
        return 1.0 - (overlap**2).sum(dim=1)

    def draw(self, fig: Any, ax: Any, states: np.ndarray, t: np.ndarray) -> None:
        """|ψ|² over t and x."""
        density = states[:, 0] ** 2 + states[:, 1] ** 2
        im = ax.imshow(density.T, aspect="auto", origin="lower",
                       extent=(0, t[-1], 0, self.solver.length))
        fig.colorbar(im, ax=ax, label="|ψ|²")
        ax.set_xlabel("t")
        ax.set_ylabel("x")
