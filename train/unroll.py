"""Gradient-flow modes of a closed loop, and the unrolled training losses that use them.

A closed loop feeds the state x_t along two paths: into the network (c_t = N(x_t)) and into
the physics (x_{t+1} = S(x_t, c_t); in List et al.'s correction setup S(x_t) + f(x_t)).
One switch, :class:`GradientFlow`, says where gradients stop (Schnell & Thuerey 2024):

* R (regular BPTT): no stops.                           List et al.'s WIG is R.
* M (modified): stop the state fed into the network only, c_t = N(stop(x_t)).
* S (stopped): stop both paths.                         List et al.'s NOG is S.
* N: stop the physics path only.
* C (combined): g = where(sign(g_M) == sign(g_R), g_M, 0), element-wise per tensor.

Beside the flows stands one more way to train a target horizon m, List et al.'s ONE: a
schedule, not a flow (:func:`schedule`): one-step training (R over a horizon of 1) with the
batch and the epochs scaled by m, so that it sees as many frames as an unrolled run.

C needs g_M and g_R. Both come from ONE forward pass and ONE backward pass over a doubled
batch: the loop runs two copies of each state with equal values (:meth:`GradientFlow.start`),
the R stream on top and the M stream below. Only the top stream feeds the network
(:meth:`GradientFlow.net`); :meth:`GradientFlow.control` hands the network's output to the top
stream and a detached leaf of the same value to the bottom one, and both go through the physics
in one (batched) solver call. One backward pass then gives g_R (the top stream's parameter
gradient) and the cotangents μ_t of the bottom stream's controls, i.e. the M chain's
λ_{t+1} ∂S/∂c; g_M = Σ_t μ_t ∂N/∂θ(x_t) is one more network pass over all steps' inputs
stacked. The loss must be a mean over the batch (both halves then count equally).
For clarity and the tests, ``gated=True`` instead routes the network input through a gate and
runs the backward twice (closed: g_M, open: g_R); both give the reference code's two
forward+backward passes' result.

The final update can be clipped by value or by global norm (``clip``), as the stable-BPTT
study sweeps it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

#: the gradient flows, and List et al.'s names for two of them
FLOWS = ("R", "M", "S", "N", "C")
ALIASES = {"WIG": "R", "NOG": "S"}
#: every way to train a horizon: the one-step schedule ONE, or unrolled with a gradient flow
MODES = ("ONE", "NOG", "WIG", *FLOWS)
CLIPS = ("none", "value", "norm")


def canonical(mode: str) -> str:
    """R/M/S/N/C for a gradient flow's name (WIG and NOG are R and S)."""
    if mode not in (*ALIASES, *FLOWS):
        extra = "; ONE is a schedule (see schedule())" if mode == "ONE" else ""
        raise ValueError(f"unknown gradient flow {mode!r}; choose from "
                         f"{', '.join((*ALIASES, *FLOWS))}{extra}")
    return ALIASES.get(mode, mode)


def schedule(mode: str, m: int, batch: int, epochs: float) -> tuple[str, int, int, float]:
    """(flow, horizon, batch, epochs) that train target horizon ``m`` with ``mode``: ONE trains
    one step with flow R on ``m`` × the batch for ``m`` × the epochs; a flow unrolls ``m``."""
    if mode == "ONE":
        return "R", 1, batch * m, epochs * m
    canonical(mode)
    return mode, m, batch, epochs


class _Switch:
    __slots__ = ("open",)

    def __init__(self) -> None:
        self.open = True


class _Gate(torch.autograd.Function):
    """Identity forward; the backward passes the cotangent only while the switch is open."""

    @staticmethod
    def forward(ctx, x, switch):
        ctx.switch = switch
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad):
        return (grad if ctx.switch.open else None), None


@dataclass
class Update:
    """What :meth:`GradientFlow.backward` computed: the update, and g_M / g_R when known."""

    grads: list[torch.Tensor]
    g_m: list[torch.Tensor] | None = None
    g_r: list[torch.Tensor] | None = None

    def cosine(self) -> float:
        """cos(g_M, g_R) over all parameters; NaN when either is unknown or zero."""
        if self.g_m is None or self.g_r is None:
            return float("nan")
        dot = sum(float((a * b).sum()) for a, b in zip(self.g_m, self.g_r))
        na = sum(float((a * a).sum()) for a in self.g_m) ** 0.5
        nb = sum(float((b * b).sum()) for b in self.g_r) ** 0.5
        return dot / (na * nb) if na > 0 and nb > 0 else float("nan")

    def norm(self) -> float:
        return sum(float((g * g).sum()) for g in self.grads) ** 0.5


