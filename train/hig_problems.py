"""The half-inverse gradients problems and their timed, resumable training runs
(``adjointsim hig``).

Problems, with the settings of Schnell, Holl & Thuerey (ICLR 2022) and their reference code
(deviations are marked):

* ``oscillators``: 2 coupled nonlinear oscillators (``oscillators-rk4``, Δt = 0.125, 96 steps),
  x ~ U[0, 1)⁴, the network 4 → 20 ×3 (ReLU) → 96 controls must bring the state back to x;
  loss ‖y − x‖². Adam batch 512, lr 3e-4; HIG and GN batch 128, lr 1, τ = 1e-6.
* ``quantum``: ``schrodinger1d-cn``, 14 interior points on (0, 2), m = ½ (H = −∂xx + u x),
  Δt = 0.05, 384 steps, from the ground state to a random normalised real superposition of
  the eigenstates 2 and 3; loss 1 − |⟨ψ*|ψ_T⟩|². Network 28 → 20 ×3 (tanh) → 384. Adam batch
  256, lr 5e-4; HIG batch 16, lr 0.5, τ = 1e-5; GN (not given by the paper) as HIG. As in the
  reference code, states enter the network and the loss with unit Euclidean norm,
  Σ_j |ψ_j|² = 1 (the solver's ψ times √h): HIG's step is not invariant to that scale.
* ``poisson``: 8×8 cells of unit width (the reference's PhiFlow grid), zero Dirichlet, the
  5-point Laplacian of ``poisson2d``. As in the reference: x* is PhiFlow's ``Noise`` (a periodic
  field with a 1/k² spectrum, zero mean and unit standard deviation per sample), y = Δ x*; the
  network 64 → 64 → 128 → 64 → 64 (tanh) maps y to x̂, loss ‖Δ x̂ − y‖², fresh samples every
  step. Adam batch 64, lr 3e-4; HIG τ = 1e-5. The reference's HIG lr 0.01 acts on the gradient
  of ½ Σ_batch ‖Δ x̂ − y‖², b/2 times ours (the batch mean of ‖·‖²), so ours is 0.01 · b/2.
  Deviation: HIG and GN use batch 4, not 64: at 64 one update takes 26 s on one core (nearly
  all of it the eigendecomposition of the 4096 × 4096 Gram matrix), 23 updates in 600 s.
* ``chain``: the PBDL book's linear chain (2 masses, coupling 0.2, RK4, Δt = 0.5, 24 steps),
  network 4 → 20 ×3 (tanh) → 24; HIG batch 32, lr 1, τ = 1e-10; Adam batch 256, lr 1e-3;
  GN as HIG; 100 s budget.

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
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from adjointsim.errors import UserError
from adjointsim.files import pyplot, save_figure, uninterrupted, write_json, write_text
from adjointsim.nets.mlp import MLP
from adjointsim.run import (
    SEEDS,
    Config,
    Interval,
    discard,
    finished_result,
    holds_run,
    plot_history,
    write_history,
)
from adjointsim.solvers.oscillators import Oscillators
from adjointsim.solvers.poisson import Poisson2D
from adjointsim.solvers.schrodinger import SchrodingerCN
from adjointsim.stepper import NonFiniteInputError, NonFiniteStateError

from .checkpoint import load_run_checkpoint, restore, save_checkpoint
from .hig import HalfInverseGradients, SolverPhysics, TorchPhysics
from .threads import use_threads

PROBLEMS = ("oscillators", "quantum", "poisson", "chain")
OPTIMIZERS = ("adam", "gn", "hig")
#: data set sizes: "tiny" shrinks them (tests, the study's smoke size); "quick" is "full"
SIZES = ("tiny", "quick", "full")
DTYPE = torch.float64
#: default time budgets (s): the paper's hour is out of reach on a shared 2-core machine
BUDGETS = {"oscillators": 600.0, "quantum": 600.0, "poisson": 600.0, "chain": 100.0}
Batch = tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # network input, physics context, target


@dataclass
class HigProblem:
    name: str
    model: Callable[[], torch.nn.Module]
    physics: SolverPhysics | TorchPhysics
    loss: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
    #: draws a training batch of the given size from a torch generator
    sample: Callable[[torch.Generator, int], Batch]
    test: Batch
    #: per optimizer: batch, lr and (HIG/GN) tau
    settings: dict[str, dict[str, float]] = field(default_factory=dict)


def _squared_error(y: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return ((y - target) ** 2).sum(dim=1)


def _from_dataset(x: torch.Tensor, context: torch.Tensor, target: torch.Tensor):
    def sample(gen: torch.Generator, batch: int) -> Batch:
        idx = torch.randperm(x.shape[0], generator=gen)[:batch]
        return x[idx], context[idx], target[idx]

    return sample


def _oscillator_problem(stepper: Oscillators, steps: int, activation: str, n_train: int,
                        n_test: int, seed: int, settings: dict) -> HigProblem:
    rng = np.random.default_rng(seed)
    train = torch.from_numpy(rng.random((n_train, 4)))
    test = torch.from_numpy(rng.random((n_test, 4)))
    physics = SolverPhysics(stepper, steps, lambda c: c.reshape(-1, 2, 2))
    return HigProblem(
        name="",
        model=lambda: MLP(4, steps, width=20, depth=3, activation=activation).to(DTYPE),
        physics=physics,
        loss=_squared_error,
        sample=_from_dataset(train, train, train),
        test=(test, test, test),
        settings=settings,
    )


def _quantum(seed: int, n_data: int) -> HigProblem:
    s = SchrodingerCN(n=14, length=2.0, dt=0.05, mass=0.5)
    steps = 384

    def mode(k: int) -> np.ndarray:
        """Box eigenstate k with unit Euclidean norm (the solver's normalisation / √h)."""
        m = np.sin(k * np.pi * s.x / s.length)
        return m / np.linalg.norm(m)

    root_h = np.sqrt(s.h)
    ground = torch.from_numpy(np.stack([mode(1), np.zeros(s.n)]) / root_h)
    rng = np.random.default_rng(seed)

    def targets(count: int) -> torch.Tensor:
        c = rng.standard_normal((count, 2))
        c /= np.linalg.norm(c, axis=1, keepdims=True)
        psi = c[:, :1] * mode(2) + c[:, 1:] * mode(3)
        return torch.from_numpy(np.concatenate([psi, np.zeros_like(psi)], axis=1))

    def infidelity(y: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        n = s.n
        yr, yi, tr, ti = y[:, :n], y[:, n:], target[:, :n], target[:, n:]
        re = (tr * yr + ti * yi).sum(dim=1)
        im = (tr * yi - ti * yr).sum(dim=1)
        return 1.0 - (re**2 + im**2)

    train, test = targets(n_data), targets(n_data)
    empty = torch.zeros(n_data, 0, dtype=DTYPE)
    physics = SolverPhysics(s, steps, lambda c: ground.expand(c.shape[0], 2, s.n), scale=root_h)
    return HigProblem(
        name="quantum",
        model=lambda: MLP(2 * s.n, steps, width=20, depth=3, activation="tanh").to(DTYPE),
        physics=physics,
        loss=infidelity,
        sample=_from_dataset(train, empty, train),
        test=(test, empty, test),
        settings={
            "adam": {"batch": 256, "lr": 5e-4},
            "hig": {"batch": 16, "lr": 0.5, "tau": 1e-5},
            "gn": {"batch": 16, "lr": 0.5, "tau": 1e-5},
        },
    )


def five_point_laplacian(x: torch.Tensor, inv_h2: float, n: int) -> torch.Tensor:
    """The 5-point Δ_h with zero Dirichlet boundaries on flattened n × n fields (b, n²)."""
    u = torch.nn.functional.pad(x.reshape(-1, 1, n, n), (1, 1, 1, 1))
    c = u[..., 1:-1, 1:-1]
    lap = u[..., :-2, 1:-1] + u[..., 2:, 1:-1] + u[..., 1:-1, :-2] + u[..., 1:-1, 2:] - 4 * c
    return (inv_h2 * lap).reshape(x.shape[0], n * n)


def phiflow_noise(rng: np.random.Generator, count: int, n: int) -> np.ndarray:
    """``count`` fields like PhiFlow's ``Noise()`` on n × n unit cells, flattened (count, n²):
    complex white noise times 1/k² (k = 0 dropped), real part, unit std, zero mean."""
    k = np.fft.fftfreq(n) * n
    k2 = k[:, None] ** 2 + k[None, :] ** 2
    weight = np.divide(1.0, k2, out=np.zeros_like(k2), where=k2 > 0)
    z = rng.standard_normal((count, n, n)) + 1j * rng.standard_normal((count, n, n))
    x = np.fft.ifft2(z * weight).real
    x /= x.std(axis=(1, 2), keepdims=True)
    x -= x.mean(axis=(1, 2), keepdims=True)
    return x.reshape(count, n * n)


def _poisson(seed: int, n_test: int) -> HigProblem:
    solver = Poisson2D(n=8, bc="dirichlet", length=9.0)  # h = 1: the reference's unit cells
    n, inv_h2 = solver.n, solver.inv_h2

    def fields(rng: np.random.Generator, count: int) -> torch.Tensor:
        return five_point_laplacian(torch.from_numpy(phiflow_noise(rng, count, n)), inv_h2, n)

    test_y = fields(np.random.default_rng(seed), n_test)
    pool: list[torch.Tensor] = []

    def sample(gen: torch.Generator, batch: int) -> Batch:
        # Fresh fields every step, made 4096 at a time (one FFT batch, not one per step).
        if not pool or pool[0].shape[0] < batch:
            rng = np.random.default_rng(int(torch.randint(2**62, (1,), generator=gen)))
            pool[:] = [fields(rng, max(4096, batch))]
        y, pool[0] = pool[0][:batch], pool[0][batch:]
        return y, torch.zeros(batch, 0, dtype=DTYPE), y

    physics = TorchPhysics(lambda f, _c: five_point_laplacian(f, inv_h2, n))
    batch = 4
    return HigProblem(
        name="poisson",
        model=lambda: MLP(n * n, n * n, widths=(64, 128, 64), activation="tanh").to(DTYPE),
        physics=physics,
        loss=_squared_error,
        sample=sample,
        test=(test_y, torch.zeros(n_test, 0, dtype=DTYPE), test_y),
        settings={
            "adam": {"batch": 64, "lr": 3e-4},
            "hig": {"batch": batch, "lr": 0.01 * batch / 2, "tau": 1e-5},
            "gn": {"batch": batch, "lr": 0.01 * batch / 2, "tau": 1e-5},
        },
    )


def make_problem(name: str, seed: int, size: str = "full") -> HigProblem:
    """Problem ``name`` with data drawn from ``seed``; ``size="tiny"`` shrinks the data sets
    (tests and the study's smoke size), nothing else."""
    if name not in PROBLEMS:
        raise ValueError(f"unknown HIG problem {name!r}; choose one of {', '.join(PROBLEMS)}")
    if size not in SIZES:
        raise ValueError(f"size must be one of {', '.join(SIZES)}, not {size!r}")
    tiny = size == "tiny"
    if name == "oscillators":
        p = _oscillator_problem(
            Oscillators(), 96, "relu", 256 if tiny else 4096, 256 if tiny else 4096, seed,
            {"adam": {"batch": 512, "lr": 3e-4}, "hig": {"batch": 128, "lr": 1.0, "tau": 1e-6},
             "gn": {"batch": 128, "lr": 1.0, "tau": 1e-6}},
        )
    elif name == "chain":
        p = _oscillator_problem(
            Oscillators.linear_chain(), 24, "tanh", 256 if tiny else 4096,
            256 if tiny else 4096, seed,
            {"adam": {"batch": 256, "lr": 1e-3}, "hig": {"batch": 32, "lr": 1.0, "tau": 1e-10},
             "gn": {"batch": 32, "lr": 1.0, "tau": 1e-10}},
        )
    elif name == "quantum":
        p = _quantum(seed, 64 if tiny else 1024)
    else:
        p = _poisson(seed, 64 if tiny else 1024)
    p.name = name
    return p


def test_loss(problem: HigProblem, model: torch.nn.Module) -> float:
    """Mean per-sample loss on the test set; inf when the physics blows up."""
    x, c, t = problem.test
    with torch.no_grad():
        try:
            value = float(problem.loss(problem.physics(model(x), c), t).mean())
        except (NonFiniteStateError, NonFiniteInputError):
            return math.inf
    return value if math.isfinite(value) else math.inf


# --------------------------------------------------------------------------- training runs
ACCEPTED: dict[str, tuple | Interval | str] = {
    "problem": PROBLEMS,
    "optimizer": OPTIMIZERS,
    "seed": SEEDS,
    # seconds of update time; unset, the problem's entry of BUDGETS
    "budget": Interval(0, lo_open=True),
    "size": SIZES,
    "max_updates": Interval(1),
    "threads": Interval(1),
}


@dataclass
class HigConfig(Config):
    """One run: ``problem`` trained by ``optimizer`` until ``budget`` seconds of update time
    (None: the problem's entry of :data:`BUDGETS`) or ``max_updates`` updates are spent."""

    problem: str
    optimizer: str = "hig"
    seed: int = 0
    budget: float | None = None
    size: str = "full"
    max_updates: int | None = None
    #: torch's and the solver's threads (they take turns); more of them buy more updates
    #: within the budget
    threads: int = 1

    ACCEPTED: ClassVar[dict[str, tuple | Interval | str]] = ACCEPTED

    def check(self, where: str) -> None:
        if self.budget is None:
            self.budget = BUDGETS[self.problem]


#: what a run may be resumed with other values of (and what a run recorded before it was a key
#: lacks)
RESUMABLE = ("threads",)
HISTORY_FIELDS = ("update", "wall_s", "train_loss", "test_loss")
#: what a run directory holds besides config.json, checkpoint.pt and result.json
RUN_FILES = ("history.csv", "loss.png")


def train_run(cfg: HigConfig, out: Path, resume: bool = False, overwrite: bool = False,
              progress: bool = True, plot: bool = True) -> dict:
    """Train ``cfg.problem`` with ``cfg.optimizer`` for ``cfg.budget`` seconds of update time.

    Writes ``out/history.csv``, ``out/loss.png`` (if ``plot``) and, when finished,
    ``out/result.json``; ``out/checkpoint.pt`` (atomic, every 30 s of real time and on Ctrl-C)
    lets an interrupted run resume. A run already in ``out`` is continued with ``resume`` (a
    finished one's result is returned as it is), discarded with ``overwrite``, and otherwise
    refused.
    """
    if resume and overwrite:
        raise UserError("--resume continues a run and --overwrite discards it: pass one")
    cfg.validate()
    use_threads(cfg.threads)
    out = Path(out)
    result_path, ckpt_path = out / "result.json", out / "checkpoint.pt"
    config = cfg.as_dict()
    if overwrite and holds_run(out, config, RESUMABLE):  # never somebody else's files
        discard(out, RUN_FILES)
    finished = finished_result(out, resume, config, ("wall_s", "updates", "test_loss"),
                               RESUMABLE)
    if finished is not None:
        return finished
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    problem = make_problem(cfg.problem, cfg.seed, cfg.size)
    settings = problem.settings[cfg.optimizer]
    model = problem.model()
    opt = _make_optimizer(cfg, problem, model)
    gen = torch.Generator().manual_seed(cfg.seed + 1)
    state = {"wall": 0.0, "updates": 0, "next_eval": 0.0, "history": [], "losses": [],
             "diverged": False}
    if ckpt_path.exists():
        ckpt = load_run_checkpoint(ckpt_path, config,
                                   ("config", "model", "optimizer", "generator", "state"),
                                   RESUMABLE)
        restore(model, ckpt["model"], ckpt_path)
        if cfg.optimizer == "adam":
            restore(opt, ckpt["optimizer"], ckpt_path)
        gen.set_state(ckpt["generator"])
        state = ckpt["state"]
    write_text(out / "config.json", json.dumps(config, indent=2))

    def evaluate() -> None:
        train = float(np.mean(state["losses"])) if state["losses"] else math.nan
        state["history"].append({"update": state["updates"], "wall_s": state["wall"],
                                 "train_loss": train, "test_loss": test_loss(problem, model)})
        state["losses"] = []
        state["next_eval"] = max(0.02, 1.4 * state["wall"])

    def checkpoint() -> None:
        save_checkpoint({"config": config, "model": model.state_dict(),
                         "optimizer": opt.state_dict() if cfg.optimizer == "adam" else None,
                         "generator": gen.get_state(), "state": state}, ckpt_path)
        write_history(out / "history.csv", state["history"], HISTORY_FIELDS)

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=round(cfg.budget, 1), initial=round(state["wall"], 1), unit="s",
                   desc=f"{cfg.problem}/{cfg.optimizer}/seed {cfg.seed}", leave=False)

    def done() -> bool:
        return (state["diverged"] or state["wall"] >= cfg.budget
                or (cfg.max_updates is not None and state["updates"] >= cfg.max_updates))

    if not done():
        _warm_up(cfg, problem, model)
    try:
        _loop(cfg, problem, settings, model, opt, gen, state, evaluate, checkpoint, done, bar)
    except KeyboardInterrupt:
        checkpoint()
        raise
    if not state["history"] or state["history"][-1]["update"] != state["updates"]:
        evaluate()  # (not again when resumed after the last checkpoint)
    if bar is not None:
        bar.close()
    checkpoint()
    final = state["history"][-1]
    result = {
        **config,
        "wall_s": state["wall"],
        "updates": state["updates"],
        "test_loss": final["test_loss"] if math.isfinite(final["test_loss"]) else None,
        "diverged": state["diverged"],
    }
    if plot:  # before result.json: a run stopped while plotting resumes to the plot
        plot_test_losses(out / "loss.png", {cfg.optimizer: state["history"]},
                         f"{cfg.problem}, seed {cfg.seed}")
    write_json(result_path, result)
    return result


def _make_optimizer(cfg: HigConfig, problem: HigProblem, model: torch.nn.Module):
    settings = problem.settings[cfg.optimizer]
    if cfg.optimizer == "adam":
        return torch.optim.Adam(model.parameters(), lr=settings["lr"])
    return HalfInverseGradients(
        model, problem.physics, problem.loss, lr=settings["lr"],
        kappa=0.5 if cfg.optimizer == "hig" else 1.0, tau=settings["tau"],
    )


def _update(problem: HigProblem, model: torch.nn.Module, opt, batch: Batch) -> float:
    """One update; returns the batch's mean loss before it."""
    if isinstance(opt, HalfInverseGradients):
        return opt.step(*batch)
    x, c, t = batch
    opt.zero_grad()
    loss = problem.loss(problem.physics(model(x), c), t).mean()
    loss.backward()
    opt.step()
    return float(loss.detach())


def _warm_up(cfg: HigConfig, problem: HigProblem, model: torch.nn.Module) -> None:
    """One untimed update of a copy of the model on the first test samples: loading numba's
    cached kernels and torch.func's first tracing (seconds, once per process) stay out of the
    timed updates, for every optimizer alike."""
    twin = copy.deepcopy(model)
    batch = int(problem.settings[cfg.optimizer]["batch"])
    with contextlib.suppress(FloatingPointError, NonFiniteStateError, NonFiniteInputError):
        _update(problem, twin, _make_optimizer(cfg, problem, twin),
                tuple(a[:batch] for a in problem.test))


def _loop(cfg, problem, settings, model, opt, gen, state, evaluate, checkpoint, done, bar):
    last_save = time.monotonic()
    while not done():
        if state["wall"] >= state["next_eval"]:
            evaluate()
            if bar is not None:
                bar.set_postfix(test=f"{state['history'][-1]['test_loss']:.3g}")
        with uninterrupted():
            x, c, t = problem.sample(gen, int(settings["batch"]))
            t0 = time.process_time()
            try:
                value = _update(problem, model, opt, (x, c, t))
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
        if bar is not None:
            bar.update(round(state["wall"], 1) - bar.n)
        if time.monotonic() - last_save > 30.0:
            checkpoint()
            last_save = time.monotonic()


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
