"""Linear advection, first-order upwind in space, explicit Euler in time (periodic, 1D and 2D).

Continuous:  u_t + a·∇u = c.
Discrete:    u_{k+1} = u_k − Σ_d |ν_d| (u_k − u_k(· − σ_d e_d)) + Δt c_k,
             ν_d = a_d Δt / h_d, σ_d = sign(a_d) (a_d = 0 counts as positive).
             Monotone (maximum principle, TVD) and stable for Σ_d |ν_d| ≤ 1; first order.
Adjoint:     ū_k = (1 − Σ_d |ν_d|) ū_{k+1} + Σ_d |ν_d| ū_{k+1}(· + σ_d e_d)  (downwind),
             c̄_k = Δt ū_{k+1},  ā_d += σ_d (Δt/h_d) ⟨ū_{k+1}, u_k(· − σ_d e_d) − u_k⟩.
The stencil depends on the sign of each velocity component, so the map is not differentiable
at a_d = 0; the velocity derivative is the one at fixed sign (one-sided at a_d = 0).
"""

from __future__ import annotations

import numpy as np

from ..registry import register
from .advection import Advection1D, Advection2D, AdvectionScene


class _Upwind(AdvectionScene):
    stability = "Σ_d |a_d| Δt / h_d ≤ 1"

    def max_dt(self, velocity: np.ndarray) -> float:
        rate = float(np.sum(np.abs(velocity.real))) / self.h
        return 1.0 / rate if rate > 0 else float("inf")

    def weights(self, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = self.dt / self.h
        w = np.zeros((3, 3), dtype=velocity.dtype)
        dw = np.zeros((self.ndim, 3, 3), dtype=velocity.dtype)
        w[1, 1] = 1
        for axis, nu in enumerate((velocity * c).tolist()):
            sign = 1 if nu.real >= 0 else -1
            upwind = self.tap(axis, -sign)
            w[1, 1] -= sign * nu
            w[upwind] = sign * nu
            dw[axis, 1, 1] = -sign * c
            dw[(axis, *upwind)] = sign * c
        return w, dw


@register
class UpwindAdvection1D(_Upwind, Advection1D):
    name = "advection1d-upwind"


@register
class UpwindAdvection2D(_Upwind, Advection2D):
    name = "advection2d-upwind"
