"""Loss weighting (train/weighting.py): every scheme against a dense reference computed here
(hand computations, scipy's QP, explicit projections and Jacobians), guards, the batched
per-term gradients, use on a loss through a solver (the guidance task's state cost + control
cost, gradients via the hand-written adjoint; the controller's own update under a scheme), and
a tiny PINN run per scheme."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from adjointsim.train.weighting import (
    RULES,
    SCHEMES,
    Weighting,
    canonical_rule,
    scheme_name,
    term_gradients,
)

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
    with pytest.raises(ValueError, match="unknown weighting 'nope'"):
        Weighting(["a"], "nope")
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
    terms, params = _guidance_terms()
    state, effort = terms["track"], terms["effort"]
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


# ----------------------------------------------------------------------------- every scheme
def _net(seed=0, n_in=2):
    torch.manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Linear(n_in, 6), torch.nn.Tanh(), torch.nn.Linear(6, 1))
    return net.double()


def _flat_grad(loss, params):
    grads = torch.autograd.grad(loss, params, retain_graph=True, materialize_grads=True)
    return torch.cat([g.reshape(-1) for g in grads])


def _two_term_losses(net, seed=1):
    torch.manual_seed(seed)
    x = torch.randn(12, 2, dtype=torch.float64)
    u = net(x)
    return {"fit": ((u - torch.sin(x[:, :1])) ** 2).mean(),
            "reg": 3.0 * (u.mean() + 2.0) ** 2}


def test_batched_per_term_gradients_equal_separate_passes():
    net = _net()
    params = list(net.parameters())
    terms = _two_term_losses(net)
    got = term_gradients(torch.stack(list(terms.values())), params, retain_graph=True)
    for row, loss in zip(got, terms.values()):
        torch.testing.assert_close(row, _flat_grad(loss, params), rtol=1e-12, atol=1e-14)


def test_the_registry_names_every_scheme_and_the_old_names_still_load():
    assert set(RULES) == {"uniform", "inverse-dirichlet", "max-avg", "mgda", "epsilon-optimal",
                          "gradnorm", "softadapt", "relobralo", "ntk", "pcgrad", "config"}
    assert scheme_name("fixed") == scheme_name("analytic") == "epsilon-optimal"
    assert canonical_rule("fixed") == "fixed"  # recorded runs resume under their name
    old = {"rule": "fixed", "weights": {"res": 0.1, "bc": 0.9}, "history": []}  # no "scheme"
    w = Weighting(["res", "bc"], "epsilon-optimal", fixed={"res": 0.1, "bc": 0.9})
    w.load_state_dict(old)
    assert w.weights == {"res": 0.1, "bc": 0.9}
    with pytest.raises(ValueError, match="does not match"):
        Weighting(["res", "bc"], "mgda").load_state_dict(old)


def _grads(*rows):
    return torch.tensor(rows, dtype=torch.float64)


def _mgda_reference(g):
    """min ‖Σ α_k g_k‖² on the simplex by scipy's SLSQP."""
    from scipy.optimize import minimize

    gram = (g @ g.T).numpy()
    k = len(gram)
    res = minimize(lambda a: a @ gram @ a, np.full(k, 1.0 / k), jac=lambda a: 2 * gram @ a,
                   bounds=[(0, 1)] * k, method="SLSQP", options={"ftol": 1e-15, "maxiter": 500},
                   constraints=[{"type": "eq", "fun": lambda a: a.sum() - 1}])
    return res.x


