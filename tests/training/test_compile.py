"""The bridge's operators under torch.compile and the torch.func transforms.

A loss of several solver steps compiles with ``fullgraph=True`` and no graph break, and gives
the eager loss and gradients bit for bit; ``vmap(grad(loss))`` over a batch of initial states
equals a loop of ``grad`` and makes one solver call per step, not one per mapped element.
"""

import numpy as np
import pytest
import torch
from torch.func import grad, jacrev, vjp, vmap

import adjointsim
from adjointsim.stepper import NonFiniteInputError
from adjointsim.train import bridge

ONCE = "once-differentiable"


def _state(stepper, batch, seed=0):
    return torch.from_numpy(stepper.random_state(np.random.default_rng(seed), batch))


def _controls(stepper, n, batch, seed=1):
    return torch.from_numpy(stepper.random_controls(np.random.default_rng(seed), n, batch))


def _correction_loss(stepper, net, steps=3):
    """A WIG-like correction loss: solver step, then a small convolution, ``steps`` times."""

    def loss(u):
        for _ in range(steps):
            u = bridge.rollout(stepper, u, 1)
            u = u + 0.01 * net(u)
        return u.square().mean()

    return loss


def _control_loss(stepper, net, steps=4):
    """A closed loop like the controllers' (mode C): a network picks each control from the
    state, one solver step per control."""

    def loss(x):
        total = x.new_zeros(())
        for _ in range(steps):
            c = net(x.flatten(1))
            x = bridge.step(stepper, x, c)
            total = total + x.square().mean() + 0.1 * c.square().mean()
        return total

    return loss


def _nets():
    torch.manual_seed(0)
    conv = torch.nn.Conv1d(1, 1, 5, padding=2, padding_mode="circular", dtype=torch.float64)
    mlp = torch.nn.Sequential(torch.nn.Linear(6, 16, dtype=torch.float64), torch.nn.Tanh(),
                              torch.nn.Linear(16, 1, dtype=torch.float64))
    return conv, mlp


def _cases():
    conv, mlp = _nets()
    ks = adjointsim.get("ks1d-etdrk1").default()
    cartpole = adjointsim.get("cartpole").default()
    heat = adjointsim.get("diffusion1d-ftcs").default()
    nu = torch.tensor(heat.param_values, dtype=torch.float64, requires_grad=True)
    ctrl = _controls(heat, 5, 3).requires_grad_()

    def heat_loss(u):
        every = bridge.rollout(heat, u, 5, ctrl, nu, keep="all", checkpoint=3)
        return every.square().mean() + bridge.rollout(heat, u, 2, ctrl[:2], nu).sum()

    grouped = [(ks, np.array([0, 2])), (adjointsim.get("ks1d-etdrk1").default(), slice(1, 4, 2))]

    def grouped_loss(u):
        return (bridge.rollout_grouped(grouped, u, 2) + 0.01 * conv(u)).square().sum()

    return {
        "ks correction": (_correction_loss(ks, conv), _state(ks, 4), list(conv.parameters())),
        "cartpole controller": (_control_loss(cartpole, mlp), _state(cartpole, 5),
                                list(mlp.parameters())),
        "heat, every state, checkpointed": (heat_loss, _state(heat, 3), [ctrl, nu]),
        "grouped": (grouped_loss, _state(ks, 4), list(conv.parameters())),
    }


def _loss_and_grads(fn, u0, params):
    u = u0.clone().requires_grad_()
    loss = fn(u)
    grads = torch.autograd.grad(loss, [u, *params])
    return loss.detach(), grads


@pytest.mark.parametrize("case", list(_cases()))
def test_a_multi_step_loss_compiles_whole_and_equals_eager_to_the_bit(case):
    fn, u0, params = _cases()[case]
    torch._dynamo.reset()
    explained = torch._dynamo.explain(fn)(u0.clone().requires_grad_())
    assert (explained.graph_count, explained.graph_break_count) == (1, 0), explained.break_reasons
    torch._dynamo.reset()
    compiled = torch.compile(fn, fullgraph=True, backend="aot_eager")
    want_loss, want = _loss_and_grads(fn, u0, params)
    for _ in range(2):  # the second call runs the cached graph
        got_loss, got = _loss_and_grads(compiled, u0, params)
        assert got_loss.numpy().tobytes() == want_loss.numpy().tobytes()
        for a, b in zip(got, want, strict=True):
            assert a.numpy().tobytes() == b.numpy().tobytes()


def test_the_adjoint_runs_in_the_compiled_backward_and_not_under_no_grad():
    ks = adjointsim.get("ks1d-etdrk1").default()
    conv, _ = _nets()
    fn = torch.compile(_correction_loss(ks, conv), fullgraph=True, backend="aot_eager")
    u0 = _state(ks, 2)
    before = bridge.ADJOINT_CALLS["count"]
    with torch.no_grad():
        fn(u0)
    assert bridge.ADJOINT_CALLS["count"] == before
    fn(u0.clone().requires_grad_()).backward()
    assert bridge.ADJOINT_CALLS["count"] == before + 3


