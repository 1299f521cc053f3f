"""Unrolled training losses: ONE, NOG and WIG (List et al.).

For a window of reference frames u_0 .. u_{w+m} the model runs from u_0; the first w steps are
the warm-up ("pushforward": no tape, not in the loss) and the loss is the mean over s = 1..m of
MSE(û_{w+s}, u_{w+s}).

* ONE: m = 1 (the trainer scales batch size and epochs by the target m).
* NOG: the state handed to the next step is detached, so every loss term back-propagates only
  through its own network call, and the solver never needs its adjoint.
* WIG: full backpropagation through time, through the network and the solver's adjoint.
  ``truncate=k`` detaches the state every k steps (truncated BPTT).
"""

from __future__ import annotations

import torch

MODES = ("ONE", "NOG", "WIG")


def unrolled_loss(
    model: torch.nn.Module,
    frames: torch.Tensor,
    params: torch.Tensor,
    conditions: torch.Tensor,
    mode: str,
    warmup: int = 0,
    truncate: int = 0,
) -> torch.Tensor:
    """``frames``: (B, w + m + 1, C, *grid) reference window; returns the scalar loss."""
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; choose from {MODES}")
    m = frames.shape[1] - 1 - warmup
    if m < 1 or (mode == "ONE" and m != 1):
        need = "1" if mode == "ONE" else "m ≥ 1"
        raise ValueError(f"{mode} needs windows of warmup + {need} + 1 frames")
    u = frames[:, 0]
    if warmup:
        with torch.no_grad():
            for _ in range(warmup):
                u = model(u, params, conditions)
    losses = []
    for s in range(1, m + 1):
        if mode == "NOG" or (truncate and s > 1 and (s - 1) % truncate == 0):
            u = u.detach()
        u = model(u, params, conditions)
        losses.append(torch.mean((u - frames[:, warmup + s]) ** 2))
    return torch.stack(losses).mean()
