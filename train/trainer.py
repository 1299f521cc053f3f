"""The training loop: curriculum stages, ONE/NOG/WIG unrolling, atomic checkpoints, resume.

A run lives in one directory: ``config.json``, ``checkpoint.pt`` (written atomically every
``checkpoint_every`` iterations and at the end), ``history.csv`` and ``training.png``. A run
started again with ``resume=True`` continues from its checkpoint at the same stage, epoch and
batch, with the optimiser, the gradient-spike statistics and the data order restored, so it
ends with the same weights as an uninterrupted run.
"""

from __future__ import annotations

import csv
import json
import math
import tomllib
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from nets import DilatedResNet, ResNet, UNet, parameter_count

from . import data as datamod
from .atomic import atomic_path, write_text
from .evaluate import BLOW_UPS
from .model import NeuralStepper
from .problems import get_problem
from .unroll import MODES, unrolled_loss

CONV_NETS = {"resnet": ResNet, "dilated": DilatedResNet, "unet": UNet}
DTYPES = {"float32": torch.float32, "float64": torch.float64}


@dataclass
class TrainConfig:
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
    checkpoint_every: int = 200
    seed: int = 0
    #: torch threads; small convolutions run fastest on one, and 2-core machines are shared
    threads: int = 1
    #: stop after this many iterations in total (for tests and interrupted-run drills)
    max_iterations: int = 0

    @classmethod
    def load(cls, path: str | Path | None = None, **overrides: Any) -> TrainConfig:
        """A config from a TOML file (optional) with keyword overrides; unknown keys fail."""
        values: dict[str, Any] = {}
        if path is not None:
            with open(path, "rb") as f:
                values.update(tomllib.load(f))
        values.update({k: v for k, v in overrides.items() if v is not None})
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown config option(s) {unknown}; known: {sorted(known)}")
        cfg = cls(**values)
        cfg.validate()
        return cfg

    def validate(self) -> None:
        get_problem(self.problem)
        if self.mode not in MODES:
            raise ValueError(f"unknown mode {self.mode!r}; choose from {MODES}")
        if self.net not in CONV_NETS:
            raise ValueError(f"unknown net {self.net!r}; choose from {sorted(CONV_NETS)}")
        if self.dtype not in DTYPES:
            raise ValueError(f"dtype must be one of {sorted(DTYPES)}, not {self.dtype!r}")
        for name in ("warmup", "truncate"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be ≥ 0, not {getattr(self, name)}")
        for name in ("unroll", "batch", "stride", "lr_decay_every", "checkpoint_every", "threads",
                     "width", "blocks"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be ≥ 1, not {getattr(self, name)}")
        if self.epochs <= 0 or self.lr <= 0:
            raise ValueError(f"epochs and lr must be > 0, not {self.epochs} and {self.lr}")
        for stage in self.curriculum:
            if not (isinstance(stage, list | tuple) and len(stage) == 2):
                raise ValueError(f"curriculum stage {stage!r} is not an [m, lr] pair")
        for m, lr in self.stages():
            if m < 1 or lr <= 0:
                raise ValueError(f"curriculum stage (m={m}, lr={lr}) needs m ≥ 1 and lr > 0")

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
    """Per stage: unroll m, batch size, epochs and iterations per epoch (ONE scales by m)."""
    plan = []
    for m, lr in cfg.stages():
        one = cfg.mode == "ONE"
        batch = cfg.batch * m if one else cfg.batch
        epochs = cfg.epochs * m if one else cfg.epochs
        horizon = 1 if one else m
        n = n_windows_fn(horizon + cfg.warmup + 1)
        per_epoch = max(1, n // batch)
        plan.append({"m": horizon, "lr": lr, "batch": batch,
                     "iterations": int(math.ceil(epochs * per_epoch)), "per_epoch": per_epoch})
    return plan


def load_checkpoint(path: str | Path) -> dict:
    path = Path(path)
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # torch raises many types for damaged files
        raise ValueError(
            f"{path} is not a readable checkpoint ({type(e).__name__}: {e}); delete it and "
            "train again, or resume from an intact copy"
        ) from None


def train(cfg: TrainConfig, resume: bool = False, progress: bool = True) -> NeuralStepper:
    """Train a model as configured; returns it (also saved in ``cfg.out``)."""
    torch.set_num_threads(cfg.threads)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    dataset = datamod.load(cfg.data)
    if dataset.problem.name != cfg.problem:
        raise ValueError(f"{cfg.data} holds {dataset.problem.name!r} data, not {cfg.problem!r}")
    split = dataset.splits["train"]
    frames_all = torch.from_numpy(split.trajectories).to(DTYPES[cfg.dtype])
    params_all = torch.from_numpy(split.params)
    cond_all = torch.from_numpy(split.conditions)
    plan = _plan(cfg, lambda length: len(datamod.windows(split, length, cfg.stride)))

    model = build_model(cfg)
    optimizer = torch.optim.Adam(model.parameters(), lr=plan[0]["lr"])
    state = {"stage": 0, "iteration": 0, "total": 0, "grad_ema": 0.0, "skipped": 0}
    history: list[dict] = []
    ckpt_path = out / "checkpoint.pt"
    if resume and ckpt_path.exists():
        ckpt = load_checkpoint(ckpt_path)
        if ckpt["config"] != asdict(cfg) | {"max_iterations": ckpt["config"]["max_iterations"]}:
            raise ValueError(f"{ckpt_path} was written with another configuration; use a new --out")
        model.load_state_dict(ckpt["model"])
        optimizer.load_state_dict(ckpt["optimizer"])
        state, history = ckpt["state"], ckpt["history"]
    write_text(out / "config.json", json.dumps(asdict(cfg), indent=2))

    def save() -> None:
        with atomic_path(ckpt_path) as tmp:
            torch.save({"config": asdict(cfg), "model": model.state_dict(),
                        "optimizer": optimizer.state_dict(), "state": state,
                        "history": history}, tmp)

    total_iterations = sum(s["iterations"] for s in plan)
    bar = tqdm(total=total_iterations, initial=state["total"], desc=f"train {cfg.mode}",
               disable=not progress, unit="it")
    while state["stage"] < len(plan):
        stage = plan[state["stage"]]
        length = stage["m"] + cfg.warmup + 1
        wins = datamod.windows(split, length, cfg.stride)
        offsets = torch.arange(length)
        while state["iteration"] < stage["iterations"]:
            if cfg.max_iterations and state["total"] >= cfg.max_iterations:
                save()
                bar.close()
                return model
            it = state["iteration"]
            epoch, pos = divmod(it, stage["per_epoch"])
            # The order of an epoch depends only on (seed, stage, epoch): resumable.
            key = np.random.SeedSequence([cfg.seed, state["stage"], epoch]).generate_state(1)
            g = torch.Generator().manual_seed(int(key[0]))
            order = torch.randperm(len(wins), generator=g)
            pick = torch.from_numpy(wins)[order[pos * stage["batch"]:(pos + 1) * stage["batch"]]]
            traj, start = pick[:, 0], pick[:, 1]
            frames = frames_all[traj[:, None], start[:, None] + offsets]
            lr = stage["lr"] * cfg.lr_decay ** (it // cfg.lr_decay_every)
            for group in optimizer.param_groups:
                group["lr"] = lr
            optimizer.zero_grad(set_to_none=True)
            try:
                loss = unrolled_loss(model, frames, params_all[traj], cond_all[traj], cfg.mode,
                                     cfg.warmup, cfg.truncate)
                skipped = not torch.isfinite(loss)
                if not skipped:
                    loss.backward()
            except BLOW_UPS:  # the coarse solver refused a state the model made
                loss, skipped = torch.tensor(float("nan")), True
            if not skipped:
                norm = float(torch.nn.utils.clip_grad_norm_(model.parameters(), float("inf")))
                # The running mean restarts each stage (a longer unroll has larger gradients)
                # and also follows skipped norms, capped, so a lasting rise is let through.
                ema, cutoff = state["grad_ema"], cfg.spike_factor * state["grad_ema"]
                spike = it > 20 and norm > cutoff
                skipped = not math.isfinite(norm) or spike
                if math.isfinite(norm):
                    state["grad_ema"] = norm if ema == 0 else 0.95 * ema + 0.05 * min(norm, cutoff)
                if not skipped:
                    optimizer.step()
            state["skipped"] += skipped
            history.append({"iteration": state["total"], "stage": state["stage"],
                            "m": stage["m"], "lr": lr, "loss": loss.item(), "skipped": skipped})
            state["iteration"] += 1
            state["total"] += 1
            bar.update()
            bar.set_postfix(loss=f"{loss.item():.3e}", m=stage["m"])
            if state["total"] % cfg.checkpoint_every == 0:
                save()
        state["stage"] += 1
        state["iteration"] = 0
        state["grad_ema"] = 0.0
    bar.close()
    state["finished"] = True
    save()
    _write_history(history, out)
    return model


def _write_history(history: list[dict], out: Path) -> None:
    with atomic_path(out / "history.csv") as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["iteration", "stage", "m", "lr", "loss", "skipped"])
        writer.writeheader()
        writer.writerows(history)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    it = np.array([h["iteration"] for h in history])
    loss = np.array([h["loss"] for h in history])
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.semilogy(it, loss, lw=0.5, alpha=0.4, label="loss")
    if len(loss) >= 20:
        k = max(1, len(loss) // 50)
        smooth = np.convolve(loss, np.ones(k) / k, mode="valid")
        ax.semilogy(it[k - 1:], smooth, label=f"mean of {k}")
    ax.set_xlabel("iteration")
    ax.set_ylabel("unrolled MSE")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "training.png", dpi=120)
    plt.close(fig)


def describe(model: NeuralStepper) -> str:
    return f"{type(model.net).__name__}: {parameter_count(model.net):,} parameters"


