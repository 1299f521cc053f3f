"""Physics-informed training with loss balancing (Maddu et al., MLST 2022): the multi-scale
Poisson problem, Sobolev training (:class:`Sobolev`), a sequential inverse problem on this
project's KS solver (:class:`KSInverse`), the training loop, history and plots. The
``adjointsim pinn`` command runs it.

Poisson, as in the note: Δu = −2ω² cos(ωx) sin(ωy) on [0, 1]², ω = kπ, k = 1..6, exact
solution u = cos(ωx) sin(ωy). L_res = mean of the squared residual over 2500 collocation points
drawn (without replacement) from the 100 × 100 grid; L_bc = the sum of the four edges' MSEs
against the exact Dirichlet data, 100 uniformly random points per edge. Network [2, 50×5, 1]
tanh, Xavier-normal weights with gain 5/3 and zero biases, inputs standardised with the
collocation points' mean and std. Adam, lr 1e-3, full batch, 30,001 epochs with lr × 0.1 at
10k, 20k and 30k (a shorter run is the start of such a run). Metric: relative L2
error on the 100 × 100 grid. The seed draws the points and the initial network.

Loss L = λ_res L_res + λ_bc L_bc with λ from :class:`adjointsim.train.weighting.Weighting` (the
residual is the reference term, as in the authors' code, unless ``reference = "max"``);
``fixed`` uses the analytic ε-optimal λ_res = 1/(1 + ω⁴), λ_bc = 1 − λ_res. Δu comes from the
forward Taylor route (:mod:`adjointsim.nets.taylor`) or, for comparison, nested autograd
(``route = "autograd"``).

A :class:`PinnConfig` is checked key by key (:data:`ACCEPTED`) and against the machine's
memory before anything is allocated. A run directory holds ``config.json``, ``checkpoint.pt``
(atomic, every minute, on Ctrl-C and at the end), ``history.csv`` (every ``log_every`` epochs:
each term, each weight, the weighted total, the relative L2 error, skipped updates, seconds),
``weights.csv`` (every weight refresh: each λ and each term's gradient spread), ``result.json``
once finished, and the plots ``field.png`` (exact, prediction, error) and ``history.png``
(terms, weights, error).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from torch import nn

from adjointsim.errors import DamagedFileError, UserError
from adjointsim.files import pyplot, save_figure, uninterrupted, write_json
from adjointsim.nets.mlp import MLP
from adjointsim.nets.taylor import jets, laplacian
from adjointsim.run import (
    SEEDS,
    Config,
    Interval,
    check_memory,
    discard,
    finished_result,
    holds_run,
    plot_history,
    write_history,
)

from .checkpoint import load_run_checkpoint, save_checkpoint
from .threads import use_threads
from .weighting import ALIASES, RECORDED, RULES, Weighting, canonical_rule, scheme_name

PROBLEMS = ("poisson", "sobolev", "ks-inverse", "sequential")
#: each problem's network: activation and the default width (``width = 0``)
NETWORKS = {"poisson": ("tanh", 50), "sobolev": ("sin", 64), "ks-inverse": ("tanh", 50),
            "sequential": ("tanh", 50)}
#: each problem's default epochs (``epochs = 0``)
EPOCHS = {"poisson": 30001, "sobolev": 30001, "ks-inverse": 6000, "sequential": 3000}
ROUTES = ("taylor", "autograd")
K_RANGE = (1, 6)
#: the authors' reported relative L2 errors (Adam, ±50%: read off their plot), per k
REPORTED = {
    "uniform": {1: 1.6e-3, 2: 1.2e-2, 3: 4e-2, 4: 1e-1, 5: 1.8e-1, 6: 2.5e-1},
    "inverse-dirichlet": {1: 3e-4, 2: 4e-4, 3: 6e-4, 4: 1.8e-3, 5: 4e-3, 6: 7e-3},
    "max-avg": {1: 1e-3, 2: 1.9e-3, 3: 3.7e-3, 4: 5.5e-3, 5: 6e-3, 6: 7.5e-3},
    "fixed": {1: 2e-4, 2: 4e-4, 3: 8.5e-4, 4: 2.5e-3, 5: 5e-3, 6: 8e-3},
}
#: the weightings only Poisson provides for: its analytic weights, its per-sample residuals
NEEDS_POISSON = ("epsilon-optimal", "ntk")
#: collocation points (and a quarter as many per edge) whose residuals give the NTK weights:
#: each is a reverse pass of its own on the Taylor route, which cannot batch them
NTK_POINTS = 32
#: consecutive non-finite losses after which a run is given up (full batch: the same
#: parameters give the same loss, so skipping cannot recover)
MAX_SKIPS = 10
CHECKPOINT_KEYS = ("config", "model", "optimizer", "scheduler", "weighting", "state")
RESULT_KEYS = ("rel_l2", "diverged", "skipped", "seconds", "weights", "coefficients", "phases")
#: what a run directory holds besides config.json, checkpoint.pt and result.json: removed by
#: ``overwrite``
RUN_FILES = ("history.csv", "weights.csv", "field.png", "history.png")

#: the accepted values of every PinnConfig field; the rules tying keys together (the route
#: and the fixed weights only on Poisson, 0 as the problem's width and epochs, the memory a
#: network needs) are in PinnConfig.check
ACCEPTED: dict[str, tuple | Interval | str] = {
    "problem": PROBLEMS,
    "k": Interval(*K_RANGE),
    "weighting": (*RULES, *ALIASES, *RECORDED),
    "reference": ("res", "max"),
    "epochs": Interval(0),
    "seed": SEEDS,
    "lr": Interval(0, lo_open=True),
    "alpha": Interval(0, 1, lo_open=True),
    "every": Interval(1),
    # wider or deeper is not a PINN of these problems but a typing mistake; within the bounds
    # the memory a run needs is checked against the machine's (PinnConfig.check)
    "width": Interval(0, 4096),
    "depth": Interval(1, 100),
    # at least 2: the inputs are standardised by the points' spread; at most the 100 × 100
    # grid, from which Poisson draws them without replacement
    "collocation": Interval(2, 100 * 100),
    "edge_points": Interval(1, 100_000),
    "route": ROUTES,
    "log_every": Interval(1),
    "threads": Interval(1),
}
#: what a run may be resumed with other values of (and what a run recorded before it was a key
#: lacks): its threads do not change its result
RESUMABLE = ("threads",)


@dataclass
class PinnConfig(Config):
    """One run of ``adjointsim pinn``: every key is a flag and a key of a ``--config`` file;
    :meth:`validate` checks them against :data:`ACCEPTED` and :meth:`check`."""

    problem: str = "poisson"
    k: int = 1
    weighting: str = "inverse-dirichlet"
    #: the ID reference term: "res", the problem's (Poisson: the residual, as in the authors'
    #: code; Sobolev: the highest derivative), or "max" (the largest spread)
    reference: str = "res"
    #: 0: the problem's (Poisson and Sobolev 30,001, as the authors; ks-inverse 6000)
    epochs: int = 0
    seed: int = 0
    lr: float = 1e-3
    alpha: float = 0.5
    every: int = 5
    #: 0: the problem's (Poisson 50, Sobolev 64, ks-inverse 50)
    width: int = 0
    depth: int = 5
    collocation: int = 2500
    edge_points: int = 100
    route: str = "taylor"
    log_every: int = 100
    #: torch's and the solver's threads (they take turns)
    threads: int = 1

    ACCEPTED: ClassVar[dict[str, tuple | Interval | str]] = ACCEPTED

    def check(self, where: str) -> None:
        """The weighting's canonical name, the rules tying keys together, 0 replaced by the
        problem's width and epochs, and the memory the run needs (before anything is made)."""
        self.weighting = canonical_rule(self.weighting)
        if self.problem != "poisson" and self.route != "taylor":
            raise UserError(f"config key 'route'{where}: the {self.problem} problem takes route "
                            "'taylor' only (fourth derivatives)")
        if self.problem != "poisson" and scheme_name(self.weighting) in NEEDS_POISSON:
            others = [r for r in RULES if r not in NEEDS_POISSON]
            raise UserError(f"config key 'weighting'{where}: the {self.problem} problem has no "
                            f"analytic weights and no per-sample residuals; choose one of "
                            f"{', '.join(others)}")
        self.width = self.width or NETWORKS[self.problem][1]
        self.epochs = self.epochs or EPOCHS[self.problem]
        check_memory(memory_needed(self), f"width {self.width}, depth {self.depth}, collocation "
                     f"{self.collocation} and edge_points {self.edge_points}{where}",
                     "choose smaller ones")


