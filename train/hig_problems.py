"""The half-inverse gradients problems and their timed, resumable training runs
(``adjointsim hig``).

The problems (:data:`adjointsim.train.higs.PROBLEMS`, one file each) own their settings, data
sizes, default budgets and scenes; a run's ``scene`` config key (``[scene]``, ``--scene
KEY=VALUE``) overrides the scene's keys, checked by the solver and recorded whole in
``config.json``. A run is a problem of the run engine (:mod:`adjointsim.engine`): its
directory, checkpoint, history and ``--resume`` follow the engine's rule, and a finished run
continues to a larger ``budget`` or ``max_updates`` with ``--resume``.

Timing follows the reference: the wall-clock of a run is the summed time of its updates
(derivatives, SVD, apply); drawing batches and evaluating the test loss are excluded, and so is
one untimed warm-up update on a copy of the model (numba cache loading, torch.func's first
tracing). Each update is timed by the process's CPU time (``time.process_time``): for these
one-thread runs it equals the wall-clock on an idle core, and unlike the wall-clock it does not
count the time other jobs on a shared machine take the core away (measured here at a load
average of 8-13 on 2 cores). Test losses are evaluated at update times spaced by a factor 1.4
(and at the end).
"""

from __future__ import annotations

import contextlib
import copy
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from adjointsim import engine
from adjointsim.errors import UserError
from adjointsim.files import pyplot, save_figure
from adjointsim.run import SEEDS, Config, Interval, plot_history
from adjointsim.stepper import NonFiniteInputError, NonFiniteStateError

from .checkpoint import STORE, restore
from .compiled import BACKENDS, compiled
from .hig import HalfInverseGradients
from .higs import OPTIMIZERS, PROBLEMS, SIZES, Batch, HigProblem, make_problem
from .threads import use_threads

HISTORY_FIELDS = ("update", "wall_s", "train_loss", "test_loss")


@dataclass
class HigConfig(Config):
    """One run: ``problem`` trained by ``optimizer`` until ``budget`` seconds of update time
    (None: the problem's own budget) or ``max_updates`` updates are spent."""

    problem: str
    optimizer: str = "hig"
    seed: int = 0
    budget: float | None = None
    size: str = "full"
    max_updates: int | None = None
    #: torch's and the solver's threads (they take turns); more of them buy more updates
    #: within the budget
    threads: int = 1
    #: the solver's keywords over the problem's scene (dt, n, ...)
    scene: dict = field(default_factory=dict)
    #: Adam's loss eager (off) or through torch.compile with that backend
    #: (:mod:`adjointsim.train.compiled`); the same training, so a run may change it
    compile: str = "off"

    ACCEPTED: ClassVar[dict[str, tuple | Interval | str]] = {
        "problem": tuple(PROBLEMS.names()),
        "optimizer": OPTIMIZERS,
        "seed": SEEDS,
        # seconds of update time; unset, the problem's own budget
        "budget": Interval(0, lo_open=True),
        "size": SIZES,
        "max_updates": Interval(1),
        "threads": Interval(1),
        "scene": "the solver's keywords (dt, n, ...)",
        "compile": BACKENDS,
    }

    def check(self, where: str) -> None:
        """The problem's budget when none is given; the scene checked by the solver and
        recorded whole (the problem's defaults included)."""
        kind = PROBLEMS.get(self.problem)
        if self.compile != "off" and self.optimizer != "adam":
            raise UserError(f"config key 'compile'{where}: the {self.optimizer} update has no "
                            "loss to compile (its Jacobian comes from the solver's batched "
                            "adjoint, its step from a decomposition); choose compile = off, or "
                            "optimizer adam")
        if self.budget is None:
            self.budget = kind.BUDGET
        try:
            kind.build_solver(self.scene)
        except ValueError as e:
            raise UserError(f"config key 'scene'{where}: {e}") from None
        self.scene = {**kind.SCENE, **self.scene}


