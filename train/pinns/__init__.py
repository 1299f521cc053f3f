"""The problems of ``adjointsim pinn``, one file each, registered by name like the solvers.

A problem is a subclass of :class:`PinnProblem` decorated with ``@PROBLEMS.register``: it
names itself, owns its defaults (network width and activation, epochs, learning-rate steps),
its loss terms and their reference, the weighting schemes it can offer, its data and its
accuracy measure. ``adjointsim pinn --help``, the config's accepted values, the studies and
the docs find it through :data:`PROBLEMS`; adding a problem is one new file here (and its
test). See :mod:`adjointsim.train.pinn` for the training run.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import torch
from torch import nn

from adjointsim.nets.mlp import MLP
from adjointsim.nets.taylor import jets, laplacian
from adjointsim.registry import Registry

from ..weighting import GENERIC, RULES

if TYPE_CHECKING:
    from ..pinn import PinnConfig

#: every PINN problem, by name (one module of this package each)
PROBLEMS = Registry("PINN problem", "adjointsim.train.pinns")
#: what a scheme beyond :data:`adjointsim.train.weighting.GENERIC` needs of a problem
NEEDS = {"epsilon-optimal": "analytic weights", "ntk": "per-sample residuals"}


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


def tanh_mlp(cfg: PinnConfig, mean: torch.Tensor, std: torch.Tensor) -> Standardized:
    """[2, width × depth, 1] tanh, Xavier-normal weights with gain 5/3, zero biases."""
    torch.manual_seed(cfg.seed)
    mlp = MLP(2, 1, cfg.width, cfg.depth, "tanh")
    for m in mlp.modules():
        if isinstance(m, nn.Linear):
            nn.init.xavier_normal_(m.weight, gain=5.0 / 3.0)
            nn.init.zeros_(m.bias)
    return Standardized(mlp, mean, std)


class PinnProblem:
    """What the training run asks of a problem; the defaults fit a problem whose terms are
    all active from the start, with no physical coefficient to learn. A problem also has
    ``__init__(cfg)`` (its points and data), ``model()`` and ``losses(model, route, terms)``,
    the named loss terms; a problem whose terms join one after another computes only those in
    ``terms`` (all when empty)."""

    #: the problem's name on the command line and in configs
    name: ClassVar[str] = ""
    #: the network width and the epochs a config's 0 stands for
    width: ClassVar[int] = 50
    epochs: ClassVar[int] = 3000
    terms: ClassVar[tuple[str, ...]] = ()
    #: the inverse-Dirichlet reference term
    reference: ClassVar[str] = ""
    #: the routes to the derivatives it offers (nested autograd only where it is second order)
    routes: ClassVar[tuple[str, ...]] = ("taylor",)
    #: the schemes of :data:`NEEDS` it offers: it has :meth:`analytic_weights`, ``residuals``
    offers: ClassVar[tuple[str, ...]] = ()
    #: learned physical coefficients (parameters of the model of these names), logged
    coefficients: ClassVar[tuple[str, ...]] = ()
    #: the terms join one after another, in equal parts of the epochs
    phased: ClassVar[bool] = False
    #: lr × 0.1 at these epochs (those below the run's epochs)
    lr_steps: ClassVar[tuple[int, ...]] = (10000, 20000, 30000)
    #: float32 values per hidden unit that a training epoch keeps at its peak, per collocation
    #: point and per edge point (measured on CPU, with a quarter more as margin): the
    #: derivative streams the reverse pass needs
    floats_per_unit: ClassVar[tuple[float, float]] = (0.0, 0.0)
    #: the evaluation grid: (rows, columns) and (first min, max, second min, max)
    shape = (100, 100)
    extent = (0.0, 1.0, 0.0, 1.0)
    axes = ("x", "y")
    title = ""
    grid: torch.Tensor
    u_grid: torch.Tensor

    def __init__(self, cfg: PinnConfig):
        self.cfg = cfg

    @classmethod
    def schemes(cls) -> tuple[str, ...]:
        """The weighting schemes it offers."""
        return tuple(r for r in RULES if r in GENERIC or r in cls.offers)

    def active(self, epoch: int) -> tuple[str, ...]:
        """The terms trained at ``epoch``."""
        if not self.phased:
            return self.terms
        return self.terms[: 1 + len(self.terms) * epoch // self.cfg.epochs]

    def extras(self, model: nn.Module) -> dict[str, float]:
        """The learned physical coefficients, logged beside the losses."""
        return {c: float(getattr(model, c).detach()) for c in self.coefficients}

    def milestones(self, epochs: int) -> list[int]:
        """The lr steps within ``epochs``: a shorter run is the start of a longer one."""
        return [m for m in self.lr_steps if m < epochs]

    def analytic_weights(self) -> dict[str, float]:
        raise NotImplementedError(f"the {self.name} problem has no analytic weights")

    @torch.no_grad()
    def rel_l2(self, model: nn.Module) -> float:
        u = model(self.grid)
        return float(torch.linalg.norm(u - self.u_grid) / torch.linalg.norm(self.u_grid))
