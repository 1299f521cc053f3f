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

import numpy as np
import torch
from numba import njit
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
        raise TypeError("jets need an adjointsim.nets.mlp.MLP or an nn.Sequential, not "
                        f"{type(model)}")
    layers = list(net)
    for layer in layers:
        if not isinstance(layer, nn.Linear | nn.Tanh | Sin):
            raise TypeError(f"jets support Linear, Tanh and Sin layers, not {type(layer)} "
                            "(build the MLP with activation='tanh' or 'sin')")
    return layers


def _alternating(layers: list[nn.Module]) -> bool:
    """Linear (with bias), activation, Linear, ..., Linear: the form the fused pass takes."""
    return (len(layers) % 2 == 1
            and all(isinstance(m, nn.Linear) and m.bias is not None for m in layers[0::2])
            and not any(isinstance(m, nn.Linear) for m in layers[1::2]))


def _directions(x: torch.Tensor, directions: torch.Tensor | None) -> torch.Tensor:
    """Check the points (N, d_in) and return the directions (D, d_in), default the axes."""
    if x.ndim != 2:
        raise ValueError(f"x must be (points, coordinates), not of shape {tuple(x.shape)}")
    if directions is None:
        return torch.eye(x.shape[1], dtype=x.dtype, device=x.device)
    if directions.ndim != 2 or directions.shape[1] != x.shape[1]:
        raise ValueError(f"directions must be (D, {x.shape[1]}), not {tuple(directions.shape)}")
    return directions


def jets(
    model: nn.Module, x: torch.Tensor, order: int = 2, directions: torch.Tensor | None = None
) -> list[torch.Tensor]:
    """[u, u^(1), ..., u^(order)] of ``model`` at ``x`` (N, d_in): u is (N, d_out) and u^(n)
    is (N, D, d_out), the n-th derivative along each row of ``directions`` (D, d_in; default
    the coordinate axes, D = d_in)."""
    if not 0 <= order <= MAX_ORDER:
        raise ValueError(f"order must be in 0..{MAX_ORDER}, not {order}")
    directions = _directions(x, directions)
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


def _sigma3(layer: nn.Module, z: torch.Tensor) -> list[torch.Tensor]:
    """σ and its first three derivatives at z (in place where a temporary allows)."""
    if isinstance(layer, nn.Tanh):
        t = torch.tanh(z)
        s1 = torch.mul(t, t).neg_().add_(1.0)
        s2 = torch.mul(t, s1).mul_(-2.0)
        s3 = torch.mul(t, t).mul_(6.0).sub_(2.0).mul_(s1)
        return [t, s1, s2, s3]
    sn, cs = torch.sin(z), torch.cos(z)
    return [sn, cs, -sn, -cs]


# The forward Laplacian's tanh layers, fused: one pass over the (N, width) elements instead of
# a dozen torch element-wise ops, each a trip through memory; torch's tanh stays in torch
# (`python benchmarks/pinn.py`: 1.60x -> 1.97x over nested autograd on the Poisson epoch).
@njit(cache=True)
def _tanh_layer(t, z1, z2, y1, y2, s1, s2, s3, q):
    """From t = tanh(z0): σ', σ'', σ‴ (s1, s2, s3), q = Σ_d z1², y1 = σ' z1 and
    y2 = σ'' q + σ' z2 (z2 empty: zero)."""
    n, dirs, width = z1.shape
    for p in range(n):
        for j in range(width):
            tt = t[p, j]
            d1 = 1.0 - tt * tt
            s1[p, j] = d1
            s2[p, j] = -2.0 * tt * d1
            s3[p, j] = d1 * (6.0 * tt * tt - 2.0)
            q[p, j] = 0.0
        for d in range(dirs):
            for j in range(width):
                v = z1[p, d, j]
                q[p, j] += v * v
                y1[p, d, j] = s1[p, j] * v
        for j in range(width):
            y2[p, j] = s2[p, j] * q[p, j]
            if z2.shape[0] > 0:
                y2[p, j] += s1[p, j] * z2[p, j]


@njit(cache=True)
def _tanh_layer_adjoint(s1, s2, s3, q, z1, z2, g0, g1, g2, zb0, zb1, zb2):
    """The reverse of :func:`_tanh_layer` (see :class:`_ForwardLaplacian`; g1, z2 empty:
    zero)."""
    n, dirs, width = z1.shape
    for p in range(n):
        for j in range(width):
            zb2[p, j] = s1[p, j] * g2[p, j]
            c = s3[p, j] * q[p, j]
            if z2.shape[0] > 0:
                c += s2[p, j] * z2[p, j]
            zb0[p, j] = c * g2[p, j] + s1[p, j] * g0[p, j]
        for d in range(dirs):
            for j in range(width):
                v = 2.0 * s2[p, j] * g2[p, j] * z1[p, d, j]
                if g1.shape[0] > 0:
                    v += s1[p, j] * g1[p, d, j]
                    zb0[p, j] += s2[p, j] * g1[p, d, j] * z1[p, d, j]
                zb1[p, d, j] = v


