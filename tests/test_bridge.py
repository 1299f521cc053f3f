"""The torch bridge: gradcheck for every registered solver, zero-copy inputs, clear errors."""

import numpy as np
import pytest
import torch

import adjointsim
from train import bridge

NAMES = adjointsim.names()


def _inputs(stepper, n, dtype=torch.float64, batch=2):
    rng = np.random.default_rng(0)
    u0 = torch.from_numpy(stepper.random_state(rng, batch)).to(dtype).requires_grad_()
    ctrl = None
    if stepper.control_shape is not None:
        ctrl = torch.from_numpy(stepper.random_controls(rng, n, batch)).to(dtype).requires_grad_()
    params = None
    if stepper.param_names:
        params = torch.tensor(stepper.param_values, dtype=dtype, requires_grad=True)
    return u0, ctrl, params


@pytest.mark.parametrize("name", NAMES)
def test_torch_gradcheck_every_solver(name):
    stepper = adjointsim.get(name).default()
    n = 3
    u0, ctrl, params = _inputs(stepper, n)
    inputs = [x for x in (u0, ctrl, params) if x is not None]

    def f(*xs):
        it = iter(xs)
        u = next(it)
        c = next(it) if ctrl is not None else None
        p = next(it) if params is not None else None
        return bridge.rollout(stepper, u, n, c, p, keep="all")

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_grouped_rollout_is_one_node_with_each_rows_own_scene():
    ks = adjointsim.get("ks1d-etdrk1")
    small, large = ks.list_et_al(0.9, coarse=True), ks.list_et_al(1.3, coarse=True)
    rng = np.random.default_rng(1)
    u0 = torch.from_numpy(small.random_state(rng, 5)).requires_grad_()
    groups = [(small, np.array([0, 3])), (large, np.array([1, 2, 4]))]

    def f(u):
        return bridge.rollout_grouped(groups, u, 2)

    assert torch.autograd.gradcheck(f, (u0,), eps=1e-6, atol=1e-6, rtol=1e-4)
    out = f(u0)
    torch.testing.assert_close(out[[0, 3]], bridge.rollout(small, u0[[0, 3]].detach(), 2))
    torch.testing.assert_close(out[[1, 2, 4]], bridge.rollout(large, u0[[1, 2, 4]].detach(), 2))
    before = bridge.ADJOINT_CALLS["count"]
    out.square().sum().backward()
    assert bridge.ADJOINT_CALLS["count"] == before + 1


@pytest.mark.parametrize("keep", ["last", "all"])
def test_in_place_edits_after_the_forward_do_not_change_the_gradient(keep):
    stepper = adjointsim.get("burgers1d-rusanov").default()
    u0, _, _ = _inputs(stepper, 4)
    (expected,) = torch.autograd.grad(bridge.rollout(stepper, u0, 4, keep=keep).sum(), u0)
    x = u0.detach().clone().requires_grad_()
    out = bridge.rollout(stepper, x, 4, keep=keep)
    with torch.no_grad():
        x.mul_(3.0)
    out.detach().mul_(-2.0)  # shares memory with out
    (got,) = torch.autograd.grad(out.sum(), x)
    torch.testing.assert_close(got, expected)


def test_checkpointed_backward_matches_stored():
    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u0, ctrl, params = _inputs(stepper, 20)
    grads = []
    for checkpoint in (None, 5):
        out = bridge.rollout(stepper, u0, 20, ctrl, params, checkpoint=checkpoint)
        grads.append(torch.autograd.grad(out.square().sum(), (u0, ctrl, params)))
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)


def test_no_grad_runs_no_adjoint_and_stores_nothing():
    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u0, _, _ = _inputs(stepper, 5)
    before = bridge.ADJOINT_CALLS["count"]
    with torch.no_grad():
        out = bridge.rollout(stepper, u0, 5)
    assert out.grad_fn is None
    out = bridge.rollout(stepper, u0.detach(), 5)
    assert out.grad_fn is None
    assert bridge.ADJOINT_CALLS["count"] == before


def test_float32_in_float32_out():
    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u0, ctrl, params = _inputs(stepper, 4, dtype=torch.float32)
    out = bridge.rollout(stepper, u0, 4, ctrl, params)
    assert out.dtype == torch.float32
    out.sum().backward()
    assert u0.grad.dtype == ctrl.grad.dtype == params.grad.dtype == torch.float32


def test_bad_tensors_get_clear_errors():
    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u0, ctrl, params = _inputs(stepper, 4)
    with pytest.raises(ValueError, match="contiguous"):
        bridge.rollout(stepper, u0.detach().transpose(0, 2).contiguous().transpose(0, 2), 4)
    with pytest.raises(TypeError, match="cast it"):
        bridge.rollout(stepper, u0, 4, ctrl, params.float())
    with pytest.raises(TypeError, match="float32 or torch.float64"):
        bridge.rollout(stepper, u0.detach().to(torch.float16), 4)
    meta = torch.empty(u0.shape, device="meta", dtype=torch.float64)
    with pytest.raises(ValueError, match="CPU"):
        bridge.rollout(stepper, meta, 4)