@pytest.mark.parametrize("rows", [
    [(1.0, 0.0, 2.0), (-0.5, 1.0, 0.3)],  # two terms: the closed form is checked too
    [(1.0, 0.0, 2.0), (-0.5, 1.0, 0.3), (0.2, -2.0, 0.5)],
    [(1.0, 1.0, 0.0), (2.0, 2.0, 0.0), (0.0, 0.0, 1.0), (3.0, -1.0, 0.5)],  # a face inside
    [(1.0, 0.0, 0.0), (5.0, 0.0, 0.0)],  # no conflict: the shorter gradient alone
])
def test_mgda_is_the_min_norm_point_of_the_convex_hull(rows):
    g = _grads(*rows)
    names = [f"t{i}" for i in range(len(g))]
    w = Weighting(names, "mgda")
    got = np.array([w.update(0, dict(zip(names, g)))[n] for n in names])
    ref = _mgda_reference(g)
    assert got.sum() == pytest.approx(1.0) and (got >= 0).all()
    assert got @ (g @ g.T).numpy() @ got == pytest.approx(ref @ (g @ g.T).numpy() @ ref,
                                                         rel=1e-7, abs=1e-12)
    np.testing.assert_allclose(got, ref, atol=1e-5)
    if len(g) == 2:  # α₁ = clip((g₂ − g₁)·g₂ / ‖g₁ − g₂‖², 0, 1)
        a = float((g[1] - g[0]) @ g[1] / ((g[0] - g[1]) @ (g[0] - g[1])))
        assert got[0] == pytest.approx(min(max(a, 0.0), 1.0))


def test_config_matches_its_closed_form_with_a_pseudo_inverse():
    g = _grads((1.0, 0.2, -0.3, 0.0), (-0.4, 1.0, 0.1, 0.5), (0.3, -0.2, 2.0, 0.1))
    unit = g / g.norm(dim=1, keepdim=True)
    gu = torch.linalg.pinv(unit) @ torch.ones(3, dtype=g.dtype)
    gu = gu / gu.norm()
    expected = (g @ gu).sum() * gu
    got = SCHEMES["config"](Weighting(["a", "b", "c"], "config")).combine(g, 0)
    torch.testing.assert_close(got, expected)
    assert (g @ got > 0).all()  # no term's loss rises along it
    cos = unit @ (got / got.norm())
    torch.testing.assert_close(cos, cos.mean().expand(3))  # equal angle to every gradient


def _projected(gi, others):
    for gj in others:
        dot = gi @ gj
        if dot < 0:
            gi = gi - dot / (gj @ gj) * gj
    return gi


def test_pcgrad_matches_explicit_projections():
    a, b = _grads((1.0, 1.0, 0.0), (-1.0, 0.5, 1.0))  # conflict: a·b = −0.5
    w = Weighting(["a", "b"], "pcgrad")
    got = w.scheme.combine(torch.stack([a, b]), 3)
    a_pc, b_pc = a - (a @ b) / (b @ b) * b, b - (a @ b) / (a @ a) * a
    torch.testing.assert_close(got, a_pc + b_pc)
    assert a_pc @ b == pytest.approx(0.0, abs=1e-12) and b_pc @ a == pytest.approx(0.0, abs=1e-12)
    # three terms, only c conflicting with a and b, which agree: any order gives the same
    c = _grads((-1.0, -1.0, 0.1))[0]
    b = _grads((1.0, 0.2, 0.3))[0]
    got = Weighting(["a", "b", "c"], "pcgrad").scheme.combine(torch.stack([a, b, c]), 7)
    expected = _projected(a, [c]) + _projected(b, [c]) + _projected(c, [a, b])
    torch.testing.assert_close(got, expected)
    same = Weighting(["a", "b"], "pcgrad").scheme.combine(torch.stack([a, b]), 0)
    torch.testing.assert_close(same, a + b)  # no conflict: the plain sum


def test_ntk_weights_are_traces_of_an_explicit_jacobian():
    net = _net(2)
    params = list(net.parameters())
    torch.manual_seed(3)
    x_in, x_bc = torch.randn(7, 2, dtype=torch.float64), torch.randn(3, 2, dtype=torch.float64)

    def residuals():
        return {"res": net(x_in)[:, 0] - 1.0, "bc": 10.0 * net(x_bc)[:, 0]}

    r = residuals()
    traces = {}
    for n, v in r.items():  # the Jacobian row by row, each sample its own reverse pass
        jac = torch.stack([_flat_grad(v[i], params) for i in range(len(v))])
        traces[n] = float(torch.trace(jac @ jac.T)) / len(v)
    total = sum(traces.values())
    w = Weighting(["res", "bc"], "ntk", alpha=1.0)
    losses = {n: (v**2).mean() for n, v in r.items()}
    g = {n: _flat_grad(v, params) for n, v in losses.items()}
    w.backward(losses, params, 0, residuals)
    assert w.weights == pytest.approx({n: total / t for n, t in traces.items()}, rel=1e-10)
    combined = torch.cat([p.grad.reshape(-1) for p in params])
    torch.testing.assert_close(combined, sum(w.weights[n] * g[n] for n in g))
    with pytest.raises(ValueError, match="needs each term's per-sample residuals"):
        Weighting(["res", "bc"], "ntk").backward(residuals(), params, 0)


