"""Controllers trained through simulators with the gradient-flow modes of stabilised BPTT.

A controller network N reads the state and outputs a control, the simulator advances one step
(``adjointsim.train.bridge.step``: the solver's compiled step forward, its hand-written adjoint
backward), and the loss judges the trajectory (Schnell & Thuerey 2024):

    c_t = N(flow.net(x_t); θ),   x_{t+1} = S(flow.phys(x_t), c_t),

where ``flow`` (:class:`adjointsim.train.unroll.GradientFlow`) decides where gradients stop
(R, M, S, N, C). The three tasks of the paper, with the note's constants:

* ``cartpole``: 1–4 poles (``--poles``), 100 steps of Δt = 0.01, loss 1 − mean_i cos θ_i at
  the last step (swing-up from hanging);
* ``guidance``: 2 drivers herd 4 evaders, 60 steps of Δt = 4/60, loss the mean over steps of
  mean_e |x_e|² + r_c mean(c²) (``--control-weight`` r_c ∈ {1, 0.1, 0.01, 0.001}): two terms,
  ``tracking`` and ``control`` (r_c included), that ``--weighting`` may balance;
* ``quantum``: ``schrodinger1d-cn`` with m = 1/2, 32 interior points, Δt = 0.0625, 128 steps,
  loss Σ_t (1 − |⟨ψ_n|ψ_t⟩|²) towards eigenstate n (``--target`` 3..5).

Training: Adam, 256 training and 256 test initial states, batch 8, the last layer of every
controller zero-initialised (c = 0 at the start, as in the reference runs). A loss of several
terms may be balanced by a scheme of :mod:`adjointsim.train.weighting` (``weighting``; the
default ``uniform`` trains the task's loss as it is). A scheme that weighs refreshes its λ
from the terms' gradients through the loop (one batched reverse pass, with the flow's stops
in place) and the flow takes the gradient of Σ_k λ_k L_k; ``pcgrad`` and ``config`` combine
the terms' gradients themselves, so they go with the flows that are one plain reverse pass
(R, M, S, N) and C is refused for every scheme that reads gradients. Where a scheme reads
gradients, the epoch's first update does not diagnose cos(g_M, g_R) (its doubled batch would
change the gradients the scheme reads). A run directory
holds ``config.json``, ``checkpoint.pt`` (atomic, every epoch, and on Ctrl-C between two
updates), ``history.csv`` (per epoch: mean minibatch loss, full training and test loss, update
norm, cos(g_M, g_R) on the epoch's first minibatch, seconds), ``result.json`` and the plots
``test_loss.png`` and ``rollout.png``. A resumed run ends with the weights of an uninterrupted
one, and may be continued to more epochs.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn
from tqdm.auto import tqdm

import adjointsim
from adjointsim.errors import RunExists, UserError
from adjointsim.files import pyplot, save_figure, uninterrupted, write_json
from adjointsim.nets.mlp import MLP
from adjointsim.run import (
    SEEDS,
    Config,
    Interval,
    check_memory,
    differing,
    discard,
    holds_run,
    plot_history,
    read_result,
    refuse_foreign,
    write_history,
)
from adjointsim.stepper import NonFiniteInputError, NonFiniteStateError

from . import bridge
from .checkpoint import load_checkpoint, restore, save_checkpoint
from .threads import use_threads
from .unroll import CLIPS, FLOWS, GradientFlow, Update, clip_update
from .weighting import GENERIC, SCHEMES, Weighting

DTYPES = {"float32": torch.float32, "float64": torch.float64}


# ----------------------------------------------------------------------------- tasks
class Task:
    """One control problem at one complexity level: scene, initial states, net, loss."""

    name: str
    knob: str  # the complexity option's config key
    levels: tuple  # accepted values, easiest first
    steps: int
    #: values per state in the controller's widest layer (for the memory estimate)
    widest = 100
    #: the loss's named terms, which a weighting may balance (see :meth:`step_terms`)
    terms: tuple[str, ...] = ("loss",)

    def __init__(self, level: Any):
        if level not in self.levels:
            raise ValueError(
                f"{self.name}: {self.knob.replace('_', '-')} must be one of "
                f"{', '.join(map(str, self.levels))}, not {level!r}"
            )
        self.level = level

    def initial_states(self, rng: np.random.Generator, count: int) -> np.ndarray:
        return self.solver.random_state(rng, count)

    def control(self, out: torch.Tensor) -> torch.Tensor:
        """Network output (B, k) to the solver's control (B, *control_shape)."""
        shape = self.solver.control_shape
        if out.ndim < 1 or out[0].numel() != int(np.prod(shape)):
            raise ValueError(
                f"{self.name}: the controller's output has shape {tuple(out.shape)}; expected "
                f"(batch, {int(np.prod(shape))}), one control {shape} per batch element"
            )
        return out.reshape(out.shape[0], *shape)

    def net(self) -> nn.Module:
        size = int(np.prod(self.solver.state_shape(1)))
        return _zero_last(nn.Sequential(
            nn.Flatten(), MLP(size, int(np.prod(self.solver.control_shape)), width=100, depth=2),
        ))

    def memory(self, train: int, test: int, batch: int, itemsize: int) -> int:
        """Bytes a run needs, about: the initial states (drawn in float64), then the larger of
        a rollout over all of them at once (no tape) and one update's tape (C's doubled
        batch). The factors are measured with the paper's controllers, rounded up."""
        size = int(np.prod(self.solver.state_shape(1)))
        states = (train + test) * size * (8 + itemsize)
        rollout = max(train, test) * (4 * self.widest * itemsize + 64 * size)
        tape = batch * self.steps * 8 * self.widest * itemsize
        return states + max(rollout, tape)

    def step_loss(self, x: torch.Tensor, c: torch.Tensor, t: int) -> torch.Tensor | None:
        """Loss term of the state x_{t+1} reached with control c_t (None: no term)."""
        raise NotImplementedError

    def step_terms(self, x: torch.Tensor, c: torch.Tensor, t: int
                   ) -> dict[str, torch.Tensor] | None:
        """The loss's terms of the state x_{t+1} reached with control c_t, one per name of
        :attr:`terms`, summing to :meth:`step_loss` (None: no term)."""
        term = self.step_loss(x, c, t)
        return None if term is None else {"loss": term}

    def total(self, terms: list[torch.Tensor]) -> torch.Tensor:
        return torch.stack(terms).sum()


