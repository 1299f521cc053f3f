"""Diffusion, explicit Euler in time with the centred 3/5-point Laplacian (FTCS).

Continuous:  u_t = ν Δu + a g + c.
Discrete:    u_{k+1} = u_k + Δt (ν Δ_h u_k + a g + c_k).   Stable for ν Δt Σ_d 1/h_d² ≤ 1/2.
Adjoint:     ū_k = ū_{k+1} + Δt ν Δ_h ū_{k+1}   (Δ_h is symmetric),
             c̄_k = Δt ū_{k+1},  ν̄ += Δt ⟨ū_{k+1}, Δ_h u_k⟩,  ā += Δt ⟨ū_{k+1}, g⟩.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .. import validate
from ..grid import laplacian
from ..registry import register
from .diffusion import DiffusionScene


@njit(cache=True, nogil=True)
def ftcs_forward(states, n, ctrl, p, dt, inv_hx2, inv_hy2, bc, g):
    s = states.shape[0]
    lap = np.empty_like(states[0])
    for k in range(n):
        u = states[k % s]
        v = states[(k + 1) % s]
        laplacian(u, lap, inv_hx2, inv_hy2, bc)
        _update(u, lap, v, ctrl, k, p, dt, g)


@njit(cache=True, nogil=True)
def ftcs_adjoint(states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p, dt, inv_hx2, inv_hy2, bc, g):
    lap = np.empty_like(ubar)
    for k in range(states.shape[0] - 1, -1, -1):
        if want_p:
            laplacian(states[k], lap, inv_hx2, inv_hy2, bc)
            pbar[0] += dt * np.sum(lap * ubar)
            if g.shape[0] > 0:
                for b in range(ubar.shape[0]):
                    pbar[1] += dt * np.sum(ubar[b] * g)
        if cbar.shape[0] > 0:
            cbar[k] = dt * ubar
        laplacian(ubar, lap, inv_hx2, inv_hy2, bc)
        _update(ubar, lap, ubar, cot[:0], 0, p[:1], dt, g[:0])
        if cmap[k] >= 0:
            ubar += cot[cmap[k]]


@njit(cache=True, nogil=True, inline="always")
def _update(u, lap, out, ctrl, k, p, dt, g):
    """out = u + Δt (ν lap + a g + ctrl[k]); the forcing and control terms only when present."""
    nb, nc, nx, ny = u.shape
    nu_dt = p[0] * dt
    for b in range(nb):
        for c in range(nc):
            for i in range(nx):
                for j in range(ny):
                    out[b, c, i, j] = u[b, c, i, j] + nu_dt * lap[b, c, i, j]
    if g.shape[0] > 0:
        for b in range(nb):
            out[b] += (p[1] * dt) * g
    if ctrl.shape[0] > 0:
        out += dt * ctrl[k]


class _FTCS(DiffusionScene):
    def default_dt(self, nu: float) -> float:
        """0.4/(ν Σ 1/h²): 80% of the stability limit; ν = 0 sets no time scale."""
        why = "dt=None derives Δt from ν; for ν = 0 give dt"
        validate.number(self.name, "nu", nu, gt=0, why=why)
        return super().default_dt(nu)

    def check_params(self, p: np.ndarray) -> None:
        validate.number(self.name, "nu", p[0], ge=0, why="backward diffusion is ill-posed")
        number = p[0] * self.dt * sum(self.inv_h2)
        if number > 0.5 * (1 + 1e-12):
            limit = 0.5 / (p[0] * sum(self.inv_h2))
            raise ValueError(
                f"{self.name}: Δt = {self.dt:.6g} breaks the FTCS stability limit "
                f"ν Δt Σ 1/h² ≤ 1/2 (diffusion number {number:.4g} at ν = {p[0]:.4g}); the "
                f"largest stable Δt is {limit:.6g}: pass dt ≤ {limit:.6g}, or dt=None for "
                "0.8 of it"
            )

    def _args(self, dtype):
        return (self.dt, *self.inv_h2, self.bc_code, self.forcing.astype(dtype))

    def _forward(self, states, n, ctrl, p):
        ftcs_forward(self.as_2d(states), n, self.as_2d(ctrl), p, *self._args(states.dtype))

    def _adjoint(self, states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p):
        ftcs_adjoint(
            self.as_2d(states), self.as_2d(ctrl), p, self.as_2d(cot), cmap, self.as_2d(ubar),
            self.as_2d(cbar), pbar, want_p, *self._args(ubar.dtype),
        )


@register
class FTCSDiffusion1D(_FTCS):
    name = "diffusion1d-ftcs"
    ndim = 1


@register
class FTCSDiffusion2D(_FTCS):
    name = "diffusion2d-ftcs"
    ndim = 2
