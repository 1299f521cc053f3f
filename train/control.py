"""Controllers trained through simulators with the gradient-flow modes of stabilised BPTT.

A controller network N reads the state and outputs a control, the simulator advances one step
(``adjointsim.train.bridge.step``: the solver's compiled step forward, its hand-written adjoint backward),
and the loss judges the trajectory (Schnell & Thuerey 2024):

    c_t = N(flow.net(x_t); θ),   x_{t+1} = S(flow.phys(x_t), c_t),

where ``flow`` (:class:`adjointsim.train.unroll.GradientFlow`) decides where gradients stop (R, M, S, N,
C). The three tasks of the paper, with the note's constants:

* ``cartpole``: 1–4 poles (``--poles``), 100 steps of Δt = 0.01, loss 1 − mean_i cos θ_i at
  the last step (swing-up from hanging);
* ``guidance``: 2 drivers herd 4 evaders, 60 steps of Δt = 4/60, loss the mean over steps of
  mean_e |x_e|² + r_c mean(c²) (``--control-weight`` r_c ∈ {1, 0.1, 0.01, 0.001});
* ``quantum``: ``schrodinger1d-cn`` with m = 1/2, 32 interior points, Δt = 0.0625, 128 steps,
  loss Σ_t (1 − |⟨ψ_n|ψ_t⟩|²) towards eigenstate n (``--target`` 3..5).

Training: Adam, 256 training and 256 test initial states, batch 8, the last layer of every
controller zero-initialised (c = 0 at the start, as in the reference runs). A run directory
holds ``config.json``, ``checkpoint.pt`` (atomic, every epoch), ``history.csv`` (per epoch:
mean minibatch loss, full training and test loss, update norm, cos(g_M, g_R) on the epoch's
first minibatch, seconds), ``result.json`` and the plots ``test_loss.png`` and ``rollout.png``.
"""

from __future__ import annotations

import csv
import json
import argparse
import math
import time
import tomllib
import warnings
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from tqdm.auto import tqdm

import adjointsim
from adjointsim.errors import RunExists
from adjointsim.files import atomic_path, pyplot, save_figure, write_json, write_text
from adjointsim.run import read_result, refuse_foreign, run_errors
from adjointsim.stepper import NonFiniteInputError, NonFiniteStateError

from . import bridge
from .checkpoint import load_checkpoint, save_checkpoint
from .unroll import CLIPS, FLOWS, GradientFlow

DTYPES = {"float32": torch.float32, "float64": torch.float64}


# ----------------------------------------------------------------------------- tasks
class Task:
    """One control problem at one complexity level: scene, initial states, net, loss."""

    name: str
    knob: str  # the complexity option's config key
    levels: tuple  # accepted values, easiest first
    steps: int

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
            nn.Flatten(), nn.Linear(size, 100), nn.Tanh(), nn.Linear(100, 100), nn.Tanh(),
            nn.Linear(100, int(np.prod(self.solver.control_shape))),
        ))

    def step_loss(self, x: torch.Tensor, c: torch.Tensor, t: int) -> torch.Tensor | None:
        """Loss term of the state x_{t+1} reached with control c_t (None: no term)."""
        raise NotImplementedError

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

    def step_loss(self, x, c, t):
        evaders = x[:, :2, self.solver.drivers:]
        return ((evaders**2).sum(dim=1).mean() + self.level * (c**2).mean()) / self.steps


class QuantumTask(Task):
    name, knob, levels, steps = "quantum", "target", (3, 4, 5), 128

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
    last = [m for m in net if isinstance(m, nn.Linear)][-1]
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
) -> tuple[torch.Tensor, list[torch.Tensor] | None]:
    """Run the controller through the simulator; returns the loss and (if ``keep``) the
    states x_0..x_n and controls. One solver call per step through ``adjointsim.train.bridge.step``."""
    flow = flow or GradientFlow("R")
    x = flow.start(x0)
    terms: list[torch.Tensor] = []
    states, controls = ([x0], []) if keep else (None, None)
    for t in range(task.steps):
        c = task.control(flow.control(net, flow.net(x)))
        x = bridge.step(task.solver, flow.phys(x), c)
        term = task.step_loss(x, c, t)
        if term is not None:
            terms.append(term)
        if keep:
            states.append(x.detach())
            controls.append(c.detach())
    return task.total(terms), (states, controls) if keep else None


