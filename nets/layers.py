"""Grid-preserving convolutions in 1D or 2D: circular padding for periodic domains, zero or
replicate padding for domains with walls and open sides."""

from __future__ import annotations

from torch import nn

#: torch's padding modes a network accepts: periodic, zero, or the edge value repeated
PADDINGS = ("circular", "zeros", "replicate")


def conv(dims: int, c_in: int, c_out: int, kernel: int = 3, dilation: int = 1,
         padding: str = "circular") -> nn.Module:
    """A convolution that keeps the grid size, padded by ``padding`` (:data:`PADDINGS`)."""
    if dims not in (1, 2):
        raise ValueError(f"dims must be 1 or 2, not {dims}")
    if padding not in PADDINGS:
        raise ValueError(f"padding must be one of {', '.join(PADDINGS)}, not {padding!r}")
    cls = nn.Conv1d if dims == 1 else nn.Conv2d
    return cls(
        c_in, c_out, kernel, padding=dilation * (kernel // 2), dilation=dilation,
        padding_mode=padding,
    )
