"""Lightweight torch networks for neural time-steppers and correctors.

All convolutional networks pad circularly (periodic domains) by default, or with zeros or the
edge values (``padding``: domains with walls and open sides), and work in 1D or 2D (``dims``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .dilated import DilatedResNet
from .mlp import MLP
from .resnet import ResNet
from .unet import UNet

if TYPE_CHECKING:
    from torch import nn

NETWORKS = {"resnet": ResNet, "dilated": DilatedResNet, "unet": UNet, "mlp": MLP}


def parameter_count(net: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in net.parameters() if p.requires_grad)


__all__ = ["NETWORKS", "MLP", "DilatedResNet", "ResNet", "UNet", "parameter_count"]
