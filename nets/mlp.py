"""Multilayer perceptron with a choice of activation (including ``sin``, SIREN-style)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn


class Sin(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sin(x)


ACTIVATIONS = {"relu": nn.ReLU, "tanh": nn.Tanh, "gelu": nn.GELU, "silu": nn.SiLU,
               "leaky_relu": nn.LeakyReLU, "sin": Sin}


class MLP(nn.Module):
    def __init__(
        self, in_features: int, out_features: int, width: int = 64, depth: int = 3,
        activation: str = "tanh", widths: Sequence[int] | None = None,
    ):
        """``widths``: the hidden layers' widths, one per layer, in place of ``width`` and
        ``depth`` (for networks whose layers differ in width)."""
        super().__init__()
        if activation not in ACTIVATIONS:
            choices = sorted(ACTIVATIONS)
            raise ValueError(f"unknown activation {activation!r}; choose from {choices}")
        sizes = [in_features] + (list(widths) if widths is not None else [width] * depth)
        layers: list[nn.Module] = []
        for a, b in zip(sizes[:-1], sizes[1:]):
            layers += [nn.Linear(a, b), ACTIVATIONS[activation]()]
        layers.append(nn.Linear(sizes[-1], out_features))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)