def test_gradnorm_weight_update_by_hand():
    w = Weighting(["a", "b"], "gradnorm")
    # step 0: L(0) = (2, 1); ‖∇_W L‖ = (3, 1); r = (1, 1); G = (3, 1), Ḡ = 2: the targets are
    # 2 and 2, so λ_a −= 0.025·3, λ_b += 0.025·1: (0.925, 1.025), sum 1.95, renormalised to 2
    got = w.update(0, {"a": torch.tensor([3.0, 0.0]), "b": torch.tensor([0.0, 1.0])},
                   {"a": 2.0, "b": 1.0})
    lam = {"a": 2 * 0.925 / 1.95, "b": 2 * 1.025 / 1.95}
    assert got == pytest.approx(lam)
    # step 1: L = (1, 0.9): L̃ = (0.5, 0.9), r = (0.5/0.7, 0.9/0.7); ‖∇_W L‖ = (2, 2)
    g = {"a": 2 * lam["a"], "b": 2 * lam["b"]}
    mean_g = (g["a"] + g["b"]) / 2
    target = {"a": mean_g * (0.5 / 0.7) ** 1.5, "b": mean_g * (0.9 / 0.7) ** 1.5}
    new = {n: lam[n] - 0.025 * math.copysign(2.0, g[n] - target[n]) for n in lam}
    got = w.update(1, {"a": torch.tensor([0.0, 2.0]), "b": torch.tensor([2.0, 0.0])},
                   {"a": 1.0, "b": 0.9})
    assert got == pytest.approx({n: 2 * v / sum(new.values()) for n, v in new.items()})
    assert got["b"] > got["a"]  # the slower-training term gains weight


def test_softadapt_by_hand_on_a_loss_history():
    w = Weighting(["a", "b"], "softadapt")
    history = [{"a": 5.0, "b": 1.0}, {"a": 4.0, "b": 1.5}, {"a": 3.5, "b": 1.2}]
    assert w.update(0, losses=history[0]) == {"a": 1.0, "b": 1.0}  # no rate yet
    for t in (1, 2):
        s = {n: history[t][n] - history[t - 1][n] for n in "ab"}
        e = {n: math.exp(0.1 * s[n]) for n in "ab"}
        expected = {n: 2 * e[n] / (e["a"] + e["b"]) for n in "ab"}
        assert w.update(t, losses=history[t]) == pytest.approx(expected, rel=1e-12)
    assert w.weights["b"] > w.weights["a"]  # b rose last step


def test_relobralo_by_hand_on_a_loss_history():
    w = Weighting(["a", "b"], "relobralo", seed=4)
    history = [{"a": 5.0, "b": 1.0}, {"a": 4.0, "b": 1.5}, {"a": 3.5, "b": 1.2},
               {"a": 3.0, "b": 1.1}]

    def bal(now, ref):
        e = {n: math.exp(now[n] / (0.1 * ref[n])) for n in now}
        return {n: 2 * e[n] / sum(e.values()) for n in now}

    lam = {"a": 1.0, "b": 1.0}
    assert w.update(0, losses=history[0]) == lam
    for t in range(1, 4):
        rho = float(np.random.default_rng([4, t]).random() < 0.999)
        b0, b1 = bal(history[t], history[0]), bal(history[t], history[t - 1])
        lam = {n: 0.999 * (rho * lam[n] + (1 - rho) * b0[n]) + 0.001 * b1[n] for n in lam}
        assert w.update(t, losses=history[t]) == pytest.approx(lam, rel=1e-12)
    # a lookback of ρ = 0 (drawn with probability 0.001) replaces the history by bal(t, 0)
    w = Weighting(["a", "b"], "relobralo")
    w.scheme.expected_rho = 0.0
    w.update(0, losses=history[0])
    b0, b1 = bal(history[1], history[0]), bal(history[1], history[0])
    assert w.update(1, losses=history[1]) == pytest.approx(
        {n: 0.999 * b0[n] + 0.001 * b1[n] for n in "ab"})


