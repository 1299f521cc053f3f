"""Vectorised NumPy versions of the solvers' forward rollouts: the references the solvers'
tests compare against, and the baseline of the solver benchmarks.

Each module exposes ``ROLLOUTS = {registry name: rollout(stepper, u0, n) -> u_n}`` (default
parameters, no controls); :func:`all_rollouts` collects them from every module here. Tests and
benchmarks import them one way: ``from tests.references import ...`` (the repository root on
the path: pytest puts it there for the ``tests`` package, the benchmarks insert it).
"""

import importlib
import pkgutil


def all_rollouts() -> dict:
    """Every module's ``ROLLOUTS``, merged."""
    found = {}
    for module in pkgutil.iter_modules(__path__):
        found.update(importlib.import_module(f"{__name__}.{module.name}").ROLLOUTS)
    return found
