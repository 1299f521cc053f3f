"""``adjointsim control``: train a controller through a simulator."""

from __future__ import annotations

from adjointsim.train.control import add_arguments as arguments
from adjointsim.train.control import run_command as run

__all__ = ["arguments", "run"]
