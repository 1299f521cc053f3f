"""``adjointsim fit``: inverse problems with the hand-written adjoints."""

from __future__ import annotations

from adjointsim.fit_cli import add_arguments as arguments
from adjointsim.fit_cli import command as run

__all__ = ["arguments", "run"]
