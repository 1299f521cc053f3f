"""Sobolev training (Maddu et al.'s problem 2): a function fitted together with its
derivatives."""

from __future__ import annotations

import math

import numpy as np
import torch

from adjointsim.nets.mlp import MLP

from . import PROBLEMS, PinnProblem, Standardized


@PROBLEMS.register
class Sobolev(PinnProblem):
    """Fit f(x, y) = Σ_{j=1}^{20} A_j cos(l_j x + φ_j) · A'_j sin(l'_j y + φ'_j) (A, A' ~
    U(−5, 5), l, l' ∈ {1..4}, φ, φ' ~ U(0, 2π), drawn from the seed) on (0, 2π]² together with
    its derivatives: five objectives, the MSEs of f, ∂x f + ∂y f, Δf, ∂xxx f + ∂yyy f and
    ∂xxxx f + ∂yyyy f at ``collocation`` uniformly random points; each is the sum over the
    axes of one order of :func:`adjointsim.nets.taylor.jets`. Network [2, 64×5, 1] with sin
    activation (PyTorch's default init), inputs standardised; 30,001 epochs with lr × 0.1 at
    10k, 20k and 30k; the ID reference is the highest derivative (the authors' code). Metric:
    relative L2 of f on the 100 × 100 grid."""

    name = "sobolev"
    width = 64
    epochs = 30001
    terms = ("f", "d1", "d2", "d3", "d4")
    reference = "d4"
    floats_per_unit = (110.0, 0.0)  # jets to fourth order along both axes
    extent = (0.0, 2.0 * math.pi) * 2
    title = "Sobolev training"

    def __init__(self, cfg):
        super().__init__(cfg)
        rng = np.random.default_rng([cfg.seed, 20])
        n = 20
        self.a, self.a2 = rng.uniform(-5.0, 5.0, n), rng.uniform(-5.0, 5.0, n)
        self.l, self.l2 = rng.integers(1, 5, n), rng.integers(1, 5, n)
        self.phi, self.phi2 = rng.uniform(0.0, 2 * math.pi, n), rng.uniform(0.0, 2 * math.pi, n)
        g = np.linspace(2 * math.pi / 100, 2 * math.pi, 100)
        gx, gy = np.meshgrid(g, g, indexing="ij")
        self.grid = torch.from_numpy(np.stack([gx.ravel(), gy.ravel()], axis=1)).float()
        self.x_col = torch.from_numpy(rng.uniform(0.0, 2 * math.pi, (cfg.collocation, 2))).float()
        self.targets = [self.target(order, self.x_col) for order in range(5)]
        self.u_grid = self.target(0, self.grid)

    def target(self, order: int, x: torch.Tensor) -> torch.Tensor:
        """f for order 0, else ∂xⁿ f + ∂yⁿ f (dⁿ/dsⁿ cos(ls + φ) = lⁿ cos(ls + φ + nπ/2))."""
        xs, ys = x[:, :1].double().numpy(), x[:, 1:].double().numpy()
        shift = order * math.pi / 2
        cx, sy = np.cos(self.l * xs + self.phi), np.sin(self.l2 * ys + self.phi2)
        if order == 0:
            out = (self.a * self.a2 * cx * sy).sum(axis=1)
        else:
            dx = self.l**order * np.cos(self.l * xs + self.phi + shift) * sy
            dy = cx * self.l2**order * np.sin(self.l2 * ys + self.phi2 + shift)
            out = (self.a * self.a2 * (dx + dy)).sum(axis=1)
        return torch.from_numpy(out[:, None]).to(x.dtype)

    def model(self) -> Standardized:
        torch.manual_seed(self.cfg.seed)
        mlp = MLP(2, 1, self.cfg.width, self.cfg.depth, "sin")
        return Standardized(mlp, self.x_col.mean(dim=0), self.x_col.std(dim=0))

    def losses(self, model: Standardized, route: str = "taylor",
               terms: tuple[str, ...] = ()) -> dict[str, torch.Tensor]:
        j = model.jets(self.x_col, 4)
        outs = [j[0]] + [jn.sum(dim=1) for jn in j[1:]]
        return {t: ((o - y) ** 2).mean() for t, o, y in zip(self.terms, outs, self.targets)}
