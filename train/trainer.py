"""The training loop: curriculum stages, ONE/NOG/WIG unrolling, atomic checkpoints, resume.

A run lives in one directory: ``config.json``, ``checkpoint.pt`` (written atomically every
``checkpoint_every`` iterations and at the end), ``history.csv`` and ``training.png``. A run
started again with ``resume=True`` continues from its checkpoint at the same stage, epoch and
batch, with the optimiser, the gradient-spike statistics and the data order restored, so it
ends with the same weights as an uninterrupted run. A run directory that already holds a run is
refused unless the call says ``resume`` or ``overwrite``.

Every value of a :class:`TrainConfig` is checked for its type and its accepted range
(:data:`ACCEPTED`). A checkpoint carries the SHA-256 digest of its contents (every tensor's
bytes, dtype and shape, and every other value), verified when it is loaded; checkpoints from
before digests load with a warning and get one at their next save.
"""

from __future__ import annotations

import copy
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from tqdm.auto import tqdm

from adjointsim.errors import RunExists, UserError
from adjointsim.files import uninterrupted, write_text
from adjointsim.nets import DilatedResNet, ResNet, UNet, parameter_count
from adjointsim.run import (
    SEEDS,
    Config,
    Interval,
    check_memory,
    differing,
    discard,
    holds_run,
    plot_history,
    refuse_foreign,
    write_history,
)

from . import data as datamod
from .checkpoint import load_checkpoint, restore, save_checkpoint
from .evaluate import BLOW_UPS
from .model import CORRECTIONS, SETUPS, NeuralStepper
from .problems import PROBLEMS, get_problem
from .threads import use_threads
from .unroll import MODES, GradientFlow, schedule, unrolled_loss

CONV_NETS = {"resnet": ResNet, "dilated": DilatedResNet, "unet": UNet}
DTYPES = {"float32": torch.float32, "float64": torch.float64}


#: the accepted values of every TrainConfig field: choices, an Interval, or (data, out,
#: curriculum) checked by their own rule in TrainConfig.check
ACCEPTED: dict[str, tuple | Interval | str] = {
    "problem": tuple(PROBLEMS),
    "data": "a non-empty path",
    "out": "a non-empty path",
    "setup": SETUPS,
    "correction": CORRECTIONS,
    "mode": MODES,
    "unroll": Interval(1),
    "curriculum": "a list of [m, lr] pairs, m ≥ 1 and lr in (0, 1]",
    "net": tuple(CONV_NETS),
    "width": Interval(1),
    "blocks": Interval(1),
    "dtype": tuple(DTYPES),
    # Adam steps beyond 1 are no longer a learning rate but a divergence.
    "lr": Interval(0, 1, lo_open=True),
    # The rate is multiplied by lr_decay every lr_decay_every iterations: ≤ 0 would flip the
    # sign of the update (gradient ascent), > 1 makes it grow without bound; 1 keeps it fixed.
    "lr_decay": Interval(0, 1, lo_open=True),
    "lr_decay_every": Interval(1),
    "batch": Interval(1),
    "epochs": Interval(0, lo_open=True),
    "stride": Interval(1),
    "warmup": Interval(0),
    "truncate": Interval(0),
    # An update is skipped when its gradient norm exceeds spike_factor × the running mean:
    # at ≤ 1 every update above the mean would be skipped. Use a large value to disable it.
    "spike_factor": Interval(1, lo_open=True),
    # 0 turns it off; in (0, 1] it would roll back on every window that is not a new best
    # (refused in TrainConfig.validate).
    "rollback": Interval(0),
    "checkpoint_every": Interval(1),
    "seed": SEEDS,
    "threads": Interval(1),
    "max_iterations": Interval(0),
}