@torch.no_grad()
def evaluate(task: Task, net: nn.Module, x0: torch.Tensor) -> float:
    """Mean loss over the initial states ``x0`` (all at once, no tape)."""
    try:
        return float(closed_loop(task, net, x0)[0])
    except (NonFiniteStateError, NonFiniteInputError, FloatingPointError):
        return float("nan")


# ----------------------------------------------------------------------------- config
@dataclass
class ControlConfig:
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
    out: str = "runs/control"
    threads: int = 1

    @classmethod
    def load(cls, path: str | Path | None = None, **overrides: Any) -> ControlConfig:
        """A config from a TOML file (optional) and keyword overrides; bad keys and values
        fail with a message naming them and what is accepted."""
        values: dict[str, Any] = {}
        if path is not None:
            try:
                with open(path, "rb") as f:
                    values.update(tomllib.load(f))
            except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
                raise ValueError(f"{path} is not valid TOML: {e}") from None
            except OSError as e:
                raise ValueError(f"cannot read config {path}: {e.strerror}") from None
        values.update({k: v for k, v in overrides.items() if v is not None})
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ValueError(f"unknown config option(s) {unknown}; known: {sorted(known)}")
        for k, v in values.items():
            want = type(known[k].default)
            ok = isinstance(v, want) and not isinstance(v, bool) or (
                want is float and isinstance(v, int) and not isinstance(v, bool))
            if not ok:
                raise ValueError(f"config key {k!r} must be {want.__name__}, got {v!r}")
            if want is float:
                values[k] = float(v)
        cfg = cls(**values)
        cfg.validate()
        return cfg

    @property
    def level(self) -> Any:
        return getattr(self, TASKS[self.task].knob) if self.task in TASKS else None

    def validate(self) -> None:
        get_task(self.task, self.level)
        if self.mode not in FLOWS:
            raise ValueError(f"unknown mode {self.mode!r}; choose from {', '.join(FLOWS)}")
        if self.clip not in CLIPS:
            raise ValueError(f"unknown clip {self.clip!r}; choose from {', '.join(CLIPS)}")
        if self.dtype not in DTYPES:
            raise ValueError(f"dtype must be one of {', '.join(DTYPES)}, not {self.dtype!r}")
        for k in ("epochs", "train", "test", "batch", "threads"):
            if getattr(self, k) < 1:
                raise ValueError(f"{k} must be ≥ 1, not {getattr(self, k)}")
        if self.batch > self.train:
            raise ValueError(f"batch ({self.batch}) must not exceed train ({self.train})")
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise ValueError(f"lr must be a finite number > 0, not {self.lr}")
        if not 0 <= self.seed < 2**63:
            raise ValueError(f"seed must be in 0..2**63 - 1, not {self.seed}")


# ----------------------------------------------------------------------------- training
HISTORY_KEYS = ("epoch", "batch_loss", "train_loss", "test_loss", "update_norm", "cos_mr",
                "skipped", "seconds")


def initial_states(cfg: ControlConfig, task: Task) -> tuple[torch.Tensor, torch.Tensor]:
    """Training and test initial states, drawn from the seed (test states from seed + 10⁶)."""
    dtype = DTYPES[cfg.dtype]
    tr = task.initial_states(np.random.default_rng([cfg.seed, 0]), cfg.train)
    te = task.initial_states(np.random.default_rng([cfg.seed, 1]), cfg.test)
    return torch.from_numpy(tr).to(dtype), torch.from_numpy(te).to(dtype)


def build_net(cfg: ControlConfig, task: Task) -> nn.Module:
    torch.manual_seed(cfg.seed)
    return task.net().to(DTYPES[cfg.dtype])


