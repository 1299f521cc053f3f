"""Linear advection–diffusion on [0, 2π)², pseudo-spectral, integrated exactly in time.

Continuous:  u_t + a·∇u = ν Δu + c,  a = (a_x, a_y) constant, doubly periodic.
Discrete:    L = −i (a_x k_x + a_y k_y) − ν|k|² is diagonal and N ≡ 0, so every ETDRK order
             reduces to the exact step u_{k+1} = ℱ⁻¹(E ℱ(u_k)) + Δt c_k with E = exp(Δt L) (the
             first-derivative wavenumbers have their Nyquist entries zeroed: that mode only
             diffuses, which keeps real fields real). One registry entry stands for all orders.
Adjoint:     λ = ℱ(ū_{k+1}) (spectral cotangents in the ⟨·,·⟩_H product of
             :mod:`adjointsim.spectral.fft2d`), ū_k = ℱ⁻¹(conj(E) λ), c̄_k = Δt ū_{k+1};
             with z = conj(λ) E ℱ(u_k): ā_x += Δt ⟨k_x Im z⟩, ā_y += Δt ⟨k_y Im z⟩,
             ν̄ −= Δt ⟨|k|² Re z⟩, ⟨f⟩ = Σ_half c_q f / n².
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

from .. import parallel, validate
from ..registry import register
from ..spectral.fft2d import (
    derivative_wavenumbers,
    hermitian_weights,
    irfft2,
    physical_with_control,
    random_smooth_field,
    rfft2,
    spectrum_zeros,
    wavenumbers,
)
from ..stepper import Choice, Range, Stepper


@njit(cache=True, nogil=True)
def advdiff_forward(states, n, ctrl, dt, e, nthreads):
    nslot, nbatch = states.shape[0], states.shape[1]
    v = spectrum_zeros(e.shape, states)
    for bi in range(nbatch):
        rfft2(states[0, bi, 0], v, nthreads)
        for k in range(n):
            v *= e
            physical_with_control(v, states[(k + 1) % nslot, bi, 0], ctrl, k, bi, dt, nthreads)


@njit(cache=True, nogil=True)
def advdiff_adjoint(states, ctrl, cot, cmap, ubar, cbar, pbar, want_p, dt, e, kx, ky, k2, weights,
                    nthreads):
    nbatch, size = states.shape[1], states.shape[-1]
    lam = spectrum_zeros(e.shape, states)
    v = np.zeros_like(lam)
    ec = e.conj()
    scale = dt / (size * size)
    for bi in range(nbatch):
        rfft2(ubar[bi, 0], lam, nthreads)
        for k in range(states.shape[0] - 1, -1, -1):
            if cbar.shape[0] > 0:
                c = cbar[k, bi, 0]
                irfft2(lam, c, nthreads)
                c *= dt
            if want_p:
                rfft2(states[k, bi, 0], v, nthreads)
                for p in range(size):
                    for q in range(e.shape[1]):
                        z = lam[p, q].conjugate() * e[p, q] * v[p, q]
                        w = weights[q] * scale
                        pbar[0] += w * kx[p] * z.imag
                        pbar[1] += w * ky[q] * z.imag
                        pbar[2] -= w * k2[p, q] * z.real
            lam *= ec
            if cmap[k] >= 0:
                rfft2(cot[cmap[k], bi, 0], v, nthreads)
                lam += v
        irfft2(lam, ubar[bi, 0], nthreads)


@register
class AdvectionDiffusion2D(Stepper):
    """u_t + a·∇u = ν Δu on [0, 2π)², exact exponential in time; parameters
    ``velocity_x``, ``velocity_y``, ``nu``."""

    name = "advdiff2d-etdrk4"
    point_cost = 4.0
    complex_step = False
    param_names = ("velocity_x", "velocity_y", "nu")
    #: smallest (even) n the kernels and the default state support
    min_points = 4
    # Velocities from a list and ν bounded away from 0: the checker perturbs a parameter by a
    # multiple of its own size, which for a value like 1e-200 moves nothing.
    space = {
        "n": Choice((8, 12, 16, 24, 32)),
        "velocity_x": Choice((-1.5, 0.0, 0.4, 2.0)),
        "velocity_y": Choice((-0.8, 0.0, 1.2)),
        "nu": Range(0.02, 0.3),
        "dt": Range(0.05, 0.25),
    }

    def __init__(
        self,
        n: int = 32,
        velocity_x: float = 1.0,
        velocity_y: float = 0.5,
        nu: float = 0.02,
        dt: float = 0.05,
    ):
        name = self.name
        n = validate.integer(name, "n", n, ge=self.min_points, even=True, why="real FFT grid")
        kx, ky = wavenumbers(n)
        dkx, dky = derivative_wavenumbers(n)
        self.n = n
        self.grid_shape = (n, n)
        self.channels = 1
        self.control_shape = (1, n, n)
        # The exact exponential has no Δt limit; Δt ≤ 0 would run backwards or stand still.
        self.dt = validate.number(name, "dt", dt, gt=0)
        self.k2 = kx**2 + ky**2
        self._dk = (dkx[:, 0], dky[0])
        self.param_values = tuple(
            validate.number(name, k, a)
            for k, a in zip(self.param_names, (velocity_x, velocity_y, nu))
        )
        self.check_params(np.array(self.param_values))

    @classmethod
    def default(cls) -> AdvectionDiffusion2D:
        return cls(n=16, velocity_x=1.0, velocity_y=-0.5, nu=0.1, dt=0.05)

    def check_params(self, p: np.ndarray) -> None:
        validate.number(
            self.name, "nu", p[2], ge=0,
            why="the viscosity ν; exp(−ν|k|²Δt) would grow without bound; the exact "
            "exponential has no Δt limit",
        )

    def random_state(
        self, rng: np.random.Generator, batch: int = 1, dtype: Any = np.float64
    ) -> np.ndarray:
        """Smooth random field (modes |k| ≤ min(4, n/4)), unit RMS per batch element."""
        return random_smooth_field(rng, self.state_shape(batch), min(4, self.n // 4), dtype)

    def propagator(self, p: np.ndarray) -> np.ndarray:
        """E = exp(Δt L) on the half spectrum, complex128, for parameters p (kernel order)."""
        ax, ay, nu = (float(x) for x in np.asarray(p).real)
        kx, ky = self._dk
        lin = -1j * (ax * kx[:, None] + ay * ky[None, :]) - nu * self.k2
        return np.exp(self.dt * lin)

    def _cplx(self, dtype) -> np.dtype:
        return np.result_type(dtype, np.complex64)

    def _forward(self, states, n, ctrl, p):
        e = self.propagator(p).astype(self._cplx(states.dtype))
        advdiff_forward(states, n, ctrl, states.dtype.type(self.dt), e,
                        parallel.threads_inside(states.shape[1], self.n**2))

    def _adjoint(self, states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p):
        real = ubar.dtype
        e = self.propagator(p).astype(self._cplx(real))
        advdiff_adjoint(
            states, ctrl, cot, cmap, ubar, cbar, pbar, want_p, real.type(self.dt), e,
            self._dk[0].astype(real), self._dk[1].astype(real), self.k2.astype(real),
            hermitian_weights(self.n), parallel.threads_inside(states.shape[1], self.n**2),
        )