class HigRun(engine.Problem):
    """One ``adjointsim hig`` run: an update is one timed optimiser step, preceded by an
    evaluation of the test loss when the summed update time has passed the next mark (a
    factor 1.4 beyond the last); the final evaluation and the plot of the test loss."""

    RESUMABLE = ("threads", "compile")
    # a finished run is continued to more: its final evaluation is not a training step
    EXTENDABLE = ("budget", "max_updates")
    ADDED = ("scene",)
    HISTORIES: ClassVar = {"history.csv": HISTORY_FIELDS}
    RUN_FILES = ("loss.png",)
    RESULT_KEYS = {"wall_s": float, "updates": int, "test_loss": float, "diverged": bool}
    STORE = STORE
    UNIT = "s"

    def __init__(self, config: HigConfig, out: str | Path, plots: bool = True):
        super().__init__(config, out)
        self.plots = plots

    def describe(self) -> str:
        cfg = self.config
        return f"{cfg.problem}/{cfg.optimizer}/seed {cfg.seed}"

    def total(self) -> float:
        return self.config.budget

    def position(self) -> float:
        return self.state["wall"]

    def done(self) -> bool:
        cfg, state = self.config, self.state
        return (state["diverged"] or state["wall"] >= cfg.budget
                or (cfg.max_updates is not None and state["updates"] >= cfg.max_updates))

    def build(self) -> None:
        cfg = self.config
        use_threads(cfg.threads)
        torch.manual_seed(cfg.seed)
        self.problem = make_problem(cfg.problem, cfg.seed, cfg.size, cfg.scene)
        self.model = self.problem.model()
        self.opt = self.optimizer(self.model)
        self.loss = compiled(adam_loss, cfg.compile)
        self.gen = torch.Generator().manual_seed(cfg.seed + 1)
        self.state: dict[str, Any] = {"wall": 0.0, "updates": 0, "next_eval": 0.0,
                                      "losses": [], "diverged": False}
        self.rows: list[dict] = []
        self.warm = False

    def optimizer(self, model: torch.nn.Module) -> Any:
        """Adam, or half-inverse gradients (κ = ½) or Gauss-Newton (κ = 1) on ``model``."""
        cfg, problem = self.config, self.problem
        settings = problem.settings[cfg.optimizer]
        if cfg.optimizer == "adam":
            return torch.optim.Adam(model.parameters(), lr=settings["lr"])
        return HalfInverseGradients(
            model, problem.physics, problem.loss, lr=settings["lr"],
            kappa=0.5 if cfg.optimizer == "hig" else 1.0, tau=settings["tau"])

    def update(self) -> bool:
        """One timed update; a boundary when an evaluation preceded it."""
        state = self.state
        if not self.warm:
            self.warm_up()
            self.warm = True
        evaluated = state["wall"] >= state["next_eval"]
        if evaluated:
            self.evaluate()
        x, c, t = self.problem.sample(self.gen, int(self.problem.settings[
            self.config.optimizer]["batch"]))
        t0 = time.process_time()
        try:
            value = step(self.problem, self.model, self.opt, (x, c, t), self.loss)
        except (FloatingPointError, NonFiniteStateError, NonFiniteInputError):
            # The previous update sent the network where the physics blows up: it ends.
            state["diverged"] = True
            value = math.inf
        state["wall"] += time.process_time() - t0
        state["updates"] += 1
        if math.isfinite(value):
            state["losses"].append(value)
        else:  # the network already left the physics' finite range: it ends here too
            state["diverged"] = True
        return evaluated

    def warm_up(self) -> None:
        """One untimed update of a copy of the model on the first test samples: loading numba's
        cached kernels and torch.func's first tracing (seconds, once per process) stay out of
        the timed updates, for every optimizer alike."""
        twin = copy.deepcopy(self.model)
        batch = int(self.problem.settings[self.config.optimizer]["batch"])
        with contextlib.suppress(FloatingPointError, NonFiniteStateError, NonFiniteInputError):
            step(self.problem, twin, self.optimizer(twin),
                 tuple(a[:batch] for a in self.problem.test), self.loss)

    def row(self) -> dict:
        """The history row of now: the mean training loss since the last row, the test
        loss."""
        state = self.state
        train = float(np.mean(state["losses"])) if state["losses"] else math.nan
        return {"update": state["updates"], "wall_s": state["wall"], "train_loss": train,
                "test_loss": self.problem.test_loss(self.model)}

    def evaluate(self) -> None:
        self.rows.append(self.row())
        self.state["losses"] = []
        self.state["next_eval"] = max(0.02, 1.4 * self.state["wall"])

    def postfix(self) -> dict[str, Any]:
        return {"test": f"{self.rows[-1]['test_loss']:.3g}"} if self.rows else {}

    def finish(self) -> dict:
        # The final row leaves the training state as it is, so that a run continued to a
        # larger budget goes on as if it had not stopped; an evaluation at the top of an
        # update is always followed by that update, so a row at the last update is this one.
        if not self.rows or self.rows[-1]["update"] != self.state["updates"]:
            self.rows.append(self.row())
        final = self.rows[-1]
        return {"wall_s": self.state["wall"], "updates": self.state["updates"],
                "test_loss": engine.finite_or_none(final["test_loss"]),
                "diverged": self.state["diverged"]}

    def extend(self, recorded: dict) -> None:
        if self.rows and self.rows[-1]["update"] == self.state["updates"]:
            self.rows.pop()

    def plot(self) -> None:
        if self.plots:
            cfg = self.config
            plot_test_losses(self.out / "loss.png", {cfg.optimizer: self.rows},
                             f"{cfg.problem}, seed {cfg.seed}")

    def state_dict(self) -> dict:
        adam = self.config.optimizer == "adam"
        return {"model": self.model.state_dict(),
                "optimizer": self.opt.state_dict() if adam else None,
                "generator": self.gen.get_state(), "data": self.problem.state_dict(),
                **self.state}

    def load_state_dict(self, state: dict) -> None:
        path = self.out / engine.CHECKPOINT
        restore(self.model, state["model"], path)
        if self.config.optimizer == "adam":
            restore(self.opt, state["optimizer"], path)
        self.gen.set_state(state["generator"])
        self.problem.load_state_dict(state["data"])
        self.state = {k: state[k] for k in self.state}

    def histories(self) -> dict[str, list[dict]]:
        return {"history.csv": self.rows}

    def load_histories(self, histories: dict[str, list[dict]]) -> None:
        self.rows = list(histories["history.csv"])


