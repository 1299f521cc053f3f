"""Controllers trained through simulators with the gradient-flow modes of stabilised BPTT.

A controller network N reads the state and outputs a control, the simulator advances one step
(``adjointsim.train.bridge.step``: the solver's compiled step forward, its hand-written adjoint
backward), and the loss judges the trajectory (Schnell & Thuerey 2024):

    c_t = N(flow.net(x_t); θ),   x_{t+1} = S(flow.phys(x_t), c_t),

where ``flow`` (:class:`adjointsim.train.unroll.GradientFlow`) decides where gradients stop
(R, M, S, N, C). The tasks register themselves in :mod:`adjointsim.train.tasks`, one file
each (the paper's ``cartpole``, ``guidance`` and ``quantum``, and ``heat``); a run takes the
task's level (``level``, on the command line the task's own flag: ``--poles``,
``--control-weight``, ``--target``, ``--wavenumber``) and its scene (``scene``: the solver's
keywords over the task's, checked by the solver).

Training: Adam, 256 training and 256 test initial states, batch 8, the last layer of every
controller zero-initialised (c = 0 at the start, as in the reference runs). A loss of several
terms may be balanced by a scheme of :mod:`adjointsim.train.weighting` (``weighting``; the
default ``uniform`` trains the task's loss as it is). A scheme that weighs refreshes its λ
from the terms' gradients through the loop (one batched reverse pass, with the flow's stops
in place) and the flow takes the gradient of Σ_k λ_k L_k; ``pcgrad`` and ``config`` combine
the terms' gradients themselves, so they go with the flows that are one plain reverse pass
(R, M, S, N) and C is refused for every scheme that reads gradients. Where a scheme reads
gradients, the epoch's first update does not diagnose cos(g_M, g_R) (its doubled batch would
change the gradients the scheme reads).

A run is a :class:`Controller` on the run engine (:mod:`adjointsim.engine`): its directory
holds ``config.json``, ``checkpoint.pt`` (every epoch, and on Ctrl-C between two updates),
``history.csv`` (per epoch: mean minibatch loss, full training and test loss, update norm,
cos(g_M, g_R) on the epoch's first minibatch, seconds), ``result.json`` (``diverged`` when the
final test loss is not finite) and the plots ``test_loss.png`` and ``rollout.png`` (the task's
own; none for a diverged run). A resumed run ends with the weights of an uninterrupted one,
and a finished one may be continued to more epochs.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

from adjointsim import engine
from adjointsim.errors import DamagedFileError, UserError
from adjointsim.files import pyplot, save_figure
from adjointsim.run import SEEDS, Config, Interval, check_memory, plot_history
from adjointsim.stepper import NonFiniteInputError, NonFiniteStateError

from . import bridge
from .checkpoint import STORE, restore
from .compiled import BACKENDS, DOUBLED_ERROR, compiled
from .tasks import TASKS, Task, get_task
from .threads import use_threads
from .unroll import CLIPS, FLOWS, GradientFlow, Update, clip_update
from .weighting import ALIASES, GENERIC, SCHEMES, Weighting, canonical_rule

DTYPES = {"float32": torch.float32, "float64": torch.float64}


# ----------------------------------------------------------------------------- the loop
def closed_loop(
    task: Task,
    net: nn.Module,
    x0: torch.Tensor,
    flow: GradientFlow | None = None,
    keep: bool = False,
    terms: bool = False,
) -> tuple[torch.Tensor | dict[str, torch.Tensor], list[torch.Tensor] | None]:
    """Run the controller through the simulator; returns the loss (with ``terms``: each of
    the task's terms, a dict) and (if ``keep``) the states x_0..x_n and controls. One solver
    call per step through ``adjointsim.train.bridge.step``."""
    flow = flow or GradientFlow("R")
    x = flow.start(x0)
    parts: list = []
    states, controls = ([x0], []) if keep else (None, None)
    for t in range(task.steps):
        c = task.control(flow.control(net, flow.net(x)))
        x = bridge.step(task.solver, flow.phys(x), c)
        part = task.step_terms(x, c, t) if terms else task.step_loss(x, c, t)
        if part is not None:
            parts.append(part)
        if keep:
            states.append(x.detach())
            controls.append(c.detach())
    loss = ({n: task.total([p[n] for p in parts]) for n in task.terms} if terms
            else task.total(parts))
    return loss, (states, controls) if keep else None


@torch.no_grad()
def evaluate(task: Task, net: nn.Module, x0: torch.Tensor, terms: bool = False
             ) -> float | dict[str, float]:
    """Mean loss over the initial states ``x0`` (all at once, no tape); with ``terms``, each of
    the task's terms."""
    try:
        loss = closed_loop(task, net, x0, terms=terms)[0]
    except (NonFiniteStateError, NonFiniteInputError, FloatingPointError):
        return dict.fromkeys(task.terms, float("nan")) if terms else float("nan")
    return {n: float(v) for n, v in loss.items()} if terms else float(loss)


# ----------------------------------------------------------------------------- config
#: the longest run accepted, in training rollouts (epochs × train): 400 times the paper's runs
#: of 1000 epochs of 256 initial states, months of computing
MAX_ROLLOUTS = 10**8


@dataclass
class ControlConfig(Config):
    task: str = "cartpole"
    mode: str = "C"
    clip: str = "none"
    #: the task's complexity level (None: its easiest), one of its ``levels``
    level: float | None = None
    #: the solver's keywords over the task's scene (dt, grid, coefficients)
    scene: dict = field(default_factory=dict)
    seed: int = 0
    epochs: int = 100
    lr: float = 1e-3
    train: int = 256
    test: int = 256
    batch: int = 8
    dtype: str = "float32"
    #: how the loss's terms are balanced (a task of one term takes uniform only)
    weighting: str = "uniform"
    out: str = "runs/control"
    threads: int = 1
    #: the closed loop's loss eager (off) or through torch.compile with that backend
    #: (:mod:`adjointsim.train.compiled`); the same training, so a run may change it
    compile: str = "off"

    ACCEPTED: ClassVar[dict[str, tuple | Interval | str]] = {
        "task": tuple(TASKS.names()),
        "mode": FLOWS,
        "clip": CLIPS,
        "level": "one of the task's levels",
        "scene": "the solver's keywords (dt, ...)",
        "seed": SEEDS,
        "epochs": Interval(1),
        "lr": Interval(0, lo_open=True),
        "train": Interval(1),
        "test": Interval(1),
        "batch": Interval(1),
        "dtype": tuple(DTYPES),
        "weighting": (*GENERIC, *(a for a, n in ALIASES.items() if n in GENERIC)),
        "out": "a non-empty path",
        "threads": Interval(1),
        "compile": BACKENDS,
    }

    def check(self, where: str) -> None:
        """The level is one of the task's (as the task spells it; None: the easiest), the
        scene one its solver accepts (recorded whole, the task's defaults included), the
        weighting one the task and mode take (recorded under its own name); a batch fits in
        the training states; the run fits in memory and in a lifetime (refused before
        anything is drawn)."""
        cls = TASKS.get(self.task)
        try:
            self.level = cls.level_of(self.level)
        except ValueError as e:
            raise UserError(f"config key 'level'{where}: {e}") from None
        self.weighting = canonical_rule(self.weighting)
        if self.weighting != "uniform" and len(cls.terms) < 2:
            raise UserError(f"config key 'weighting'{where}: the {self.task} task's loss has "
                            "one term; only uniform applies")
        if self.mode == "C" and SCHEMES[self.weighting].needs == "grads":
            others = [n for n in GENERIC if SCHEMES[n].needs != "grads"]
            raise UserError(f"config key 'weighting'{where}: {self.weighting} reads the terms' "
                            "gradients, which mode C's doubled batch does not give; choose "
                            f"mode R, M, S or N, or one of {', '.join(others)}")
        if self.compile != "off" and self.mode == "C":
            raise UserError(f"config key 'compile'{where}: {DOUBLED_ERROR}")
        if self.batch > self.train:
            raise UserError(f"config key 'batch'{where}: {self.batch} exceeds train "
                            f"({self.train}), the initial states it is drawn from")
        try:
            task = get_task(self.task, self.level, self.scene)
        except ValueError as e:
            raise UserError(f"config key 'scene'{where}: {e}") from None
        self.scene = dict(task.scene)
        need = task.memory(self.train, self.test, self.batch, DTYPES[self.dtype].itemsize)
        check_memory(need, f"config keys 'train', 'test' and 'batch'{where}: {self.train} "
                     f"training and {self.test} test initial states in batches of "
                     f"{self.batch} (the states, a rollout over all of them at once, an "
                     "update's tape)", "use fewer")
        if self.epochs * self.train > MAX_ROLLOUTS:
            raise UserError(f"config keys 'epochs' and 'train'{where}: {self.epochs} × "
                            f"{self.train} = {self.epochs * self.train:.3g} training rollouts "
                            f"of {task.steps} steps, more than the {MAX_ROLLOUTS:.0e} accepted "
                            "(the paper's runs take 2.6e+05); use fewer")

    def make_task(self) -> Task:
        """The configured task at its level, in its scene."""
        return get_task(self.task, self.level, self.scene)


# ----------------------------------------------------------------------------- one run
HISTORY_KEYS = ("epoch", "batch_loss", "train_loss", "test_loss", "update_norm", "cos_mr",
                "skipped", "seconds")


def initial_states(cfg: ControlConfig, task: Task) -> tuple[torch.Tensor, torch.Tensor]:
    """Training and test initial states, drawn from the seed (two independent streams)."""
    dtype = DTYPES[cfg.dtype]
    tr = task.initial_states(np.random.default_rng([cfg.seed, 0]), cfg.train)
    te = task.initial_states(np.random.default_rng([cfg.seed, 1]), cfg.test)
    return torch.from_numpy(tr).to(dtype), torch.from_numpy(te).to(dtype)


def build_net(cfg: ControlConfig, task: Task) -> nn.Module:
    torch.manual_seed(cfg.seed)
    return task.net().to(DTYPES[cfg.dtype])


def fresh_epoch() -> dict:
    """An epoch's progress before its first update."""
    return {"step": 0, "losses": [], "norms": [], "cos": float("nan"), "skipped": 0,
            "seconds": 0.0}


def record(state: dict, loss: float, update: Update, first: bool) -> None:
    """An update's loss and norm (and on the epoch's first update, the diagnosed cos(g_M, g_R))
    in the epoch's progress ``state``."""
    state["losses"].append(loss)
    state["norms"].append(update.norm())
    if first:
        state["cos"] = update.cosine()


def minibatch_update(cfg: ControlConfig, task: Task, net: nn.Module, opt: torch.optim.Optimizer,
                     params: list[torch.Tensor], x0: torch.Tensor, state: dict,
                     weighting: Weighting | None = None, step: int = 0,
                     loop: Callable[..., tuple] | None = None) -> None:
    """One minibatch's update (the run's ``step``-th), recorded in the epoch's progress
    (``state``); ``weighting`` balances the task's terms (None: its loss as it is); ``loop``
    runs the closed loop (:func:`closed_loop`, or it compiled; a doubled batch, the epoch's
    diagnosis, runs eager: its leaves break the graph at every step). An update whose rollout
    or gradient is not finite is skipped and counted."""
    reads = weighting is not None and weighting.scheme.needs == "grads"
    first = state["step"] == 0 and not reads
    flow = GradientFlow(cfg.mode, cfg.clip, diagnose=first)
    try:
        run = loop if loop is not None and not flow.doubled else closed_loop
        loss = run(task, net, x0, flow, terms=weighting is not None)[0]
    except (NonFiniteStateError, NonFiniteInputError):
        state["skipped"] += 1  # the simulator blew up under this controller: skip the update
        return
    if weighting is None:
        update = flow.backward(loss, params)
    elif weighting.scheme.direction:
        for p in params:
            p.grad = None
        loss = weighting.backward(loss, params, step)
        update = Update(clip_update([p.grad for p in params], cfg.clip))
        for p, g in zip(params, update.grads):
            p.grad = g
    else:
        loss = weighting.weigh(loss, params, step)
        update = flow.backward(loss, params)
    if not (math.isfinite(float(loss.detach())) and math.isfinite(update.norm())):
        state["skipped"] += 1
        return
    opt.step()
    record(state, float(loss.detach()), update, first)


class Controller(engine.Problem):
    """One controller's run: build (task, initial states, net, Adam, weighting), one
    minibatch update at a time (the last of an epoch evaluates the full training and test
    loss: a checkpoint's boundary), the history, the result and the plots. An ensemble
    (:mod:`adjointsim.train.ensemble`) steps several through :meth:`batch`, :meth:`advance` and
    :meth:`end_epoch`, as :meth:`update` does for one."""

    RESUMABLE = ("out", "threads", "compile")
    EXTENDABLE = ("epochs",)
    ADDED = ("level", "scene")
    RETIRED = ("poles", "target", "control_weight")
    HISTORIES = {"history.csv": HISTORY_KEYS}
    RUN_FILES = ("test_loss.png", "rollout.png")
    RESULT_KEYS = {"test_loss": float, "train_loss": float, "test_terms": dict,
                   "weights": (dict, type(None)), "parameters": int, "seconds": float,
                   "diverged": bool}
    UNIT = "epoch"
    STORE = STORE

    def __init__(self, config: ControlConfig):
        super().__init__(config, config.out)
        self.per_epoch = config.train // config.batch

    def describe(self) -> str:
        return f"{self.config.task} {self.config.mode}"

    def total(self) -> float:
        return self.config.epochs

    def position(self) -> float:
        return self.state["epoch"] + self.state["step"] / self.per_epoch

    def build(self) -> None:
        cfg = self.config
        self.task = cfg.make_task()
        self.x_train, self.x_test = initial_states(cfg, self.task)
        self.net = build_net(cfg, self.task)
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=cfg.lr)
        self.params = list(self.net.parameters())
        self.loop = compiled(closed_loop, cfg.compile)
        # max/avg keeps one term's weight at 1: the PINNs' PDE residual, here the objective the
        # controller exists for (the task's first term); ID takes the largest spread as reference
        reference = self.task.terms[0] if cfg.weighting == "max-avg" else None
        self.weighting = None if cfg.weighting == "uniform" else Weighting(
            self.task.terms, cfg.weighting, reference=reference, seed=cfg.seed)
        # the epoch's progress too, so that Ctrl-C between two updates resumes where it stopped
        self.state = {"epoch": 0, **fresh_epoch()}
        self.history: list[dict] = []
        self._order: tuple[int, torch.Tensor] | None = None

    def batch(self) -> torch.Tensor:
        """The next minibatch of training initial states, in the epoch's order (drawn from the
        seed and the epoch)."""
        epoch, i, size = self.state["epoch"], self.state["step"], self.config.batch
        if self._order is None or self._order[0] != epoch:
            seed = int(np.random.SeedSequence([self.config.seed, epoch]).generate_state(1)[0])
            order = torch.randperm(self.config.train,
                                   generator=torch.Generator().manual_seed(seed))
            self._order = (epoch, order)
        return self.x_train[self._order[1][i * size:(i + 1) * size]]

    def update(self) -> bool:
        start = time.perf_counter()
        minibatch_update(self.config, self.task, self.net, self.optimizer, self.params,
                         self.batch(), self.state, self.weighting,
                         self.state["epoch"] * self.per_epoch + self.state["step"], self.loop)
        if not self.advance(time.perf_counter() - start):
            return False
        self.end_epoch()
        return True

    def advance(self, seconds: float) -> bool:
        """Count an update that took ``seconds``; whether it was the epoch's last (then
        :meth:`end_epoch` is due)."""
        self.state["step"] += 1
        self.state["seconds"] += seconds
        return self.state["step"] == self.per_epoch

    def end_epoch(self, losses: tuple[float, float] | None = None, seconds: float = 0.0
                  ) -> None:
        """The epoch's history row, with the full training and test losses (evaluated here
        unless ``losses`` gives them, taken in ``seconds``); the next epoch begins."""
        start = time.perf_counter()
        s = self.state
        s["seconds"] += seconds
        train, test = losses or (evaluate(self.task, self.net, self.x_train),
                                 evaluate(self.task, self.net, self.x_test))
        self.history.append({
            "epoch": s["epoch"] + 1,
            "batch_loss": float(np.mean(s["losses"])) if s["losses"] else float("nan"),
            "train_loss": train,
            "test_loss": test,
            "update_norm": float(np.mean(s["norms"])) if s["norms"] else float("nan"),
            "cos_mr": s["cos"],
            "skipped": s["skipped"],
            "seconds": s["seconds"] + time.perf_counter() - start,
        })
        self.state = {"epoch": s["epoch"] + 1, **fresh_epoch()}

    def postfix(self) -> dict[str, Any]:
        return {"test": f"{self.history[-1]['test_loss']:.3e}"} if self.history else {}

    def state_dict(self) -> dict:
        return {**self.state, "net": self.net.state_dict(),
                "optimizer": self.optimizer.state_dict(),
                **({} if self.weighting is None else {"weighting": self.weighting.state_dict()})}

    def load_state_dict(self, state: dict) -> None:
        path = self.out / engine.CHECKPOINT
        state = dict(state)
        wanted = ("net", "optimizer", *(() if self.weighting is None else ("weighting",)))
        missing = [k for k in wanted if k not in state]
        if missing:
            raise DamagedFileError(f"{path} holds no controller's {', '.join(missing)}; delete "
                                   "it, or start the run again with --overwrite")
        restore(self.net, state.pop("net"), path)
        restore(self.optimizer, state.pop("optimizer"), path)
        if self.weighting is not None:
            restore(self.weighting, state.pop("weighting"), path)
        self.state = {**self.state, **state}

    def histories(self) -> dict[str, list[dict]]:
        return {"history.csv": self.history}

    def load_histories(self, histories: dict[str, list[dict]]) -> None:
        self.history = list(histories["history.csv"])

    @property
    def diverged(self) -> bool:
        """Whether the final test loss is not finite (the controller blew the simulator up)."""
        return not math.isfinite(self.history[-1]["test_loss"])

    def finish(self) -> dict:
        """The final losses, the test loss's terms, the weights, the size and time, whether
        the run diverged, and the level under the task's own name (``poles``: 4)."""
        last = self.history[-1]
        return {"test_loss": last["test_loss"], "train_loss": last["train_loss"],
                "test_terms": evaluate(self.task, self.net, self.x_test, terms=True),
                "weights": None if self.weighting is None else dict(self.weighting.weights),
                "parameters": sum(p.numel() for p in self.net.parameters()),
                "seconds": float(sum(h["seconds"] for h in self.history)),
                "diverged": self.diverged, self.task.key: self.task.level}

    def plot(self) -> None:
        """``test_loss.png``, and ``rollout.png`` unless the run diverged (its rollout is not
        finite: an earlier run's is removed)."""
        cfg = self.config
        title = f"{cfg.task}, {self.task.key.replace('_', ' ')} {cfg.level}, mode {cfg.mode}"
        plot_history(self.out / "test_loss.png", {cfg.mode: self.history}, "epoch",
                     "test_loss", "epoch", "test loss", title=title, smooth=30)
        if self.diverged:
            (self.out / "rollout.png").unlink(missing_ok=True)
        else:
            plot_rollout(self.task, self.net, self.x_test[:1], self.out / "rollout.png", title)


