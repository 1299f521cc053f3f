"""PBDL's Burgers comparison (train/burgers_pinn.py): the PINN side as a training run on the
engine (residual, history, kill/resume), the DP side as the fit demo's run. Tiny: seconds."""

import math

import numpy as np
import pytest
import torch

from adjointsim.run import read_history
from adjointsim.train.burgers_pinn import (
    BurgersPinn,
    BurgersPinnConfig,
    BurgersPinnRun,
    run_dp,
    run_pinn,
)

TINY = {"collocation": 50, "boundary_points": 10, "dtype": "float64", "epochs": 12,
        "log_every": 4, "width": 8, "depth": 3}


def test_residual_equals_nested_autograd():
    prob = BurgersPinn(BurgersPinnConfig(**TINY))
    net = prob.model()
    p = prob.col.clone().requires_grad_(True)
    u = prob.u(net, p)
    du = torch.autograd.grad(u.sum(), p, create_graph=True)[0]
    u_xx = torch.autograd.grad(du[:, 0].sum(), p)[0][:, 0]
    res = du[:, 1] + u[:, 0] * du[:, 0] - prob.true_nu * u_xx
    jet_residual = float(prob.losses(net)["residual"].detach())
    assert jet_residual == pytest.approx(float((res.detach() ** 2).mean()), rel=1e-12)
    assert prob.true_nu == 0.01 / math.pi and prob.obs.shape == (128, 1)
    assert not prob.learn_nu and prob.obs_in[:, 1].unique().tolist() == [0.5]


def test_training_run_logs_weights_and_metrics(tmp_path):
    cfg = BurgersPinnConfig(**TINY, weighting="inverse-dirichlet")
    result = run_pinn(cfg, tmp_path / "r")
    history = result["history"]
    assert [h["epoch"] for h in history] == [1, 4, 8, 12] and result["epochs"] == 12
    assert history[-1]["misfit"] < history[0]["misfit"]
    assert history[-1]["weight/data"] != 1.0  # inverse-Dirichlet updated the weights
    assert result["misfit"] == history[-1]["misfit"] and len(result["fitted_u0"]) == 128
    # the viscosity demo learns ν from its start, 2 ν_true
    nu = run_pinn(BurgersPinnConfig(**TINY, demo="burgers-nu"), tmp_path / "nu")
    # ν must have moved off its start: a frozen ν would sit at 2 ν_true to round-off
    assert 1e-3 < abs(nu["nu"] / (2 * nu["true_nu"]) - 1) < 0.1


def test_interrupted_run_resumes_to_the_same_rows(tmp_path, monkeypatch):
    cfg = BurgersPinnConfig(**TINY)
    straight = run_pinn(cfg, tmp_path / "a")
    real, calls = BurgersPinnRun.update, []

    def interrupt(self):
        calls.append(1)
        if len(calls) == 6:
            raise KeyboardInterrupt
        return real(self)

    monkeypatch.setattr(BurgersPinnRun, "update", interrupt)
    with pytest.raises(KeyboardInterrupt, match="--resume"):
        run_pinn(cfg, tmp_path / "b")
    monkeypatch.setattr(BurgersPinnRun, "update", real)
    again = run_pinn(cfg, tmp_path / "b")  # a study's cell continues its run
    drop = ("seconds", "history")
    assert {k: v for k, v in again.items() if k not in drop} == \
        {k: v for k, v in straight.items() if k not in drop}
    rows = [[{k: v for k, v in h.items() if k != "seconds"}
             for h in read_history(tmp_path / d / "history.csv")] for d in ("a", "b")]
    assert rows[0] == rows[1]


def test_a_finished_run_continues_to_a_larger_budget(tmp_path):
    straight = run_pinn(BurgersPinnConfig(**TINY), tmp_path / "a")
    run_pinn(BurgersPinnConfig(**{**TINY, "epochs": 6}), tmp_path / "b")
    longer = run_pinn(BurgersPinnConfig(**TINY), tmp_path / "b")
    assert [h["epoch"] for h in longer["history"]] == [1, 4, 8, 12]
    drop = ("seconds", "history")
    assert {k: v for k, v in longer.items() if k not in drop} == \
        {k: v for k, v in straight.items() if k not in drop}
    rows = [[{k: v for k, v in h.items() if k != "seconds"} for h in r["history"]]
            for r in (straight, longer)]
    assert rows[0] == rows[1]


def test_dp_side_is_the_fit_demo_run(tmp_path):
    from adjointsim.fit import fit
    from adjointsim.fit_demos import pbdl_state

    d = run_dp("burgers", tmp_path / "dp", maxiter=3, tol=0.0)
    data = d["data"]
    scene, steps, states = data["scene"], data["steps"], data["prob"]["states"]
    r = fit(scene, dict(zip(steps.tolist(), states)), wrt="state", maxiter=3, tol=0.0)
    assert d["misfit"] == r.misfit and d["iterations"] == r.iterations
    np.testing.assert_array_equal(d["fitted_u0"], r.state[0, 0])
    assert d["u0_mse"] == float(np.mean((r.state - pbdl_state(scene)) ** 2))
    assert d["history"][-1]["cpu_seconds"] > 0
    assert (tmp_path / "dp" / "result.json").exists()
    assert run_dp("burgers", tmp_path / "dp", maxiter=3, tol=0.0)["misfit"] == d["misfit"]
