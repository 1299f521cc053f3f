"""FTCS diffusion in NumPy: u_{k+1} = u_k + Δt ν Δ_h u_k (+ Δt a g)."""

import numpy as np


def laplacian(u: np.ndarray, stepper) -> np.ndarray:
    """Δ_h u over the trailing grid axes, with the stepper's boundary condition."""
    out = np.zeros_like(u)
    mode = {"periodic": "wrap", "dirichlet": "constant", "neumann": "edge"}[stepper.bc]
    for axis in range(u.ndim - stepper.ndim, u.ndim):
        pad = [(0, 0)] * u.ndim
        pad[axis] = (1, 1)
        p = np.pad(u, pad, mode=mode)
        n = u.shape[axis]
        out += (p.take(range(0, n), axis) - 2 * u + p.take(range(2, n + 2), axis)) / stepper.h**2
    return out


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
