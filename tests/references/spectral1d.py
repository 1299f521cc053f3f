"""Fourier pseudo-spectral ETDRK1–4 in NumPy (numpy.fft), batched: the update formulas of
:mod:`adjointsim.spectral.etdrk` written out per order, for KS, Burgers and advection–diffusion.

N(v) = −½ i k · rfft(irfft(v)²) (times the 2/3 mask when dealiased) plus the forcing; the
advection–diffusion scenes have no nonlinear term. Default parameters, no controls.
"""

import numpy as np

from adjointsim.spectral.etdrk import etdrk_coefficients, reference_step


def rollout(stepper, u0: np.ndarray, n: int) -> np.ndarray:
    npts = stepper.grid_shape[0]
    lin = stepper.linear_operator()
    c = etdrk_coefficients(lin, stepper.dt / stepper.substeps, stepper.order)
    g = 1j * stepper.nonlinear_multiplier
    force = (
        stepper.forcing_hat * stepper.param_values[-1] if stepper.forcing_hat.size else 0.0
    )

    def nonlinear(v):
        if not stepper.nonlinear:
            return force + 0 * v
        return g * np.fft.rfft(np.fft.irfft(v, npts) ** 2) + force

    v = np.fft.rfft(u0)
    for _ in range(n * stepper.substeps):
        v = reference_step(v, c, stepper.order, nonlinear)
    return np.fft.irfft(v, npts).astype(u0.dtype)


ROLLOUTS = {
    f"{scene}-etdrk{order}": rollout
    for scene in ("ks1d", "burgers1d", "advdiff1d")
    for order in (1, 2, 3, 4)
}
