"""The thread count of a process that trains: torch's intra-op threads and the solvers'."""

from __future__ import annotations

import torch

from adjointsim import parallel


def use_threads(n: int) -> None:
    """Give torch and the solvers ``n`` threads each: they take turns (a network's forward or
    backward, then a solver's rollout or sweep), so each may use them all in its turn."""
    parallel.set_threads(n)
    torch.set_num_threads(n)