@pytest.mark.parametrize("rule", ["softadapt", "relobralo", "gradnorm"])
def test_loss_rules_keep_the_weights_on_non_finite_losses(rule):
    w = Weighting(["a", "b"], rule)
    grads = {"a": torch.tensor([1.0, 2.0]), "b": torch.tensor([0.5, 0.1])}
    w.update(0, grads, {"a": 2.0, "b": 1.0})
    w.update(1, grads, {"a": 1.0, "b": 0.5})
    before = dict(w.weights)
    w.update(2, grads, {"a": math.nan, "b": 0.5})
    assert w.weights == before


def test_state_dict_keeps_what_a_scheme_remembers():
    w = Weighting(["a", "b"], "relobralo")
    w.update(0, losses={"a": 2.0, "b": 1.0})
    w.update(1, losses={"a": 1.0, "b": 1.0})
    again = Weighting(["a", "b"], "relobralo")
    again.load_state_dict(w.state_dict())
    assert again.update(2, losses={"a": 0.5, "b": 0.7}) == w.update(2, losses={"a": 0.5,
                                                                                "b": 0.7})


# ----------------------------------------------------------------------------- any loss
def _guidance_terms():
    """The guidance task through the solver's adjoint: tracking (evader distance) and control
    effort, two terms of a differentiable-physics loss."""
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
    return {"track": state, "effort": effort}, list(net.parameters())


@pytest.mark.parametrize("rule", ["pcgrad", "config", "gradnorm"])
def test_a_differentiable_physics_loss_takes_any_scheme(rule):
    terms, params = _guidance_terms()
    g = {n: _flat_grad(v, params) for n, v in terms.items()}
    w = Weighting(list(terms), rule)
    total = w.backward(terms, params, 0)
    got = torch.cat([p.grad.reshape(-1) for p in params])
    a, b = g["track"], g["effort"]
    if rule == "pcgrad":
        expected = _projected(a, [b]) + _projected(b, [a])
    elif rule == "config":
        unit = torch.stack([a / a.norm(), b / b.norm()])
        gu = torch.linalg.pinv(unit) @ torch.ones(2, dtype=a.dtype)
        expected = (torch.stack([a, b]) @ gu).sum() * gu / gu.norm() ** 2
    else:  # the weights moved off 1 (the layer norms differ), and the update is Σ λ_k g_k
        assert w.weights["track"] != 1.0 and sum(w.weights.values()) == pytest.approx(2.0)
        expected = w.weights["track"] * a + w.weights["effort"] * b
    torch.testing.assert_close(got, expected)
    assert float(total) == pytest.approx(sum(w.weights[n] * float(v.detach())
                                             for n, v in terms.items()))


def _controller(mode="R", weighting="uniform", clip="none"):
    """A guidance controller whose last layer is not zero (so both terms pull), a batch of
    four initial states, and a configuration."""
    from adjointsim.train import control

    cfg = control.ControlConfig(task="guidance", mode=mode, weighting=weighting, clip=clip,
                                train=4, test=4, batch=4, dtype="float64")
    cfg.validate()
    task = control.get_task("guidance", cfg.level)
    net = control.build_net(cfg, task)
    for m in net.modules():
        if isinstance(m, torch.nn.Linear):
            m.reset_parameters()
    return cfg, task, net, control.initial_states(cfg, task)[0]


def _one_update(cfg, task, net, x0, weighting):
    """The gradient that control's update hands the optimiser (whose step does nothing)."""
    from types import SimpleNamespace

    from adjointsim.train import control

    params = list(net.parameters())
    state = control.fresh_epoch()
    control.minibatch_update(cfg, task, net, SimpleNamespace(step=lambda: None), params, x0,
                             state, weighting, 0)
    return torch.cat([p.grad.reshape(-1) for p in params]), state


