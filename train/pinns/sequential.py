"""A synthetic sequential problem: objectives of very different scales join one after
another."""

from __future__ import annotations

import math

import numpy as np
import torch

from . import PROBLEMS, PinnProblem, Standardized, tanh_mlp


@PROBLEMS.register
class Sequential(PinnProblem):
    """In the setting of Maddu et al.'s active-turbulence problem: the target is
    u* = sin(2πx) sin(2πy) on [0, 1]², with three objectives at ``collocation`` uniform
    points, each met exactly by u*:

    * ``data``: MSE of u against u* (scale 1);
    * ``grad``: 10⁻³ × MSE of ∂x u + ∂y u against u*'s (a weak objective);
    * ``lap``: 10³ × MSE of Δu against Δu* = −8π² u* (a strong one).

    ``data`` alone for the first third of the epochs, ``+ grad`` for the second, ``+ lap``
    for the last; the ID reference is ``data``. 3000 epochs, no lr steps. Network
    [2, 50×5, 1] tanh as for Poisson. Metric: relative L2 of u on the 100 × 100 grid; the
    result's phases hold every term and gradient spread at the end of each phase, which shows
    whether ``data`` is forgotten when a weak or a strong objective joins."""

    name = "sequential"
    width = 50
    epochs = 3000
    terms = ("data", "grad", "lap")
    reference = "data"
    phased = True
    lr_steps = ()
    scales = {"data": 1.0, "grad": 1e-3, "lap": 1e3}
    floats_per_unit = (60.0, 0.0)  # second-order jets along both axes
    title = "sequential (scales 1, 1e-3, 1e3)"

    def __init__(self, cfg):
        super().__init__(cfg)
        rng = np.random.default_rng([cfg.seed, 30])
        g = np.linspace(0.0, 1.0, 100)
        gx, gy = np.meshgrid(g, g, indexing="ij")
        self.grid = torch.from_numpy(np.stack([gx.ravel(), gy.ravel()], axis=1)).float()
        self.u_grid = self.exact(self.grid)
        self.x_col = torch.from_numpy(rng.uniform(0.0, 1.0, (cfg.collocation, 2))).float()
        w = 2.0 * math.pi
        x, y = self.x_col[:, :1], self.x_col[:, 1:]
        self.targets = (self.exact(self.x_col),
                        w * (torch.cos(w * x) * torch.sin(w * y)
                             + torch.sin(w * x) * torch.cos(w * y)),
                        -2.0 * w**2 * self.exact(self.x_col))

    @staticmethod
    def exact(x: torch.Tensor) -> torch.Tensor:
        return torch.sin(2.0 * math.pi * x[:, :1]) * torch.sin(2.0 * math.pi * x[:, 1:])

    def model(self) -> Standardized:
        return tanh_mlp(self.cfg, self.x_col.mean(dim=0), self.x_col.std(dim=0))

    def losses(self, model: Standardized, route: str = "taylor",
               terms: tuple[str, ...] = ()) -> dict[str, torch.Tensor]:
        terms = terms or self.terms
        if terms == ("data",):
            outs = [model(self.x_col)]
        else:
            j = model.jets(self.x_col, 2)
            outs = [j[0], j[1].sum(dim=1), j[2].sum(dim=1)]
        return {t: self.scales[t] * ((o - y) ** 2).mean()
                for t, o, y in zip(self.terms, outs, self.targets) if t in terms}
