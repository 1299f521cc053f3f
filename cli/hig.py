"""``adjointsim hig``: training through a solver with half-inverse gradients."""

from __future__ import annotations

from adjointsim.train.hig_problems import add_arguments as arguments
from adjointsim.train.hig_problems import main as run

__all__ = ["arguments", "run"]
