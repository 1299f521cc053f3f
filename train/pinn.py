"""Physics-informed training with loss balancing (Maddu et al., MLST 2022): the training run of
``adjointsim pinn`` on the run engine (:mod:`adjointsim.engine`), for any problem of
:mod:`adjointsim.train.pinns` (Poisson, Sobolev, the KS inverse problem, the synthetic
sequential problem: one file each).

Loss L = Σ λ_t L_t over the problem's terms with λ from
:class:`adjointsim.train.weighting.Weighting` (the problem's reference term unless
``reference = "max"``; ``epsilon-optimal`` takes the problem's analytic weights). Adam, full
batch, lr × 0.1 at the problem's steps (Poisson and Sobolev: 10k, 20k and 30k of the authors'
30,001 epochs; a shorter run is the start of such a run). A problem whose terms join one
after another records every term and its gradient spread when each phase ends.

A :class:`PinnConfig` is checked key by key (:data:`ACCEPTED`) and against the machine's
memory before anything is allocated. A run directory holds what the engine writes for every
command (``config.json``, ``checkpoint.pt``, ``result.json``), ``history.csv`` (every
``log_every`` epochs: each term, each weight, the weighted total, the relative L2 error,
learned coefficients, skipped updates, seconds), ``weights.csv`` (every weight refresh: each
λ and each term's gradient spread), and the plots ``field.png`` (exact, prediction, error)
and ``history.png`` (terms, weights, error).
"""

from __future__ import annotations

import math
import time
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from adjointsim import engine
from adjointsim.errors import UserError
from adjointsim.files import pyplot, save_figure
from adjointsim.run import SEEDS, Config, Interval, check_memory, plot_history
from adjointsim.runner import runs_show_progress

from .checkpoint import STORE, restore
from .compiled import BACKENDS, compiled
from .pinns import NEEDS, PROBLEMS, PinnProblem
from .threads import use_threads
from .weighting import ALIASES, RECORDED, RULES, Weighting, canonical_rule, scheme_name

ROUTES = ("taylor", "autograd")
K_RANGE = (1, 6)
#: collocation points (and a quarter as many per edge) whose residuals give the NTK weights:
#: each is a reverse pass of its own on the Taylor route, which cannot batch them
NTK_POINTS = 32
#: consecutive non-finite losses after which a run is given up (full batch: the same
#: parameters give the same loss, so skipping cannot recover)
MAX_SKIPS = 10

#: the accepted values of every PinnConfig field; the rules tying keys together (the routes
#: and schemes a problem offers, 0 as the problem's width and epochs, the memory a network
#: needs) are in PinnConfig.check
ACCEPTED: dict[str, tuple | Interval | str] = {
    "problem": tuple(PROBLEMS.names()),
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
    "compile": BACKENDS,
}