def _np(t: torch.Tensor | None, like: torch.Tensor) -> np.ndarray:
    """A contiguous array view of ``t``, or an empty one of ``like``'s dtype for None."""
    if t is None:
        return np.empty((0,) * like.ndim, dtype=like.numpy().dtype)
    return t.contiguous().numpy()


class _Buffers:
    """The forward Laplacian's (N, width) arrays for one shape of problem, handed to the next
    call once the graph that used them is gone (:class:`_Lease`). Fresh arrays every epoch
    are fresh pages, and their page faults cost about a fifth of a Poisson epoch
    (`python benchmarks/pinn.py`); a training loop's epochs share one set instead."""

    free: dict[tuple, list[_Buffers]] = {}
    SHAPES = 4  # shapes kept (oldest dropped): a loop over many batch sizes holds no more

    def __init__(self) -> None:
        self.arrays: dict[str, torch.Tensor] = {}

    def __call__(self, name: str, shape: tuple, like: torch.Tensor) -> torch.Tensor:
        t = self.arrays.get(name)
        if t is None:
            t = self.arrays[name] = like.new_empty(shape)
        return t


class _Lease:
    """Holds a :class:`_Buffers` for one graph (as an attribute of its autograd context) and
    frees it for reuse when the graph is deleted."""

    def __init__(self, key: tuple) -> None:
        free = _Buffers.free.get(key)
        self.key, self.buffers = key, free.pop() if free else _Buffers()

    def __del__(self) -> None:
        free = _Buffers.free.setdefault(self.key, [])
        free.append(self.buffers)
        while len(_Buffers.free) > _Buffers.SHAPES:
            del _Buffers.free[next(iter(_Buffers.free))]