def test_another_stepper_compiles_another_graph():
    small = adjointsim.get("diffusion1d-ftcs")(n=16, nu=0.05)
    large = adjointsim.get("diffusion1d-ftcs")(n=16, nu=0.2)
    fn = torch.compile(lambda s, u: bridge.rollout(s, u, 3), fullgraph=True, backend="aot_eager")
    u0 = _state(small, 2)
    for stepper in (small, large, small):
        assert torch.equal(fn(stepper, u0), bridge.rollout(stepper, u0, 3))


def test_the_input_checks_run_in_a_compiled_graph():
    heat = adjointsim.get("diffusion1d-ftcs").default()
    u0, ctrl = _state(heat, 2), _controls(heat, 2, 2)

    @torch.compile(fullgraph=True, backend="aot_eager")
    def fn(u, c):
        return bridge.rollout(heat, u * 1.0, 2, c * 1.0)

    fn(u0, ctrl)
    with pytest.raises(TypeError, match="cast it"):
        fn(u0, ctrl.float())
    bad = u0.clone()
    bad[1, 0, 3] = float("nan")
    with pytest.raises(NonFiniteInputError, match=r"u0 has non-finite values in batch element"):
        fn(bad, ctrl)
    with pytest.raises(ValueError, match="checkpoint must be an integer of at least"):
        torch.compile(lambda u: bridge.rollout(heat, u, 2, checkpoint=1), fullgraph=True,
                      backend="aot_eager")(u0)


# ------------------------------------------------------------------ torch.func
def _counting(stepper):
    """Counts the stepper's forward sweeps (from now on)."""
    calls = {"n": 0}
    method = stepper.rollout_prepared

    def counted(*args, **kwargs):
        calls["n"] += 1
        return method(*args, **kwargs)

    stepper.rollout_prepared = counted
    return calls


def _func_cases():
    ks = adjointsim.get("ks1d-etdrk2").default()
    heat = adjointsim.get("diffusion1d-ftcs").default()
    cartpole = adjointsim.get("cartpole").default()
    _, mlp = _nets()
    ctrl = _controls(heat, 3, 1)

    def ks_loss(u):  # u: one initial state (1, 1, N)
        return bridge.rollout(ks, u, 3).square().mean()

    def heat_loss(u):
        return (bridge.rollout(heat, u, 3, ctrl, keep="all") ** 3).sum()

    return {
        "ks1d (spectral)": (ks, ks_loss, _state(ks, 5), 1),
        "diffusion1d (stencil, controlled)": (heat, heat_loss, _state(heat, 5), 1),
        "cartpole (control)": (cartpole, _control_loss(cartpole, mlp, steps=3),
                               _state(cartpole, 5), 3),
    }


@pytest.mark.parametrize("case", list(_func_cases()))
def test_vmap_of_grad_equals_a_loop_of_grad_in_one_solver_call_per_step(case):
    stepper, loss, states, solver_calls = _func_cases()[case]
    batched = states[:, None]  # five initial states, each a batch of one
    looped = torch.stack([grad(loss)(u) for u in batched])
    calls = _counting(stepper)
    mapped = vmap(grad(loss))(batched)
    assert calls["n"] == solver_calls  # the five states at once, not one call for each
    torch.testing.assert_close(mapped, looped, rtol=1e-12, atol=1e-15)


def _mapped_cases():
    """A vmapped call of each public function over three batches of two: (call, mapped inputs,
    unmapped inputs)."""
    cartpole = adjointsim.get("cartpole").default()
    heat = adjointsim.get("diffusion1d-ftcs").default()
    ks = adjointsim.get("ks1d-etdrk1").default()
    nu = torch.tensor(heat.param_values, dtype=torch.float64)
    grouped = [(ks, [0]), (adjointsim.get("ks1d-etdrk1").default(), [1])]

    def threes(t, axis=0):  # (.., 6, ..) -> (3, .., 2, ..)
        return t.unflatten(axis, (3, 2)).movedim(axis, 0)

    return {
        "step": (lambda x, c: bridge.step(cartpole, x, c),
                 [threes(_state(cartpole, 6)), threes(_controls(cartpole, 1, 6)[0])], []),
        "rollout": (lambda u, c: bridge.rollout(heat, u, 4, c),
                    [threes(_state(heat, 6)), threes(_controls(heat, 4, 6), 1)], []),
        "rollout, every state, checkpointed, shared parameters": (
            lambda u, c, p: bridge.rollout(heat, u, 4, c, p, keep="all", checkpoint=3),
            [threes(_state(heat, 6)), threes(_controls(heat, 4, 6), 1)], [nu]),
        "grouped": (lambda u: bridge.rollout_grouped(grouped, u, 2), [threes(_state(ks, 6))], []),
    }


