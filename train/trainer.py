"""``adjointsim train``: a neural time-stepper (prediction or correction) trained through its
coarse solver with ONE, NOG or WIG, as a problem on the run engine.

The engine (:mod:`adjointsim.engine`) owns the run directory: the claim (``resume``,
``overwrite``), ``config.json``, ``checkpoint.pt`` (every ``checkpoint_every`` iterations, at
least every 30 s, on Ctrl-C and at the end), ``history.csv`` (and ``curve.csv``, the test error
every ``eval_every`` updates), the progress bar and ``result.json``. This module holds what is
this problem's own: the config and its accepted values (:data:`ACCEPTED`), the model, the plan
of curriculum stages, one update (with the gradient-spike cutoff and the rollback guard), its
state, history rows, result and plot (``training.png``). A run continued with ``resume`` picks
up at the same stage, epoch and batch, with the optimiser, the spike statistics and the data
order restored, so it ends with the same weights as an uninterrupted run. ``max_iterations``
stops a run early, unfinished and resumable.

The solver's scene comes from the dataset (``adjointsim data --scene``); the ``scene`` key
may repeat it and is refused where it disagrees.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from adjointsim import engine
from adjointsim.errors import RunExists, UserError
from adjointsim.nets import DilatedResNet, ResNet, UNet, parameter_count
from adjointsim.run import SEEDS, Config, Interval, check_memory, plot_history

from . import data as datamod
from .checkpoint import STORE, load_checkpoint, restore
from .compiled import BACKENDS, DOUBLED_ERROR, compiled
from .evaluate import BLOW_UPS, TEST_SPLITS, relative_error, rollout
from .model import CORRECTIONS, SETUPS, NeuralStepper
from .problems import PROBLEMS, get_problem
from .threads import use_threads
from .unroll import MODES, GradientFlow, schedule, unrolled_loss

CONV_NETS = {"resnet": ResNet, "dilated": DilatedResNet, "unet": UNet}
DTYPES = {"float32": torch.float32, "float64": torch.float64}


#: the accepted values of every TrainConfig field: choices, an Interval, or (data, out,
#: curriculum, scene) checked by their own rule
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
    # (refused in TrainConfig.check).
    "rollback": Interval(0),
    "checkpoint_every": Interval(1),
    "seed": SEEDS,
    "threads": Interval(1),
    "max_iterations": Interval(0),
    "eval_every": Interval(0),
    "eval_horizon": Interval(1),
    "scene": "the dataset's scene keys (train takes the scene from its dataset)",
    "compile": BACKENDS,
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
    #: iterations between two checkpoints (and history writes)
    checkpoint_every: int = 200
    seed: int = 0
    #: torch's and the solver's threads (they take turns); small convolutions run fastest on
    #: one, and 2-core machines are shared
    threads: int = 1
    #: stop after this many iterations in total, unfinished (for tests and interrupted-run
    #: drills): continue with resume
    max_iterations: int = 0
    #: updates between two measurements of the test error along the way (``curve.csv``: the
    #: relative error over ``eval_horizon`` steps, the metric of the studies' tables, at
    #: update 0, every ``eval_every`` updates and at the end); 0: none. Neither key changes
    #: the training, so a run may be continued with other values
    eval_every: int = 0
    eval_horizon: int = 12
    #: the solver's scene: the dataset's (recorded here when the run starts); a key given
    #: must agree with it
    scene: dict = field(default_factory=dict)
    #: the update's loss eager (off) or through torch.compile with that backend
    #: (:mod:`adjointsim.train.compiled`); the same training, so a run may change it
    compile: str = "off"

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
        if self.compile != "off" and self.mode == "C":
            raise UserError(f"config key 'compile'{where}: {DOUBLED_ERROR}")
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
        return [(int(m), float(lr)) for m, lr in self.curriculum] or [(self.unroll, self.lr)]


def build_model(cfg: TrainConfig) -> NeuralStepper:
    """The untrained model ``cfg`` describes (its initialisation is the seed's)."""
    problem = get_problem(cfg.problem, cfg.scene)
    torch.manual_seed(cfg.seed)
    kwargs = {"width": cfg.width}
    if cfg.net == "resnet":
        kwargs["blocks"] = cfg.blocks
    # The state's channels plus the conditioning channel in, the state's channels out.
    net = CONV_NETS[cfg.net](problem.channels + 1, problem.channels, problem.dims,
                             padding=problem.padding, **kwargs).to(DTYPES[cfg.dtype])
    solver = problem.coarse if cfg.setup == "correction" else None
    return NeuralStepper(net, cfg.setup, solver, cfg.correction)


def describe(model: NeuralStepper) -> str:
    return f"{type(model.net).__name__}: {parameter_count(model.net):,} parameters"


def plan(cfg: TrainConfig, n_windows: Callable[[int], int]) -> list[dict]:
    """Per stage: the flow, unroll horizon, batch size, iterations per epoch and in all;
    ``n_windows(length)`` counts the training windows of ``length`` frames."""
    stages = []
    for m, lr in cfg.stages():
        flow, horizon, batch, epochs = schedule(cfg.mode, m, cfg.batch, cfg.epochs)
        n = n_windows(horizon + cfg.warmup + 1)
        per_epoch = max(1, n // batch)
        stages.append({"flow": flow, "m": horizon, "lr": lr, "batch": batch,
                       "iterations": int(math.ceil(epochs * per_epoch)), "per_epoch": per_epoch})
    return stages


# ----------------------------------------------------------------------------- the data
@dataclass
class TrainData:
    """A dataset's training split as tensors: what the members of an ensemble share."""

    split: Any
    frames: torch.Tensor
    params: torch.Tensor
    conditions: torch.Tensor
    #: the test splits, for the test error along the way (``eval_every``)
    tests: dict = field(default_factory=dict)

    @classmethod
    def of(cls, dataset: datamod.Dataset, dtype: str) -> TrainData:
        split = dataset.splits["train"]
        return cls(split, torch.from_numpy(split.trajectories).to(DTYPES[dtype]),
                   torch.from_numpy(split.params), torch.from_numpy(split.conditions),
                   {name: dataset.splits[name] for name in TEST_SPLITS})

    def test_error(self, model: NeuralStepper, horizon: int, dtype: str) -> float:
        """The relative error over ``horizon`` steps from every test trajectory's first frame,
        mean over the rollouts of both test splits: the ``rel_error`` of
        :func:`adjointsim.train.evaluate.evaluate` (which rolls out further, step by step the
        same), without its long rollouts and plots."""
        errors = [relative_error(rollout(model, split, horizon, DTYPES[dtype]),
                                 split.trajectories[:, :horizon + 1].astype(np.float64))
                  for split in self.tests.values()]
        return float(np.mean(np.concatenate(errors)))

    def plan_of(self, cfg: TrainConfig) -> list[dict]:
        """``cfg``'s plan on this split (an ensemble's members differ in their rates)."""
        return plan(cfg, lambda length: len(datamod.windows(self.split, length, cfg.stride)))

    def batch(self, cfg: TrainConfig, stage: dict, state: dict, wins: np.ndarray
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
        """The reference windows, scene parameters and conditions of a run's next update, and
        its learning rate."""
        it = state["iteration"]
        epoch, pos = divmod(it, stage["per_epoch"])
        order = epoch_order(cfg.seed, state["stage"], epoch, len(wins))
        pick = torch.from_numpy(wins)[order[pos * stage["batch"]:(pos + 1) * stage["batch"]]]
        traj, start = pick[:, 0], pick[:, 1]
        frames = self.frames[traj[:, None], start[:, None] + torch.arange(window(stage, cfg))]
        lr = stage["lr"] * cfg.lr_decay ** (it // cfg.lr_decay_every) * state["lr_scale"]
        return frames, self.params[traj], self.conditions[traj], lr


@functools.lru_cache(maxsize=8)
def epoch_order(seed: int, stage: int, epoch: int, windows: int) -> torch.Tensor:
    """The order of the windows in an epoch, which depends only on (seed, stage, epoch):
    resumable. Kept for the epoch's updates (an ensemble's members each have their own)."""
    key = np.random.SeedSequence([seed, stage, epoch]).generate_state(1)
    return torch.randperm(windows, generator=torch.Generator().manual_seed(int(key[0])))


def window(stage: dict, cfg: TrainConfig) -> int:
    """The frames of one reference window of ``stage``."""
    return stage["m"] + cfg.warmup + 1


def prepare(cfgs: list[TrainConfig]) -> tuple[list[TrainConfig], TrainData]:
    """Runs of ``cfgs`` (one, or an ensemble's members, of one dataset) as they start: checked,
    each with the dataset's scene recorded, and the dataset's training split."""
    for cfg in cfgs:
        cfg.validate()
    cfg = cfgs[0]
    use_threads(cfg.threads)
    dataset = datamod.load(cfg.data)
    if dataset.problem.name != cfg.problem:
        raise UserError(f"{cfg.data} holds {dataset.problem.name!r} data, not {cfg.problem!r}")
    theirs = dataset.problem.scene
    for key, value in cfg.scene.items():
        if theirs.get(key, object()) != value:
            was = f"{key} = {theirs[key]!r}" if key in theirs else f"no {key}"
            raise UserError(f"config key 'scene': {key} = {value!r} conflicts with the scene of "
                            f"the dataset {cfg.data} ({was}); train takes the scene from its "
                            "dataset: leave the key out, or train on data made with it")
    return ([dataclasses.replace(c, scene=dict(theirs)) for c in cfgs],
            TrainData.of(dataset, cfg.dtype))


# ----------------------------------------------------------------------------- the problem
#: updates per window of the rollback guard
ROLLBACK_WINDOW = 100
HISTORY_FIELDS = ("iteration", "stage", "m", "lr", "loss", "skipped")
#: the test error along the way (``eval_every``), one row per evaluation
CURVE_FIELDS = ("updates", "horizon", "rel_error")


class StepperRun(engine.Problem):
    """One neural-stepper run on the engine. Its pieces (:meth:`begin`, :meth:`batch`,
    :meth:`spike`, :meth:`record`, :meth:`guard`, :meth:`boundary`) also make an ensemble's
    update (:class:`adjointsim.train.ensemble.StepperEnsemble`)."""

    RESUMABLE = ("out", "threads", "max_iterations", "eval_every", "eval_horizon", "compile")
    ADDED = ("scene",)
    HISTORIES = {"history.csv": HISTORY_FIELDS}
    RUN_FILES = ("training.png", "results.json", "metrics.json", "rollout-*.png")
    RESULT_KEYS = {"iterations": int, "final_loss": float, "skipped": int, "rollbacks": int,
                   "parameters": int}
    UNIT = "it"
    STORE = STORE

    def __init__(self, config: TrainConfig, data: TrainData):
        super().__init__(config, config.out)
        self.config: TrainConfig = config
        self.data = data
        self.model: NeuralStepper | None = None
        if config.eval_every:  # this run's files: the test error's history besides the loss's
            self.HISTORIES = {**self.HISTORIES, "curve.csv": CURVE_FIELDS}

    def describe(self) -> str:
        return f"train {self.config.mode}"

    def build(self) -> None:
        cfg = self.config
        self.plan = self.data.plan_of(cfg)
        self.model = build_model(cfg)
        self.loss = compiled(unrolled_loss, cfg.compile)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=self.plan[0]["lr"])
        self.state = {"stage": 0, "iteration": 0, "total": 0, "grad_ema": 0.0, "skipped": 0,
                      "lr_scale": 1.0, "best": math.inf, "rollbacks": 0}
        #: the weights and optimiser state at state["best"], for a rollback
        self.kept: dict | None = None
        self.history: list[dict] = []
        self.curve: list[dict] = []
        self.wins: tuple[int, np.ndarray] | None = None

    # how far
    def total(self) -> int:
        return sum(s["iterations"] for s in self.plan)

    def position(self) -> int:
        return self.state["total"]

    def paused(self) -> bool:
        cap = self.config.max_iterations
        return super().paused() or bool(cap) and cap <= self.position() < self.total()

    def boundary(self) -> bool:
        """Whether the update just made ends a checkpoint interval, or was followed by an
        evaluation (its row is kept at once)."""
        evaluated = bool(self.curve) and self.curve[-1]["updates"] == self.state["total"]
        return self.state["total"] % self.config.checkpoint_every == 0 or evaluated

    def evaluation_due(self) -> bool:
        """Whether the test error is due at this point (``eval_every``: update 0, every
        ``eval_every`` updates, the end) and not yet measured."""
        every, total = self.config.eval_every, self.state["total"]
        return bool(every) and (total % every == 0 or total == self.total()) and not (
            self.curve and self.curve[-1]["updates"] == total)

    def evaluate_curve(self) -> None:
        """The curve's row at this point, from the model's current weights."""
        cfg = self.config
        self.curve.append({"updates": self.state["total"], "horizon": cfg.eval_horizon,
                           "rel_error": self.data.test_error(self.model, cfg.eval_horizon,
                                                             cfg.dtype)})

    def postfix(self) -> dict[str, Any]:
        return {"loss": f"{self.history[-1]['loss']:.3e}", "m": self.history[-1]["m"]}

    # one update
    def update(self) -> bool:
        if self.evaluation_due():  # the untrained model (update 0)
            self.evaluate_curve()
        stage, wins = self.begin()
        model, optimizer = self.model, self.optimizer
        frames, params, conditions, lr = self.batch(wins)
        for group in optimizer.param_groups:
            group["lr"] = lr
        optimizer.zero_grad(set_to_none=True)
        try:
            flow = GradientFlow(stage["flow"])
            loss = self.loss(model, frames, params, conditions, flow, self.config.warmup,
                             self.config.truncate)
            skipped = not torch.isfinite(loss)
            if not skipped:
                flow.backward(loss, list(model.parameters()))
        except BLOW_UPS:  # the coarse solver refused a state the model made
            loss, skipped = torch.tensor(float("nan")), True
        if not skipped:
            norm = float(torch.nn.utils.clip_grad_norm_(model.parameters(), float("inf")))
            skipped = self.spike(norm)
            if not skipped:
                optimizer.step()
        if self.record(stage, lr, loss.item(), skipped):
            self.guard()
        if self.evaluation_due():
            self.evaluate_curve()
        return self.boundary()

    def begin(self) -> tuple[dict, np.ndarray]:
        """The stage of the next update (the next stage once this one's iterations are done)
        and its training windows."""
        state = self.state
        if state["iteration"] >= self.plan[state["stage"]]["iterations"]:
            state["stage"] += 1
            state["iteration"] = 0
            state["grad_ema"] = 0.0
            state["best"], self.kept = math.inf, None  # a longer unroll has a larger loss
        stage = self.plan[state["stage"]]
        if self.wins is None or self.wins[0] != state["stage"]:
            self.wins = (state["stage"], datamod.windows(self.data.split,
                                                         window(stage, self.config),
                                                         self.config.stride))
        return stage, self.wins[1]

    def batch(self, wins: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
        """This run's next reference windows, parameters, conditions and learning rate."""
        return self.data.batch(self.config, self.plan[self.state["stage"]], self.state, wins)

    def spike(self, norm: float) -> bool:
        """Whether an update of gradient norm ``norm`` is skipped (not finite, or a spike);
        follows the running mean."""
        # The running mean restarts each stage (a longer unroll has larger gradients)
        # and also follows skipped norms, capped, so a lasting rise is let through.
        state = self.state
        ema, cutoff = state["grad_ema"], self.config.spike_factor * state["grad_ema"]
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
        return bool(self.config.rollback) and state["iteration"] % ROLLBACK_WINDOW == 0

    def guard(self) -> None:
        """The divergence guard: after each window, remember the weights of the best window so
        far, or, when the window's median loss exceeds ``rollback`` × the best, restore them
        and halve the learning rate. Unrolled NOG training can run away late in training
        (docs/results-notes.md, "Unrolling across seeds"): the loss rises 100x over ~100
        updates, too gradually for the spike cutoff, and does not come back."""
        state, model, optimizer = self.state, self.model, self.optimizer
        losses = [h["loss"] for h in self.history[-ROLLBACK_WINDOW:] if not h["skipped"]]
        median = float(np.median(losses)) if losses else math.inf
        if median < state["best"]:
            state["best"] = median
            self.kept = copy.deepcopy({"model": model.state_dict(),
                                       "optimizer": optimizer.state_dict()})
        elif self.kept is not None and not median <= self.config.rollback * state["best"]:
            model.load_state_dict(self.kept["model"])
            # Adam takes the state's tensors as its own and updates them in place: a copy
            # keeps the snapshot intact for a later rollback to it
            optimizer.load_state_dict(copy.deepcopy(self.kept["optimizer"]))
            state["lr_scale"] *= 0.5
            state["rollbacks"] += 1

    # what it keeps
    def state_dict(self) -> dict:
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                "kept": self.kept, "progress": dict(self.state)}

    def load_state_dict(self, state: dict) -> None:
        path = self.out / engine.CHECKPOINT
        if "progress" not in state:
            raise RunExists(f"{path} was written by an earlier version, which kept the weights "
                            "elsewhere: it can be evaluated but not continued; start the run "
                            "again with --overwrite, or into another --out")
        restore(self.model, state["model"], path)
        restore(self.optimizer, state["optimizer"], path)
        self.kept = state.get("kept")
        self.state |= state["progress"]

    def histories(self) -> dict[str, list[dict]]:
        return {"history.csv": self.history, "curve.csv": self.curve}

    def load_histories(self, histories: dict[str, list[dict]]) -> None:
        self.history = list(histories["history.csv"])
        # a run continued with eval_every set where it had none starts its curve there
        self.curve = list(histories.get("curve.csv", []))

    # the end
    def finish(self) -> dict:
        history = self.history
        return {"iterations": len(history), "skipped": sum(h["skipped"] for h in history),
                "rollbacks": self.state["rollbacks"],
                "final_loss": engine.finite_or_none(history[-1]["loss"]) if history else None,
                "parameters": parameter_count(self.model.net)}

    def plot(self) -> None:
        history = self.history
        plot_history(self.out / "training.png", {"loss": history}, "iteration", "loss",
                     "iteration", "unrolled MSE",
                     smooth=max(1, len(history) // 50) if len(history) >= 20 else 0)

    def trained(self) -> NeuralStepper:
        """The model: as trained here, or, for a finished run the engine returned as it was,
        as its checkpoint holds it."""
        return self.model if self.model is not None else load_model(self.out, warn=False)[0]


def train(cfg: TrainConfig, resume: bool = False, progress: bool = True,
          overwrite: bool = False) -> NeuralStepper:
    """Train a model as configured; returns it (also saved in ``cfg.out``).

    A ``cfg.out`` that already holds a run is refused unless ``resume`` (continue it from its
    checkpoint; a finished run is returned as it is) or ``overwrite`` (discard it) is given.
    """
    (cfg,), data = prepare([cfg])
    run = StepperRun(cfg, data)
    engine.run(run, resume=resume, overwrite=overwrite, progress=progress)
    return run.trained()


def load_model(run: str | Path, warn: bool = True) -> tuple[NeuralStepper, TrainConfig]:
    """The model of the run directory ``run``, and its config; an unfinished run's, with a
    warning unless ``warn`` is False."""
    run = Path(run)
    ckpt = load_checkpoint(run / engine.CHECKPOINT, ("config", "state"))
    cfg = TrainConfig(**ckpt["config"])
    state = ckpt["state"]
    # an earlier version kept the weights beside the state, and marked a finished run there
    progress, weights = (state["progress"], state["model"]) if "progress" in state else (
        state, ckpt["model"])
    if warn and not ((run / engine.RESULT).exists() or progress.get("finished")):
        warnings.warn(
            f"{run} holds an unfinished run (stopped after {progress['total']} iterations); "
            "finish it by running its `adjointsim train` command again with --resume, or "
            "expect a partly trained model",
            stacklevel=2,
        )
    model = build_model(cfg)
    restore(model, weights, run / engine.CHECKPOINT)
    return model, cfg