@dataclass
class PinnConfig(Config):
    """One run of ``adjointsim pinn``: every key is a flag and a key of a ``--config`` file;
    :meth:`validate` checks them against :data:`ACCEPTED` and :meth:`check`."""

    problem: str = "poisson"
    #: the Poisson wavenumber
    k: int = 1
    weighting: str = "inverse-dirichlet"
    #: the ID reference term: "res", the problem's (Poisson: the residual, as in the authors'
    #: code; Sobolev: the highest derivative), or "max" (the largest spread)
    reference: str = "res"
    #: 0: the problem's
    epochs: int = 0
    seed: int = 0
    lr: float = 1e-3
    alpha: float = 0.5
    every: int = 5
    #: 0: the problem's
    width: int = 0
    depth: int = 5
    collocation: int = 2500
    edge_points: int = 100
    route: str = "taylor"
    log_every: int = 100
    #: torch's and the solver's threads (they take turns)
    threads: int = 1
    #: the epoch's losses eager (off) or through torch.compile with that backend
    #: (:mod:`adjointsim.train.compiled`); the same training, so a run may change it
    compile: str = "off"

    ACCEPTED: ClassVar[dict[str, tuple | Interval | str]] = ACCEPTED

    def check(self, where: str) -> None:
        """The weighting's canonical name, the routes and schemes the problem offers, 0
        replaced by the problem's width and epochs, and the memory the run needs (before
        anything is made)."""
        problem = PROBLEMS.get(self.problem)
        self.weighting = canonical_rule(self.weighting)
        if self.route not in problem.routes:
            raise UserError(f"config key 'route'{where}: the {self.problem} problem takes route "
                            f"{' or '.join(repr(r) for r in problem.routes)} only")
        if scheme_name(self.weighting) not in problem.schemes():
            lacks = " and ".join(f"no {what}" for rule, what in NEEDS.items()
                                 if rule not in problem.offers)
            raise UserError(f"config key 'weighting'{where}: the {self.problem} problem has "
                            f"{lacks}; choose one of {', '.join(problem.schemes())}")
        self.width = self.width or problem.width
        self.epochs = self.epochs or problem.epochs
        check_memory(memory_needed(self), f"width {self.width}, depth {self.depth}, collocation "
                     f"{self.collocation} and edge_points {self.edge_points}{where}",
                     "choose smaller ones")


def memory_needed(cfg: PinnConfig) -> int:
    """Bytes one training epoch of ``cfg`` holds at its peak, roughly and from above: the
    parameters with their gradient, Adam's two moments and one gradient per loss term (the
    weighting's), and per hidden unit the problem's :attr:`PinnProblem.floats_per_unit`."""
    w, d = cfg.width, cfg.depth
    params = 3 * w + (d - 1) * (w * w + w) + w + 1
    problem = PROBLEMS.get(cfg.problem)
    per_col, per_edge = problem.floats_per_unit
    activations = (per_col * cfg.collocation + per_edge * cfg.edge_points) * w * d
    return int(4 * ((4 + len(problem.terms)) * params + activations))


def make_problem(cfg: PinnConfig) -> PinnProblem:
    """The problem of ``cfg``, validated first (nothing is allocated for a refused one)."""
    cfg.validate()
    return PROBLEMS.get(cfg.problem)(cfg)


def make_weighting(cfg: PinnConfig, problem: PinnProblem) -> Weighting:
    fixed = problem.analytic_weights() if scheme_name(cfg.weighting) == "epsilon-optimal" \
        else None
    reference = None if cfg.reference == "max" and cfg.weighting == "inverse-dirichlet" \
        else problem.reference
    return Weighting(problem.terms, cfg.weighting, reference=reference, alpha=cfg.alpha,
                     every=cfg.every, fixed=fixed, seed=cfg.seed)


