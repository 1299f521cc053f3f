"""Forward Taylor-mode input derivatives (nets/taylor.py) against nested reverse-mode autograd."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from nets.mlp import MLP
from nets.taylor import jets, laplacian


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
            scale = 1.0 + float(ref.abs().max())
            torch.testing.assert_close(g[:, k], ref, rtol=0, atol=1e-11 * scale)


def test_parameter_gradient_of_a_laplacian_loss_matches_nested_autograd():
    torch.manual_seed(1)
    model = MLP(2, 1, 6, 3, "tanh").double()
    x = torch.rand(10, 2, dtype=torch.float64, requires_grad=True)
    _, lap = laplacian(model, x)
    params = list(model.parameters())  # the last bias drops out of Δu: its gradient is None
    g_fast = torch.autograd.grad((lap**2).mean(), params, allow_unused=True)
    u = model(x)
    grad = torch.autograd.grad(u.sum(), x, create_graph=True)[0]
    lap_ref = sum(torch.autograd.grad(grad[:, i].sum(), x, create_graph=True)[0][:, i]
                  for i in range(2))
    torch.testing.assert_close(lap[:, 0], lap_ref, rtol=1e-12, atol=1e-12)
    g_ref = torch.autograd.grad((lap_ref**2).mean(), params, allow_unused=True)
    assert g_fast[-1] is None and g_ref[-1] is None
    for a, b in zip(g_fast[:-1], g_ref[:-1]):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_bad_input_is_named():
    with pytest.raises(TypeError, match="Linear, Tanh and Sin"):
        jets(MLP(2, 1, 4, 1, "relu"), torch.zeros(3, 2), 2)
    with pytest.raises(ValueError, match="order must be in 0..4"):
        jets(MLP(2, 1, 4, 1), torch.zeros(3, 2), 5)
    with pytest.raises(ValueError, match=r"directions must be \(D, 2\)"):
        jets(MLP(2, 1, 4, 1), torch.zeros(3, 2), 1, torch.zeros(2, 3))
    with pytest.raises(ValueError, match="points, coordinates"):
        jets(MLP(2, 1, 4, 1), torch.zeros(3), 1)
