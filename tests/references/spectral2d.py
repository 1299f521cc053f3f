"""2D pseudo-spectral solvers in NumPy (numpy.fft), batched over B: vorticity-form Navier–Stokes
with ETDRK1–4 written out order by order (the update formulas of adjointsim.spectral.etdrk,
independently of the kernels' tableau) and exact advection–diffusion. Like the kernels, they
carry the spectrum from step to step and produce every physical state u_k = irfft2(v_k)."""

import numpy as np

from adjointsim.spectral.etdrk import etdrk_coefficients, reference_step
from adjointsim.spectral.fft2d import dealias_multiplier, derivative_wavenumbers, wavenumbers


def _ns_nonlinear(stepper):
    n = stepper.n
    shape = (n, n)
    kx, ky = derivative_wavenumbers(n)
    k2 = np.add(*(k**2 for k in wavenumbers(n)))
    inv_k2 = np.where(k2 > 0, 1.0 / np.where(k2 > 0, k2, 1.0), 0.0)
    mask = dealias_multiplier(n) if stepper.dealias else np.ones_like(k2)
    forcing = np.zeros_like(k2, dtype=complex)
    if stepper.forcing_wavenumber is not None:
        amplitude = stepper.params["forcing"]
        kf = stepper.forcing_wavenumber
        forcing[0, kf] = -amplitude * kf * n * n / 2

    def nonlinear(vh):
        x = mask * vh
        psi = inv_k2 * x
        u = np.fft.irfft2(1j * ky * psi, s=shape)
        v = np.fft.irfft2(-1j * kx * psi, s=shape)
        w = np.fft.irfft2(x, s=shape)
        fx, fy = np.fft.rfft2(u * w), np.fft.rfft2(v * w)
        return -mask * (1j * kx * fx + 1j * ky * fy) + forcing

    lin = -stepper.params["nu"] * k2 - stepper.params.get("drag", 0.0)
    return nonlinear, etdrk_coefficients(lin, stepper.dt, stepper.order)


def navier_stokes(stepper, u0: np.ndarray, n: int) -> np.ndarray:
    N, c = _ns_nonlinear(stepper)
    v = np.fft.rfft2(u0[:, 0])
    for _ in range(n):
        v = reference_step(v, c, stepper.order, N)
        u = np.fft.irfft2(v, s=stepper.grid_shape)
    return u[:, None].astype(u0.dtype) if n else u0.copy()


def advection_diffusion(stepper, u0: np.ndarray, n: int) -> np.ndarray:
    e = stepper.propagator(np.array(stepper.param_values))
    v = np.fft.rfft2(u0[:, 0])
    for _ in range(n):
        v = e * v
        u = np.fft.irfft2(v, s=stepper.grid_shape)
    return u[:, None].astype(u0.dtype) if n else u0.copy()


ROLLOUTS = {f"ns2d-etdrk{order}": navier_stokes for order in (1, 2, 3, 4)}
ROLLOUTS["advdiff2d-etdrk4"] = advection_diffusion