# ----------------------------------------------------------------------------- the run
class PinnRun(engine.Problem):
    """One ``adjointsim pinn`` run: an update is one full-batch epoch (skipped, with a
    warning, when a trained term is not finite; :data:`MAX_SKIPS` in a row end the run as
    diverged), a history row every ``log_every`` epochs (a checkpoint with it), every term
    and its gradient spread when a phase ends, the final evaluation and plots."""

    RESUMABLE = ("threads", "compile")
    RUN_FILES = ("field.png", "history.png")
    RESULT_KEYS = {"rel_l2": float, "diverged": bool, "skipped": int, "seconds": float,
                   "weights": dict, "coefficients": dict, "phases": list}
    STORE = STORE
    UNIT = "epoch"

    def __init__(self, config: PinnConfig, out: str | Path, plots: bool = True):
        super().__init__(config, out)
        self.plots = plots
        kind = PROBLEMS.get(config.problem)
        terms = kind.terms
        self.HISTORIES = {  # the columns follow the problem's terms and coefficients
            "history.csv": ("epoch", *(f"loss/{t}" for t in terms),
                            *(f"weight/{t}" for t in terms), "total", "rel_l2",
                            *kind.coefficients, "lr", "skipped", "seconds"),
            # every weight refresh: the step, each λ and each term's gradient spread
            "weights.csv": ("step", *terms, *(f"spread/{t}" for t in terms))}
        # a finished run continues to more epochs, unless its terms join at fractions of them
        self.EXTENDABLE = () if kind.phased else ("epochs",)

    def describe(self) -> str:
        return f"{self.problem.title} {self.config.weighting} seed {self.config.seed}"

    def total(self) -> int:
        return self.config.epochs

    def position(self) -> int:
        return self.state["epoch"]

    def done(self) -> bool:
        return self.state["diverged"] or self.state["epoch"] >= self.config.epochs

    def build(self) -> None:
        cfg = self.config
        use_threads(cfg.threads)
        self.problem = make_problem(cfg)
        self.model = self.problem.model()
        self.losses = compiled(self.problem.losses, cfg.compile)
        self.params = list(self.model.parameters())
        self.opt = torch.optim.Adam(self.params, lr=cfg.lr)
        self.sched = torch.optim.lr_scheduler.MultiStepLR(
            self.opt, self.problem.milestones(cfg.epochs), gamma=0.1)
        self.weighting = make_weighting(cfg, self.problem)
        self.state: dict[str, Any] = {"epoch": 0, "skipped": 0, "streak": 0, "seconds": 0.0,
                                      "diverged": False, "phases": []}
        self.rows: list[dict] = []

    def update(self) -> bool:
        """One epoch; a boundary when it logged a history row."""
        cfg, problem, state = self.config, self.problem, self.state
        epoch = state["epoch"]
        t0 = time.perf_counter()
        self.opt.zero_grad(set_to_none=True)
        active = problem.active(epoch)
        logging = epoch % cfg.log_every == 0
        losses = self.losses(self.model, cfg.route, problem.terms if logging else active)
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
            return False
        state["streak"] = 0
        if logging:
            self.log(epoch, values)  # the weights before this epoch's refresh
        self.weighting.backward({t: losses[t] for t in active}, self.params, epoch,
                                lambda: problem.residuals(self.model, cfg.route, NTK_POINTS))
        self.opt.step()
        self.sched.step()
        state["seconds"] += time.perf_counter() - t0
        state["epoch"] += 1
        if state["epoch"] < cfg.epochs and problem.active(state["epoch"]) != active:
            self.end_of_phase(state["epoch"])
        return logging

    def log(self, epoch: int, losses: dict[str, float]) -> None:
        if self.rows and self.rows[-1]["epoch"] == epoch:
            self.rows.pop()  # the finish logged again after a resume
        terms, weights = self.problem.terms, self.weighting.weights
        self.rows.append({
            "epoch": epoch, **{f"loss/{t}": losses[t] for t in terms},
            **{f"weight/{t}": weights[t] for t in terms},
            "total": sum(weights[t] * losses[t] for t in terms),
            "rel_l2": self.problem.rel_l2(self.model), **self.problem.extras(self.model),
            "lr": self.opt.param_groups[0]["lr"], "skipped": self.state["skipped"],
            "seconds": self.state["seconds"]})

    def end_of_phase(self, epoch: int) -> None:
        """Every term, its gradient spread (as ID measures it, whether trained or not) and
        every coefficient when a phase (the set of trained terms) ends."""
        problem, model = self.problem, self.model
        with torch.enable_grad():
            terms = problem.losses(model, self.config.route)
            rows = self.weighting.gradients(list(terms.values()), self.params)
        losses = {t: float(v.detach()) for t, v in terms.items()}
        spreads = {f"spread/{t}": float(r.std(unbiased=False)) for t, r in zip(terms, rows)}
        self.state["phases"].append({"epoch": epoch, "active": list(problem.active(epoch - 1)),
                                     **losses, **spreads, "rel_l2": problem.rel_l2(model),
                                     **problem.extras(model)})

    def postfix(self) -> dict[str, Any]:
        return {"rel_l2": f"{self.rows[-1]['rel_l2']:.2e}"} if self.rows else {}

    def extend(self, recorded: dict) -> None:
        """A finished run continued to more epochs, as the longer run would have trained: its
        lr steps, and neither the final evaluation's phase record nor its history row (the
        next epoch logs that row again where it is due)."""
        epoch = self.state["epoch"]
        self.sched.milestones = Counter(self.problem.milestones(self.config.epochs))
        if self.state["phases"] and self.state["phases"][-1]["epoch"] == epoch:
            self.state["phases"].pop()
        if self.rows and self.rows[-1]["epoch"] == epoch and epoch % self.config.log_every:
            self.rows.pop()

    def finish(self) -> dict:
        state = self.state
        if not state["diverged"]:
            if not state["phases"] or state["phases"][-1]["epoch"] != state["epoch"]:
                self.end_of_phase(state["epoch"])  # (not again when resumed after the finish)
            final = {t: state["phases"][-1][t] for t in self.problem.terms}
            if all(math.isfinite(v) for v in final.values()):
                self.log(state["epoch"], final)
        return {"rel_l2": engine.finite_or_none(self.problem.rel_l2(self.model)),
                "diverged": state["diverged"], "skipped": state["skipped"],
                "seconds": state["seconds"], "weights": dict(self.weighting.weights),
                "coefficients": self.problem.extras(self.model), "phases": state["phases"]}

    def plot(self) -> None:
        if self.plots:
            plot_run(self.problem, self.model, self.rows, self.out, self.config,
                     self.state["phases"])

    def state_dict(self) -> dict:
        # the weighting's refresh history is weights.csv's rows, kept once
        weighting = {k: v for k, v in self.weighting.state_dict().items() if k != "history"}
        return {"model": self.model.state_dict(), "optimizer": self.opt.state_dict(),
                "scheduler": self.sched.state_dict(), "weighting": weighting, **self.state}

    def load_state_dict(self, state: dict) -> None:
        path = self.out / engine.CHECKPOINT
        restore(self.model, state["model"], path)
        restore(self.opt, state["optimizer"], path)
        restore(self.sched, state["scheduler"], path)
        restore(self.weighting, {**state["weighting"], "history": []}, path)
        self.state = {k: state[k] for k in self.state}

    def histories(self) -> dict[str, list[dict]]:
        return {"history.csv": self.rows, "weights.csv": self.weighting.history}

    def load_histories(self, histories: dict[str, list[dict]]) -> None:
        self.rows = list(histories["history.csv"])
        self.weighting.history = list(histories["weights.csv"])


