"""Forward Taylor-mode input derivatives (nets/taylor.py) against nested reverse-mode autograd."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from adjointsim.nets.mlp import MLP
from adjointsim.nets.taylor import jets, laplacian


def _nested(model, x, v, order):
    """dⁿ/dtⁿ u(x + t v) by nested autograd: n reverse passes of v·∇."""
    u = model(x)
    out = [u]
    cur = u
    for _ in range(order):
        cols = []
        for j in range(cur.shape[1]):
            g = torch.autograd.grad(cur[:, j].sum(), x, create_graph=True)[0]
            cols.append(g @ v)
        cur = torch.stack(cols, dim=1)
        out.append(cur)
    return out


@settings(max_examples=25, deadline=None)
@given(
    width=st.integers(1, 9), depth=st.integers(1, 4), activation=st.sampled_from(["tanh", "sin"]),
    d_in=st.integers(1, 3), d_out=st.integers(1, 2), order=st.integers(0, 4),
    axes=st.booleans(), seed=st.integers(0, 2**16),
)
def test_jets_match_nested_autograd(width, depth, activation, d_in, d_out, order, axes, seed):
    torch.manual_seed(seed)
    model = MLP(d_in, d_out, width, depth, activation).double()
    x = torch.randn(4, d_in, dtype=torch.float64, requires_grad=True)
    dirs = None if axes else torch.randn(2, d_in, dtype=torch.float64)
    got = jets(model, x, order, dirs)
    v = torch.eye(d_in, dtype=torch.float64) if axes else dirs
    assert len(got) == order + 1
    torch.testing.assert_close(got[0], model(x), rtol=1e-12, atol=1e-12)
    for n, g in enumerate(got[1:], start=1):
        assert g.shape == (4, v.shape[0], d_out)
        for k in range(v.shape[0]):
            ref = _nested(model, x, v[k], n)[n]
            scale = 1.0 + float(ref.detach().abs().max())
            torch.testing.assert_close(g[:, k], ref, rtol=0, atol=1e-11 * scale)


@settings(max_examples=20, deadline=None)
@given(width=st.integers(1, 9), depth=st.integers(1, 4),
       activation=st.sampled_from(["tanh", "sin"]), d_in=st.integers(1, 3),
       d_out=st.integers(1, 2), seed=st.integers(0, 2**16))
def test_fused_laplacian_and_its_parameter_gradient_match_nested_autograd(
    width, depth, activation, d_in, d_out, seed
):
    """The hand-written reverse pass of the forward Laplacian (x without grad) against nested
    reverse-mode autograd, values and the parameter gradient of a loss of u and Δu."""
    torch.manual_seed(seed)
    model = MLP(d_in, d_out, width, depth, activation).double()
    x = torch.randn(7, d_in, dtype=torch.float64)
    u, lap = laplacian(model, x)
    assert lap.grad_fn is not None and "ForwardLaplacian" in type(lap.grad_fn).__name__
    params = list(model.parameters())  # the last bias drops out of Δu
    g_fast = torch.autograd.grad((lap**2).mean() + (u**3).mean(), params)
    xr = x.clone().requires_grad_(True)
    ur = model(xr)
    lap_ref = torch.zeros_like(ur)
    for j in range(d_out):
        g = torch.autograd.grad(ur[:, j].sum(), xr, create_graph=True)[0]
        for i in range(d_in):
            lap_ref[:, j] += torch.autograd.grad(g[:, i].sum(), xr, create_graph=True)[0][:, i]
    torch.testing.assert_close(u, ur, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(lap, lap_ref, rtol=1e-10, atol=1e-10)
    g_ref = torch.autograd.grad((lap_ref**2).mean() + (ur**3).mean(), params)
    for a, b in zip(g_fast, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10 * (1 + float(b.abs().max())))


def test_bad_input_is_named():
    with pytest.raises(TypeError, match="Linear, Tanh and Sin"):
        jets(MLP(2, 1, 4, 1, "relu"), torch.zeros(3, 2), 2)
    with pytest.raises(ValueError, match="order must be in 0..4"):
        jets(MLP(2, 1, 4, 1), torch.zeros(3, 2), 5)
    with pytest.raises(ValueError, match=r"directions must be \(D, 2\)"):
        jets(MLP(2, 1, 4, 1), torch.zeros(3, 2), 1, torch.zeros(2, 3))
    with pytest.raises(ValueError, match="points, coordinates"):
        jets(MLP(2, 1, 4, 1), torch.zeros(3), 1)


def test_fused_tanh_layers_in_float32_match_float64():
    """The numba tanh layers compile per dtype: float32 agrees with float64 to its precision,
    values and parameter gradient."""
    torch.manual_seed(1)
    model = MLP(2, 1, 16, 3, "tanh").double()
    x = torch.randn(50, 2, dtype=torch.float64)
    out = {}
    for dtype in (torch.float64, torch.float32):
        m = model.to(dtype)
        u, lap = laplacian(m, x.to(dtype))
        grads = torch.autograd.grad((lap**2).mean() + u.mean(), list(m.parameters()))
        out[dtype] = [t.detach().double() for t in (u, lap, *grads)]
    for a, b in zip(out[torch.float32], out[torch.float64]):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4 * (1 + float(b.abs().max())))


def test_graphs_alive_at_once_keep_their_own_buffers():
    """The forward Laplacian reuses its arrays only once a graph is gone: two graphs of the
    same shape alive together, one of them differentiated twice (retain_graph), and a third
    made after the first is deleted all give the gradients of fresh, separate calls."""
    torch.manual_seed(3)
    model = MLP(2, 1, 8, 3, "tanh").double()
    params = list(model.parameters())
    xs = [torch.randn(20, 2, dtype=torch.float64) for _ in range(3)]

    def grads(lap, **kw):
        return torch.autograd.grad((lap**2).sum(), params, **kw)

    ref = [grads(laplacian(model, x)[1]) for x in xs]
    lap0, lap1 = laplacian(model, xs[0])[1], laplacian(model, xs[1])[1]
    got1 = grads(lap1, retain_graph=True)
    got0 = grads(lap0)
    again1 = grads(lap1)
    del lap0
    got2 = grads(laplacian(model, xs[2])[1])
    for want, have in ((ref[0], got0), (ref[1], got1), (ref[1], again1), (ref[2], got2)):
        for a, b in zip(have, want):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
