"""The plots of the torch layer, inspected as matplotlib figures: rollout heat maps with
labelled colour bars and axes; learning curves with one colour per mode and the seeds told
apart by line style, which the legend says."""

from __future__ import annotations

import numpy as np
import pytest

from adjointsim import files
from adjointsim.train import evaluate
from adjointsim.train.studies import neural_steppers


def shown_labels(axis) -> list[str]:
    lo, hi = sorted(axis.get_view_interval())
    return [t.label1.get_text() for t in axis.get_major_ticks() + axis.get_minor_ticks()
            if t.label1.get_visible() and t.label1.get_text() and lo <= t.get_loc() <= hi]


@pytest.mark.parametrize("grid", [(16,), (8, 8)])
def test_rollout_plot_has_labelled_colour_bars_and_axes(tmp_path, figures, grid):
    rng = np.random.default_rng(0)
    ref = rng.standard_normal((2, 30, 1, *grid))
    pred = ref + 0.01 * rng.standard_normal(ref.shape) * np.arange(30)[:, None, None].reshape(
        (1, 30) + (1,) * (ref.ndim - 2))
    pred[0, 20:] = np.inf  # blown up
    evaluate.plot_rollout(pred, ref, tmp_path / "r.png", horizon=5, coarse=1.01 * ref,
                          quantity="vorticity ω")
    fig, = figures
    maps = [ax for ax in fig.axes if ax.images]
    assert len(maps) == 2
    for ax in maps:
        bar = ax.images[0].colorbar
        assert bar is not None and bar.ax.get_ylabel() == "vorticity ω"
        assert ax.get_xlabel() and ax.get_ylabel() and ax.get_title()
    error = next(ax for ax in fig.axes if ax.get_title().startswith("relative error"))
    assert error.get_xlabel() == "step" and "reference" in error.get_ylabel()
    ticks = shown_labels(error.yaxis)
    assert len(ticks) >= 2 and len(set(ticks)) == len(ticks)


def _write_history(path, losses):
    path.mkdir(parents=True)
    lines = ["iteration,stage,m,lr,loss,skipped"]
    lines += [f"{i},0,1,0.001,{v},False" for i, v in enumerate(losses)]
    (path / "history.csv").write_text("\n".join(lines) + "\n")


def test_learning_curves_one_colour_per_mode_seeds_by_line_style(tmp_path, figures):
    rows = []
    for mode in ("ONE", "NOG"):
        for seed in (0, 1):
            row = {"id": f"correction-{mode}-seed{seed}", "setup": "correction", "mode": mode,
                   "seed": seed}
            _write_history(tmp_path / row["id"], [1.0 / (i + 1 + seed) for i in range(50)])
            rows.append(row)
    neural_steppers._plot_curves(rows, tmp_path, files.pyplot())
    fig, = figures
    ax, = fig.axes
    drawn = {line.get_gid(): line for line in ax.get_lines() if line.get_gid()}
    assert sorted(drawn) == sorted(r["id"] for r in rows)
    style = {r["id"]: (drawn[r["id"]].get_color(), drawn[r["id"]].get_linestyle()) for r in rows}
    for mode in ("ONE", "NOG"):
        (c0, s0), (c1, s1) = style[f"correction-{mode}-seed0"], style[f"correction-{mode}-seed1"]
        assert c0 == c1 and s0 != s1
    assert style["correction-ONE-seed0"][0] != style["correction-NOG-seed0"][0]
    legend = ax.get_legend()
    assert [t.get_text() for t in legend.get_texts()] == ["NOG", "ONE", "seed 0", "seed 1"]
    assert legend.get_title().get_text() == "colour: mode, line style: seed"
    # 50 updates: the medians are over blocks of 2, and the label says so
    assert ax.get_ylabel() == "training loss (median of blocks of 2 updates)"
    ticks = shown_labels(ax.yaxis)
    assert len(ticks) >= 2 and len(set(ticks)) == len(ticks)