def memory_needed(cfg: PinnConfig) -> int:
    """Bytes one training epoch of ``cfg`` holds at its peak, roughly and from above: the
    parameters with their gradient, Adam's two moments and one gradient per loss term (the
    weighting's), and per hidden unit the problem's :attr:`PinnProblem.floats_per_unit`."""
    w, d = cfg.width, cfg.depth
    params = 3 * w + (d - 1) * (w * w + w) + w + 1
    problem = _PROBLEMS[cfg.problem]
    per_col, per_edge = problem.floats_per_unit
    activations = (per_col * cfg.collocation + per_edge * cfg.edge_points) * w * d
    return int(4 * ((4 + len(problem.terms)) * params + activations))


# ----------------------------------------------------------------------------- the problem
class Standardized(nn.Module):
    """An MLP of standardised inputs (x − μ)/σ."""

    def __init__(self, mlp: MLP, mean: torch.Tensor, std: torch.Tensor):
        super().__init__()
        self.mlp = mlp
        self.register_buffer("mean", mean)
        self.register_buffer("std", std)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.mlp((x - self.mean) / self.std)

    def laplacian(self, x: torch.Tensor, route: str = "taylor") -> torch.Tensor:
        """Δu at ``x`` (N, 1) in the physical coordinates."""
        if route == "taylor":
            # d/dx_i = (1/σ_i) d/dx̃_i: the jets run along the scaled axes of x̃
            dirs = torch.diag(1.0 / self.std)
            return laplacian(self.mlp, (x - self.mean) / self.std, dirs)[1]
        x = x.detach().requires_grad_(True)
        u = self(x)
        g = torch.autograd.grad(u.sum(), x, create_graph=True)[0]
        return sum(torch.autograd.grad(g[:, i].sum(), x, create_graph=True)[0][:, i:i + 1]
                   for i in range(x.shape[1]))

    def jets(self, x: torch.Tensor, order: int, axes: tuple[int, ...] = ()) -> list[torch.Tensor]:
        """:func:`adjointsim.nets.taylor.jets` along the physical coordinate axes (``axes``: only
        these)."""
        dirs = torch.diag(1.0 / self.std)
        return jets(self.mlp, (x - self.mean) / self.std, order, dirs[list(axes)] if axes else dirs)


