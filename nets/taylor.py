"""Input derivatives of an MLP (tanh or sin) carried forward through its layers (Taylor mode).

For directions v_1..v_D in input space, the n-th directional derivatives
u^(n)_d = dⁿ/dtⁿ u(x + t v_d) |_{t=0}, n ≤ 4, are pushed through each layer in one pass:
a linear layer maps every order alike (z_0 = W y_0 + b, z_n = W y_n), and an activation
σ acts by Faà di Bruno's formula,

    y_1 = σ' z_1
    y_2 = σ'' z_1² + σ' z_2
    y_3 = σ''' z_1³ + 3 σ'' z_1 z_2 + σ' z_3
    y_4 = σ'''' z_1⁴ + 6 σ''' z_1² z_2 + σ'' (4 z_1 z_3 + 3 z_2²) + σ' z_4,

with σ^(k) of tanh from t = tanh z, s = 1 − t²: s, −2ts, s(6t² − 2), 8ts(2 − 3t²); of sin:
cos, −sin, −cos, sin. At the input y_0 = x, y_1 = v_d, y_{n≥2} = 0, so the first layer's
z_1 = W v_d is the same for every point and higher orders start at zero.

With the coordinate axes as directions this gives ∇u (order 1), the pure second derivatives
∂²u/∂x_i² (whose sum is Δu) and ∂³u/∂x_i³, ∂⁴u/∂x_i⁴; mixed derivatives follow from other
directions by polarisation. Everything is ordinary torch, so one reverse pass then gives the
parameter gradient of any loss of these (no nested autograd).
"""

from __future__ import annotations

import torch
from torch import nn

from .mlp import MLP, Sin

MAX_ORDER = 4


def _tanh_derivatives(z: torch.Tensor, order: int) -> list[torch.Tensor]:
    t = torch.tanh(z)
    s = 1.0 - t * t
    out = [t, s]
    if order >= 2:
        out.append(-2.0 * t * s)
    if order >= 3:
        out.append(s * (6.0 * t * t - 2.0))
    if order >= 4:
        out.append(8.0 * t * s * (2.0 - 3.0 * t * t))
    return out


def _sin_derivatives(z: torch.Tensor, order: int) -> list[torch.Tensor]:
    s, c = torch.sin(z), torch.cos(z)
    return [s, c, -s, -c, s][: order + 1]


_DERIVATIVES = {nn.Tanh: _tanh_derivatives, Sin: _sin_derivatives}


def _activate(layer: nn.Module, z: list, order: int) -> list:
    """Faà di Bruno for σ applied to the jet z = [z_0, z_1, ...] (z_n may be None: zero)."""
    d = _DERIVATIVES[type(layer)](z[0], order)
    s0 = d[0]
    d = [x.unsqueeze(-2) for x in d]  # broadcast over the direction axis
    z1, z2, z3, z4 = (z + [None] * 4)[1:5]
    y = [s0]
    if order >= 1:
        y.append(d[1] * z1)
    if order >= 2:
        q = z1 * z1
        y.append(d[2] * q + (0 if z2 is None else d[1] * z2))
    if order >= 3:
        y3 = d[3] * q * z1
        if z2 is not None:
            y3 = y3 + 3.0 * d[2] * z1 * z2 + (0 if z3 is None else d[1] * z3)
        y.append(y3)
    if order >= 4:
        y4 = d[4] * q * q
        if z2 is not None:
            y4 = y4 + 6.0 * d[3] * q * z2 + d[2] * (3.0 * z2 * z2)
        if z3 is not None:
            y4 = y4 + 4.0 * d[2] * z1 * z3 + (0 if z4 is None else d[1] * z4)
        y.append(y4)
    return y


def _layers(model: nn.Module) -> list[nn.Module]:
    net = model.net if isinstance(model, MLP) else model
    if not isinstance(net, nn.Sequential):
        raise TypeError(f"jets need an nets.mlp.MLP or an nn.Sequential, not {type(model)}")
    layers = list(net)
    for layer in layers:
        if not isinstance(layer, nn.Linear | nn.Tanh | Sin):
            raise TypeError(f"jets support Linear, Tanh and Sin layers, not {type(layer)} "
                            "(build the MLP with activation='tanh' or 'sin')")
    return layers


def jets(
    model: nn.Module, x: torch.Tensor, order: int = 2, directions: torch.Tensor | None = None
) -> list[torch.Tensor]:
    """[u, u^(1), ..., u^(order)] of ``model`` at ``x`` (N, d_in): u is (N, d_out) and u^(n)
    is (N, D, d_out), the n-th derivative along each row of ``directions`` (D, d_in; default
    the coordinate axes, D = d_in)."""
    if not 0 <= order <= MAX_ORDER:
        raise ValueError(f"order must be in 0..{MAX_ORDER}, not {order}")
    if x.ndim != 2:
        raise ValueError(f"x must be (points, coordinates), not of shape {tuple(x.shape)}")
    if directions is None:
        directions = torch.eye(x.shape[1], dtype=x.dtype, device=x.device)
    if directions.ndim != 2 or directions.shape[1] != x.shape[1]:
        raise ValueError(f"directions must be (D, {x.shape[1]}), not {tuple(directions.shape)}")
    layers = _layers(model)
    z: list = [x] + ([directions] if order >= 1 else [])  # z_1 shared by every point at first
    for layer in layers:
        if isinstance(layer, nn.Linear):
            z = [layer(z[0])] + [None if zn is None else zn @ layer.weight.T for zn in z[1:]]
        else:
            z = _activate(layer, z + [None] * (order + 1 - len(z)), order)
    shape = (x.shape[0], directions.shape[0], z[0].shape[1])
    out = [z[0]]
    for k in range(1, order + 1):
        zn = z[k] if k < len(z) else None
        if zn is None:  # no activation yet saw this order: it vanishes (an affine model)
            zn = torch.zeros(shape, dtype=x.dtype, device=x.device)
        out.append(zn.expand(shape) if zn.ndim == 2 else zn)
    return out


def laplacian(
    model: nn.Module, x: torch.Tensor, directions: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """(u, Σ_d u^(2)_d) at ``x``, both (N, d_out): with the default axes, (u, Δu).

    The second-order parts enter every layer linearly, so only their sum over the directions
    is carried, y₂ = σ'' Σ_d z_{1,d}² + σ' z₂ (the "forward Laplacian"): one (N, width) tensor
    instead of D of them, next to the D first-order ones."""
    if x.ndim != 2:
        raise ValueError(f"x must be (points, coordinates), not of shape {tuple(x.shape)}")
    if directions is None:
        directions = torch.eye(x.shape[1], dtype=x.dtype, device=x.device)
    if directions.ndim != 2 or directions.shape[1] != x.shape[1]:
        raise ValueError(f"directions must be (D, {x.shape[1]}), not {tuple(directions.shape)}")
    z0, z1, z2 = x, directions, None
    for layer in _layers(model):
        if isinstance(layer, nn.Linear):
            z0 = layer(z0)
            z1 = z1 @ layer.weight.T
            z2 = None if z2 is None else z2 @ layer.weight.T
            continue
        d = _DERIVATIVES[type(layer)](z0, 2)
        q = (z1 * z1).sum(dim=-2)  # (N, w), or (w,) while z1 is shared by every point
        z2 = d[2] * q if z2 is None else d[2] * q + d[1] * z2
        z1 = d[1].unsqueeze(-2) * z1
        z0 = d[0]
    if z2 is None:  # an affine model
        z2 = torch.zeros_like(z0)
    return z0, z2