class CartPoleTask(Task):
    name, knob, levels, steps = "cartpole", "poles", (1, 2, 3, 4), 100

    def __init__(self, level: Any = 1):
        super().__init__(level)
        self.solver = adjointsim.get("cartpole")(poles=level)

    def step_loss(self, x, c, t):
        if t < self.steps - 1:
            return None
        return (1.0 - torch.cos(x[:, 0, 1:]).mean(dim=1)).mean()


class GuidanceTask(Task):
    name, knob, levels, steps = "guidance", "control_weight", (1.0, 0.1, 0.01, 0.001), 60

    def __init__(self, level: Any = 1.0):
        super().__init__(float(level) if isinstance(level, int | float) else level)
        self.solver = adjointsim.get("guidance")(drivers=2, evaders=4, dt=4.0 / self.steps)

    terms = ("tracking", "control")

    def _costs(self, x: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """mean_e |x_e|² and mean(c²)."""
        return (x[:, :2, self.solver.drivers:] ** 2).sum(dim=1).mean(), (c**2).mean()

    def step_loss(self, x, c, t):
        track, effort = self._costs(x, c)
        return (track + self.level * effort) / self.steps

    def step_terms(self, x, c, t):
        track, effort = self._costs(x, c)
        return {"tracking": track / self.steps, "control": self.level * effort / self.steps}


class QuantumTask(Task):
    name, knob, levels, steps = "quantum", "target", (3, 4, 5), 128
    widest = 60 * 16  # the first convolution's channels × points

    def __init__(self, level: Any = 3):
        super().__init__(level)
        self.solver = adjointsim.get("schrodinger1d-cn")(n=32, length=2.0, dt=0.0625, mass=0.5)
        j = np.arange(1, 33)
        self.eigen = [np.sin(k * np.pi * j / 33) for k in range(1, 6)]
        self._target = None

    def initial_states(self, rng, count):
        """(c1 e^{i p1} ψ1 + c2 e^{i p2} ψ2)/norm, c ~ N(0, 1), p ~ U(0, 2π)."""
        c = rng.standard_normal((count, 2))
        p = rng.uniform(0.0, 2.0 * np.pi, (count, 2))
        psi = (c[:, :1] * np.exp(1j * p[:, :1]) * self.eigen[0]
               + c[:, 1:] * np.exp(1j * p[:, 1:]) * self.eigen[1])
        psi /= np.sqrt(self.solver.h * np.sum(np.abs(psi) ** 2, axis=1, keepdims=True))
        return np.stack([psi.real, psi.imag], axis=1)

    def net(self):
        return _zero_last(nn.Sequential(
            nn.Conv1d(2, 60, 3, stride=2, padding=1), nn.Tanh(),
            nn.Conv1d(60, 60, 3, stride=2, padding=1), nn.Tanh(),
            nn.Flatten(), nn.Linear(60 * 8, 1),
        ))

    def step_loss(self, x, c, t):
        if self._target is None or self._target.dtype != x.dtype:
            self._target = torch.tensor(self.eigen[self.level - 1], dtype=x.dtype)
        # ⟨ψ_n|ψ⟩ = h Σ ψ_n ψ (ψ_n real, both normalised as h Σ|ψ|² = 1)
        overlap = self.solver.h * (x @ self._target)  # (B, 2): real and imaginary part
        return (1.0 - (overlap**2).sum(dim=1)).mean()


TASKS: dict[str, type[Task]] = {t.name: t for t in (CartPoleTask, GuidanceTask, QuantumTask)}


def get_task(name: str, level: Any = None) -> Task:
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; choose from {', '.join(TASKS)}")
    cls = TASKS[name]
    return cls() if level is None else cls(level)


def _zero_last(net: nn.Sequential) -> nn.Sequential:
    last = [m for m in net.modules() if isinstance(m, nn.Linear)][-1]
    nn.init.zeros_(last.weight)
    nn.init.zeros_(last.bias)
    return net


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
    #: complexity: poles (cartpole), target (quantum), control_weight (guidance)
    poles: int = 1
    target: int = 3
    control_weight: float = 1.0
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

    ACCEPTED: ClassVar[dict[str, tuple | Interval | str]] = {
        "task": tuple(TASKS),
        "mode": FLOWS,
        "clip": CLIPS,
        **{cls.knob: cls.levels for cls in TASKS.values()},
        "seed": SEEDS,
        "epochs": Interval(1),
        "lr": Interval(0, lo_open=True),
        "train": Interval(1),
        "test": Interval(1),
        "batch": Interval(1),
        "dtype": tuple(DTYPES),
        "weighting": GENERIC,
        "out": "a non-empty path",
        "threads": Interval(1),
    }

    @property
    def level(self) -> Any:
        return getattr(self, TASKS[self.task].knob)

    def check(self, where: str) -> None:
        """Only the task's own level knob may leave its default; a batch fits in the training
        states; the run fits in memory and in a lifetime (refused before anything is drawn)."""
        defaults = {f.name: f.default for f in dataclasses.fields(self)}
        for name, cls in TASKS.items():
            if name != self.task and getattr(self, cls.knob) != defaults[cls.knob]:
                raise UserError(f"config key {cls.knob!r}{where}: applies to the {name} task, "
                                f"not {self.task}")
        if self.weighting != "uniform" and len(TASKS[self.task].terms) < 2:
            raise UserError(f"config key 'weighting'{where}: the {self.task} task's loss has "
                            "one term; only uniform applies")
        if self.mode == "C" and SCHEMES[self.weighting].needs == "grads":
            others = [n for n in GENERIC if SCHEMES[n].needs != "grads"]
            raise UserError(f"config key 'weighting'{where}: {self.weighting} reads the terms' "
                            "gradients, which mode C's doubled batch does not give; choose "
                            f"mode R, M, S or N, or one of {', '.join(others)}")
        if self.batch > self.train:
            raise UserError(f"config key 'batch'{where}: {self.batch} exceeds train "
                            f"({self.train}), the initial states it is drawn from")
        task = get_task(self.task, self.level)
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


# ----------------------------------------------------------------------------- training
HISTORY_KEYS = ("epoch", "batch_loss", "train_loss", "test_loss", "update_norm", "cos_mr",
                "skipped", "seconds")
#: a run directory's files besides config.json, checkpoint.pt and result.json
RUN_FILES = ("history.csv", "test_loss.png", "rollout.png")
#: what may change when a run is resumed: its length, where it lives, how many threads it uses
RESUMABLE = ("epochs", "out", "threads")


def initial_states(cfg: ControlConfig, task: Task) -> tuple[torch.Tensor, torch.Tensor]:
    """Training and test initial states, drawn from the seed (two independent streams)."""
    dtype = DTYPES[cfg.dtype]
    tr = task.initial_states(np.random.default_rng([cfg.seed, 0]), cfg.train)
    te = task.initial_states(np.random.default_rng([cfg.seed, 1]), cfg.test)
    return torch.from_numpy(tr).to(dtype), torch.from_numpy(te).to(dtype)


def build_net(cfg: ControlConfig, task: Task) -> nn.Module:
    torch.manual_seed(cfg.seed)
    return task.net().to(DTYPES[cfg.dtype])


def train_controller(cfg: ControlConfig, resume: bool = False, progress: bool = True,
                     overwrite: bool = False) -> dict:
    """Train a controller as configured; returns the result (also in ``cfg.out``).

    A ``cfg.out`` holding a run is refused unless ``resume`` (continue it, to more epochs too)
    or ``overwrite`` (discard it and start again) is given. Ctrl-C saves a checkpoint between
    two updates and re-raises.
    """
    cfg.validate()
    if resume and overwrite:
        raise UserError("--resume continues a run and --overwrite discards it: pass one")
    use_threads(cfg.threads)
    out = Path(cfg.out)
    ckpt = _claim(cfg, out, resume, overwrite)
    if ckpt is not None and _finished(ckpt, cfg, out):
        return read_result(out / "result.json")
    task = get_task(cfg.task, cfg.level)
    x_train, x_test = initial_states(cfg, task)
    net = build_net(cfg, task)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    # max/avg keeps one term's weight at 1: the PINNs' PDE residual, here the objective the
    # controller exists for (the task's first term); ID takes the largest spread as reference
    reference = task.terms[0] if cfg.weighting == "max-avg" else None
    weighting = None if cfg.weighting == "uniform" else Weighting(
        task.terms, cfg.weighting, reference=reference, seed=cfg.seed)
    # the epoch's progress too, so that Ctrl-C between two updates resumes where it stopped
    state = {"epoch": 0, "finished": False, **_fresh_epoch()}
    history: list[dict] = []
    if ckpt is not None:
        restore(net, ckpt["net"], out / "checkpoint.pt")
        restore(opt, ckpt["optimizer"], out / "checkpoint.pt")
        if weighting is not None:
            restore(weighting, ckpt["weighting"], out / "checkpoint.pt")
        state, history = state | ckpt["state"], ckpt["history"]
        state["finished"] = False
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "config.json", cfg.as_dict())

    def save() -> None:
        save_checkpoint({"config": cfg.as_dict(), "net": net.state_dict(),
                         "optimizer": opt.state_dict(), "state": dict(state),
                         "history": history,
                         **({} if weighting is None else {"weighting": weighting.state_dict()})},
                        out / "checkpoint.pt")

    params = list(net.parameters())
    per_epoch = cfg.train // cfg.batch
    bar = tqdm(total=cfg.epochs, initial=state["epoch"], unit="epoch", disable=not progress,
               desc=f"{cfg.task} {cfg.mode}")
    try:
        while state["epoch"] < cfg.epochs:
            order = torch.randperm(cfg.train, generator=torch.Generator().manual_seed(
                int(np.random.SeedSequence([cfg.seed, state["epoch"]]).generate_state(1)[0])))
            while state["step"] < per_epoch:
                with uninterrupted():
                    start, i = time.perf_counter(), state["step"]
                    _update(cfg, task, net, opt, params,
                            x_train[order[i * cfg.batch:(i + 1) * cfg.batch]], state,
                            weighting, state["epoch"] * per_epoch + i)
                    state["step"] += 1
                    state["seconds"] += time.perf_counter() - start
            with uninterrupted():
                _end_epoch(cfg, task, net, x_train, x_test, state, history)
                write_history(out / "history.csv", history, HISTORY_KEYS)
            save()
            bar.update()
            bar.set_postfix(test=f"{history[-1]['test_loss']:.3e}")
    except KeyboardInterrupt:
        save()
        raise
    finally:
        bar.close()
    return _finish(cfg, task, net, x_test, history, weighting)


