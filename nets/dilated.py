"""Dilated ResNet: residual blocks whose dilation grows then shrinks (1, 2, 4, 8, 4, 2, 1), so
the receptive field spans the domain with few parameters."""

from __future__ import annotations

from .resnet import ResNet


class DilatedResNet(ResNet):
    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        dims: int = 1,
        width: int = 32,
        dilations: tuple[int, ...] = (1, 2, 4, 8, 4, 2, 1),
        kernel: int = 3,
        padding: str = "circular",
    ):
        super().__init__(in_channels, out_channels, dims, width, len(dilations), kernel, dilations,
                         padding)