def train_run(cfg: HigConfig, out: str | Path, resume: bool = False, overwrite: bool = False,
              progress: bool = True, plot: bool = True) -> dict:
    """Train ``cfg.problem`` with ``cfg.optimizer`` for ``cfg.budget`` seconds of update time
    in ``out``: ``history.csv``, ``loss.png`` (if ``plot``), ``result.json`` when finished,
    ``checkpoint.pt`` to resume from. The directory follows the engine's rule: a run already in
    ``out`` is continued with ``resume`` (a finished one's result is returned as it is, or
    continued to a larger budget or max_updates), discarded with ``overwrite``, and otherwise
    refused."""
    cfg.validate()
    return engine.run(HigRun(cfg, out, plots=plot), resume=resume, overwrite=overwrite,
                      progress=progress)


def adam_loss(problem: HigProblem, model: torch.nn.Module, x: torch.Tensor, c: torch.Tensor,
              t: torch.Tensor) -> torch.Tensor:
    """The batch's mean loss through the physics, which Adam's update backpropagates."""
    return problem.loss(problem.physics(model(x), c), t).mean()


def step(problem: HigProblem, model: torch.nn.Module, opt: Any, batch: Batch,
         loss_fn: Callable[..., torch.Tensor] = adam_loss) -> float:
    """One update of ``model`` by ``opt``; returns the batch's mean loss before it. Adam's
    loss is ``loss_fn`` (:func:`adam_loss`, or it compiled)."""
    if isinstance(opt, HalfInverseGradients):
        return opt.step(*batch)
    x, c, t = batch
    opt.zero_grad()
    loss = loss_fn(problem, model, x, c, t)
    loss.backward()
    opt.step()
    return float(loss.detach())


def loss_at(history: list[dict], mark: float) -> float:
    """The test loss of the last evaluation at or before ``mark`` seconds (inf before any)."""
    value = math.inf
    for row in history:
        if row["wall_s"] <= mark and not math.isnan(row["test_loss"]):
            value = row["test_loss"]
    return value


def plot_test_losses(path: Path, curves: dict[str, list[dict]], title: str,
                     ax: Any = None) -> None:
    """Test loss against the wall-clock of the updates (log-log), one curve per label; saved to
    ``path`` unless drawn into ``ax``."""
    fig = None
    if ax is None:
        fig, ax = pyplot().subplots(figsize=(5, 3.5))
    timed = {label: [r for r in rows if r["wall_s"] > 0] for label, rows in curves.items()}
    plot_history(path, timed, "wall_s", "test_loss", "wall-clock of the updates (s)",
                 "test loss", title, ax=ax)
    ax.set_xscale("log")
    if fig is not None:
        save_figure(fig, path, dpi=120)