def train_run(cfg: PinnConfig, out: str | Path, resume: bool = False, progress: bool = True,
              plot: bool = True, overwrite: bool = False) -> dict:
    """Train ``cfg`` in ``out`` (see the module doc) on ``cfg.threads`` torch and solver threads;
    returns the result (also result.json). The run directory follows the engine's rule: a run
    already in ``out`` is continued with ``resume`` (a finished one's result is returned as it
    is, or the run continued when ``epochs`` was raised), discarded with ``overwrite``, and
    otherwise never overwritten."""
    cfg.validate()
    return engine.run(PinnRun(cfg, out, plots=plot), resume=resume, overwrite=overwrite,
                      progress=progress)


def train_cell(cfg: PinnConfig, run_dir: str | Path, plot: bool = True) -> dict:
    """A study's cell: :func:`train_run` in ``run_dir``, continuing the run there if it holds
    one (an interrupted study resumes each cell from its checkpoint)."""
    cfg.validate()
    run = PinnRun(cfg, run_dir, plots=plot)
    return engine.run(run, resume=engine.RunDir(run).holds(), progress=runs_show_progress())


# ----------------------------------------------------------------------------- plots
def plot_run(problem: PinnProblem, model: torch.nn.Module, history: list[dict], out: Path,
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

    extras = problem.coefficients
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
