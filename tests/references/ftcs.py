"""FTCS diffusion in NumPy: u_{k+1} = u_k + Δt ν Δ_h u_k (+ Δt a g)."""

import numpy as np

from .implicit_diffusion import second_difference


def laplacian(u: np.ndarray, stepper) -> np.ndarray:
    """Δ_h u over the trailing grid axes, with the stepper's boundary condition."""
    return sum(second_difference(u, axis, stepper.bc)
               for axis in range(u.ndim - stepper.ndim, u.ndim)) / stepper.h**2


def rollout(stepper, u0: np.ndarray, n: int) -> np.ndarray:
    nu = stepper.param_values[0]
    g = stepper.forcing.reshape((1, *stepper.grid_shape)) if stepper.forcing.size else None
    u = u0.copy()
    for _ in range(n):
        u = u + stepper.dt * nu * laplacian(u, stepper)
        if g is not None:
            u += stepper.dt * stepper.param_values[1] * g
    return u


ROLLOUTS = {"diffusion1d-ftcs": rollout, "diffusion2d-ftcs": rollout}
