"""NumPy reference of the Rusanov finite-volume Burgers solvers (forward only, batched).

Same discrete update as :mod:`adjointsim.solvers.burgers_fv`, written with ``np.roll``.
"""

from __future__ import annotations

import numpy as np


def _rusanov(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    alpha = np.maximum(np.abs(a), np.abs(b))
    return 0.25 * (a * a + b * b) - 0.5 * alpha * (b - a)


def rusanov(stepper, u0: np.ndarray, n: int) -> np.ndarray:
    u = np.array(u0, dtype=np.float64)
    tau = stepper.dt / stepper.substeps
    nu = stepper.param_values[0]
    axes = tuple(range(2, 2 + stepper.ndim))
    c, d = tau / stepper.h, tau * nu / stepper.h**2
    for _ in range(n * stepper.substeps):
        v = u.copy()
        for ax in axes:
            east = np.roll(u, -1, ax)
            flux = _rusanov(u, east)
            v -= c * (flux - np.roll(flux, 1, ax))
            v += d * (east - 2 * u + np.roll(u, 1, ax))
        u = v
    return u


def rollout(stepper, u0: np.ndarray, n: int) -> np.ndarray:
    """u_n from u0 (B, 1, *grid), no controls, the scene's parameters."""
    return ROLLOUTS[stepper.name](stepper, u0, n)


ROLLOUTS = {"burgers1d-rusanov": rusanov, "burgers2d-rusanov": rusanov}
