"""Vectorised NumPy versions of the solvers' forward rollouts, the baseline of the benchmarks.

Each module exposes ``ROLLOUTS = {registry name: rollout(stepper, u0, n) -> u_n}`` (default
parameters, no controls); the benchmark collects them from every module here.
"""

import importlib
import pkgutil


def all_rollouts() -> dict:
    found = {}
    for module in pkgutil.iter_modules(__path__):
        found.update(importlib.import_module(f"{__name__}.{module.name}").ROLLOUTS)
    return found