def test_the_guidance_loss_is_the_sum_of_its_terms():
    from adjointsim.train import control

    cfg, task, net, x0 = _controller()
    loss = control.closed_loop(task, net, x0)[0]
    terms = control.closed_loop(task, net, x0, terms=True)[0]
    assert set(terms) == {"tracking", "control"} == set(task.terms)
    assert float(terms["control"].detach()) > 0
    assert float(sum(terms.values()).detach()) == pytest.approx(float(loss.detach()), rel=1e-12)
    got = control.evaluate(task, net, x0, terms=True)
    assert got == pytest.approx({n: float(v.detach()) for n, v in terms.items()})


def test_a_controller_update_follows_the_schemes_rule():
    """ID through control's update: the term of the larger spread keeps λ = 1, the other
    gets (1 − α) + α s_ref / s_k, and the update is Σ λ_k g_k; pcgrad's update is the
    projected sum, clipped as configured; uniform's is the plain gradient of the loss."""
    from adjointsim.train import control

    cfg, task, net, x0 = _controller()
    params = list(net.parameters())
    terms = control.closed_loop(task, net, x0, terms=True)[0]
    g = {n: _flat_grad(v, params) for n, v in terms.items()}
    plain, state = _one_update(cfg, task, net, x0, None)
    torch.testing.assert_close(plain, g["tracking"] + g["control"])
    assert math.isfinite(state["cos"])  # uniform keeps the diagnosis

    cfg, task, net, x0 = _controller(weighting="inverse-dirichlet")
    w = Weighting(task.terms, cfg.weighting)
    got, state = _one_update(cfg, task, net, x0, w)
    spread = {n: float(v.std(unbiased=False)) for n, v in g.items()}
    top = max(spread, key=spread.get)
    low = min(spread, key=spread.get)
    lam = 0.5 + 0.5 * spread[top] / spread[low]
    assert w.weights == pytest.approx({top: 1.0, low: lam}) and lam > 1.5
    torch.testing.assert_close(got, g[top] + lam * g[low])
    assert math.isnan(state["cos"])  # no doubled batch under a scheme that reads gradients

    cfg, task, net, x0 = _controller(weighting="pcgrad", clip="norm")
    got, _ = _one_update(cfg, task, net, x0, Weighting(task.terms, "pcgrad"))
    a, b = g["tracking"], g["control"]
    expected = _projected(a, [b]) + _projected(b, [a])
    torch.testing.assert_close(got, expected / max(float(expected.norm()), 1.0))


def test_controller_weighting_is_refused_where_it_cannot_act():
    from adjointsim.errors import UserError
    from adjointsim.train import control

    with pytest.raises(UserError, match="cartpole task's loss has one term"):
        control.ControlConfig(task="cartpole", weighting="inverse-dirichlet").validate()
    with pytest.raises(UserError, match="mode C's doubled batch"):
        control.ControlConfig(task="guidance", mode="C", weighting="mgda").validate()
    control.ControlConfig(task="guidance", mode="C", weighting="softadapt").validate()
    with pytest.raises(UserError, match="weighting"):
        control.ControlConfig(task="guidance", weighting="ntk").validate()


def test_a_weighted_controller_run_resumes_to_the_uninterrupted_run(tmp_path):
    from adjointsim.train import control

    def cfg(out, epochs):
        return control.ControlConfig(task="guidance", weighting="relobralo", epochs=epochs,
                                     train=8, test=4, batch=4, out=str(tmp_path / out))

    whole = control.train_controller(cfg("a", 2), progress=False)
    control.train_controller(cfg("b", 1), progress=False)
    resumed = control.train_controller(cfg("b", 2), resume=True, progress=False)
    assert resumed["weights"] == whole["weights"] and whole["weights"] != {
        "tracking": 1.0, "control": 1.0}
    assert resumed["test_loss"] == whole["test_loss"]
    assert sum(whole["test_terms"].values()) == pytest.approx(whole["test_loss"], rel=1e-5)