@pytest.mark.parametrize("case", list(_mapped_cases()))
def test_vmap_then_backward_equals_a_loop_then_backward(case, monkeypatch):
    """A vmapped tensor reports requires_grad=False whatever the tensor it wraps does: the
    solver's node must be recorded all the same (and, without a gradient, keep no tape)."""
    call, mapped, shared = _mapped_cases()[case]
    inputs, k = mapped + shared, len(mapped)
    by_vmap = vmap(call, in_dims=(0,) * k + (None,) * len(shared))
    w = torch.from_numpy(np.random.default_rng(5).standard_normal(by_vmap(*inputs).shape))

    def autograd_grads(run):
        leaves = [x.clone().requires_grad_() for x in inputs]
        out = run(*leaves)
        assert out.grad_fn is not None
        return torch.autograd.grad((w * out).sum(), leaves)

    looped = autograd_grads(
        lambda *xs: torch.stack([call(*(x[i] for x in xs[:k]), *xs[k:]) for i in range(3)]))
    transformed = grad(lambda *xs: (w * by_vmap(*xs)).sum(), argnums=tuple(range(len(inputs))))
    for got in (autograd_grads(by_vmap), transformed(*inputs)):
        for g, want in zip(got, looped, strict=True):
            torch.testing.assert_close(g, want, rtol=1e-12, atol=1e-15)

    saved = []
    forward = bridge._forward

    def spy(*args, **kwargs):
        out, kept = forward(*args, **kwargs)
        saved.append(kept)
        return out, kept

    monkeypatch.setattr(bridge, "_forward", spy)
    with torch.no_grad():
        assert by_vmap(*(x.clone().requires_grad_() for x in inputs)).grad_fn is None
    assert by_vmap(*inputs).grad_fn is None  # nothing needs a gradient
    assert saved and all(kept is None for kept in saved)


def test_grad_vjp_and_jacrev_equal_autograd():
    ks = adjointsim.get("ks1d-etdrk1").default()
    u0 = _state(ks, 2)

    def f(u):
        return bridge.rollout(ks, u, 2)

    w = torch.from_numpy(np.random.default_rng(4).standard_normal(u0.shape))
    x = u0.clone().requires_grad_()
    (want,) = torch.autograd.grad(f(x), x, w)
    out, pullback = vjp(f, u0)
    assert torch.equal(out, f(u0))
    assert torch.equal(pullback(w)[0], want)
    assert torch.equal(grad(lambda u: (w * f(u)).sum())(u0), want)
    jac = jacrev(f)(u0)
    torch.testing.assert_close(torch.einsum("bcx,bcxdey->dey", w, jac), want,
                               rtol=1e-12, atol=1e-14)


def test_jacrev_of_the_parameters_and_a_batched_parameter_vector():
    heat = adjointsim.get("diffusion1d-ftcs").default()
    u0 = _state(heat, 2)
    nu = torch.tensor(heat.param_values, dtype=torch.float64)

    def f(p):
        return bridge.rollout(heat, u0, 3, params=p).sum(dim=(1, 2))

    jac = jacrev(f)(nu)
    for b in range(2):
        x = nu.clone().requires_grad_()
        (row,) = torch.autograd.grad(f(x)[b], x)
        torch.testing.assert_close(jac[b], row, rtol=1e-12, atol=1e-15)
    several = torch.stack([nu, 0.5 * nu])
    mapped = vmap(lambda p: bridge.rollout(heat, u0, 3, params=p))(several)
    for p, got in zip(several, mapped, strict=True):
        assert torch.equal(got, bridge.rollout(heat, u0, 3, params=p))


def test_vmap_of_the_grouped_rollout():
    ks = adjointsim.get("ks1d-etdrk1")
    small, large = (ks(n=48, length=2 * np.pi * 8 * f, dt=1.0, substeps=2) for f in (0.9, 1.3))
    groups = [(small, [0]), (large, [1])]
    states = _state(groups[0][0], 6).reshape(3, 2, 1, -1)

    def loss(u):
        return bridge.rollout_grouped(groups, u, 2).square().sum()

    looped = torch.stack([grad(loss)(u) for u in states])
    torch.testing.assert_close(vmap(grad(loss))(states), looped, rtol=1e-12, atol=1e-15)


def test_second_derivatives_through_the_transforms_are_refused_with_the_clear_error():
    burgers = adjointsim.get("burgers1d-rusanov").default()

    def loss(u):
        return bridge.rollout(burgers, u, 2).square().sum()

    u0 = _state(burgers, 1)
    with pytest.raises(RuntimeError, match=f"burgers1d-rusanov.*{ONCE}.*finite differences"):
        grad(lambda u: grad(loss)(u).square().sum())(u0)
    with pytest.raises(RuntimeError, match=ONCE):
        jacrev(jacrev(lambda u: bridge.rollout(burgers, u, 1)))(u0)


@pytest.mark.slow
@pytest.mark.parametrize("case", list(_cases()))
def test_inductor_compiles_the_losses_to_round_off(case):
    """Inductor fuses and reorders the network's arithmetic: round-off, not bits."""
    fn, u0, params = _cases()[case]
    torch._dynamo.reset()
    compiled = torch.compile(fn, fullgraph=True, backend="inductor")
    want_loss, want = _loss_and_grads(fn, u0, params)
    got_loss, got = _loss_and_grads(compiled, u0, params)
    torch.testing.assert_close(got_loss, want_loss, rtol=1e-12, atol=1e-14)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-13)
