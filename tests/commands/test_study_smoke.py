"""adjointsim study smoke: the book's smoke-to-target optimisation with the adjoint of
incompressible2d-sl. The tiny size runs both optimisers end to end and lowers the loss; the
objective's gradient agrees with central differences; the book's scene lifts the flow with a
step's own source; the book size runs and prints the book's losses beside ours."""

from __future__ import annotations

import json

import numpy as np
import pytest

from adjointsim.cli import main
from adjointsim.smoke_study import (
    BOOK,
    BOOK_LOSSES,
    LOCATIONS,
    STUDY,
    objective,
    scene,
    sources,
    summed,
)


def test_smoke_study_tiny(tmp_path, capsys):
    out = tmp_path / "smoke"
    argv = ["study", "smoke", "--size", "tiny", "--cluster", "none", "--no-progress",
            "--out", str(out), "--json", str(tmp_path / "rows.json")]
    assert main(argv) == 0
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert sorted(r["optimiser"] for r in rows) == ["gd", "lbfgs"]
    for r in rows:
        losses = [h["loss"] for h in r["history"]]
        seconds = [h["seconds"] for h in r["history"]]
        assert len(losses) == r["iterations_run"] + 1 == r["iterations"] + 1 == 6
        assert r["final_loss"] == losses[-1] < losses[0] == r["initial_loss"]
        assert all(b >= a for a, b in zip(seconds, seconds[1:]))
        assert np.asarray(r["fields"]["reached"]).shape == (16, 20)
    lbfgs = next(r for r in rows if r["optimiser"] == "lbfgs")
    assert lbfgs["reduction"] < 0.8
    assert "| lbfgs | (12, 4) |" in (out / "smoke.md").read_text()
    assert "| gd | (12, 4) |" in capsys.readouterr().out
    for name in ("loss.png", "fields.png"):
        assert (out / name).stat().st_size > 0


def test_smoke_objective_gradient_matches_central_differences():
    flow = scene(16, 20)
    n = 6
    rest = np.zeros(flow.state_shape(1))
    target = flow.rollout(rest, n, sources(flow, LOCATIONS[-1], n))[0, 2]
    fn, mask, last = objective(flow, n, sources(flow, LOCATIONS[0], n), target)
    rng = np.random.default_rng(0)
    z = 0.3 * rng.uniform(-1, 1, int(mask.sum()))
    d = rng.standard_normal(z.size)
    loss, grad = fn(z)
    assert last["loss"] == loss and np.array_equal(last["z"], z)
    eps = 1e-6  # small enough that no sample point crosses a cell edge
    fd = (fn(z + eps * d)[0] - fn(z - eps * d)[0]) / (2 * eps)
    assert abs(fd - grad @ d) <= 1e-6 * abs(fd)


def test_book_lift_is_the_buoyancy_of_the_steps_own_source():
    """The book adds a step's source before that step's buoyancy: from rest and empty, one
    step with the lift equals one step from the source's smoke already there (advection at
    rest leaves it in place), velocity and smoke; without the lift the flow stays at rest."""
    physics = {**BOOK, "advection": "semi-lagrangian"}
    flow = scene(16, 20, physics)
    ctrl = sources(flow, LOCATIONS[0], 1, physics)
    rest = np.zeros(flow.state_shape(1))
    lifted = flow.rollout(rest, 1, ctrl)
    there = rest.copy()
    there[0, 2] = ctrl[0, 0, 2] * flow.dt
    assert np.abs(lifted[0, 1]).max() > 0.1
    np.testing.assert_allclose(lifted, flow.rollout(there, 1, np.zeros_like(ctrl)), atol=1e-12)
    unlifted = flow.rollout(rest, 1, sources(flow, LOCATIONS[0], 1, {**physics, "lift": False}))
    assert np.abs(unlifted[0, :2]).max() == 0.0
    assert STUDY["lift"] is False


def test_summed_loss_keeps_a_stopped_run_at_its_last_point():
    rows = [{"optimiser": "gd", "history": [{"loss": v} for v in (4.0, 3.0, 2.0)]},
            {"optimiser": "lbfgs", "history": [{"loss": v} for v in (4.0, 1.0)]},
            {"optimiser": "lbfgs", "history": [{"loss": v} for v in (5.0, 4.0, 0.5)]}]
    assert summed(rows, "lbfgs") == {0: 9.0, 1: 5.0, 2: 1.5}
    assert summed(rows, "gd") == {0: 4.0, 1: 3.0, 2: 2.0}


@pytest.mark.slow
def test_smoke_study_book(tmp_path, capsys):
    """The book size: 80 gradient-descent steps on each of three plumes at the book's rate, and
    the report's table of the book's printed losses beside ours summed over the plumes; run
    again, it finds its rows finished."""
    out = tmp_path / "smoke"
    argv = ["study", "smoke", "--size", "book", "--cluster", "none", "--no-progress",
            "--out", str(out), "--json", str(tmp_path / "rows.json")]
    assert main(argv) == 0
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert len(rows) == 6 and all(r["advection"] == "maccormack" for r in rows)
    gd = summed(rows, "gd")
    assert len(gd) == 81 and gd[79] < 0.9 * gd[0]
    printed = capsys.readouterr().out
    for k, loss in BOOK_LOSSES.items():
        assert f"| {k} | {loss:.1f} | {gd[k]:.1f} |" in printed
    assert "| 79 / 0 | 0.57 |" in (out / "smoke.md").read_text()
    assert (out / "loss.png").stat().st_size > 0
    # a stopped L-BFGS-B row still belongs to its cell: a second run reports the same rows
    assert main(argv) == 0
    assert json.loads((tmp_path / "rows.json").read_text()) == rows