class _ForwardLaplacian(torch.autograd.Function):
    """(u, Σ_d u^(2)_d) of a Linear/activation stack with a hand-written reverse pass for the
    parameters. Per hidden layer, with q = Σ_d z1², the forward is
    y0 = σ(z0), y1 = σ' z1, y2 = σ'' q + σ' z2, and the reverse is
    z̄2 = σ' ȳ2,  z̄1 = σ' ȳ1 + 2σ'' ȳ2 z1,  z̄0 = σ' ȳ0 + σ'' Σ_d ȳ1 z1 + ȳ2 (σ‴ q + σ'' z2),
    then the linear layer's usual products. Fewer, in-place passes than autograd's op-by-op
    graph, into reused buffers (tanh layers); no gradient for x or the directions."""

    @staticmethod
    def forward(ctx, x, dirs, acts, *wb):
        weights, biases = wb[0::2], wb[1::2]
        n, k = x.shape[0], dirs.shape[0]
        ctx.lease = _Lease((n, k, x.dtype, *(tuple(W.shape) for W in weights)))
        buf = ctx.lease.buffers
        a0, a1, a2 = x, dirs, None
        saved = []
        for i, (W, b, act) in enumerate(zip(weights[:-1], biases[:-1], acts)):
            w = W.shape[0]
            if isinstance(act, nn.Tanh):
                z0 = torch.addmm(b, a0, W.T, out=buf(f"z0{i}", (n, w), x))
                z1 = buf(f"z1{i}", (n, k, w), x)
                if a1.ndim == 2:  # first layer: W v_d, the same for every point
                    z1.copy_((a1 @ W.T).expand(n, k, w))
                else:
                    torch.matmul(a1, W.T, out=z1)
                z2 = None if a2 is None else torch.mm(a2, W.T, out=buf(f"z2{i}", (n, w), x))
                s0, s1, s2, s3, q, y2 = (buf(f"{name}{i}", (n, w), x)
                                         for name in ("s0", "s1", "s2", "s3", "q", "y2"))
                y1 = buf(f"y1{i}", (n, k, w), x)
                np.tanh(z0.numpy(), out=s0.numpy())  # NumPy's SIMD tanh: 2x torch's here
                _tanh_layer(s0.numpy(), z1.numpy(), _np(z2, z0), y1.numpy(), y2.numpy(),
                            s1.numpy(), s2.numpy(), s3.numpy(), q.numpy())
            else:
                z0 = torch.addmm(b, a0, W.T)
                z1 = a1 @ W.T  # (D, w) at the first layer, then (N, D, w)
                z2 = None if a2 is None else a2 @ W.T
                s0, s1, s2, s3 = _sigma3(act, z0)
                q = (z1 * z1).sum(dim=-2)
                y2 = s2 * q
                if z2 is not None:
                    y2.addcmul_(s1, z2)
                y1 = s1.unsqueeze(-2) * z1
            saved.append((a0, a1, a2, z1, z2, q, s1, s2, s3, act))
            a0, a1, a2 = s0, y1, y2
        W, b = weights[-1], biases[-1]
        u = torch.addmm(b, a0, W.T)
        lap = a2 @ W.T if a2 is not None else torch.zeros_like(u)
        ctx.saved, ctx.last = saved, (a0, a2)
        ctx.save_for_backward(*wb)
        return u, lap

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, gu, gl):
        weights = ctx.saved_tensors[0::2]
        buf = ctx.lease.buffers
        a0, a2 = ctx.last
        W = weights[-1]
        grads = [gu.T @ a0 + (gl.T @ a2 if a2 is not None else 0.0), gu.sum(dim=0)]
        g0, g1, g2 = gu @ W, None, gl @ W
        for i in range(len(ctx.saved) - 1, -1, -1):
            a0, a1, a2, z1, z2, q, s1, s2, s3, act = ctx.saved[i]
            W = weights[i]
            if isinstance(act, nn.Tanh):
                zb0, zb2 = buf(f"zb0{i}", s1.shape, s1), buf(f"zb2{i}", s1.shape, s1)
                zb1 = buf(f"zb1{i}", z1.shape, z1)
                _tanh_layer_adjoint(s1.numpy(), s2.numpy(), s3.numpy(), q.numpy(), z1.numpy(),
                                    _np(z2, s1), _np(g0, s1), _np(g1, z1), _np(g2, s1),
                                    zb0.numpy(), zb1.numpy(), zb2.numpy())
            else:
                zb2 = s1 * g2
                zb1 = (2.0 * s2 * g2).unsqueeze(-2) * z1
                zb0 = s3 * q
                if z2 is not None:
                    zb0.addcmul_(s2, z2)
                zb0.mul_(g2).addcmul_(s1, g0)
                if g1 is not None:
                    zb1.addcmul_(s1.unsqueeze(-2), g1)
                    zb0.addcmul_(s2, (g1 * z1).sum(dim=-2))
            if a1.ndim == 2:  # first layer: the directions are shared by every point
                gW = zb0.T @ a0 + zb1.sum(dim=0).T @ a1
            else:
                gW = zb0.T @ a0 + zb1.reshape(-1, zb1.shape[-1]).T @ a1.reshape(-1, a1.shape[-1])
            if a2 is not None:
                gW = gW + zb2.T @ a2
            grads = [gW, zb0.sum(dim=0), *grads]
            if i > 0:
                w = W.shape[1]
                g0 = torch.mm(zb0, W, out=buf(f"g0{i}", (zb0.shape[0], w), zb0))
                g1 = torch.matmul(zb1, W, out=buf(f"g1{i}", (*zb1.shape[:2], w), zb1))
                g2 = torch.mm(zb2, W, out=buf(f"g2{i}", (zb2.shape[0], w), zb2))
        return (None, None, None, *grads)


# Its numba kernels write into buffers reused across calls (:class:`_Lease`), which no traced
# graph can hold: under torch.compile it runs eager, a graph break.
@torch.compiler.disable
def _forward_laplacian(x: torch.Tensor, directions: torch.Tensor, acts: tuple,
                       wb: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    return _ForwardLaplacian.apply(x, directions, acts, *wb)


def laplacian(
    model: nn.Module, x: torch.Tensor, directions: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """(u, Σ_d u^(2)_d) at ``x``, both (N, d_out): with the default axes, (u, Δu).

    The second-order parts enter every layer linearly, so only their sum over the directions
    is carried, y₂ = σ'' Σ_d z_{1,d}² + σ' z₂ (the "forward Laplacian"): one (N, width) tensor
    instead of D of them, next to the D first-order ones."""
    directions = _directions(x, directions)
    layers = _layers(model)
    if not (x.requires_grad or directions.requires_grad) and _alternating(layers):
        wb = [t for m in layers[0::2] for t in (m.weight, m.bias)]
        return _forward_laplacian(x, directions, tuple(layers[1::2]), wb)
    z0, z1, z2 = x, directions, None
    for layer in layers:
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