def train(cfg: ControlConfig, resume: bool = False, progress: bool = True) -> dict:
    """Train a controller as configured; returns the result (also in ``cfg.out``)."""
    torch.set_num_threads(cfg.threads)
    out = Path(cfg.out)
    ckpt_path = out / "checkpoint.pt"
    task = get_task(cfg.task, cfg.level)
    x_train, x_test = initial_states(cfg, task)
    net = build_net(cfg, task)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    state = {"epoch": 0, "finished": False}
    history: list[dict] = []
    if not ckpt_path.exists():
        if (out / "result.json").exists():
            raise RunExists(f"{out} holds a finished run without its checkpoint; choose "
                            "another --out")
        refuse_foreign(out, asdict(cfg))
    else:
        ckpt = _load(ckpt_path)
        # the epoch count may grow; where the run lives and how many threads it uses may change
        differ = sorted(k for k, v in asdict(cfg).items()
                        if k not in ("epochs", "out", "threads") and ckpt["config"].get(k) != v)
        if differ:
            raise ValueError(f"{out} holds a run of another configuration (differs in "
                             f"{', '.join(differ)}); use a new --out")
        if ckpt["state"]["epoch"] > cfg.epochs:
            raise ValueError(f"{out} holds {ckpt['state']['epoch']} epochs; pass --epochs "
                             f"{ckpt['state']['epoch']} or more, or choose another --out")
        # (a run stopped between its last checkpoint and result.json resumes to write it)
        if (ckpt["state"]["finished"] and ckpt["config"]["epochs"] == cfg.epochs
                and (out / "result.json").exists()):
            if not resume:
                raise ValueError(f"{out} holds a finished run; choose another --out "
                                 "(or delete it to train again)")
            return read_result(out / "result.json")
        if not resume:
            raise ValueError(f"{out} holds an unfinished run; continue it with --resume or "
                             "choose another --out")
        net.load_state_dict(ckpt["net"])
        opt.load_state_dict(ckpt["optimizer"])
        state, history = ckpt["state"], ckpt["history"]
        state["finished"] = False
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "config.json", json.dumps(asdict(cfg), indent=2))
    params = list(net.parameters())
    per_epoch = cfg.train // cfg.batch
    bar = tqdm(total=cfg.epochs, initial=state["epoch"], unit="epoch", disable=not progress,
               desc=f"{cfg.task} {cfg.mode}")
    while state["epoch"] < cfg.epochs:
        epoch, start = state["epoch"], time.perf_counter()
        order = torch.randperm(cfg.train, generator=torch.Generator().manual_seed(
            int(np.random.SeedSequence([cfg.seed, epoch]).generate_state(1)[0])))
        losses, norms, cos, skipped = [], [], float("nan"), 0
        for i in range(per_epoch):
            flow = GradientFlow(cfg.mode, cfg.clip, diagnose=i == 0)
            x0 = x_train[order[i * cfg.batch:(i + 1) * cfg.batch]]
            try:
                loss = closed_loop(task, net, x0, flow)[0]
            except (NonFiniteStateError, NonFiniteInputError):
                skipped += 1  # the simulator blew up under this controller: skip the update
                continue
            update = flow.backward(loss, params)
            if not (math.isfinite(float(loss.detach())) and math.isfinite(update.norm())):
                skipped += 1
                continue
            opt.step()
            losses.append(float(loss.detach()))
            norms.append(update.norm())
            if i == 0:
                cos = update.cosine()
        history.append({
            "epoch": epoch + 1,
            "batch_loss": float(np.mean(losses)) if losses else float("nan"),
            "train_loss": evaluate(task, net, x_train),
            "test_loss": evaluate(task, net, x_test),
            "update_norm": float(np.mean(norms)) if norms else float("nan"),
            "cos_mr": cos,
            "skipped": skipped,
            "seconds": time.perf_counter() - start,
        })
        state["epoch"] += 1
        state["finished"] = state["epoch"] == cfg.epochs
        _write_history(history, out)
        _save(ckpt_path, cfg, net, opt, state, history)
        bar.update()
        bar.set_postfix(test=f"{history[-1]['test_loss']:.3e}")
    bar.close()
    result = {**asdict(cfg), "level": cfg.level, "test_loss": history[-1]["test_loss"],
              "train_loss": history[-1]["train_loss"], "parameters": sum(p.numel() for p in params),
              "seconds": float(sum(h["seconds"] for h in history))}
    # the plots first: a run stopped while plotting has no result.json and resumes to them
    plot_history([history], [f"{cfg.mode}"], out / "test_loss.png", title=_title(cfg))
    try:
        plot_rollout(task, net, x_test[:1], out / "rollout.png", title=_title(cfg))
    except (NonFiniteStateError, NonFiniteInputError) as e:
        warnings.warn(f"no rollout.png: the controlled rollout is not finite ({e})",
                      RuntimeWarning, stacklevel=2)
    write_json(out / "result.json", result)
    return result


def _title(cfg: ControlConfig) -> str:
    return f"{cfg.task}, {cfg.task and TASKS[cfg.task].knob} {cfg.level}, mode {cfg.mode}"