# ----------------------------------------------------------------------------- pinn
@pytest.mark.parametrize("rule", [*RULES, "fixed"])
def test_a_tiny_poisson_run_takes_every_scheme(rule, tmp_path):
    from adjointsim.train.pinn import PinnConfig, train_run

    cfg = PinnConfig(problem="poisson", k=2, weighting=rule, epochs=7, collocation=20,
                     edge_points=4, width=8, depth=2, every=2, log_every=3)
    result = train_run(cfg, tmp_path, progress=False, plot=False)
    assert math.isfinite(result["rel_l2"]) and not result["diverged"]
    assert result["weighting"] == rule
    assert all(math.isfinite(v) and v >= 0 for v in result["weights"].values())


@pytest.mark.parametrize("route, batched", [("autograd", True), ("taylor", False)])
def test_poisson_terms_are_batched_where_the_graph_allows(route, batched):
    """The Taylor route's hand-written reverse pass has no batching rule: its per-term
    gradients are taken one after another, and equal separate passes either way."""
    from adjointsim.train.pinn import PinnConfig, make_problem

    problem = make_problem(PinnConfig(problem="poisson", collocation=30, edge_points=5,
                                      width=8, depth=2, route=route))
    model = problem.model()
    params = list(model.parameters())
    terms = problem.losses(model, route)
    w = Weighting(["res", "bc"], "config")
    rows = w.gradients(list(terms.values()), params)
    assert w._batched is batched
    for row, loss in zip(rows, terms.values()):
        torch.testing.assert_close(row, _flat_grad(loss, params))


def test_pinn_offers_every_scheme_and_refuses_what_a_problem_lacks():
    from adjointsim.errors import UserError
    from adjointsim.train.pinn import ACCEPTED, PinnConfig

    assert set(RULES) <= set(ACCEPTED["weighting"]) and "fixed" in ACCEPTED["weighting"]
    for rule in ("ntk", "epsilon-optimal", "fixed"):
        with pytest.raises(UserError, match="no analytic weights and no per-sample residuals"):
            PinnConfig(problem="sobolev", weighting=rule).validate()


def test_the_sequential_problem_records_each_phase_and_the_spreads_when_terms_join(tmp_path):
    """Terms of scales 1, 1e-3 and 1e3 join one after another; each phase's end holds every
    term and its gradient spread, the weak term's spread below data's, the strong one's far
    above, and ID lifts the weak term (data is its reference)."""
    from adjointsim.train.pinn import PinnConfig, train_run

    cfg = PinnConfig(problem="sequential", weighting="id", epochs=15, collocation=40, width=8,
                     depth=2, log_every=5, alpha=1.0)
    result = train_run(cfg, tmp_path, progress=False, plot=False)
    phases = result["phases"]
    assert [p["epoch"] for p in phases] == [5, 10, 15]
    assert [p["active"] for p in phases] == [["data"], ["data", "grad"],
                                             ["data", "grad", "lap"]]
    first = phases[0]
    assert first["spread/grad"] < first["spread/data"] < 1e3 * first["spread/data"] \
        < first["spread/lap"]
    assert result["weights"]["grad"] > 1.0 > result["weights"]["lap"]
    assert result["weights"]["data"] == 1.0


def test_every_scheme_the_controller_accepts_trains_the_guidance_task(tmp_path):
    """One epoch per scheme that a guidance controller's config accepts (max/avg keeps the
    objective, the tracking term, at λ = 1)."""
    from adjointsim.train import control

    accepted = control.ControlConfig.ACCEPTED["weighting"]
    assert "max-avg" in accepted and "ntk" not in accepted
    for scheme in accepted:
        cfg = control.ControlConfig(task="guidance", mode="R", weighting=scheme, epochs=1,
                                    train=4, test=4, batch=4, out=str(tmp_path / scheme))
        result = control.train_controller(cfg, progress=False)
        assert math.isfinite(result["test_loss"]), scheme
        if scheme == "max-avg":
            assert result["weights"]["tracking"] == 1.0