@dataclass
class TrainConfig(Config):
    problem: str = "ks"
    data: str = "data/ks-quick.h5"
    out: str = "runs/ks"
    setup: str = "correction"
    correction: str = "parallel"
    mode: str = "WIG"
    unroll: int = 3
    #: [[m, lr], ...]: stages of the unroll horizon, each starting from the previous weights
    curriculum: list = field(default_factory=list)
    net: str = "resnet"
    width: int = 26
    blocks: int = 8
    dtype: str = "float32"
    lr: float = 1e-4
    lr_decay: float = 0.9
    lr_decay_every: int = 2000
    batch: int = 16
    epochs: float = 1.0
    #: frames between window starts (1 uses every window)
    stride: int = 1
    warmup: int = 0
    truncate: int = 0
    #: skip an update whose gradient norm exceeds this multiple of the running mean
    spike_factor: float = 10.0
    #: roll back to the best weights and halve the learning rate when the median loss of the
    #: last ROLLBACK_WINDOW updates exceeds this multiple of the best such median (0: off)
    rollback: float = 0.0
    checkpoint_every: int = 200
    seed: int = 0
    #: torch's and the solver's threads (they take turns); small convolutions run fastest on
    #: one, and 2-core machines are shared
    threads: int = 1
    #: stop after this many iterations in total (for tests and interrupted-run drills)
    max_iterations: int = 0

    ACCEPTED: ClassVar[dict[str, tuple | Interval | str]] = ACCEPTED

    def check(self, where: str) -> None:
        # The weights alone, with their gradient and Adam's two moments (kernel 3, the deepest
        # of the networks): a bound from below, enough to refuse what cannot be allocated.
        layers = 2 * max(self.blocks, 4) + 8
        weights = layers * self.width**2 * 3 ** PROBLEMS[self.problem].dims
        check_memory(4 * weights * torch.finfo(DTYPES[self.dtype]).bits // 8,
                     f"config keys 'width' and 'blocks'{where}: a {self.net} of width "
                     f"{self.width} and {self.blocks} blocks (its weights, their gradient and "
                     "Adam's moments)", "choose a smaller network")
        if not (self.rollback == 0 or self.rollback > 1):
            raise UserError(f"config key 'rollback'{where}: {self.rollback!r} is not "
                            "0 (off) or a number > 1")
        for stage in self.curriculum:
            ok = (isinstance(stage, list | tuple) and len(stage) == 2
                  and type(stage[0]) is int and type(stage[1]) in (int, float)
                  and stage[0] >= 1 and stage[1] in ACCEPTED["lr"])
            if not ok:
                raise UserError(f"config key 'curriculum'{where}: stage {stage!r} is not an "
                                f"[m, lr] pair with m an integer ≥ 1 and lr {ACCEPTED['lr']}")

    def stages(self) -> list[tuple[int, float]]:
        stages = [(int(m), float(lr)) for m, lr in self.curriculum] or [(self.unroll, self.lr)]
        return stages


def build_model(cfg: TrainConfig) -> NeuralStepper:
    problem = get_problem(cfg.problem)
    torch.manual_seed(cfg.seed)
    kwargs = {"width": cfg.width}
    if cfg.net == "resnet":
        kwargs["blocks"] = cfg.blocks
    # One state channel plus the conditioning channel in, one state channel out.
    net = CONV_NETS[cfg.net](2, 1, problem.dims, **kwargs).to(DTYPES[cfg.dtype])
    solver = problem.coarse if cfg.setup == "correction" else None
    return NeuralStepper(net, cfg.setup, solver, cfg.correction)


