"""Gradient-flow modes of a closed loop, and the unrolled training losses that use them.

A closed loop feeds the state x_t along two paths: into the network (c_t = N(x_t)) and into
the physics (x_{t+1} = S(x_t, c_t); in List et al.'s correction setup S(x_t) + f(x_t)).
One switch, :class:`GradientFlow`, says where gradients stop (Schnell & Thuerey 2024):

* R (regular BPTT): no stops.                           List et al.'s WIG is R.
* M (modified): stop the state fed into the network only, c_t = N(stop(x_t)).
* S (stopped): stop both paths.                         List et al.'s NOG is S.
* N: stop the physics path only.
* C (combined): g = where(sign(g_M) == sign(g_R), g_M, 0), element-wise per tensor.
* ONE: List et al.'s one-step training, R with a horizon of 1.

C needs g_M and g_R. Both come from ONE forward pass: the network input goes through a gate
whose backward either passes the cotangent (R) or drops it (M); :meth:`GradientFlow.backward`
runs the backward twice over the same tape with the gate closed, then open. Only the backward
changes between the two, so this is exactly the reference code's two forward+backward passes
minus one forward.

The final update can be clipped by value or by global norm (``clip``), as the stable-BPTT
study sweeps it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

#: canonical gradient-flow modes and List et al.'s names
FLOWS = ("R", "M", "S", "N", "C")
ALIASES = {"WIG": "R", "NOG": "S", "ONE": "R"}
MODES = ("ONE", "NOG", "WIG", *FLOWS)
CLIPS = ("none", "value", "norm")


def canonical(mode: str) -> str:
    """R/M/S/N/C for any accepted mode name (ONE/NOG/WIG map to R/S/R)."""
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; choose from {', '.join(MODES)}")
    return ALIASES.get(mode, mode)


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
    """Where gradients stop in a closed loop: ``net(x)`` / ``phys(x)`` wrap the two uses of a
    state, :meth:`backward` turns the loss into the mode's update.

    ``diagnose=True`` (any mode) gates the network path like C so that :meth:`backward` also
    returns g_M and g_R (for the cosine between them), while the update stays the mode's own.
    """

    def __init__(self, mode: str, clip: str = "none", clip_at: float = 1.0,
                 diagnose: bool = False):
        self.name, self.mode = mode, canonical(mode)
        if clip not in CLIPS:
            raise ValueError(f"unknown clip {clip!r}; choose from {', '.join(CLIPS)}")
        if not clip_at > 0:
            raise ValueError(f"clip_at must be > 0, not {clip_at}")
        self.clip, self.clip_at = clip, float(clip_at)
        self.gated = self.mode == "C" or (diagnose and self.mode in ("R", "M"))
        self._switch = _Switch()

    def net(self, x: torch.Tensor) -> torch.Tensor:
        """The state as fed into the network."""
        if self.gated:
            return _Gate.apply(x, self._switch)
        return x.detach() if self.mode in ("M", "S") else x

    def phys(self, x: torch.Tensor) -> torch.Tensor:
        """The state as fed into the physics."""
        return x.detach() if self.mode in ("S", "N") else x

    def backward(self, loss: torch.Tensor, params: Sequence[torch.Tensor]) -> Update:
        """Compute the update of ``params`` from ``loss``, clip it, store it in ``.grad``."""
        params = list(params)
        g_m = g_r = None
        if self.gated:
            self._switch.open = False
            g_m = _grad(loss, params, retain=True)
            self._switch.open = True
            g_r = _grad(loss, params, retain=False)
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
) -> torch.Tensor:
    """List et al.'s unrolled loss. ``frames``: (B, w + m + 1, C, *grid) reference window.

    The model runs from u_0; the first w steps are the warm-up ("pushforward": no tape, not in
    the loss) and the loss is the mean over s = 1..m of MSE(û_{w+s}, u_{w+s}). ``mode`` is a
    mode name or a :class:`GradientFlow` (needed for C, whose update then comes from
    ``flow.backward(loss, params)``). ONE needs m = 1 (the trainer scales batch size and epochs
    by the target m). ``truncate=k`` detaches the state every k steps (truncated BPTT).
    """
    name = mode.name if isinstance(mode, GradientFlow) else mode
    flow = mode if isinstance(mode, GradientFlow) else GradientFlow(mode)
    m = frames.shape[1] - 1 - warmup
    if m < 1 or (name == "ONE" and m != 1):
        need = "1" if name == "ONE" else "m ≥ 1"
        raise ValueError(f"{name} needs windows of warmup + {need} + 1 frames")
    u = frames[:, 0]
    if warmup:
        with torch.no_grad():
            for _ in range(warmup):
                u = model(u, params, conditions)
    losses = []
    for s in range(1, m + 1):
        if truncate and s > 1 and (s - 1) % truncate == 0:
            u = u.detach()
        u = model(u, params, conditions, flow)
        losses.append(torch.mean((u - frames[:, warmup + s]) ** 2))
    return torch.stack(losses).mean()
