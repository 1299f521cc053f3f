"""Linear advection, Lax–Wendroff (second order in space and time; periodic, 1D and 2D).

Continuous:  u_t + a·∇u = c.
Discrete:    the Taylor series u_{k+1} = u − Δt a·∇u + (Δt²/2)(a·∇)²u with centred differences,
             ν_d = a_d Δt / h_d, D_d u = (u(·+e_d) − u(·−e_d))/2, δ_d² u = u(·+e_d) − 2u + u(·−e_d):
             u_{k+1} = u_k − Σ_d ν_d D_d u_k + Σ_d (ν_d²/2) δ_d² u_k
                       + (ν_x ν_y / 4)(u_{++} − u_{+−} − u_{−+} + u_{−−}) + Δt c_k,
             the last (cross) term in 2D only, u_{±±} = u_k(· ± e_x ± e_y).
             Stable for |ν| ≤ 1 in 1D and |ν_x|^{2/3} + |ν_y|^{2/3} ≤ 1 in 2D (von Neumann;
             e.g. |ν_x| = |ν_y| ≤ 2^{-3/2} ≈ 0.354), i.e. Δt ≤ (Σ_d (|a_d|/h_d)^{2/3})^{-3/2}.
Adjoint:     ū_k = the same 9-point (3-point) stencil mirrored, applied to ū_{k+1};
             c̄_k = Δt ū_{k+1},  ā_d += Σ_o (∂w_o/∂a_d) ⟨ū_{k+1}, u_k(· + o)⟩ over the taps o.
"""

from __future__ import annotations

import numpy as np

from ..registry import register
from .advection import Advection1D, Advection2D, AdvectionScene


class _LaxWendroff(AdvectionScene):
    stability = "Σ_d |a_d Δt / h_d|^{2/3} ≤ 1 (|a| Δt / h ≤ 1 in 1D)"

    def max_dt(self, velocity: np.ndarray) -> float:
        rate = float(np.sum((np.abs(velocity.real) / self.h) ** (2 / 3)))
        return rate**-1.5 if rate > 0 else float("inf")

    def weights(self, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = self.dt / self.h
        nu = (velocity * c).tolist()
        w = np.zeros((3, 3), dtype=velocity.dtype)
        dw = np.zeros((self.ndim, 3, 3), dtype=velocity.dtype)
        w[1, 1] = 1
        for axis, v in enumerate(nu):
            w[1, 1] -= v * v
            dw[axis, 1, 1] = -2 * v * c
            for s in (1, -1):
                w[self.tap(axis, s)] = (v * v - s * v) / 2
                dw[(axis, *self.tap(axis, s))] = (v - s / 2) * c
        if self.ndim == 2:
            for sx in (1, -1):
                for sy in (1, -1):
                    w[1 + sx, 1 + sy] = sx * sy * nu[0] * nu[1] / 4
                    dw[:, 1 + sx, 1 + sy] = [sx * sy * nu[1] * c / 4, sx * sy * nu[0] * c / 4]
        return w, dw


@register
class LaxWendroffAdvection1D(_LaxWendroff, Advection1D):
    name = "advection1d-lax-wendroff"


@register
class LaxWendroffAdvection2D(_LaxWendroff, Advection2D):
    name = "advection2d-lax-wendroff"
