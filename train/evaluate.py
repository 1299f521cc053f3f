"""Evaluation of trained neural steppers (List et al.'s metrics) and the plots people look at.

* relative error over ``horizon`` steps (12 for KS): mean over space and time of
  (û − u)² / max(u²), max over the reference window, then mean over test rollouts;
* correlation time: the first step at which the spatial correlation between û and u falls
  below 0.2, averaged over rollouts (capped at the rollout length);
* long-rollout stability: the fraction of rollouts that stay finite and below 5× the
  reference's largest magnitude over ``long_steps`` steps (500 by default, ten or more
  correlation times; capped by the test trajectory's length);
* the same relative error for the coarse solver alone, the baseline a correction must beat;
  its median over rollouts is reported, since the coarse solver alone may blow up.
Evaluation runs under ``torch.no_grad()``: the solver stores no tape.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from adjointsim import NonFiniteInputError, NonFiniteStateError
from adjointsim.errors import UserError
from adjointsim.files import log_axis, pyplot, save_figure

from .data import Dataset, Split
from .model import NeuralStepper

TEST_SPLITS = ("interpolation", "extrapolation")
#: what a solver raises when a state is or becomes non-finite (the model's rollout blew up)
BLOW_UPS = (NonFiniteInputError, FloatingPointError)
#: steps shown in the error-over-time plots
PLOT_STEPS = 200
#: the name of each problem's state, on the colour bars of its rollout plots
QUANTITIES = {"ks": "u", "kolmogorov": "vorticity ω"}


@torch.no_grad()
def rollout(model: NeuralStepper, split: Split, steps: int, dtype: torch.dtype) -> np.ndarray:
    """Model rollouts from every test trajectory's first frame: (S, steps + 1, C, *grid).

    All trajectories advance together as one batch. A rollout that blows up (non-finite, or
    beyond 100× the reference's largest magnitude, well past the stability bound) is filled
    with inf from there on and continues from zeros, so it neither stops nor poisons the others.
    """
    traj = split.trajectories
    out = np.full((traj.shape[0], steps + 1, *traj.shape[2:]), np.inf)
    limit = 100 * np.max(np.abs(traj), axis=tuple(range(1, traj.ndim)))
    alive = np.ones(traj.shape[0], dtype=bool)
    u = torch.from_numpy(traj[:, 0]).to(dtype)
    params = torch.from_numpy(split.params)
    cond = torch.from_numpy(split.conditions)
    out[:, 0] = traj[:, 0]
    for k in range(1, steps + 1):
        u = _step_rows(model, u, params, cond)
        v = u.numpy()
        with np.errstate(invalid="ignore"):
            alive &= np.max(np.abs(v), axis=tuple(range(1, v.ndim))) <= limit
        if not alive.any():
            break
        out[alive, k] = v[alive]
        u[torch.from_numpy(~alive)] = 0
    return out


def _step_rows(model: NeuralStepper, u, params, cond) -> torch.Tensor:
    """One model step of a batch; if the solver refuses it, row by row (NaN for refused rows)."""
    try:
        return model(u, params, cond)
    except BLOW_UPS:
        rows = []
        for i in range(u.shape[0]):
            try:
                rows.append(model(u[i : i + 1], params[i : i + 1], cond[i : i + 1]))
            except BLOW_UPS:
                rows.append(torch.full_like(u[i : i + 1], float("nan")))
        return torch.cat(rows)


def coarse_rollout(model: NeuralStepper, split: Split, steps: int) -> np.ndarray:
    """The coarse solver alone from the same frames (float64); inf once it blows up."""
    out = np.full((split.trajectories.shape[0], steps + 1, *split.trajectories.shape[2:]), np.inf)
    for s in range(out.shape[0]):
        solver = model.solver(float(split.params[s]))
        u0 = split.trajectories[s, :1].astype(np.float64)
        try:
            out[s] = solver.rollout(u0, steps, keep="all")[:, 0]
        except NonFiniteStateError as e:  # keep the steps before the blow-up
            out[s, : e.step] = solver.rollout(u0, e.step - 1, keep="all")[:, 0]
    return out


def relative_error(pred: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Per rollout: mean over steps 1.. and space of (pred − ref)² / max(ref²)."""
    axes = tuple(range(1, pred.ndim))
    scale = np.max(ref[:, 1:] ** 2, axis=axes)
    with np.errstate(over="ignore", invalid="ignore"):
        err = np.mean((pred[:, 1:] - ref[:, 1:]) ** 2, axis=axes) / scale
    return np.where(np.isfinite(err), err, np.inf)


def error_over_time(pred: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Mean over rollouts and space of (pred − ref)² / max(ref²), per step: (steps + 1,); the
    max runs over steps 1.. of the window, as in :func:`relative_error`."""
    space = tuple(range(2, pred.ndim))
    scale = np.max(ref[:, 1:] ** 2, axis=(1, *space))[:, None]
    with np.errstate(over="ignore", invalid="ignore"):
        return np.mean(np.mean((pred - ref) ** 2, axis=space) / scale, axis=0)


def correlation_time(pred: np.ndarray, ref: np.ndarray, threshold: float = 0.2) -> np.ndarray:
    """Per rollout, the first step whose spatial correlation with the reference < threshold."""
    s, t = pred.shape[:2]
    a = pred.reshape(s, t, -1)
    b = ref.reshape(s, t, -1)
    with np.errstate(over="ignore", invalid="ignore"):  # blown-up (inf) rollouts give NaN
        a = a - a.mean(-1, keepdims=True)
        b = b - b.mean(-1, keepdims=True)
        corr = (a * b).sum(-1) / np.sqrt((a * a).sum(-1) * (b * b).sum(-1))
    below = ~(corr >= threshold)  # NaN (blown-up) counts as decorrelated
    return np.where(below.any(1), below.argmax(1), t - 1).astype(float)


def evaluate(
    model: NeuralStepper,
    dataset: Dataset,
    horizon: int = 12,
    dtype: torch.dtype = torch.float32,
    plots: Path | None = None,
    long_steps: int = 500,
) -> dict:
    """Metrics per test split and over all test rollouts; optional plots in ``plots``.

    The horizon must fit the test trajectories, and ``long_steps`` (capped by their length)
    must be at least the horizon. A metric is inf when a rollout blew up within the horizon.
    """
    longest = min(dataset.splits[name].trajectories.shape[1] for name in TEST_SPLITS) - 1
    if not 1 <= horizon <= longest:
        raise UserError(f"the horizon must be between 1 and {longest} steps (the length of the "
                        f"dataset's test trajectories), not {horizon}")
    if long_steps < horizon:
        raise UserError(f"long_steps ({long_steps}) must be at least the horizon ({horizon})")
    results: dict = {}
    errors, coarse_errors, corr_times, stable = [], [], [], []
    for name in TEST_SPLITS:
        split = dataset.splits[name]
        t = min(split.trajectories.shape[1] - 1, long_steps)
        long = rollout(model, split, t, dtype)
        ref = split.trajectories[:, : t + 1].astype(np.float64)
        err = relative_error(long[:, : horizon + 1], ref[:, : horizon + 1])
        base = coarse = None
        if model.setup == "correction":
            # Beyond the horizon only for the plot of its error over time.
            steps = min(t, max(horizon, PLOT_STEPS)) if plots is not None else horizon
            coarse = coarse_rollout(model, split, steps)
            base = relative_error(coarse[:, : horizon + 1], ref[:, : horizon + 1])
            coarse_errors.append(base)
        ct = correlation_time(long, ref)
        bound = 5 * np.max(np.abs(ref), axis=tuple(range(1, ref.ndim)))
        with np.errstate(invalid="ignore"):
            ok = np.all(np.isfinite(long), axis=tuple(range(1, long.ndim))) & (
                np.max(np.abs(long), axis=tuple(range(1, long.ndim))) <= bound
            )
        results[name] = {
            "rel_error": float(np.mean(err)),
            "coarse_rel_error": None if base is None else float(np.median(base)),
            "correlation_time": float(np.mean(ct)),
            "stable_fraction": float(np.mean(ok)),
        }
        errors.append(err)
        corr_times.append(ct)
        stable.append(ok)
        if plots is not None:
            plot_rollout(long, ref, Path(plots) / f"rollout-{name}.png", horizon, coarse,
                         QUANTITIES.get(dataset.problem.name, "u"))
    results["rel_error"] = float(np.mean(np.concatenate(errors)))
    results["coarse_rel_error"] = (
        float(np.median(np.concatenate(coarse_errors))) if coarse_errors else None
    )
    results["correlation_time"] = float(np.mean(np.concatenate(corr_times)))
    results["stable_fraction"] = float(np.mean(np.concatenate(stable)))
    return results


def plot_rollout(
    pred: np.ndarray, ref: np.ndarray, path: Path, horizon: int, coarse: np.ndarray | None = None,
    quantity: str = "u",
) -> None:
    """Space–time (1D) or snapshots (2D) of the first rollout against the reference, each with
    a colour bar of ``quantity``, and the error over time of all rollouts (and of the coarse
    solver alone, if given, until it blows up)."""
    from matplotlib import ticker

    plt = pyplot()

    path.parent.mkdir(parents=True, exist_ok=True)
    t = min(pred.shape[1], 4 * horizon + 1, PLOT_STEPS)
    fig, axes = plt.subplots(1, 3, figsize=(13.5, 3.6))
    cmap = plt.get_cmap("RdBu_r").with_extremes(bad="0.75")  # grey: the rollout blew up
    blown = np.flatnonzero(~np.all(np.isfinite(pred[0, :t]), axis=tuple(range(1, pred.ndim - 1))))
    if pred.ndim == 4:  # (S, T, 1, N): space–time diagrams
        lim = np.max(np.abs(ref[0, :t, 0]))
        after = f" (grey: blown up from step {blown[0]})" if blown.size else ""
        for ax, data, title in ((axes[0], ref[0, :t, 0], "reference"),
                                (axes[1], pred[0, :t, 0], f"model{after}")):
            im = ax.imshow(np.ma.masked_invalid(data.T), aspect="auto", origin="lower", cmap=cmap,
                           vmin=-lim, vmax=lim)
            ax.set(title=title, xlabel="step", ylabel="grid point")
            fig.colorbar(im, ax=ax, label=quantity)
    else:  # (S, T, 1, N, N): final snapshots
        k = min(t - 1, horizon)
        lim = np.max(np.abs(ref[0, k, 0]))
        after = f" (grey: blown up from step {blown[0]})" if blown.size and blown[0] <= k else ""
        for ax, data, title in ((axes[0], ref[0, k, 0], f"reference, step {k}"),
                                (axes[1], pred[0, k, 0], f"model, step {k}{after}")):
            im = ax.imshow(np.ma.masked_invalid(data.T), origin="lower", cmap=cmap, vmin=-lim,
                           vmax=lim)
            ax.set(title=title, xlabel="grid point x", ylabel="grid point y")
            fig.colorbar(im, ax=ax, label=quantity)

    def shown(curve: np.ndarray) -> np.ndarray:
        # A relative error above 10 only says "blown up", and 0 (the first frame) has no place
        # on a log axis: leave both out.
        with np.errstate(invalid="ignore"):
            return np.where(np.isfinite(curve) & (curve > 0) & (curve < 10), curve, np.nan)

    axes[2].plot(np.arange(t), shown(error_over_time(pred[:, :t], ref[:, :t])), label="model")
    if coarse is not None:
        tc = min(t, coarse.shape[1])
        axes[2].plot(np.arange(tc), shown(error_over_time(coarse[:, :tc], ref[:, :tc])), "r--",
                     label="coarse solver alone")
    axes[2].axvline(horizon, color="gray", lw=0.5, label=f"horizon ({horizon} steps)")
    log_axis(axes[2])
    axes[2].xaxis.set_major_locator(ticker.MaxNLocator(integer=True, steps=[1, 2, 5, 10]))
    axes[2].set(title="relative error over time, all rollouts", xlabel="step",
                ylabel="mean (model − reference)² / max reference²")
    axes[2].legend(fontsize=8)
    save_figure(fig, path, dpi=110)