def _plan(cfg: TrainConfig, n_windows_fn) -> list[dict]:
    """Per stage: the flow, unroll horizon, batch size, iterations per epoch and in all."""
    plan = []
    for m, lr in cfg.stages():
        flow, horizon, batch, epochs = schedule(cfg.mode, m, cfg.batch, cfg.epochs)
        n = n_windows_fn(horizon + cfg.warmup + 1)
        per_epoch = max(1, n // batch)
        plan.append({"flow": flow, "m": horizon, "lr": lr, "batch": batch,
                     "iterations": int(math.ceil(epochs * per_epoch)), "per_epoch": per_epoch})
    return plan


#: keys a run may be resumed with other values of
RESUMABLE = ("out", "threads", "max_iterations")

#: what a run directory holds besides config.json: replaced by ``overwrite``
RUN_FILES = ("history.csv", "training.png", "results.json", "metrics.json", "rollout-*.png")
_RECOVER = ("copy an intact run directory over it and continue with --resume, or train again "
            "from scratch with --overwrite")


def _claim(out: Path, config: dict, resume: bool, overwrite: bool) -> None:
    """Refuse a directory holding another run unless told to resume or overwrite it, and one
    holding somebody else's files always."""
    if resume and overwrite:
        raise UserError("--resume continues a run and --overwrite discards it: pass one")
    if not holds_run(out, config):
        refuse_foreign(out, config)
    ckpt_path = out / "checkpoint.pt"
    if resume or overwrite or not (ckpt_path.exists() or (out / "config.json").exists()):
        return
    what = "a run that saved no checkpoint yet"
    if ckpt_path.exists():
        try:
            state = load_checkpoint(ckpt_path, recover=_RECOVER)["state"]
            what = (f"a finished run ({state['total']} iterations)" if state.get("finished") else
                    f"an unfinished run (stopped after {state['total']} iterations)")
        except (UserError, KeyError):
            what = "a run whose checkpoint cannot be read"
    raise RunExists(f"{out} already holds {what}; continue it with --resume, train into a new "
                    "--out, or start it again with --overwrite")


def train(cfg: TrainConfig, resume: bool = False, progress: bool = True,
          overwrite: bool = False) -> NeuralStepper:
    """Train a model as configured; returns it (also saved in ``cfg.out``).

    A ``cfg.out`` that already holds a run is refused unless ``resume`` (continue it from its
    checkpoint; a run without one starts over) or ``overwrite`` (discard it) is given.
    """
    cfg.validate()
    use_threads(cfg.threads)
    _claim(Path(cfg.out), asdict(cfg), resume, overwrite)
    data = TrainData.load(cfg)
    run = Run.open(cfg, data.plan, resume, overwrite)
    bar = tqdm(total=data.total, initial=run.state["total"], desc=f"train {cfg.mode}",
               disable=not progress, unit="it")
    try:
        loop(cfg, data, [run], lambda stage, wins: _iteration(cfg, stage, wins, data, run),
             run.save, bar)
    except KeyboardInterrupt:
        run.save()  # between updates (see uninterrupted): the run resumes bit-identically
        raise
    finally:
        bar.close()
    run.finish(data.plan)
    return run.model


@dataclass
class TrainData:
    """A run's training split as tensors, and its plan (:func:`_plan`): what the members of an
    ensemble share."""

    split: Any
    frames: torch.Tensor
    params: torch.Tensor
    conditions: torch.Tensor
    plan: list[dict]

    @classmethod
    def load(cls, cfg: TrainConfig) -> TrainData:
        dataset = datamod.load(cfg.data)
        if dataset.problem.name != cfg.problem:
            raise UserError(f"{cfg.data} holds {dataset.problem.name!r} data, not "
                            f"{cfg.problem!r}")
        split = dataset.splits["train"]
        data = cls(split, torch.from_numpy(split.trajectories).to(DTYPES[cfg.dtype]),
                   torch.from_numpy(split.params), torch.from_numpy(split.conditions), [])
        data.plan = data.plan_of(cfg)
        return data

    def plan_of(self, cfg: TrainConfig) -> list[dict]:
        """``cfg``'s plan on this split (an ensemble's members differ in their rates)."""
        return _plan(cfg, lambda length: len(datamod.windows(self.split, length, cfg.stride)))

    @property
    def total(self) -> int:
        return sum(s["iterations"] for s in self.plan)

    def batch(self, cfg: TrainConfig, stage: dict, state: dict, wins: np.ndarray
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
        """The reference windows, scene parameters and conditions of a run's next update, and
        its learning rate."""
        it = state["iteration"]
        epoch, pos = divmod(it, stage["per_epoch"])
        # The order of an epoch depends only on (seed, stage, epoch): resumable.
        key = np.random.SeedSequence([cfg.seed, state["stage"], epoch]).generate_state(1)
        g = torch.Generator().manual_seed(int(key[0]))
        order = torch.randperm(len(wins), generator=g)
        pick = torch.from_numpy(wins)[order[pos * stage["batch"]:(pos + 1) * stage["batch"]]]
        traj, start = pick[:, 0], pick[:, 1]
        frames = self.frames[traj[:, None], start[:, None] + torch.arange(window(stage, cfg))]
        lr = stage["lr"] * cfg.lr_decay ** (it // cfg.lr_decay_every) * state["lr_scale"]
        return frames, self.params[traj], self.conditions[traj], lr


def window(stage: dict, cfg: TrainConfig) -> int:
    """The frames of one reference window of ``stage``."""
    return stage["m"] + cfg.warmup + 1


@dataclass
class Run:
    """One run's model, optimiser, progress and history, and its directory's files."""

    cfg: TrainConfig
    model: NeuralStepper
    optimizer: torch.optim.Adam
    state: dict
    history: list[dict]
    #: the weights and optimiser state at state["best"], for a rollback
    kept: dict[str, Any]

    @classmethod
    def open(cls, cfg: TrainConfig, plan: list[dict], resume: bool, overwrite: bool) -> Run:
        """A fresh run, or with ``resume`` the one its checkpoint holds (checked against
        ``cfg``); writes ``config.json``."""
        out = Path(cfg.out)
        out.mkdir(parents=True, exist_ok=True)
        if overwrite:  # only now that the new run is known to start
            discard(out, RUN_FILES)
        model = build_model(cfg)
        optimizer = torch.optim.Adam(model.parameters(), lr=plan[0]["lr"])
        state = {"stage": 0, "iteration": 0, "total": 0, "grad_ema": 0.0, "skipped": 0,
                 "lr_scale": 1.0, "best": math.inf, "rollbacks": 0}
        kept: dict[str, Any] = {"best": None}
        history: list[dict] = []
        ckpt_path = out / "checkpoint.pt"
        if resume and ckpt_path.exists():
            ckpt = load_checkpoint(ckpt_path, recover=_RECOVER)
            # options added since the checkpoint was written take their defaults
            theirs = asdict(TrainConfig()) | ckpt["config"]
            # where the run lives, how many threads and when to stop do not change its result
            ours = asdict(cfg) | {k: theirs[k] for k in RESUMABLE}
            if str(Path(theirs["data"]).resolve()) == str(Path(cfg.data).resolve()):
                ours["data"] = theirs["data"]
            if theirs != ours:
                differ = differing(ours, theirs)
                raise UserError(f"{ckpt_path} was written with another configuration (differs "
                                f"in {', '.join(differ)}); train into a new --out or use "
                                "--overwrite")
            restore(model, ckpt["model"], ckpt_path)
            restore(optimizer, ckpt["optimizer"], ckpt_path)
            state, history = state | ckpt["state"], ckpt["history"]
            kept["best"] = ckpt.get("best")
        write_text(out / "config.json", json.dumps(asdict(cfg), indent=2))
        return cls(cfg, model, optimizer, state, history, kept)

    def save(self) -> None:
        save_checkpoint({"config": asdict(self.cfg), "model": self.model.state_dict(),
                         "optimizer": self.optimizer.state_dict(), "state": self.state,
                         "history": self.history, "best": self.kept["best"]},
                        Path(self.cfg.out) / "checkpoint.pt")

    def spike(self, norm: float) -> bool:
        """Whether an update of gradient norm ``norm`` is skipped (not finite, or a spike);
        follows the running mean."""
        # The running mean restarts each stage (a longer unroll has larger gradients)
        # and also follows skipped norms, capped, so a lasting rise is let through.
        state = self.state
        ema, cutoff = state["grad_ema"], self.cfg.spike_factor * state["grad_ema"]
        spike = state["iteration"] > 20 and norm > cutoff
        if math.isfinite(norm):
            state["grad_ema"] = norm if ema == 0 else 0.95 * ema + 0.05 * min(norm, cutoff)
        return not math.isfinite(norm) or spike

    def record(self, stage: dict, lr: float, loss: float, skipped: bool) -> bool:
        """The update's history row and counters; whether the rollback guard is due."""
        state = self.state
        state["skipped"] += skipped
        self.history.append({"iteration": state["total"], "stage": state["stage"],
                             "m": stage["m"], "lr": lr, "loss": loss, "skipped": skipped})
        state["iteration"] += 1
        state["total"] += 1
        return bool(self.cfg.rollback) and state["iteration"] % ROLLBACK_WINDOW == 0

    def guard(self) -> None:
        self.kept["best"] = _guard(self.cfg.rollback, self.history, self.state, self.model,
                                   self.optimizer, self.kept["best"])

    def next_stage(self) -> None:
        state = self.state
        state["stage"] += 1
        state["iteration"] = 0
        state["grad_ema"] = 0.0
        state["best"], self.kept["best"] = math.inf, None  # a longer unroll has a larger loss

    def finish(self, plan: list[dict]) -> None:
        """Mark the run finished and write its history, unless ``max_iterations`` stopped it."""
        if self.cfg.max_iterations and self.state["stage"] < len(plan):
            return
        self.state["finished"] = True
        self.save()
        _write_history(self.history, Path(self.cfg.out))


def loop(cfg: TrainConfig, data: TrainData, runs: list[Run], iterate, save, bar) -> None:
    """The stages' iterations of ``runs`` (one run, or an ensemble's members, all at the same
    point), each update ``iterate(stage, windows)`` held together against Ctrl-C."""
    state = runs[0].state
    while state["stage"] < len(data.plan):
        stage = data.plan[state["stage"]]
        wins = datamod.windows(data.split, window(stage, cfg), cfg.stride)
        while state["iteration"] < stage["iterations"]:
            if cfg.max_iterations and state["total"] >= cfg.max_iterations:
                save()
                return
            with uninterrupted():
                iterate(stage, wins)
            bar.update()
            loss = np.mean([r.history[-1]["loss"] for r in runs])
            bar.set_postfix(loss=f"{loss:.3e}", m=stage["m"])
            if state["total"] % cfg.checkpoint_every == 0:
                save()
        for run in runs:
            run.next_stage()


def _iteration(cfg: TrainConfig, stage: dict, wins: np.ndarray, data: TrainData,
               run: Run) -> None:
    """One update, its history row and counters, and the rollback guard."""
    model, optimizer = run.model, run.optimizer
    frames, params, conditions, lr = data.batch(cfg, stage, run.state, wins)
    for group in optimizer.param_groups:
        group["lr"] = lr
    optimizer.zero_grad(set_to_none=True)
    try:
        flow = GradientFlow(stage["flow"])
        loss = unrolled_loss(model, frames, params, conditions, flow, cfg.warmup, cfg.truncate)
        skipped = not torch.isfinite(loss)
        if not skipped:
            flow.backward(loss, list(model.parameters()))
    except BLOW_UPS:  # the coarse solver refused a state the model made
        loss, skipped = torch.tensor(float("nan")), True
    if not skipped:
        norm = float(torch.nn.utils.clip_grad_norm_(model.parameters(), float("inf")))
        skipped = run.spike(norm)
        if not skipped:
            optimizer.step()
    if run.record(stage, lr, loss.item(), skipped):
        run.guard()


#: updates per window of the rollback guard
ROLLBACK_WINDOW = 100


def _guard(factor: float, history: list[dict], state: dict, model, optimizer, best):
    """The divergence guard: after each window, remember the weights of the best window so far,
    or, when the window's median loss exceeds ``factor`` × the best, restore them and halve the
    learning rate. Unrolled NOG training can run away late in training (docs/results-notes.md,
    "Unrolling across seeds"): the loss rises 100x over ~100 updates, too gradually for the
    spike cutoff, and does not come back. Returns the (possibly new) best snapshot."""
    losses = [h["loss"] for h in history[-ROLLBACK_WINDOW:] if not h["skipped"]]
    median = float(np.median(losses)) if losses else math.inf
    if median < state["best"]:
        state["best"] = median
        return copy.deepcopy({"model": model.state_dict(), "optimizer": optimizer.state_dict()})
    if best is not None and not median <= factor * state["best"]:
        model.load_state_dict(best["model"])
        # Adam takes the state's tensors as its own and updates them in place: a copy keeps
        # the snapshot intact for a later rollback to it
        optimizer.load_state_dict(copy.deepcopy(best["optimizer"]))
        state["lr_scale"] *= 0.5
        state["rollbacks"] += 1
    return best


HISTORY_FIELDS = ("iteration", "stage", "m", "lr", "loss", "skipped")


def _write_history(history: list[dict], out: Path) -> None:
    write_history(out / "history.csv", history, HISTORY_FIELDS)
    plot_history(out / "training.png", {"loss": history}, "iteration", "loss", "iteration",
                 "unrolled MSE", smooth=max(1, len(history) // 50) if len(history) >= 20 else 0)


def describe(model: NeuralStepper) -> str:
    return f"{type(model.net).__name__}: {parameter_count(model.net):,} parameters"


