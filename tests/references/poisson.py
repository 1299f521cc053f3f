"""Screened Poisson (−Δ_h + κ) u = f in NumPy/SciPy, by 2D fast transforms; one step = one solve.

Dirichlet: u = idstn(dstn(f) / (λ_i + λ_j + κ)) with DST-I on both axes. Periodic: the same with
rfft2/irfft2, the mean mode set to zero (the zero-mean solution, as in the numba solver).
"""

import numpy as np
import scipy.fft


def rollout(stepper, u0: np.ndarray, n: int) -> np.ndarray:
    lam = stepper.eigenvalues
    kappa = stepper.param_values[0]
    u = u0.copy()
    if stepper.bc == "dirichlet":
        inverse = 1.0 / (lam[:, None] + lam[None, :] + kappa)
        axes = (2, 3)
        for _ in range(n):
            u = scipy.fft.idstn(scipy.fft.dstn(u, type=1, axes=axes) * inverse, type=1, axes=axes)
        return u
    half = stepper.n // 2 + 1
    symbol = lam[:, None] + lam[None, :half] + kappa
    symbol[0, 0] = np.inf
    inverse = 1.0 / symbol
    for _ in range(n):
        u = scipy.fft.irfft2(scipy.fft.rfft2(u) * inverse, s=u.shape[2:])
    return u


ROLLOUTS = {"poisson2d": rollout}
