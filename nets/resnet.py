"""ResNet with circular padding (or ``padding`` zeros/replicate for walls), as in List et al.:
an encoder convolution, residual blocks of two convolutions with LeakyReLU, a decoder
convolution. Presets: ``small`` = width 26 × 8 blocks (≈ 33k parameters in 1D with two input
channels), ``large`` = 52 × 12 (≈ 196k)."""

from __future__ import annotations

import torch
from torch import nn

from .layers import check_input, check_sizes, conv

PRESETS = {"small": (26, 8), "large": (52, 12)}


class _Block(nn.Module):
    def __init__(self, dims: int, width: int, kernel: int, dilation: int = 1,
                 padding: str = "circular"):
        super().__init__()
        self.conv1 = conv(dims, width, width, kernel, dilation, padding)
        self.conv2 = conv(dims, width, width, kernel, dilation, padding)
        self.act = nn.LeakyReLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(self.act(self.conv1(self.act(x))))


class ResNet(nn.Module):
    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        dims: int = 1,
        width: int = 26,
        blocks: int = 8,
        kernel: int = 3,
        dilations: tuple[int, ...] | None = None,
        padding: str = "circular",
    ):
        super().__init__()
        net = type(self).__name__
        check_sizes(net, in_channels=in_channels, out_channels=out_channels, width=width)
        check_sizes(net, 0, blocks=blocks)
        dilations = dilations or (1,) * blocks
        self.dims, self.in_channels = dims, in_channels
        self.smallest = max((1, *dilations)) * (kernel // 2) if padding == "circular" else 1
        self.encode = conv(dims, in_channels, width, kernel, padding=padding)
        self.blocks = nn.Sequential(*[_Block(dims, width, kernel, d, padding) for d in dilations])
        self.decode = conv(dims, width, out_channels, kernel, padding=padding)

    @classmethod
    def preset(cls, name: str, in_channels: int, out_channels: int, dims: int = 1) -> ResNet:
        try:
            width, blocks = PRESETS[name]
        except KeyError:
            choices = sorted(PRESETS)
            raise ValueError(f"unknown ResNet preset {name!r}; choose from {choices}") from None
        return cls(in_channels, out_channels, dims, width, blocks)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        check_input(type(self).__name__, x, self.dims, self.in_channels, self.smallest)
        return self.decode(self.blocks(self.encode(x)))
