"""Circularly padded convolutions in 1D or 2D."""

from __future__ import annotations

from torch import nn


def conv(dims: int, c_in: int, c_out: int, kernel: int = 3, dilation: int = 1) -> nn.Module:
    """A convolution that keeps the grid size, with periodic (circular) padding."""
    if dims not in (1, 2):
        raise ValueError(f"dims must be 1 or 2, not {dims}")
    cls = nn.Conv1d if dims == 1 else nn.Conv2d
    return cls(
        c_in, c_out, kernel, padding=dilation * (kernel // 2), dilation=dilation,
        padding_mode="circular",
    )