def _load(path: Path) -> dict:
    return load_checkpoint(path, ("config", "net", "optimizer", "state", "history"))


def _save(path: Path, cfg, net, opt, state, history) -> None:
    save_checkpoint({"config": asdict(cfg), "net": net.state_dict(),
                     "optimizer": opt.state_dict(), "state": dict(state),
                     "history": history}, path)


def _write_history(history: list[dict], out: Path) -> None:
    with atomic_path(out / "history.csv") as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=HISTORY_KEYS)
        w.writeheader()
        w.writerows(history)


def load_history(path: str | Path) -> list[dict]:
    with open(path, newline="") as f:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(f)]


# ----------------------------------------------------------------------------- plots
def moving_average(y: np.ndarray, k: int = 30) -> np.ndarray:
    """Trailing mean over up to ``k`` epochs (the paper's 30-epoch smoothing)."""
    y = np.asarray(y, dtype=float)
    c = np.cumsum(np.insert(np.nan_to_num(y, nan=0.0), 0, 0.0))
    n = np.arange(1, len(y) + 1)
    lo = np.maximum(0, n - k)
    return (c[n] - c[lo]) / (n - lo)


def plot_history(histories: list[list[dict]], labels: list[str], path: Path,
                 title: str = "") -> None:
    """Test loss over epochs, log scale, raw (faint) and 30-epoch moving average."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.8))
    for h, label in zip(histories, labels):
        e = np.array([r["epoch"] for r in h])
        y = np.array([r["test_loss"] for r in h])
        (line,) = ax.plot(e, moving_average(y), label=label)
        ax.plot(e, y, color=line.get_color(), alpha=0.25, lw=0.7)
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("test loss (30-epoch mean)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    save_figure(fig, path, dpi=110)


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


# ----------------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("task", help=f"one of {', '.join(TASKS)}")
    p.add_argument("--config", type=Path, default=None, help="TOML file of ControlConfig keys")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    p.add_argument("--no-progress", action="store_true")
    helps = {
        "mode": "R, M, S, N or C (default C)", "clip": "none, value or norm (at 1; default none)",
        "poles": "cartpole: 1..4 (default 1)", "target": "quantum: eigenstate 3..5 (default 3)",
        "control_weight": "guidance: 1, 0.1, 0.01 or 0.001 (default 1)",
        "out": "run directory (default runs/control-TASK-MODE)",
    }
    for f in fields(ControlConfig):
        if f.name == "task":
            continue
        p.add_argument("--" + f.name.replace("_", "-"), dest=f.name, type=str, default=None,
                       help=helps.get(f.name, f"default {f.default!r}"))
    p.set_defaults(func=run_command)


def run_command(args) -> int:
    known = {f.name: f for f in fields(ControlConfig)}
    overrides: dict[str, Any] = {"task": args.task}
    for k, f in known.items():
        v = getattr(args, k, None)
        if k == "task" or v is None:
            continue
        kind = type(f.default)
        try:
            overrides[k] = kind(v) if kind is not str else v
        except ValueError:
            raise ValueError(f"--{k.replace('_', '-')} must be {kind.__name__}, got {v!r}") \
                from None
    if args.task not in TASKS:
        raise ValueError(f"unknown task {args.task!r}; choose from {', '.join(TASKS)}")
    for t, cls in TASKS.items():
        if t != args.task and cls.knob in overrides:
            raise ValueError(f"--{cls.knob.replace('_', '-')} applies to {t}, not {args.task}")
    if "out" not in overrides and args.config is None:
        overrides["out"] = str(Path("runs") / f"control-{args.task}-{overrides.get('mode', 'C')}")
    cfg = ControlConfig.load(args.config, **overrides)
    task = get_task(cfg.task, cfg.level)
    n = sum(p.numel() for p in task.net().parameters())
    print(f"{cfg.task} ({task.knob} {cfg.level}), mode {cfg.mode}, clip {cfg.clip}: "
          f"{n:,} parameters", flush=True)
    out = Path(cfg.out)
    with run_errors(out):
        result = train(cfg, resume=args.resume, progress=not args.no_progress)
    loss = result["test_loss"]
    loss = f"{loss:.4e}" if loss is not None and math.isfinite(loss) else "not finite"
    print(f"final test loss {loss}; run in {out} (history.csv, test_loss.png, rollout.png)")
    return 0