def _finish(cfg: ControlConfig, task: Task, net: nn.Module, x_test: torch.Tensor,
            history: list[dict], weighting: Weighting | None = None) -> dict:
    """A finished run's plots and ``result.json``; returns the result."""
    out = Path(cfg.out)
    result = {**cfg.as_dict(), "level": cfg.level, "test_loss": history[-1]["test_loss"],
              "train_loss": history[-1]["train_loss"],
              "test_terms": evaluate(task, net, x_test, terms=True),
              "weights": None if weighting is None else dict(weighting.weights),
              "parameters": sum(p.numel() for p in net.parameters()),
              "seconds": float(sum(h["seconds"] for h in history))}
    # the plots first: a run stopped while plotting has no result.json and resumes to them
    plot_history(out / "test_loss.png", {cfg.mode: history}, "epoch", "test_loss", "epoch",
                 "test loss", title=_title(cfg), smooth=30)
    try:
        plot_rollout(task, net, x_test[:1], out / "rollout.png", title=_title(cfg))
    except (NonFiniteStateError, NonFiniteInputError) as e:
        warnings.warn(f"no rollout.png: the controlled rollout is not finite ({e})",
                      RuntimeWarning, stacklevel=2)
    write_json(out / "result.json", result)
    return result


def _fresh_epoch() -> dict:
    """An epoch's progress before its first update."""
    return {"step": 0, "losses": [], "norms": [], "cos": float("nan"), "skipped": 0,
            "seconds": 0.0}


