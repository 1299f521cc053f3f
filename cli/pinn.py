"""``adjointsim pinn``: physics-informed training with loss balancing."""

from __future__ import annotations

from adjointsim.train.pinn import add_arguments as arguments
from adjointsim.train.pinn import run_command as run

__all__ = ["arguments", "run"]
