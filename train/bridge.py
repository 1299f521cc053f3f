"""The torch bridge: a stepper's fused rollout as a ``torch.autograd.Function``.

Tensors cross to numba without copies (``Tensor.numpy()`` shares memory). The backward pass
calls the stepper's hand-written adjoint, never autograd through the solver. When no input
needs a gradient (evaluation, ``torch.no_grad()``, NOG's detached solver calls) the forward
stores nothing; otherwise it keeps the trajectory, or only checkpoints when ``checkpoint`` is
set, so that the backward pass does not recompute it.
"""

from __future__ import annotations

import numpy as np
import torch

from adjointsim import Stepper

#: counts adjoint sweeps, so tests can prove that a training mode never ran one
ADJOINT_CALLS = {"count": 0}


def _as_numpy(t: torch.Tensor | None, what: str, dtype: torch.dtype | None) -> np.ndarray | None:
    if t is None:
        return None
    if t.device.type != "cpu":
        raise ValueError(
            f"{what} is on {t.device}; adjointsim's solvers run on the CPU: pass {what}.cpu()"
        )
    if dtype is not None and t.dtype != dtype:
        raise TypeError(
            f"{what} has dtype {t.dtype} but the state is {dtype}; cast it with .to({dtype})"
        )
    if not t.is_contiguous():
        raise ValueError(f"{what} is not contiguous; pass {what}.contiguous()")
    return t.detach().numpy()


class _Rollout(torch.autograd.Function):
    @staticmethod
    def forward(ctx, stepper, n, keep, checkpoint, u0, controls, params):
        u = _as_numpy(u0, "u0", None)
        if u0.dtype not in (torch.float32, torch.float64):
            raise TypeError(f"u0 has dtype {u0.dtype}; expected torch.float32 or torch.float64")
        c = _as_numpy(controls, "controls", u0.dtype)
        p = _as_numpy(params, "params", u0.dtype)
        grad = any(ctx.needs_input_grad[4:])
        store = grad and checkpoint is None
        states = stepper.rollout(u, n, c, p, keep="all" if store or keep == "all" else "last")
        ctx.stepper, ctx.n, ctx.keep, ctx.checkpoint = stepper, n, keep, checkpoint
        if grad:
            # Copies, so that in-place edits of the inputs or the output after this call cannot
            # change what the backward pass reverses (the arrays share memory with tensors).
            u, c, p = (None if a is None else a.copy() for a in (u, c, p))
            ctx.arrays = (u, c, p, states if store else None)
        if store:
            return torch.from_numpy(states.copy() if keep == "all" else states[-1].copy())
        return torch.from_numpy(states)

    @staticmethod
    def backward(ctx, grad):
        u, c, p, trajectory = ctx.arrays
        n = ctx.n
        cot = np.ascontiguousarray(grad.detach().numpy())
        ADJOINT_CALLS["count"] += 1
        g = ctx.stepper.vjp(
            u, n, cot, c, p,
            wrt_params=ctx.needs_input_grad[6],
            checkpoint=ctx.checkpoint,
            trajectory=trajectory,
        )
        grad_u = torch.from_numpy(g.state) if ctx.needs_input_grad[4] else None
        grad_c = torch.from_numpy(g.controls) if ctx.needs_input_grad[5] else None
        grad_p = None
        if ctx.needs_input_grad[6]:
            grad_p = torch.tensor([g.params[k] for k in ctx.stepper.param_names], dtype=grad.dtype)
        return None, None, None, None, grad_u, grad_c, grad_p


class _GroupedRollout(torch.autograd.Function):
    @staticmethod
    def forward(ctx, groups, n, u0):
        u = _as_numpy(u0, "u0", None)
        store = ctx.needs_input_grad[2]
        out = np.empty_like(u)
        inputs, trajectories = [], []
        for stepper, rows in groups:
            part = np.array(u[rows])  # a copy: the backward pass must see u0 as it was
            states = stepper.rollout(part, n, keep="all" if store else "last")
            out[rows] = states[-1] if store else states
            inputs.append(part)
            trajectories.append(states if store else None)
        ctx.groups, ctx.n, ctx.arrays = groups, n, (inputs, trajectories)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad):
        inputs, trajectories = ctx.arrays
        cot = grad.detach().numpy()
        out = np.empty_like(cot)
        ADJOINT_CALLS["count"] += 1
        for (stepper, rows), part, states in zip(ctx.groups, inputs, trajectories, strict=True):
            g = stepper.vjp(part, ctx.n, np.ascontiguousarray(cot[rows]), trajectory=states)
            out[rows] = g.state
        return None, None, torch.from_numpy(out)


def rollout_grouped(
    groups: list[tuple[Stepper, np.ndarray | slice]], u0: torch.Tensor, n: int
) -> torch.Tensor:
    """Differentiable rollout of a batch whose rows belong to different scenes.

    ``groups`` pairs each stepper with the batch rows it advances (together a partition of the
    batch), e.g. one KS domain size each. It is one autograd node whatever the number of
    groups: a batch mixing six scenes pays torch's per-node cost once, not six times, and
    needs no gather or scatter in torch.
    """
    return _GroupedRollout.apply(groups, n, u0)


def rollout(
    stepper: Stepper,
    u0: torch.Tensor,
    n: int,
    controls: torch.Tensor | None = None,
    params: torch.Tensor | None = None,
    keep: str = "last",
    checkpoint: int | None = None,
) -> torch.Tensor:
    """Differentiable ``stepper.rollout``: gradients reach ``u0``, ``controls`` and ``params``.

    ``params`` is a 1-D tensor in ``stepper.param_names`` order (e.g. a learnable viscosity);
    None uses the scene's values. ``keep="all"`` returns u_0 .. u_n; ``checkpoint`` bounds the
    number of states held for the backward pass (see :meth:`Stepper.vjp`).
    """
    if keep not in ("last", "all"):
        raise ValueError(f"keep must be 'last' or 'all', not {keep!r}")
    return _Rollout.apply(stepper, n, keep, checkpoint, u0, controls, params)


def step(
    stepper: Stepper,
    u: torch.Tensor,
    control: torch.Tensor | None = None,
    params: torch.Tensor | None = None,
) -> torch.Tensor:
    """Differentiable single step; ``control`` has shape (B, *control_shape)."""
    return rollout(stepper, u, 1, None if control is None else control.unsqueeze(0), params)
