"""PBDL's Burgers problems: differentiable physics (DP) against a physics-informed network, both
runs on the run engine.

The problems are the fit demos of :mod:`adjointsim.fit_demos` (Thuerey et al.,
*Physics-based Deep Learning*): viscous Burgers u_t + u u_x = ν u_xx on [−1, 1],
ν = 0.01/π, true initial state u_0 = −sin(πx), boundary values u(±1, t) = 0, N = 128 cells,
Δt = 1/32. ``burgers``: the initial state from the cell values at t = 0.5 (step 16) only;
``burgers-nu``: ν (from 2 ν_true) from every step of the trajectory, with optional noise.

* DP: the fit of the demo (``adjointsim fit --demo NAME``, :func:`adjointsim.fit_run.run_fit`)
  in its own run directory, through the Rusanov solver's hand-written adjoint, L-BFGS-B
  (:func:`run_dp`).
* PINN: :class:`BurgersPinnRun`, u(x, t) an MLP (tanh, 8 × 20, as the book's) trained with Adam
  on three terms: the observations, the Burgers residual at collocation points of
  [−1, 1] × [0, 1] (u_t, u_x, u_xx from the forward Taylor jets of
  :mod:`adjointsim.nets.taylor`, no nested autograd) and the boundary values, through
  :mod:`adjointsim.train.weighting` (uniform by default: inverse-Dirichlet weighting drives the
  network to the trivial u ≈ 0 here, see :class:`BurgersPinnConfig`); ν is learned with the
  network where the demo fits ν. It trains for ``epochs`` or ``seconds`` of CPU time,
  whichever comes first.

For both: the misfit (MSE) against the observations, the MSE of the reconstructed u(·, 0)
against −sin(πx) on the cell centres, the fitted ν, and the run time (CPU seconds of this
process on one thread, robust to a loaded machine; the DP time excludes numba's one-off
compilation). The PINN runs in float32 (as the book's), DP in float64. The comparisons are the
studies ``adjointsim study burgers-dp-pinn`` and ``adjointsim study burgers-nu-dp-pinn``
(:mod:`adjointsim.train.studies.burgers`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from adjointsim import engine
from adjointsim.nets.mlp import MLP
from adjointsim.nets.taylor import jets
from adjointsim.run import SEEDS, Config, Interval, read_history
from adjointsim.runner import runs_show_progress

from .checkpoint import STORE, restore
from .threads import use_threads
from .weighting import RULES, Weighting

#: the book's DP run (phiflow, TensorFlow, eager): MSE after 50 gradient steps, seconds
BOOK_DP = {"misfit": 0.0033, "seconds": 132.0, "steps": 50}
DEMOS = ("burgers", "burgers-nu")
TERMS = ("data", "residual", "boundary")


def demo_data(demo: str, noise: float = 0.0, seed: int = 0) -> dict[str, Any]:
    """The demo's scene, cell centres ``x``, observation ``times``, observed states (one row
    per time), true initial state, true ν and, where the demo fits ν, its start."""
    from adjointsim.fit_demos import demo_problem, demo_scene, pbdl_state

    prob = demo_problem(demo, noise, seed)
    scene, _ = demo_scene(demo)
    return {"scene": scene, "x": scene.nodes(), "steps": prob["steps"],
            "times": tuple(float(k) * scene.dt for k in prob["steps"]),
            "observed": prob["states"][:, 0, 0], "u0": pbdl_state(scene)[0, 0],
            "nu": prob["truth_params"]["nu"],
            "nu_start": prob["params"]["nu"] if prob["wrt"] == "nu" else None, "prob": prob}


@dataclass
class BurgersPinnConfig(Config):
    """The PINN side of a Burgers comparison."""

    demo: str = "burgers"
    #: the demo's relative observation noise (its seed is ``seed``)
    noise: float = 0.0
    width: int = 20
    depth: int = 8
    collocation: int = 1000
    boundary_points: int = 100
    lr: float = 1e-3
    #: uniform: inverse-Dirichlet fails here. With the residual as its reference (the authors'
    #: choice for Poisson) the data weight collapses to ~0; with the largest spread as the
    #: reference the residual weight grows to ~1e6. Either way the network settles on u ≈ 0,
    #: which satisfies the residual and the boundary values
    #: (docs/results/fit/fit-burgers-id-residual.*)
    weighting: str = "uniform"
    reference: str = "max"
    every: int = 5
    seed: int = 0
    #: stop after this many epochs or this many CPU seconds, whichever comes first
    epochs: int = 100_000
    seconds: float = 60.0
    log_every: int = 50
    dtype: str = "float32"
    threads: int = 1

    ACCEPTED: ClassVar[dict[str, tuple | Interval | str]] = {
        "demo": DEMOS, "noise": Interval(0), "width": Interval(1, 4096),
        "depth": Interval(1, 100), "collocation": Interval(1, 1_000_000),
        "boundary_points": Interval(1, 1_000_000), "lr": Interval(0, lo_open=True),
        "weighting": RULES, "reference": ("max", *TERMS), "every": Interval(1), "seed": SEEDS,
        "epochs": Interval(1), "seconds": Interval(0, lo_open=True), "log_every": Interval(1),
        "dtype": ("float32", "float64"), "threads": Interval(1)}


class BurgersPinn:
    """The PINN side's points, network, loss terms and metrics on the solver's cell centres."""

    terms = TERMS

    def __init__(self, cfg: BurgersPinnConfig):
        self.cfg = cfg
        data = demo_data(cfg.demo, cfg.noise, cfg.seed)
        self.learn_nu = data["nu_start"] is not None
        self.true_nu = data["nu"]
        gen = torch.Generator().manual_seed(cfg.seed)
        dt = getattr(torch, cfg.dtype)
        self.x = torch.from_numpy(data["x"]).to(dt)[:, None]
        self.obs_in = torch.cat([torch.cat([self.x, torch.full_like(self.x, t)], dim=1)
                                 for t in data["times"]])
        self.obs = torch.from_numpy(np.asarray(data["observed"]).reshape(-1)).to(dt)[:, None]
        # ν > 0 as exp(log ν); the true one unless learned
        self.log_nu = torch.tensor(math.log(data["nu_start"] if self.learn_nu else data["nu"]),
                                   dtype=dt, requires_grad=self.learn_nu)
        col = torch.rand(cfg.collocation, 2, generator=gen, dtype=dt)
        self.col = torch.stack([2 * col[:, 0] - 1, col[:, 1]], dim=1)
        tb = torch.rand(cfg.boundary_points, 1, generator=gen, dtype=dt)
        side = torch.where(torch.arange(cfg.boundary_points)[:, None] % 2 == 0, -1.0, 1.0)
        self.bnd = torch.cat([side.to(dt), tb], dim=1)
        self.init_in = torch.cat([self.x, torch.zeros_like(self.x)], dim=1)
        self.u0_true = -torch.sin(math.pi * self.x)
        # inputs standardised to [-1, 1]²: t̃ = 2t − 1; d/dt = 2 d/dt̃
        self.shift = torch.tensor([0.0, -1.0], dtype=dt)
        self.scale = torch.tensor([1.0, 2.0], dtype=dt)

    def model(self) -> MLP:
        torch.manual_seed(self.cfg.seed)
        return MLP(2, 1, self.cfg.width, self.cfg.depth, "tanh").to(self.obs.dtype)

    def u(self, net: MLP, p: torch.Tensor) -> torch.Tensor:
        return net(p * self.scale + self.shift)

    def losses(self, net: MLP) -> dict[str, torch.Tensor]:
        u, d1, d2 = jets(net, self.col * self.scale + self.shift, 2, torch.diag(self.scale))
        u_x, u_t, u_xx = d1[:, 0], d1[:, 1], d2[:, 0]
        res = u_t + u * u_x - torch.exp(self.log_nu) * u_xx
        return {"data": ((self.u(net, self.obs_in) - self.obs) ** 2).mean(),
                "residual": (res**2).mean(),
                "boundary": (self.u(net, self.bnd) ** 2).mean()}

    @torch.no_grad()
    def metrics(self, net: MLP) -> dict[str, float]:
        return {"misfit": float(((self.u(net, self.obs_in) - self.obs) ** 2).mean()),
                "u0_mse": float(((self.u(net, self.init_in) - self.u0_true) ** 2).mean()),
                "nu": float(torch.exp(self.log_nu))}


class BurgersPinnRun(engine.Problem):
    """The PINN side as a training run: an update is one full-batch epoch; a history row
    (epoch, CPU seconds, each term and weight, misfit, u0_mse, ν) after the first epoch, every
    ``log_every`` and the last, a checkpoint with each; the result holds the last row's
    metrics, the weights, the cell centres, the prediction at the first observed time and the
    reconstructed u(·, 0)."""

    RESUMABLE = ("threads",)
    EXTENDABLE = ("epochs", "seconds")
    HISTORIES = {"history.csv": ("epoch", "seconds", *(f"loss/{t}" for t in TERMS),
                                 *(f"weight/{t}" for t in TERMS), "misfit", "u0_mse", "nu")}
    RESULT_KEYS = {"epochs": int, "seconds": float, "misfit": float, "u0_mse": float,
                   "nu": float, "weights": dict}
    STORE = STORE
    UNIT = "epoch"

    def describe(self) -> str:
        return f"Burgers PINN ({self.config.demo})"

    def total(self) -> int:
        return self.config.epochs

    def position(self) -> int:
        return self.state["epoch"]

    def done(self) -> bool:
        return (self.state["epoch"] >= self.config.epochs
                or self.state["seconds"] >= self.config.seconds)

    def build(self) -> None:
        cfg = self.config
        use_threads(cfg.threads)
        self.prob = BurgersPinn(cfg)
        self.net = self.prob.model()
        self.params = [*self.net.parameters(), *([self.prob.log_nu] if self.prob.learn_nu
                                                 else [])]
        self.opt = torch.optim.Adam(self.params, lr=cfg.lr)
        self.weighting = Weighting(self.prob.terms, cfg.weighting, every=cfg.every,
                                   reference=None if cfg.reference == "max" else cfg.reference)
        self.state: dict[str, Any] = {"epoch": 0, "seconds": 0.0}
        self.rows: list[dict] = []

    def update(self) -> bool:
        """One epoch; a boundary when it logged a row."""
        start = time.process_time()
        self.opt.zero_grad(set_to_none=True)
        losses = self.prob.losses(self.net)
        self.weighting.backward(losses, self.params, self.state["epoch"])
        self.opt.step()
        self.state["epoch"] += 1
        self.state["seconds"] += time.process_time() - start
        epoch = self.state["epoch"]
        logging = epoch % self.config.log_every == 0 or self.done() or epoch == 1
        if logging:
            self.rows.append({"epoch": epoch, "seconds": self.state["seconds"],
                              **{f"loss/{k}": float(v.detach()) for k, v in losses.items()},
                              **{f"weight/{k}": w for k, w in self.weighting.weights.items()},
                              **self.prob.metrics(self.net)})
        return logging

    def postfix(self) -> dict[str, Any]:
        return {"misfit": f"{self.rows[-1]['misfit']:.2e}"} if self.rows else {}

    def extend(self, recorded: dict) -> None:
        """A finished run continued to more epochs or seconds: its last row goes where only
        the end of the run logged it."""
        epoch = self.state["epoch"]
        if self.rows and self.rows[-1]["epoch"] == epoch and epoch % self.config.log_every \
                and epoch != 1:
            self.rows.pop()

    def finish(self) -> dict:
        with torch.no_grad():
            predicted = self.prob.u(self.net, self.prob.obs_in[:len(self.prob.x)])
            fitted_u0 = self.prob.u(self.net, self.prob.init_in)
        return {"epochs": self.state["epoch"], "seconds": self.state["seconds"],
                **self.prob.metrics(self.net), "true_nu": self.prob.true_nu,
                "weights": dict(self.weighting.weights),
                "x": self.prob.x[:, 0].tolist(), "predicted": predicted[:, 0].tolist(),
                "fitted_u0": fitted_u0[:, 0].tolist()}

    def state_dict(self) -> dict:
        return {"net": self.net.state_dict(), "optimizer": self.opt.state_dict(),
                "weighting": self.weighting.state_dict(), "log_nu": self.prob.log_nu.detach(),
                **self.state}

    def load_state_dict(self, state: dict) -> None:
        path = self.out / engine.CHECKPOINT
        restore(self.net, state["net"], path)
        restore(self.opt, state["optimizer"], path)
        restore(self.weighting, state["weighting"], path)
        with torch.no_grad():
            self.prob.log_nu.copy_(state["log_nu"])
        self.state = {k: state[k] for k in self.state}

    def histories(self) -> dict[str, list[dict]]:
        return {"history.csv": self.rows}

    def load_histories(self, histories: dict[str, list[dict]]) -> None:
        self.rows = list(histories["history.csv"])


def run_pinn(cfg: BurgersPinnConfig, out: str | Path) -> dict:
    """The PINN side in ``out`` (continued if it holds the run): its result and history."""
    cfg.validate()
    run = BurgersPinnRun(cfg, out)
    result = engine.run(run, resume=engine.RunDir(run).holds(), progress=runs_show_progress())
    return {**result, "history": read_history(run.out / "history.csv")}


def run_dp(demo: str, out: str | Path, noise: float = 0.0, seed: int = 0,
           **keys: Any) -> dict:
    """The DP side in ``out``: the fit of ``demo`` (``adjointsim fit --demo``,
    :class:`adjointsim.fit_run.FitRun`, with config ``keys``; its result returned if ``out``
    holds it), after numba's compilation; its result, history (with CPU seconds), the fitted
    initial state and the predicted states."""
    from adjointsim.fit import fit
    from adjointsim.fit_run import FitConfig, FitRun, read_observations

    cfg = FitConfig(demo=demo, noise=noise, seed=seed, **keys)
    cfg.validate()
    run = FitRun(cfg, out, plots=False)
    data = demo_data(demo, noise, seed)
    prob = data["prob"]
    obs = {int(k): v for k, v in zip(prob["steps"], prob["states"])}
    fit(data["scene"], obs, wrt=prob["wrt"], u0=prob["u0"], params=prob["params"],
        maxiter=1)  # numba's compilation, not timed
    result = engine.run(run, resume=engine.RunDir(run).holds(), progress=runs_show_progress())
    fitted = read_observations(run.out / "fitted.h5", None)
    return {**result, "history": read_history(run.out / "history.csv"), "data": data,
            "fitted_u0": fitted["u0"][0, 0], "predicted": fitted["states"][:, 0, 0]}
