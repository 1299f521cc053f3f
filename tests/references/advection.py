"""NumPy reference of the linear-advection schemes (forward only, batched, default parameters).

Same discrete updates as :mod:`adjointsim.solvers.upwind` and
:mod:`adjointsim.solvers.lax_wendroff`, written with ``np.roll`` on the periodic grid.
"""

from __future__ import annotations

import numpy as np


def _setup(stepper, u0: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
    nu = np.array(stepper.param_values) * (stepper.dt / stepper.h)
    return np.array(u0, dtype=np.float64), nu, tuple(range(2, 2 + stepper.ndim))


def upwind(stepper, u0: np.ndarray, n: int) -> np.ndarray:
    u, nu, axes = _setup(stepper, u0)
    for _ in range(n):
        v = u.copy()
        for c, ax in zip(nu, axes, strict=True):
            v -= c * (u - np.roll(u, 1, ax)) if c >= 0 else c * (np.roll(u, -1, ax) - u)
        u = v
    return u


def lax_wendroff(stepper, u0: np.ndarray, n: int) -> np.ndarray:
    u, nu, axes = _setup(stepper, u0)
    for _ in range(n):
        v = u.copy()
        for c, ax in zip(nu, axes, strict=True):
            east, west = np.roll(u, -1, ax), np.roll(u, 1, ax)
            v -= 0.5 * c * (east - west)
            v += 0.5 * c**2 * (east - 2 * u + west)
        if len(axes) == 2:
            for sx in (1, -1):
                for sy in (1, -1):
                    v += (0.25 * sx * sy * nu[0] * nu[1]) * np.roll(u, (-sx, -sy), axes)
        u = v
    return u


def rollout(stepper, u0: np.ndarray, n: int) -> np.ndarray:
    """u_n from u0 (B, 1, *grid), no controls, the scene's parameters."""
    return ROLLOUTS[stepper.name](stepper, u0, n)


ROLLOUTS = {
    "advection1d-upwind": upwind,
    "advection2d-upwind": upwind,
    "advection1d-lax-wendroff": lax_wendroff,
    "advection2d-lax-wendroff": lax_wendroff,
}
