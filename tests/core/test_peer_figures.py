"""The benchmarks that quote a peer measure it in the same run, on the same scene, or say that
it is not installed: no peer figure is written into them."""

from __future__ import annotations

import json
import sys

import ks_speed
import numpy as np
import pytest

from adjointsim.solvers.kuramoto_sivashinsky import KS


def test_ks_speed_without_exponax_says_so_and_prints_no_peer_figure(monkeypatch, capsys):
    monkeypatch.setattr(ks_speed, "load_exponax", lambda: None)
    monkeypatch.setattr(sys, "argv", ["ks_speed.py", "--repeats", "1"])
    ks_speed.main()
    out = capsys.readouterr().out
    assert "exponax not installed (pip install 'adjointsim[peers]'): no peer figures" in out
    assert "exponax forward" not in out and "x (target" not in out
    assert [line.split(":")[0] for line in out.splitlines()[1:]] == [
        "batch   1 median", "batch   1   best", "batch  64 median", "batch  64   best"]


def test_ks_speed_times_exponax_on_our_scene():
    pytest.importorskip("exponax")
    stepper = KS[4](n=128, length=64.0, dt=0.25, dealias=True)
    u0 = stepper.random_state(np.random.default_rng(0), 2)
    calls, difference = ks_speed.exponax_calls(stepper, u0)
    assert difference < 1e-10  # the same dealiased scene, to round-off after 200 steps
    assert set(calls) == {"exponax forward", "exponax forward+gradient"}


def test_incompressible_without_phiflow_says_so_and_writes_no_peer_keys(
        monkeypatch, capsys, tmp_path):
    import importlib.util

    import incompressible

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "phi" else find_spec(name, *a))
    monkeypatch.setattr(sys, "argv", ["incompressible.py", "--n", "4", "--steps", "2",
                                      "--repeats", "1", "--json", str(tmp_path / "rows.json")])
    incompressible.main()
    out = capsys.readouterr().out
    assert "PhiFlow is not installed: no peer figures" in out and "× ours" not in out
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert len(rows) == 1 and not any(key.startswith("peer") for key in rows[0])


def test_the_phiflow_twin_runs_our_scene_from_our_state():
    pytest.importorskip("phi.torch.flow")
    import phiflow_peer
    from phi import math

    from adjointsim import get

    stepper = get("incompressible2d-sl").benchmark_scene(8)
    rng = np.random.default_rng(0)
    u0 = stepper.rollout(np.zeros(stepper.state_shape(1)), 10)
    u0[:, 2] = stepper.random_state(rng, 1)[:, 2]
    peer = phiflow_peer.prepare(stepper, u0, rng.standard_normal(u0.shape), steps=3)
    ours, theirs = stepper.rollout(u0, 3), peer["last"]()
    # the same flow, discretised apart at the cylinder and the outlet: near, not equal
    difference = np.linalg.norm(theirs[:, :2] - ours[:, :2]) / np.linalg.norm(ours[:, :2])
    assert 1e-6 < difference < 0.3
    assert np.array_equal(theirs[:, :, stepper.nx + 1:], ours[:, :, stepper.nx + 1:])
    gradient = peer["gradient"]()
    assert len(gradient) == 2 and all(math.is_finite(g).all for g in gradient)
