"""Linear advection–diffusion in 1D, Fourier pseudo-spectral with ETDRK1–4 (kernel:
:mod:`.spectral1d`).

Continuous:  u_t + c u_x = ν u_xx + a g(x) on [0, length), periodic; c ("velocity"), ν ("nu") ≥ 0.
Discrete:    û_t = L û, L = −i c k − ν k² (N ≡ 0), so every order is exact in time:
             v' = E v plus the φ-weighted forcing; u_{k+1} = S(u_k) + Δt c_k.
Adjoint:     v̄ = conj(E) v̄' (see :mod:`.spectral1d`); c̄, ν̄ from the coefficient cotangents and
             d(coefficient)/dL · (−i k, −k²).
"""

from __future__ import annotations

import numpy as np

from .. import validate
from ..spectral import fft1d
from ..stepper import Choice, Range
from .spectral1d import ETDRKScene1D, register_orders


class AdvectionDiffusionETDRK(ETDRKScene1D):
    """Linear advection–diffusion u_t + c u_x = ν u_xx (+ a g), parameters ``velocity``, ``nu``.
    N ≡ 0 (or the constant forcing), so every order is exact in time."""

    nonlinear = False
    linear_params = ("velocity", "nu")
    space = {
        "n": Choice((16, 24, 32, 48)),
        # (tiny |c| or ν leave the finite-difference reference of the checker to round-off)
        "velocity": Range(0.25, 2.0),
        "nu": Range(0.02, 0.5),
        "substeps": Range(1, 3, integer=True),
    }

    def __init__(
        self,
        n: int = 32,
        length: float = 2 * np.pi,
        velocity: float = 1.0,
        nu: float = 0.05,
        dt: float = 0.05,
        substeps: int = 1,
        forcing: np.ndarray | None = None,
        forcing_amplitude: float = 1.0,
    ):
        super().__init__(
            n, length, dt, (velocity, nu), substeps, False, forcing, forcing_amplitude
        )

    def linear_basis(self) -> list[np.ndarray]:
        return [-fft1d.derivative_multiplier(self.grid_shape[0], self.length, 1), -self.k**2]

    def check_params(self, p: np.ndarray) -> None:
        validate.number(
            self.name, "nu", p[1], ge=0,
            why="the viscosity ν; ν < 0 is ill-posed: exp(−ν k² Δt) grows without bound",
        )


ADVECTION_DIFFUSION = register_orders(AdvectionDiffusionETDRK, "advdiff1d", globals())