class PinnProblem:
    """What the training loop asks of a problem; the defaults fit a problem whose terms are
    all active from the start, with no physical coefficient to learn. Each problem also has
    ``model()`` and ``losses(model, route, terms)``, the named loss terms; a problem whose
    terms join one after another computes only those in ``terms`` (all when empty)."""

    terms: tuple[str, ...] = ()
    reference = ""
    #: float32 values per hidden unit that a training epoch keeps at its peak, per collocation
    #: point and per edge point (measured on CPU, with a quarter more as margin): the
    #: derivative streams the reverse pass needs
    floats_per_unit: tuple[float, float] = (0.0, 0.0)
    #: the evaluation grid: (rows, columns) and (first min, max, second min, max)
    shape = (100, 100)
    extent = (0.0, 1.0, 0.0, 1.0)
    axes = ("x", "y")
    grid: torch.Tensor
    u_grid: torch.Tensor

    def active(self, epoch: int) -> tuple[str, ...]:
        """The terms trained at ``epoch``."""
        return self.terms

    def extras(self, model: nn.Module) -> dict[str, float]:
        """Learned physical coefficients, logged beside the losses."""
        return {}

    def milestones(self, epochs: int) -> list[int]:
        """lr × 0.1 at epochs 10k, 20k and 30k, as in the authors' 30,001-epoch runs; a
        shorter run is the start of theirs (below 10k epochs the lr stays 1e-3)."""
        return [m for m in (10000, 20000, 30000) if m < epochs]

    @torch.no_grad()
    def rel_l2(self, model: nn.Module) -> float:
        u = model(self.grid)
        return float(torch.linalg.norm(u - self.u_grid) / torch.linalg.norm(self.u_grid))


