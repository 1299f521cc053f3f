"""Crank–Nicolson Schrödinger in NumPy/SciPy, uncontrolled: (I + iΔt/2 H) ψ' = (I − iΔt/2 H) ψ.

ψ is complex here (the solver carries (Re ψ, Im ψ) channels); the complex tridiagonal system
goes to LAPACK (scipy.linalg.solve_banded) with the whole batch as right-hand sides.
"""

import numpy as np
from scipy.linalg import solve_banded


def rollout(stepper, u0: np.ndarray, n: int) -> np.ndarray:
    half_dt = 0.5 * stepper.dt
    diag = np.full(stepper.n, 2.0 * stepper.kinetic)
    if stepper.potential.size:
        diag = diag + stepper.param_values[0] * stepper.potential
    off = -stepper.kinetic
    banded = np.empty((3, stepper.n), dtype=complex)
    banded[0] = banded[2] = 1j * half_dt * off
    banded[1] = 1 + 1j * half_dt * diag
    psi = (u0[:, 0] + 1j * u0[:, 1]).T  # (N, B): one column per batch element
    for _ in range(n):
        h_psi = diag[:, None] * psi
        h_psi[1:] += off * psi[:-1]
        h_psi[:-1] += off * psi[1:]
        psi = solve_banded((1, 1), banded, psi - 1j * half_dt * h_psi, check_finite=False)
    return np.stack([psi.real.T, psi.imag.T], axis=1)


ROLLOUTS = {"schrodinger1d-cn": rollout}