class GradientFlow:
    """Where gradients stop in a closed loop.

    A loop written against it calls ``x = flow.start(x0)`` (and on every per-row input that
    must follow the batch), feeds ``flow.net(x)`` to the network through
    ``flow.control(fn, *inputs)`` (``fn`` the network, returning the control), feeds
    ``flow.phys(x)`` to the physics, and ends with :meth:`backward`. ``diagnose=True`` (modes
    R and M) also computes g_M and g_R, for the cosine between them, while the update stays the
    mode's own. ``gated=True`` computes C (and the diagnosis) by two backward passes over a
    gate instead of the doubled batch (the reference implementation for the tests).
    """

    def __init__(self, mode: str, clip: str = "none", clip_at: float = 1.0,
                 diagnose: bool = False, gated: bool = False):
        self.name, self.mode = mode, canonical(mode)
        if clip not in CLIPS:
            raise ValueError(f"unknown clip {clip!r}; choose from {', '.join(CLIPS)}")
        if not clip_at > 0:
            raise ValueError(f"clip_at must be > 0, not {clip_at}")
        self.clip, self.clip_at = clip, float(clip_at)
        both = self.mode == "C" or (diagnose and self.mode in ("R", "M"))
        self.gated = both and gated
        self.doubled = both and not gated
        self._switch = _Switch()
        self._records: list[tuple] = []  # (fn, detached inputs, bottom-stream leaf)
        self._rows: int | None = None

    def start(self, x: torch.Tensor) -> torch.Tensor:
        """A per-row input of the loop (state, targets, row parameters), doubled for C."""
        if not self.doubled:
            return x
        self._rows = x.shape[0]
        return torch.cat([x, x])

    def net(self, x: torch.Tensor) -> torch.Tensor:
        """The state as fed into the network."""
        if self.doubled:
            return x[: x.shape[0] // 2]
        if self.gated:
            return _Gate.apply(x, self._switch)
        return x.detach() if self.mode in ("M", "S") else x

    def control(self, fn: Callable[..., torch.Tensor], *inputs: torch.Tensor) -> torch.Tensor:
        """``fn(*inputs)`` (the network on ``net(x)``), as fed into the physics."""
        out = fn(*inputs)
        if not self.doubled:
            return out
        leaf = out.detach().requires_grad_()
        self._records.append((fn, tuple(i.detach() for i in inputs), leaf))
        return torch.cat([out, leaf])

    def phys(self, x: torch.Tensor) -> torch.Tensor:
        """The state as fed into the physics."""
        return x.detach() if self.mode in ("S", "N") else x

    def backward(self, loss: torch.Tensor, params: Sequence[torch.Tensor]) -> Update:
        """Compute the update of ``params`` from ``loss``, clip it, store it in ``.grad``."""
        params = list(params)
        g_m = g_r = None
        if self.doubled:
            g_r, g_m = self._doubled(loss, params)
        elif self.gated:
            self._switch.open = False
            g_m = _grad(loss, params, retain=True)
            self._switch.open = True
            g_r = _grad(loss, params, retain=False)
        if g_m is not None:
            if self.mode == "C":
                grads = [torch.where(torch.sign(a) == torch.sign(b), a, torch.zeros_like(a))
                         for a, b in zip(g_m, g_r)]
            else:
                grads = list(g_m if self.mode == "M" else g_r)
        else:
            grads = _grad(loss, params, retain=False)
        grads = clip_update(grads, self.clip, self.clip_at)
        for p, g in zip(params, grads):
            p.grad = g
        return Update(grads, g_m, g_r)

    def _doubled(self, loss, params):
        leaves = [r[2] for r in self._records]
        gs = torch.autograd.grad(loss, params + leaves, allow_unused=True)
        # the loss is a mean over the doubled batch: each stream's gradient is twice its share
        g_r = [2 * g if g is not None else torch.zeros_like(p) for p, g in zip(params, gs)]
        mu = [2 * g if g is not None else torch.zeros_like(leaf)
              for leaf, g in zip(leaves, gs[len(params):])]
        fns = {id(r[0]) for r in self._records}
        if len(fns) == 1 and self._records:
            # one network pass over every step's inputs stacked
            fn = self._records[0][0]
            inputs = [torch.cat(group) for group in zip(*(r[1] for r in self._records))]
            total = (fn(*inputs) * torch.cat(mu)).sum()
        else:
            total = sum((r[0](*r[1]) * m).sum() for r, m in zip(self._records, mu))
        self._records = []
        if not torch.is_tensor(total) or not total.requires_grad:
            return g_r, [torch.zeros_like(p) for p in params]
        return g_r, _grad(total, params, retain=False)


def _grad(loss: torch.Tensor, params: list[torch.Tensor], retain: bool) -> list[torch.Tensor]:
    gs = torch.autograd.grad(loss, params, retain_graph=retain, allow_unused=True)
    return [torch.zeros_like(p) if g is None else g for p, g in zip(params, gs)]


def clip_update(grads: list[torch.Tensor], clip: str, at: float = 1.0) -> list[torch.Tensor]:
    """``value``: each element into [-at, at]; ``norm``: scale so the global norm is ≤ at."""
    if clip == "none":
        return grads
    if clip == "value":
        return [g.clamp(-at, at) for g in grads]
    if clip == "norm":
        norm = torch.sqrt(sum((g * g).sum() for g in grads))
        scale = torch.clamp(at / (norm + 1e-12), max=1.0)
        return [g * scale for g in grads]
    raise ValueError(f"unknown clip {clip!r}; choose from {', '.join(CLIPS)}")


def unrolled_loss(
    model: torch.nn.Module,
    frames: torch.Tensor,
    params: torch.Tensor,
    conditions: torch.Tensor,
    mode: str | GradientFlow,
    warmup: int = 0,
    truncate: int = 0,
    members: int = 0,
) -> torch.Tensor:
    """List et al.'s unrolled loss. ``frames``: (B, w + m + 1, C, *grid) reference window.

    The model runs from u_0; the first w steps are the warm-up ("pushforward": no tape, not in
    the loss) and the loss is the mean over s = 1..m of MSE(û_{w+s}, u_{w+s}). ``mode`` is a
    mode name or a :class:`GradientFlow` (needed for C, whose update then comes from
    ``flow.backward(loss, params)``). ``truncate=k`` detaches the state every k steps
    (truncated BPTT). ``members=K`` returns K losses, one per member of an ensemble whose rows
    come in K equal blocks (member-major, see :mod:`adjointsim.train.ensemble`): each the
    loss of its own rows, as its separate run computes it.
    """
    name = mode.name if isinstance(mode, GradientFlow) else mode
    flow = mode if isinstance(mode, GradientFlow) else GradientFlow(mode)
    if flow.doubled and flow is not mode:
        # loss.backward() over the doubled batch would silently give g_R / 2, not C's update
        raise ValueError(f"mode {name!r} needs a GradientFlow: pass flow = GradientFlow("
                         f"{name!r}) and take the update from flow.backward(loss, params)")
    m = frames.shape[1] - 1 - warmup
    if m < 1:
        raise ValueError(f"{name} needs windows of warmup + m + 1 frames, m ≥ 1")
    u = frames[:, 0]
    if warmup:
        with torch.no_grad():
            for _ in range(warmup):
                u = model(u, params, conditions)
    u, frames, params, conditions = (flow.start(t) for t in (u, frames, params, conditions))
    losses = []
    for s in range(1, m + 1):
        if truncate and s > 1 and (s - 1) % truncate == 0:
            u = u.detach()
        u = model(u, params, conditions, flow)
        error = (u - frames[:, warmup + s]) ** 2
        if members:  # C's doubled batch holds two blocks of members, each member's rows in both
            losses.append(error.reshape(2 if flow.doubled else 1, members, -1).mean(dim=(0, 2)))
        else:
            losses.append(torch.mean(error))
    return torch.stack(losses).mean(dim=0) if members else torch.stack(losses).mean()