def _tanh_mlp(cfg: PinnConfig, mean: torch.Tensor, std: torch.Tensor) -> Standardized:
    """[2, width × depth, 1] tanh, Xavier-normal weights with gain 5/3, zero biases."""
    torch.manual_seed(cfg.seed)
    mlp = MLP(2, 1, cfg.width, cfg.depth, "tanh")
    for m in mlp.modules():
        if isinstance(m, nn.Linear):
            nn.init.xavier_normal_(m.weight, gain=5.0 / 3.0)
            nn.init.zeros_(m.bias)
    return Standardized(mlp, mean, std)


class Poisson(PinnProblem):
    """The multi-scale Poisson problem at wavenumber k (see the module doc)."""

    terms = ("res", "bc")
    reference = "res"
    floats_per_unit = (48.0, 10.0)  # Δu at the collocation points; u on four edges
    #: the boundary's edges (axis held fixed, its value): one MSE term each, summed
    EDGES = ((0, 0.0), (0, 1.0), (1, 0.0), (1, 1.0))

    def __init__(self, cfg: PinnConfig):
        self.cfg = cfg
        self.omega = cfg.k * math.pi
        rng = np.random.default_rng([cfg.seed, cfg.k])
        g = np.linspace(0.0, 1.0, 100)
        gx, gy = np.meshgrid(g, g, indexing="ij")
        self.grid = torch.from_numpy(np.stack([gx.ravel(), gy.ravel()], axis=1)).float()
        pick = rng.choice(len(self.grid), cfg.collocation, replace=False)
        self.x_col = self.grid[pick]
        self.f_col = self.source(self.x_col)
        edges = []
        for axis, value in self.EDGES:
            pts = np.empty((cfg.edge_points, 2))
            pts[:, axis] = value
            pts[:, 1 - axis] = rng.uniform(0.0, 1.0, cfg.edge_points)
            edges.append(pts)
        # the four edges, one after another: one pass of the network for all of them
        self.x_bc = torch.from_numpy(np.concatenate(edges)).float()
        self.u_bc = self.exact(self.x_bc)
        self.u_grid = self.exact(self.grid)

    def exact(self, x: torch.Tensor) -> torch.Tensor:
        return (torch.cos(self.omega * x[:, :1]) * torch.sin(self.omega * x[:, 1:]))

    def source(self, x: torch.Tensor) -> torch.Tensor:
        return -2.0 * self.omega**2 * self.exact(x)

    @property
    def title(self) -> str:
        return f"Poisson k={self.cfg.k}"

    def model(self) -> Standardized:
        return _tanh_mlp(self.cfg, self.x_col.mean(dim=0), self.x_col.std(dim=0))

    def residuals(self, model: Standardized, route: str = "taylor",
                  points: int = 0) -> dict[str, torch.Tensor]:
        """Δu − f at the collocation points and u − g at the edge points; with ``points``, at
        the first ``points`` of them and the first ``points // 4`` of each edge."""
        x_col, f_col, x_bc, u_bc = self.x_col, self.f_col, self.x_bc, self.u_bc
        if points:
            x_col, f_col = x_col[:points], f_col[:points]
            edge = slice(0, max(points // len(self.EDGES), 1))
            x_bc = x_bc.view(len(self.EDGES), -1, 2)[:, edge].reshape(-1, 2)
            u_bc = u_bc.view(len(self.EDGES), -1, 1)[:, edge].reshape(-1, 1)
        return {"res": model.laplacian(x_col, route) - f_col, "bc": model(x_bc) - u_bc}

    def losses(self, model: Standardized, route: str = "taylor",
               terms: tuple[str, ...] = ()) -> dict[str, torch.Tensor]:
        r = self.residuals(model, route)
        bc = (r["bc"] ** 2).view(len(self.EDGES), -1).mean(dim=1).sum()
        return {"res": (r["res"] ** 2).mean(), "bc": bc}

    def analytic_weights(self) -> dict[str, float]:
        lam = 1.0 / (1.0 + self.omega**4)
        return {"res": lam, "bc": 1.0 - lam}


class Sobolev(PinnProblem):
    """Sobolev training (the note's problem 2): fit f(x, y) = Σ_{j=1}^{20} A_j cos(l_j x + φ_j)
    · A'_j sin(l'_j y + φ'_j) (A, A' ~ U(−5, 5), l, l' ∈ {1..4}, φ, φ' ~ U(0, 2π), drawn from the
    seed) on (0, 2π]² together with its derivatives: five objectives, the MSEs of f,
    ∂x f + ∂y f, Δf, ∂xxx f + ∂yyy f and ∂xxxx f + ∂yyyy f at ``collocation`` uniformly random
    points; each is the sum over the axes of one order of
    :func:`adjointsim.nets.taylor.jets`. Network [2, 64×5, 1] with sin activation (PyTorch's
    default init), inputs standardised; the ID reference is the highest derivative (the
    authors' code). Metric: relative L2 of f on the 100 × 100 grid."""

    terms = ("f", "d1", "d2", "d3", "d4")
    reference = "d4"
    floats_per_unit = (110.0, 0.0)  # jets to fourth order along both axes
    extent = (0.0, 2.0 * math.pi) * 2
    title = "Sobolev training"

    def __init__(self, cfg: PinnConfig):
        self.cfg = cfg
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


class KSInverse(PinnProblem):
    """A sequential inverse problem on this project's Kuramoto–Sivashinsky solver: learn u(x, t)
    and the coefficients α, β of u_t + u u_x + α u_xx + β u_xxxx = 0 from a trajectory.

    Data: ``ks1d-etdrk4`` (N = 64, L = 22, Δt = 0.1, α = β = 1) from the smooth random state
    of ``adjointsim fit --demo ks-params`` (rng 1234), 100 steps: a 64 × 101 space-time grid,
    t ∈ [0, 10]. The seed draws the points and the network; the trajectory is fixed.
    Objectives, added one after another (the note's sequential training, with periodicity as
    the constraint where the active-turbulence problem has incompressibility):

    * ``data``: MSE of u against ``collocation`` grid values drawn from the trajectory;
    * ``periodic``: Σ_{m=0..3} mean (∂xᵐ u(0, t) − ∂xᵐ u(L, t))² at ``edge_points`` times;
    * ``res``: mean squared residual u_t + u u_x + α u_xx + β u_xxxx at ``collocation``
      uniform points, ∂x to fourth order and ∂t from :mod:`adjointsim.nets.taylor` (two passes, so t
      carries only its first order).

    Phases: ``data`` alone for the first third of the epochs, ``+ periodic`` for the second,
    ``+ res`` for the last; α and β (trainable, starting at 0.5) get gradients only from the
    residual. The ID reference is ``data``, the one objective of every phase (the authors
    name none for this problem); ``reference = "max"`` takes the largest spread. No lr
    steps. Network [2, 50×5, 1] tanh as for Poisson. Metric: relative L2 of u on the whole
    trajectory; the result also holds α, β and the data loss at the end of each phase, which
    shows whether the first objective is forgotten when the others join."""

    terms = ("data", "periodic", "res")
    reference = "data"
    floats_per_unit = (110.0, 110.0)  # the residual's jets; third-order jets at both ends
    axes = ("x", "t")
    title = "KS inverse (sequential)"
    start = 0.5

    def __init__(self, cfg: PinnConfig):
        from adjointsim import registry
        from adjointsim.fit_run import demo_problem

        self.cfg = cfg
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
        model = _tanh_mlp(self.cfg, scale / 2, scale / math.sqrt(12.0))  # uniform's moments
        model.alpha = nn.Parameter(torch.tensor(self.start))
        model.beta = nn.Parameter(torch.tensor(self.start))
        return model

    def active(self, epoch: int) -> tuple[str, ...]:
        return self.terms[: 1 + 3 * epoch // self.cfg.epochs]

    def extras(self, model: nn.Module) -> dict[str, float]:
        return {"alpha": float(model.alpha.detach()), "beta": float(model.beta.detach())}

    def milestones(self, epochs: int) -> list[int]:
        return []

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


class Sequential(PinnProblem):
    """A synthetic sequential problem in the setting of the note's active-turbulence problem:
    objectives of very different scales join one after another. The target is
    u* = sin(2πx) sin(2πy) on [0, 1]², with three objectives at ``collocation`` uniform
    points, each met exactly by u*:

    * ``data``: MSE of u against u* (scale 1);
    * ``grad``: 10⁻³ × MSE of ∂x u + ∂y u against u*'s (a weak objective);
    * ``lap``: 10³ × MSE of Δu against Δu* = −8π² u* (a strong one).

    ``data`` alone for the first third of the epochs, ``+ grad`` for the second, ``+ lap``
    for the last; the ID reference is ``data``. No lr steps. Network [2, 50×5, 1] tanh as
    for Poisson. Metric: relative L2 of u on the 100 × 100 grid; the result's phases hold
    every term and gradient spread at the end of each phase, which shows whether ``data`` is
    forgotten when a weak or a strong objective joins."""

    terms = ("data", "grad", "lap")
    reference = "data"
    scales = {"data": 1.0, "grad": 1e-3, "lap": 1e3}
    floats_per_unit = (60.0, 0.0)  # second-order jets along both axes
    title = "sequential (scales 1, 1e-3, 1e3)"

    def __init__(self, cfg: PinnConfig):
        self.cfg = cfg
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
        return _tanh_mlp(self.cfg, self.x_col.mean(dim=0), self.x_col.std(dim=0))

    def active(self, epoch: int) -> tuple[str, ...]:
        return self.terms[: 1 + 3 * epoch // self.cfg.epochs]

    def milestones(self, epochs: int) -> list[int]:
        return []

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


_PROBLEMS: dict[str, type[PinnProblem]] = {"poisson": Poisson, "sobolev": Sobolev,
                                           "ks-inverse": KSInverse, "sequential": Sequential}


def make_problem(cfg: PinnConfig) -> PinnProblem:
    """The problem of ``cfg``, validated first (nothing is allocated for a refused one)."""
    cfg.validate()
    return _PROBLEMS[cfg.problem](cfg)


def make_weighting(cfg: PinnConfig, problem: PinnProblem) -> Weighting:
    fixed = problem.analytic_weights() if scheme_name(cfg.weighting) == "epsilon-optimal" \
        else None
    reference = None if cfg.reference == "max" and cfg.weighting == "inverse-dirichlet" \
        else problem.reference
    return Weighting(problem.terms, cfg.weighting, reference=reference, alpha=cfg.alpha,
                     every=cfg.every, fixed=fixed, seed=cfg.seed)


# ----------------------------------------------------------------------------- training
def train_run(cfg: PinnConfig, out: str | Path, resume: bool = False, progress: bool = True,
              plot: bool = True, overwrite: bool = False) -> dict:
    """Train ``cfg`` in ``out`` (see the module doc) on ``cfg.threads`` torch and solver threads;
    returns the result (also result.json). A run already in ``out`` is continued with ``resume`` (a
    finished one's result is returned as it is), discarded with ``overwrite``, and otherwise
    never overwritten."""
    use_threads(cfg.threads)
    problem = make_problem(cfg)
    config = cfg.as_dict()
    out = Path(out)
    result_path, ckpt_path = out / "result.json", out / "checkpoint.pt"
    if overwrite and holds_run(out, config, RESUMABLE):
        discard(out, RUN_FILES)
    else:
        finished = finished_result(out, resume, config, RESULT_KEYS, RESUMABLE)
        if finished is not None:
            return finished
    model = problem.model()
    params = list(model.parameters())
    opt = torch.optim.Adam(params, lr=cfg.lr)
    sched = torch.optim.lr_scheduler.MultiStepLR(opt, problem.milestones(cfg.epochs),
                                                 gamma=0.1)
    weighting = make_weighting(cfg, problem)
    extras = tuple(problem.extras(model))
    fields = ["epoch", *(f"loss/{t}" for t in problem.terms),
              *(f"weight/{t}" for t in problem.terms), "total", "rel_l2", *extras, "lr",
              "skipped", "seconds"]
    # every weight refresh: the step, each λ and each term's gradient spread (ID, max/avg)
    weight_fields = ["step", *problem.terms, *(f"spread/{t}" for t in problem.terms)]
    state = {"epoch": 0, "history": [], "skipped": 0, "streak": 0, "seconds": 0.0,
             "diverged": False, "phases": []}
    if ckpt_path.exists():
        ckpt = load_run_checkpoint(ckpt_path, config, CHECKPOINT_KEYS, RESUMABLE)
        try:
            model.load_state_dict(ckpt["model"])
            opt.load_state_dict(ckpt["optimizer"])
            sched.load_state_dict(ckpt["scheduler"])
            weighting.load_state_dict(ckpt["weighting"])
        except (RuntimeError, ValueError, KeyError) as e:
            raise DamagedFileError(f"{ckpt_path} does not fit this run's model or optimiser "
                                   f"({type(e).__name__}: {' '.join(str(e).split())[:200]}); "
                                   "delete it to start again") from None
        state = {"phases": [], **ckpt["state"]}
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "config.json", config)

    def checkpoint() -> None:
        save_checkpoint({"config": config, "model": model.state_dict(),
                         "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                         "weighting": weighting.state_dict(), "state": state}, ckpt_path)
        write_history(out / "history.csv", state["history"], fields)
        write_history(out / "weights.csv", weighting.history, weight_fields)

    def log(epoch: int, losses: dict[str, float]) -> None:
        if state["history"] and state["history"][-1]["epoch"] == epoch:
            state["history"].pop()  # interrupted right after logging: log it again
        state["history"].append({
            "epoch": epoch, **{f"loss/{t}": losses[t] for t in problem.terms},
            **{f"weight/{t}": weighting.weights[t] for t in problem.terms},
            "total": sum(weighting.weights[t] * losses[t] for t in problem.terms),
            "rel_l2": problem.rel_l2(model), **problem.extras(model),
            "lr": opt.param_groups[0]["lr"], "skipped": state["skipped"],
            "seconds": state["seconds"]})

    def end_of_phase(epoch: int) -> None:
        """Every term, its gradient spread (as ID measures it, whether trained or not) and
        every coefficient when a phase (the set of trained terms) ends."""
        with torch.enable_grad():
            terms = problem.losses(model, cfg.route)
            rows = weighting.gradients(list(terms.values()), params)
        losses = {t: float(v.detach()) for t, v in terms.items()}
        spreads = {f"spread/{t}": float(r.std(unbiased=False)) for t, r in zip(terms, rows)}
        state["phases"].append({"epoch": epoch, "active": list(problem.active(epoch - 1)),
                                **losses, **spreads, "rel_l2": problem.rel_l2(model),
                                **problem.extras(model)})

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=cfg.epochs, initial=state["epoch"], unit="epoch", leave=False,
                   desc=f"{problem.title} {cfg.weighting} seed {cfg.seed}")
    last_save = time.monotonic()
    try:
        while state["epoch"] < cfg.epochs and not state["diverged"]:
            epoch = state["epoch"]
            t0 = time.perf_counter()
            opt.zero_grad(set_to_none=True)
            active = problem.active(epoch)
            logging = epoch % cfg.log_every == 0
            losses = problem.losses(model, cfg.route, problem.terms if logging else active)
            values = {t: float(v.detach()) for t, v in losses.items()}
            if not all(math.isfinite(values[t]) for t in active):
                state["skipped"] += 1
                state["streak"] += 1
                warnings.warn(f"epoch {epoch}: non-finite loss {values}; update skipped "
                              f"({state['streak']} of at most {MAX_SKIPS} in a row)",
                              RuntimeWarning, stacklevel=2)
                if state["streak"] >= MAX_SKIPS:
                    state["diverged"] = True
                state["seconds"] += time.perf_counter() - t0
                continue
            state["streak"] = 0
            if logging:
                log(epoch, values)  # the weights before this epoch's refresh
            with uninterrupted():
                weighting.backward({t: losses[t] for t in active}, params, epoch,
                                   lambda: problem.residuals(model, cfg.route, NTK_POINTS))
                opt.step()
                sched.step()
                state["seconds"] += time.perf_counter() - t0
                state["epoch"] += 1
                if state["epoch"] < cfg.epochs and problem.active(state["epoch"]) != active:
                    end_of_phase(state["epoch"])
            if bar is not None:
                bar.update()
                if epoch % cfg.log_every == 0:
                    bar.set_postfix(rel_l2=f"{state['history'][-1]['rel_l2']:.2e}")
            if time.monotonic() - last_save > 60.0:
                checkpoint()
                last_save = time.monotonic()
    except KeyboardInterrupt:
        checkpoint()
        raise
    finally:
        if bar is not None:
            bar.close()
    if not state["diverged"]:
        if not state["phases"] or state["phases"][-1]["epoch"] != state["epoch"]:
            end_of_phase(state["epoch"])  # (not again when resumed after the last checkpoint)
        final = {t: state["phases"][-1][t] for t in problem.terms}
        if all(math.isfinite(v) for v in final.values()):
            log(state["epoch"], final)
    checkpoint()
    rel = problem.rel_l2(model)
    result = {**config, "rel_l2": rel if math.isfinite(rel) else None,
              "diverged": state["diverged"], "skipped": state["skipped"],
              "seconds": state["seconds"], "weights": dict(weighting.weights),
              "coefficients": problem.extras(model), "phases": state["phases"]}
    if plot:
        plot_run(problem, model, state["history"], out, cfg, state["phases"])
    write_json(result_path, result)
    return result


# ----------------------------------------------------------------------------- plots
def plot_run(problem: PinnProblem, model: nn.Module, history: list[dict], out: Path,
             cfg: PinnConfig, phases: list[dict] = ()) -> None:
    """``field.png``: exact solution, prediction, |error|; ``history.png``: each term, each
    weight, the relative L2 error and any learned coefficient over epochs, with the phase
    boundaries dotted."""
    plt = pyplot()
    with torch.no_grad():
        u = model(problem.grid).reshape(problem.shape).numpy()
    exact = problem.u_grid.reshape(problem.shape).numpy()
    title = f"{problem.title}, {cfg.weighting}, seed {cfg.seed}"
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
    for ax, field, name in zip(axes, (exact, u, np.abs(u - exact)),
                               ("exact u", "network u", "|error|")):
        im = ax.imshow(field.T, origin="lower", extent=problem.extent, cmap="viridis",
                       aspect="auto")
        ax.set(title=name, xlabel=problem.axes[0], ylabel=problem.axes[1])
        fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle(title)
    save_figure(fig, out / "field.png", dpi=110)

    extras = tuple(problem.extras(model))
    fig, axes = plt.subplots(1, 3 + bool(extras), figsize=(12 + 4 * bool(extras), 3.4))
    path = out / "history.png"
    for t in problem.terms:
        plot_history(path, {f"L_{t}": history}, "epoch", f"loss/{t}", "epoch", "loss",
                     title="loss terms", ax=axes[0])
        plot_history(path, {f"λ_{t}": history}, "epoch", f"weight/{t}", "epoch", "weight",
                     title="weights", ax=axes[1])
    plot_history(path, {"relative L2": history}, "epoch", "rel_l2", "epoch",
                 "relative L2 error", title="relative L2 error", ax=axes[2])
    for name in extras:
        plot_history(path, {name: history}, "epoch", name, "epoch", "value",
                     title="coefficients", log=False, ax=axes[3])
    for ax in axes:
        for p in phases[:-1]:
            ax.axvline(p["epoch"], color="0.6", ls=":", lw=0.8)
    fig.suptitle(title)
    save_figure(fig, path, dpi=110)
