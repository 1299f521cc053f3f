"""``quantum``: ``schrodinger1d-cn``, 14 interior points on (0, 2), m = ½ (H = −∂xx + u x),
Δt = 0.05, 384 steps, from the ground state to a random normalised real superposition of the
eigenstates 2 and 3; loss 1 − |⟨ψ*|ψ_T⟩|². Network 28 → 20 ×3 (tanh) → 384. Adam batch 256,
lr 5e-4; HIG batch 16, lr 0.5, τ = 1e-5; GN (not given by the paper) as HIG. As in the
reference code, states enter the network and the loss with unit Euclidean norm,
Σ_j |ψ_j|² = 1 (the solver's ψ times √h): HIG's step is not invariant to that scale."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch

from adjointsim.nets.mlp import MLP
from adjointsim.solvers.schrodinger import SchrodingerCN

from ..hig import SolverPhysics
from . import DTYPE, PROBLEMS, HigProblem


@PROBLEMS.register
class QuantumTransfer(HigProblem):
    """Controls that carry the ground state to a superposition of the next two."""

    name = "quantum"
    SOLVER = SchrodingerCN
    SCENE: ClassVar[dict[str, Any]] = {"n": 14, "length": 2.0, "dt": 0.05, "mass": 0.5}
    SETTINGS: ClassVar = {"adam": {"batch": 256, "lr": 5e-4},
                          "hig": {"batch": 16, "lr": 0.5, "tau": 1e-5},
                          "gn": {"batch": 16, "lr": 0.5, "tau": 1e-5}}
    DATA: ClassVar = {"tiny": 64, "full": 1024}
    STEPS = 384

    def __init__(self, seed: int, size: str = "full", scene: dict[str, Any] | None = None):
        super().__init__(seed, size, scene)
        s = self.solver
        root_h = np.sqrt(s.h)
        ground = torch.from_numpy(np.stack([self.mode(1), np.zeros(s.n)]) / root_h)
        rng = np.random.default_rng(seed)

        def targets(count: int) -> torch.Tensor:
            c = rng.standard_normal((count, 2))
            c /= np.linalg.norm(c, axis=1, keepdims=True)
            psi = c[:, :1] * self.mode(2) + c[:, 1:] * self.mode(3)
            return torch.from_numpy(np.concatenate([psi, np.zeros_like(psi)], axis=1))

        train, test = targets(self.count), targets(self.count)
        empty = torch.zeros(self.count, 0, dtype=DTYPE)
        self.physics = SolverPhysics(s, self.STEPS, lambda c: ground.expand(c.shape[0], 2, s.n),
                                     scale=root_h)
        self.train, self.test = (train, empty, train), (test, empty, test)

    def mode(self, k: int) -> np.ndarray:
        """Box eigenstate k with unit Euclidean norm (the solver's normalisation / √h)."""
        s = self.solver
        m = np.sin(k * np.pi * s.x / s.length)
        return m / np.linalg.norm(m)

    def model(self) -> torch.nn.Module:
        return MLP(2 * self.solver.n, self.STEPS, width=20, depth=3,
                   activation="tanh").to(DTYPE)

    def loss(self, y: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """The infidelity 1 − |⟨target|y⟩|² of states stored as (real, imaginary) halves."""
        n = self.solver.n
        yr, yi, tr, ti = y[:, :n], y[:, n:], target[:, :n], target[:, n:]
        re = (tr * yr + ti * yi).sum(dim=1)
        im = (tr * yi - ti * yr).sum(dim=1)
        return 1.0 - (re**2 + im**2)