def _update(cfg: ControlConfig, task: Task, net: nn.Module, opt: torch.optim.Optimizer,
            params: list[torch.Tensor], x0: torch.Tensor, state: dict,
            weighting: Weighting | None = None, step: int = 0) -> None:
    """One minibatch's update (the run's ``step``-th), recorded in the epoch's progress
    (``state``); ``weighting`` balances the task's terms (None: its loss as it is)."""
    reads = weighting is not None and weighting.scheme.needs == "grads"
    first = state["step"] == 0 and not reads
    flow = GradientFlow(cfg.mode, cfg.clip, diagnose=first)
    try:
        loss = closed_loop(task, net, x0, flow, terms=weighting is not None)[0]
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
    state["losses"].append(float(loss.detach()))
    state["norms"].append(update.norm())
    if first:
        state["cos"] = update.cosine()


def _end_epoch(cfg: ControlConfig, task: Task, net: nn.Module, x_train: torch.Tensor,
               x_test: torch.Tensor, state: dict, history: list[dict],
               losses: tuple[float, float] | None = None) -> None:
    """The epoch's history row (with the full training and test losses, evaluated here unless
    ``losses`` gives them); the next epoch."""
    start = time.perf_counter()
    train, test = losses or (evaluate(task, net, x_train), evaluate(task, net, x_test))
    row = {
        "epoch": state["epoch"] + 1,
        "batch_loss": float(np.mean(state["losses"])) if state["losses"] else float("nan"),
        "train_loss": train,
        "test_loss": test,
        "update_norm": float(np.mean(state["norms"])) if state["norms"] else float("nan"),
        "cos_mr": state["cos"],
        "skipped": state["skipped"],
    }
    history.append({**row, "seconds": state["seconds"] + time.perf_counter() - start})
    state.update(epoch=state["epoch"] + 1, **_fresh_epoch())
    state["finished"] = state["epoch"] == cfg.epochs


