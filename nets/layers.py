"""Grid-preserving convolutions in 1D or 2D: circular padding for periodic domains, zero or
replicate padding for domains with walls and open sides."""

from __future__ import annotations

import torch
from torch import nn

from adjointsim import validate

#: torch's padding modes a network accepts: periodic, zero, or the edge value repeated
PADDINGS = ("circular", "zeros", "replicate")


def conv(dims: int, c_in: int, c_out: int, kernel: int = 3, dilation: int = 1,
         padding: str = "circular") -> nn.Module:
    """A convolution that keeps the grid size, padded by ``padding`` (:data:`PADDINGS`)."""
    if dims not in (1, 2):
        raise ValueError(f"dims must be 1 or 2, not {dims}")
    if padding not in PADDINGS:
        raise ValueError(f"padding must be one of {', '.join(PADDINGS)}, not {padding!r}")
    check_sizes("conv", in_channels=c_in, out_channels=c_out, kernel=kernel, dilation=dilation)
    if kernel % 2 == 0:  # an even kernel has no centre: the output would grow by a point
        raise ValueError(f"kernel must be odd to keep the grid size, not {kernel}")
    cls = nn.Conv1d if dims == 1 else nn.Conv2d
    return cls(
        c_in, c_out, kernel, padding=dilation * (kernel // 2), dilation=dilation,
        padding_mode=padding,
    )


def check_sizes(net: str, least: int = 1, **sizes: object) -> None:
    """Refuse a size of ``net`` (a width, a count of channels, blocks or levels) that is not an
    integer of at least ``least``, naming its argument."""
    for name, value in sizes.items():
        validate.integer(net, name, value, ge=least)


def check_input(net: str, x: torch.Tensor, dims: int, channels: int, smallest: int = 1) -> None:
    """Refuse an input a network of ``dims`` grid axes and ``channels`` input channels cannot
    take, naming the network: torch's own errors name a layer's padding or weights instead.
    ``smallest`` is the least grid size (a circular pad cannot wrap a grid more than once)."""
    grid = "N" if dims == 1 else "H, W"
    if x.ndim != dims + 2 or x.shape[1] != channels:
        raise ValueError(f"{net} takes a tensor of shape (batch, {channels}, {grid}), not "
                         f"{tuple(x.shape)}")
    if min(x.shape[2:]) < smallest:
        why = (" (its widest kernel wraps a smaller periodic grid more than once)"
               if smallest > 1 else "")
        raise ValueError(f"{net} needs at least {smallest} grid point(s) per axis{why}, not "
                         f"{tuple(x.shape[2:])}")
