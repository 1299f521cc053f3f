"""A sequential inverse problem on this project's Kuramoto–Sivashinsky solver."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from . import PROBLEMS, PinnProblem, Standardized, tanh_mlp


@PROBLEMS.register
class KSInverse(PinnProblem):
    """Learn u(x, t) and the coefficients α, β of u_t + u u_x + α u_xx + β u_xxxx = 0 from a
    trajectory.

    Data: ``ks1d-etdrk4`` (N = 64, L = 22, Δt = 0.1, α = β = 1) from the smooth random state
    of ``adjointsim fit --demo ks-params`` (rng 1234), 100 steps: a 64 × 101 space-time grid,
    t ∈ [0, 10]. The seed draws the points and the network; the trajectory is fixed.
    Objectives, added one after another (Maddu et al.'s sequential training, with periodicity as
    the constraint where the active-turbulence problem has incompressibility):

    * ``data``: MSE of u against ``collocation`` grid values drawn from the trajectory;
    * ``periodic``: Σ_{m=0..3} mean (∂xᵐ u(0, t) − ∂xᵐ u(L, t))² at ``edge_points`` times;
    * ``res``: mean squared residual u_t + u u_x + α u_xx + β u_xxxx at ``collocation``
      uniform points, ∂x to fourth order and ∂t from :mod:`adjointsim.nets.taylor` (two passes,
      so t carries only its first order).

    Phases: ``data`` alone for the first third of the epochs, ``+ periodic`` for the second,
    ``+ res`` for the last; α and β (trainable, starting at 0.5) get gradients only from the
    residual. The ID reference is ``data``, the one objective of every phase (the authors
    name none for this problem); ``reference = "max"`` takes the largest spread. 6000 epochs,
    no lr steps. Network [2, 50×5, 1] tanh as for Poisson. Metric: relative L2 of u on the
    whole trajectory; the result also holds α, β and the data loss at the end of each phase,
    which shows whether the first objective is forgotten when the others join."""

    name = "ks-inverse"
    width = 50
    epochs = 6000
    terms = ("data", "periodic", "res")
    reference = "data"
    coefficients = ("alpha", "beta")
    phased = True
    lr_steps = ()
    floats_per_unit = (110.0, 110.0)  # the residual's jets; third-order jets at both ends
    axes = ("x", "t")
    title = "KS inverse (sequential)"
    start = 0.5

    def __init__(self, cfg):
        from adjointsim import registry
        from adjointsim.fit_run import demo_problem

        super().__init__(cfg)
        prob = demo_problem("ks-params")
        scene = registry.get(prob["scene"])(**prob["config"])
        traj = scene.rollout(prob["u0"], 100, keep="all")[:, 0, 0]  # (101, 64)
        self.length, self.t_end = scene.length, 100 * scene.dt
        self.shape = (traj.shape[1], traj.shape[0])
        self.extent = (0.0, self.length, 0.0, self.t_end)
        gx, gt = np.meshgrid(np.arange(self.shape[0]) * scene.length / self.shape[0],
                             np.arange(self.shape[1]) * scene.dt, indexing="ij")
        self.grid = torch.from_numpy(np.stack([gx.ravel(), gt.ravel()], axis=1)).float()
        self.u_grid = torch.from_numpy(traj.T.reshape(-1, 1).copy()).float()
        rng = np.random.default_rng([cfg.seed, 22])
        pick = rng.choice(len(self.grid), min(cfg.collocation, len(self.grid)), replace=False)
        self.x_data, self.u_data = self.grid[pick], self.u_grid[pick]
        t = torch.from_numpy(rng.uniform(0.0, self.t_end, (cfg.edge_points, 1))).float()
        self.left = torch.cat([torch.zeros_like(t), t], dim=1)
        self.right = torch.cat([torch.full_like(t, self.length), t], dim=1)
        self.x_col = torch.from_numpy(
            rng.uniform((0.0, 0.0), (self.length, self.t_end), (cfg.collocation, 2))).float()

    def model(self) -> Standardized:
        scale = torch.tensor([self.length, self.t_end])
        model = tanh_mlp(self.cfg, scale / 2, scale / math.sqrt(12.0))  # uniform's moments
        model.alpha = nn.Parameter(torch.tensor(self.start))
        model.beta = nn.Parameter(torch.tensor(self.start))
        return model

    def losses(self, model: Standardized, route: str = "taylor",
               terms: tuple[str, ...] = ()) -> dict[str, torch.Tensor]:
        """The terms named in ``terms`` (all if empty): a term not trained now costs
        nothing."""
        terms = terms or self.terms
        out = {}
        if "data" in terms:
            out["data"] = ((model(self.x_data) - self.u_data) ** 2).mean()
        if "periodic" in terms:
            left = model.jets(self.left, 3, axes=(0,))
            right = model.jets(self.right, 3, axes=(0,))
            out["periodic"] = sum(((a - b) ** 2).mean() for a, b in zip(left, right))
        if "res" in terms:
            u, ux, uxx, _, uxxxx = model.jets(self.x_col, 4, axes=(0,))
            ut = model.jets(self.x_col, 1, axes=(1,))[1]
            res = (ut[:, 0] + u * ux[:, 0] + model.alpha * uxx[:, 0]
                   + model.beta * uxxxx[:, 0])
            out["res"] = (res**2).mean()
        return out
