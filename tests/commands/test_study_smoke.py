"""adjointsim study smoke: the book's smoke-to-target optimisation with the adjoint of
incompressible2d-sl. The tiny size runs both optimisers end to end and lowers the loss; the
objective's gradient agrees with central differences."""

from __future__ import annotations

import json

import numpy as np

from adjointsim.cli import main
from adjointsim.smoke_study import LOCATIONS, objective, scene, sources


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
        assert len(losses) == r["iterations"] + 1 == 6
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
