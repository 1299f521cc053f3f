"""A small U-Net with circular padding (or ``padding`` zeros/replicate): ``levels``
down-sampling stages (average pooling), channel count doubling per level, nearest up-sampling
and skip connections. Grid sizes must be divisible by 2**levels."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from .layers import check_input, check_sizes, conv


def _double(dims: int, c_in: int, c_out: int, padding: str) -> nn.Module:
    return nn.Sequential(conv(dims, c_in, c_out, padding=padding), nn.GELU(),
                         conv(dims, c_out, c_out, padding=padding), nn.GELU())


class UNet(nn.Module):
    def __init__(
        self, in_channels: int, out_channels: int, dims: int = 1, width: int = 16, levels: int = 2,
        padding: str = "circular",
    ):
        super().__init__()
        check_sizes("UNet", in_channels=in_channels, out_channels=out_channels, width=width)
        check_sizes("UNet", 0, levels=levels)
        self.dims, self.levels, self.in_channels = dims, levels, in_channels
        widths = [width * 2**i for i in range(levels + 1)]
        self.down = nn.ModuleList(
            [_double(dims, in_channels, widths[0], padding)]
            + [_double(dims, widths[i], widths[i + 1], padding) for i in range(levels)]
        )
        self.up = nn.ModuleList(
            [_double(dims, widths[i + 1] + widths[i], widths[i], padding)
             for i in reversed(range(levels))]
        )
        self.out = conv(dims, widths[0], out_channels, kernel=1, padding=padding)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        check_input("UNet", x, self.dims, self.in_channels)
        factor = 2**self.levels
        if any(s % factor for s in x.shape[2:]):
            raise ValueError(
                f"UNet with {self.levels} levels needs grid sizes divisible by {factor}"
            )
        pool = F.avg_pool1d if self.dims == 1 else F.avg_pool2d
        skips = []
        for i, block in enumerate(self.down):
            x = block(x if i == 0 else pool(x, 2))
            skips.append(x)
        skips.pop()
        for block in self.up:
            x = F.interpolate(x, scale_factor=2, mode="nearest")
            x = block(torch.cat([x, skips.pop()], dim=1))
        return self.out(x)
