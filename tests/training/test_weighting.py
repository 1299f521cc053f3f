"""Loss weighting (train/weighting.py): hand-computed updates, guards, and use on a loss through
a solver (the guidance task's state cost + control cost, gradients via the hand-written
adjoint)."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from adjointsim.train.weighting import Weighting

RES = torch.tensor([1.0, -1.0, 1.0, -1.0], dtype=torch.float64)  # std 1, max|.| 1


def test_inverse_dirichlet_residual_reference_by_hand():
    w = Weighting(["res", "bc"], "inverse-dirichlet", reference="res")
    # s_bc = 0.1: target 10, λ = 0.5·1 + 0.5·10 = 5.5, then 0.5·5.5 + 5 = 7.75
    assert w.update(0, {"res": RES, "bc": 0.1 * RES}) == {"res": 1.0, "bc": 5.5}
    assert w.update(5, {"res": RES, "bc": 0.1 * RES})["bc"] == pytest.approx(7.75)
    assert [h["step"] for h in w.history] == [0, 0, 5]
    assert w.history[-1]["spread/bc"] == pytest.approx(0.1)


def test_inverse_dirichlet_largest_spread_reference_by_hand():
    w = Weighting(["a", "b", "c"], "id")
    # spreads 2, 1, 0.5: the reference is a; targets 1, 2, 4
    got = w.update(0, {"a": 2 * RES, "b": [RES[:2], RES[2:]], "c": 0.5 * RES})
    assert got == {"a": 1.0, "b": 1.5, "c": 2.5}
    # b now has the largest spread: a's target is 3/2
    got = w.update(5, {"a": 2 * RES, "b": 3 * RES, "c": 0.5 * RES})
    assert got["a"] == pytest.approx(1.25) and got["b"] == pytest.approx(0.5 * 1.5 + 0.5)
    assert got["c"] == pytest.approx(0.5 * 2.5 + 0.5 * 6)


def test_max_avg_uses_the_current_weight_inside_the_mean():
    w = Weighting(["res", "bc"], "maxavg", reference="res")
    g = {"res": torch.tensor([3.0, -1.0]), "bc": torch.tensor([0.5, -0.5])}
    assert w.update(0, g)["bc"] == pytest.approx(0.5 + 0.5 * 3 / 0.5)  # 3.5
    assert w.update(5, g)["bc"] == pytest.approx(0.5 * 3.5 + 0.5 * 3 / (3.5 * 0.5))


@pytest.mark.parametrize("rule", ["inverse-dirichlet", "max-avg"])
@pytest.mark.parametrize("bad", [0.0, math.nan, math.inf])
def test_zero_or_non_finite_gradients_keep_the_weights(rule, bad):
    w = Weighting(["res", "bc"], rule, reference="res")
    w.update(0, {"res": RES, "bc": 0.1 * RES})
    before = dict(w.weights)
    w.update(5, {"res": RES, "bc": torch.full((4,), bad)})  # the term
    assert w.weights == before
    w.update(10, {"res": torch.full((4,), bad), "bc": RES})  # the reference
    assert w.weights == before
    assert all(math.isfinite(v) for h in w.history for k, v in h.items() if "spread" not in k)


def test_all_zero_largest_spread_reference_keeps_every_weight():
    w = Weighting(["a", "b"], "inverse-dirichlet")
    w.update(0, {"a": torch.zeros(3), "b": torch.zeros(3)})
    assert w.weights == {"a": 1.0, "b": 1.0}


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(1e-6, 1e6), min_size=2, max_size=5), st.integers(1, 6))
def test_inverse_dirichlet_fixed_point_equalises_weighted_spreads(scales, updates):
    names = [f"t{i}" for i in range(len(scales))]
    w = Weighting(names, "inverse-dirichlet", reference="t0", alpha=1.0)
    for s in range(updates):
        w.update(s, {n: c * RES for n, c in zip(names, scales)})
    spreads = [w.weights[n] * c for n, c in zip(names, scales)]
    assert spreads == pytest.approx([scales[0]] * len(scales), rel=1e-9)


def test_uniform_and_fixed_never_change_and_bad_options_are_named():
    assert Weighting(["a", "b"]).update(0, {"a": RES, "b": 0 * RES}) == {"a": 1.0, "b": 1.0}
    w = Weighting(["a", "b"], "analytic", fixed={"a": 0.25})
    assert w.update(0, {"a": RES, "b": RES}) == {"a": 0.25, "b": 1.0} and not w.due(0)
    with pytest.raises(ValueError, match="unknown weighting 'gradnorm'"):
        Weighting(["a"], "gradnorm")
    with pytest.raises(ValueError, match="reference term 'x'"):
        Weighting(["a"], "id", reference="x")
    with pytest.raises(ValueError, match="max-avg weighting needs a reference"):
        Weighting(["a", "b"], "max-avg")
    with pytest.raises(ValueError, match="finite and ≥ 0"):
        Weighting(["a"], "fixed", fixed={"a": math.nan})


def test_backward_equals_the_gradient_of_the_weighted_sum_and_refreshes_when_due():
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(2, 8), torch.nn.Tanh(), torch.nn.Linear(8, 1))
    head = torch.nn.Linear(1, 1)  # a parameter only one term uses: its gradient there is 0
    x = torch.randn(16, 2)
    params = [*net.parameters(), *head.parameters()]

    def losses():
        u = net(x)
        return {"res": (u**2).mean() * 100.0, "bc": (head(u) - 1).pow(2).mean()}

    w = Weighting(["res", "bc"], "id", reference="res", every=2)
    for step in range(3):
        for p in params:
            p.grad = None
        terms = losses()
        total = w.backward(terms, params, step)
        got = [p.grad.clone() for p in params]
        for p in params:
            p.grad = None
        w.total(losses()).backward()
        for g, p in zip(got, params):
            torch.testing.assert_close(g, p.grad)
        assert float(total) == pytest.approx(float(w.total(terms).detach()))
    assert [h["step"] for h in w.history] == [0, 0, 2] and w.weights["bc"] != 1.0


def test_on_a_differentiable_physics_loss_state_and_control_cost():
    """The guidance task through the solver's adjoint: evader distance and control effort are
    two terms of very different spread; ID lifts the weaker one to the reference's spread."""
    from adjointsim.train import bridge, control

    task = control.get_task("guidance", 1.0)
    torch.manual_seed(0)
    net = task.net().double()
    for m in net.modules():
        if isinstance(m, torch.nn.Linear):
            m.reset_parameters()
    x = torch.from_numpy(task.initial_states(np.random.default_rng(0), 4))
    state, effort = 0.0, 0.0
    for _ in range(5):
        c = task.control(net(x))
        x = bridge.step(task.solver, x, c)
        state = state + (x[:, :2, task.solver.drivers:] ** 2).sum(dim=1).mean()
        effort = effort + 1e-3 * (c**2).mean()
    params = list(net.parameters())
    g_s = torch.cat([g.reshape(-1) for g in torch.autograd.grad(state, params,
                                                                 retain_graph=True)])
    g_c = torch.cat([g.reshape(-1) for g in torch.autograd.grad(effort, params,
                                                                 retain_graph=True)])
    w = Weighting(["state", "control"], "inverse-dirichlet", reference="state", alpha=1.0)
    w.backward({"state": state, "control": effort}, params, 0)
    assert float(g_c.std()) < float(g_s.std())  # the control term pulls weaker
    assert w.weights["control"] * float(g_c.std()) == pytest.approx(float(g_s.std()), rel=1e-9)
    combined = torch.cat([p.grad.reshape(-1) for p in params])
    torch.testing.assert_close(combined, g_s + w.weights["control"] * g_c)


def test_terms_join_one_after_another_and_absent_ones_keep_their_weights():
    w = Weighting(["data", "bc", "res"], "id", reference="res", alpha=1.0)
    w.update(0, {"data": RES})  # only the first term is active: nothing to balance
    assert w.weights == {"data": 1.0, "bc": 1.0, "res": 1.0}
    # while the named reference is absent, the largest active spread is the reference
    w.update(1, {"data": RES, "bc": 4 * RES})
    assert w.weights == pytest.approx({"data": 4.0, "bc": 1.0, "res": 1.0})
    assert "spread/res" not in w.history[-1]
    w.update(2, {"data": RES, "bc": 4 * RES, "res": 2 * RES})
    assert w.weights == pytest.approx({"data": 2.0, "bc": 0.5, "res": 1.0})
    m = Weighting(["data", "res"], "max-avg", reference="res")
    assert m.update(0, {"data": RES}) == {"data": 1.0, "res": 1.0}  # its reference is absent
    with pytest.raises(ValueError, match=r"unknown term\(s\) \['x'\]"):
        w.update(3, {"x": RES})