def _claim(cfg: ControlConfig, out: Path, resume: bool, overwrite: bool) -> dict | None:
    """The checkpoint of the run in ``out`` to continue (None: start afresh). Somebody else's
    files, a run of another configuration, and a run not to be continued are refused."""
    ckpt_path = out / "checkpoint.pt"
    again = "choose another --out, or start again with --overwrite"
    if overwrite:
        if not holds_run(out, cfg.as_dict()):
            refuse_foreign(out, cfg.as_dict())
        discard(out, RUN_FILES)
        return None
    if not ckpt_path.exists():
        if (out / "result.json").exists():
            raise RunExists(f"{out} holds a finished run without its checkpoint; {again}")
        refuse_foreign(out, cfg.as_dict())
        return None
    ckpt = load_checkpoint(ckpt_path, ("config", "net", "optimizer", "state", "history"),
                           recover=f"delete it, or {again}")
    # a run recorded before the weighting was a key trained its loss as it is
    recorded = {"weighting": "uniform", **ckpt["config"]}
    differ = differing(cfg.as_dict(), recorded, RESUMABLE)
    if differ:
        raise RunExists(f"{out} holds a run of another configuration (differs in "
                        f"{', '.join(differ)}); {again}")
    state = ckpt["state"]
    begun = state["epoch"] + (state.get("step", 0) > 0)  # epochs finished or begun
    if begun > cfg.epochs:
        part = " and part of the next" if begun > state["epoch"] else ""
        raise UserError(f"{out} holds {state['epoch']} epochs{part}; pass --epochs {begun} or "
                        f"more, or {again}")
    if not resume:
        what = ("a finished run; continue it to more --epochs with --resume"
                if _finished(ckpt, cfg, out) else "an unfinished run; continue it with --resume")
        raise RunExists(f"{out} holds {what}, {again}")
    return ckpt