def train_controller(cfg: ControlConfig, resume: bool = False, progress: bool = True,
                     overwrite: bool = False) -> dict:
    """Train a controller as configured; returns the result (also in ``cfg.out``).

    A ``cfg.out`` holding a run is refused unless ``resume`` (continue it, to more epochs too)
    or ``overwrite`` (discard it and start again) is given; ``resume`` where ``cfg.out`` holds
    no run is refused too (a study's cell passes ``resume=engine.started(cfg.out)``). Ctrl-C
    saves a checkpoint between two updates and re-raises.
    """
    cfg.validate()
    use_threads(cfg.threads)
    return engine.run(Controller(cfg), resume=resume, overwrite=overwrite, progress=progress)


# ----------------------------------------------------------------------------- plots
@torch.no_grad()
def plot_rollout(task: Task, net: nn.Module, x0: torch.Tensor, path: Path,
                 title: str = "") -> None:
    """One controlled rollout from ``x0`` (one state), drawn by the task."""
    plt = pyplot()
    _, (states, _) = closed_loop(task, net, x0, keep=True)
    xs = torch.stack(states)[:, 0].numpy()  # (n + 1, C, *grid)
    fig, ax = plt.subplots(figsize=(6, 4))
    task.draw(fig, ax, xs, np.arange(len(xs)) * task.solver.dt)
    ax.set_title(title, fontsize=9)
    save_figure(fig, path, dpi=110)
