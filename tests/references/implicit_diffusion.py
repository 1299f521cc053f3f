"""Implicit θ-scheme diffusion in NumPy/SciPy: backward Euler (θ = 1), Crank–Nicolson (θ = 1/2).

Same discrete update as :mod:`adjointsim.solvers.implicit_diffusion`, with X = Δt ν δ²_x/h²:
1D  (I − θX) u_{k+1} = (I + (1−θ)X) u_k + Δt a g;
2D  (I − θX) u* = (I + (1−θ)Y) u_k + θΔt a g,  (I − θY) u_{k+1} = (I + (1−θ)X) u* + (1−θ)Δt a g.
The tridiagonal systems go to LAPACK (scipy.linalg.solve_banded) for Dirichlet and Neumann and
to an FFT (scipy.linalg.solve_circulant) for the periodic, circulant, ones, all lines at once.
"""

import numpy as np
from scipy.linalg import solve_banded, solve_circulant

_PAD = {"periodic": "wrap", "dirichlet": "constant", "neumann": "edge"}


def second_difference(u: np.ndarray, axis: int, bc: str) -> np.ndarray:
    """δ² u along ``axis`` (unscaled), with the ghost values of boundary ``bc``."""
    pad = [(0, 0)] * u.ndim
    pad[axis] = (1, 1)
    p = np.pad(u, pad, mode=_PAD[bc])
    n = u.shape[axis]
    return p.take(range(0, n), axis) - 2 * u + p.take(range(2, n + 2), axis)


def implicit_solver(n: int, s: float, bc: str):
    """``solve(d, axis)`` = (I − s δ²)⁻¹ d along ``axis`` of d, for all its lines at once."""
    if bc == "periodic":
        column = np.zeros(n)
        column[0] = 1 + 2 * s
        column[1] -= s
        column[-1] -= s

        def solve(d: np.ndarray, axis: int) -> np.ndarray:
            return solve_circulant(column, d, baxis=axis, outaxis=axis).real

        return solve
    banded = np.empty((3, n))
    banded[0], banded[1], banded[2] = -s, 1 + 2 * s, -s
    if bc == "neumann":
        banded[1, [0, -1]] = 1 + s

    def solve(d: np.ndarray, axis: int) -> np.ndarray:
        lines = np.moveaxis(d, axis, 0)
        x = solve_banded((1, 1), banded, lines.reshape(n, -1), check_finite=False)
        return np.moveaxis(x.reshape(lines.shape), 0, axis)

    return solve


def rollout(stepper, u0: np.ndarray, n: int) -> np.ndarray:
    theta, dt, bc = stepper.theta, stepper.dt, stepper.bc
    nu = stepper.param_values[0]
    s_implicit = theta * dt * nu / stepper.h**2
    s_explicit = (1 - theta) * dt * nu / stepper.h**2
    solve = implicit_solver(stepper.grid_shape[0], s_implicit, bc)
    f = 0.0
    if stepper.forcing.size:
        f = stepper.param_values[1] * stepper.forcing.reshape((1, *stepper.grid_shape))

    def explicit(u: np.ndarray, axis: int) -> np.ndarray:
        return u + s_explicit * second_difference(u, axis, bc) if s_explicit else u

    u = u0.copy()
    for _ in range(n):
        if stepper.ndim == 1:
            u = solve(explicit(u, -1) + dt * f, -1)
        else:
            u = solve(explicit(u, -1) + theta * dt * f, -2)
            u = solve(explicit(u, -2) + (1 - theta) * dt * f, -1)
    return u


ROLLOUTS = {
    "diffusion1d-backward-euler": rollout,
    "diffusion1d-crank-nicolson": rollout,
    "diffusion2d-backward-euler": rollout,
    "diffusion2d-crank-nicolson": rollout,
}