def _finished(ckpt: dict, cfg: ControlConfig, out: Path) -> bool:
    """Whether the checkpoint's run is the finished run of ``cfg``, its result written (a run
    stopped between its last checkpoint and result.json resumes to write it)."""
    return (ckpt["state"]["finished"] and ckpt["config"]["epochs"] == cfg.epochs
            and (out / "result.json").exists())


def _title(cfg: ControlConfig) -> str:
    return f"{cfg.task}, {TASKS[cfg.task].knob} {cfg.level}, mode {cfg.mode}"


# ----------------------------------------------------------------------------- plots
@torch.no_grad()
def plot_rollout(task: Task, net: nn.Module, x0: torch.Tensor, path: Path,
                 title: str = "") -> None:
    """One controlled rollout: pole angles; driver and evader paths; |ψ|² over t and x."""
    plt = pyplot()
    _, (states, controls) = closed_loop(task, net, x0, keep=True)
    xs = torch.stack(states)[:, 0].numpy()  # (n + 1, C, *grid)
    t = np.arange(len(xs)) * task.solver.dt
    fig, ax = plt.subplots(figsize=(6, 4))
    if task.name == "cartpole":
        for i in range(1, xs.shape[2]):
            ax.plot(t, xs[:, 0, i], label=f"θ_{i}")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel("t")
        ax.set_ylabel("pole angle (0 = upright)")
        ax.legend(fontsize=8)
    elif task.name == "guidance":
        nd = task.solver.drivers
        for i in range(xs.shape[2]):
            driver = i < nd
            ax.plot(xs[:, 0, i], xs[:, 1, i], color="C3" if driver else "C0", lw=1)
            ax.plot(xs[0, 0, i], xs[0, 1, i], "o", color="C3" if driver else "C0", ms=3)
        ax.plot([], [], color="C3", label="drivers")
        ax.plot([], [], color="C0", label="evaders")
        ax.plot(0, 0, "k+", ms=10)
        # the scene of the start (drivers r ≤ 4) and the evaders: far-flung drivers leave it
        r = max(float(np.abs(xs[0, :2]).max()), float(np.abs(xs[:, :2, nd:]).max())) + 0.5
        ax.set_xlim(-r, r)
        ax.set_ylim(-r, r)
        ax.set_aspect("equal")
        ax.legend(fontsize=8)
    else:
        density = xs[:, 0] ** 2 + xs[:, 1] ** 2
        im = ax.imshow(density.T, aspect="auto", origin="lower",
                       extent=(0, t[-1], 0, task.solver.length))
        fig.colorbar(im, ax=ax, label="|ψ|²")
        ax.set_xlabel("t")
        ax.set_ylabel("x")
    ax.set_title(title, fontsize=9)
    save_figure(fig, path, dpi=110)
