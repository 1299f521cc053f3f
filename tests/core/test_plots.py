"""The plots people read, inspected as matplotlib figures: every scheme of the stability sweep
has a panel and the title fits; the shared history plot has log ticks whose labels differ and a
moving mean only where there are enough points, named by its window."""

from __future__ import annotations

import pytest

from adjointsim import files, run, stability


def labels(axis, minor: bool = False) -> list[str]:
    """The tick labels shown inside the view."""
    lo, hi = sorted(axis.get_view_interval())
    ticks = axis.get_minor_ticks() if minor else axis.get_major_ticks()
    return [t.label1.get_text() for t in ticks
            if t.label1.get_visible() and t.label1.get_text() and lo <= t.get_loc() <= hi]


def assert_readable(axis, least: int = 2) -> None:
    shown = labels(axis) + labels(axis, minor=True)
    assert len(shown) >= least, f"fewer than {least} tick labels: {shown}"
    assert len(set(shown)) == len(shown), f"repeated tick labels: {shown}"


def inside(artist, fig) -> bool:
    box, page = artist.get_window_extent(), fig.bbox
    return page.x0 <= box.x0 and box.x1 <= page.x1 and page.y0 <= box.y0 and box.y1 <= page.y1


def _row(scheme, n, found, stated, coefficients=None):
    return {"id": scheme, "scheme": scheme, "n": n, "coefficients": coefficients or {},
            "default_dt": 0.01, "params": {}, "stated": stated, "found": found,
            "verdict": stability.verdict(stated, found)}


def test_stability_plot_has_every_scheme_and_its_title_fits(tmp_path, figures):
    rows = [_row("advection1d-upwind", 16, 0.065, 0.0625),
            _row("advection1d-upwind", 32, 0.033, 0.03125),
            _row("oscillators-rk4", None, 2.229, 2.828),  # no grid size: n is not a grid
            _row("cartpole", None, 0.521, None),
            _row("guidance", None, None, None)]  # stable up to the search cap
    stability.report(rows, tmp_path)
    fig, = figures
    panels = [ax for ax in fig.axes if ax.get_visible() and ax.axison]
    assert len(panels) == 2  # the advection1d family, and the schemes without a grid
    named = {t.get_text() for ax in panels for t in ax.get_xticklabels()}
    named |= {t.get_text() for ax in panels if ax.get_legend()
              for t in ax.get_legend().get_texts()}
    assert {"upwind", "oscillators-rk4", "cartpole", "guidance"} <= named
    assert inside(fig._suptitle, fig)
    for ax in panels:
        assert ax.get_ylabel() and ax.get_xlabel()
        assert_readable(ax.yaxis)


@pytest.mark.parametrize("row, named", [
    (_row("oscillators-rk4", None, 2.229, 2.828), "oscillators-rk4"),
    (_row("advection1d-upwind", 16, 0.065, 0.0625), "upwind")])
def test_stability_plot_of_one_panel_fits_its_title(tmp_path, figures, row, named):
    stability.report([row], tmp_path)
    fig, = figures
    ax, = fig.axes
    legend = [t.get_text() for t in ax.get_legend().get_texts()] if ax.get_legend() else []
    assert named in [t.get_text() for t in ax.get_xticklabels()] + legend
    assert inside(fig._suptitle, fig)


def _history(values):
    return [{"epoch": i + 1, "test_loss": v} for i, v in enumerate(values)]


@pytest.mark.parametrize("values", [
    [1.984281, 1.983932],  # two epochs, a change of 2e-4
    [7.429998e-3, 7.430005e-3],  # a change of 1e-6: matplotlib's labels repeat
    [0.0301, 0.0652],  # under a decade with no power of ten inside
    [0.3, 2.0],
    [1e-6, 1e2],
    [2.5],  # one epoch
])
def test_history_plot_log_ticks_read(tmp_path, figures, values):
    run.plot_history(tmp_path / "h.png", {"C": _history(values)}, "epoch", "test_loss",
                     "epoch", "test loss", title="cartpole", smooth=30)
    fig, = figures
    ax = fig.axes[0]
    assert_readable(ax.yaxis)
    assert_readable(ax.xaxis, least=min(2, len(values)))
    assert all(float(t).is_integer() for t in labels(ax.xaxis))  # epochs are whole numbers
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["C"]  # no mean of 30


def test_history_plot_names_the_window_it_draws(tmp_path, figures):
    curves = {"short": _history([1.0 / (i + 1) for i in range(40)]),
              "long": _history([2.0 / (i + 1) for i in range(200)])}
    run.plot_history(tmp_path / "h.png", curves, "epoch", "test_loss", "epoch", "loss",
                     smooth=30)
    legend = [t.get_text() for t in figures[0].axes[0].get_legend().get_texts()]
    assert legend == ["short", "short, moving mean of 13 points",
                      "long", "long, moving mean of 30 points"]
    means = [line for line in figures[0].axes[0].get_lines() if "mean" in line.get_label()]
    assert [len(line.get_xdata()) for line in means] == [40 - 12, 200 - 29]


@pytest.mark.parametrize("lo, hi", [(1.98, 1.99), (9.251572, 9.251579), (0.9, 1.1),
                                    (0.03, 0.065), (0.08, 1.2), (1e-8, 1e3), (2e-5, 3e-5)])
def test_log_axis_labels_differ(lo, hi):
    plt = files.pyplot()
    fig, ax = plt.subplots(figsize=(4, 3))
    ax.plot([0, 1], [lo, hi])
    files.log_axis(ax)
    fig.canvas.draw()
    assert_readable(ax.yaxis)
    plt.close(fig)
