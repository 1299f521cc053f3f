"""The benchmarks that quote a peer measure it in the same run, on the same scene, or say that
it is not installed: no peer figure is written into them."""

from __future__ import annotations

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
