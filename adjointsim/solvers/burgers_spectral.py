"""Viscous Burgers, Fourier pseudo-spectral with ETDRK1–4 (kernel: :mod:`.spectral1d`).

Continuous:  u_t + u u_x = ν u_xx + a g(x) on [0, length), periodic, ν ("nu") ≥ 0.
Discrete:    û_t = L û − ½ i k · DFT(u²), L = −ν k²; ``substeps`` ETDRK steps of h = Δt/substeps
             per stored frame, u_{k+1} = S(u_k) + Δt c_k; ``dealias=True`` applies the 2/3 rule
             to the nonlinear term.
Adjoint:     reversed ETDRK stages (see :mod:`.spectral1d`); ν̄ from the coefficient cotangents
             and d(coefficient)/dL · (−k²).
"""

from __future__ import annotations

import numpy as np

from .. import validate
from ..stepper import Choice, Range
from .spectral1d import ETDRKScene1D, register_orders


class BurgersETDRK(ETDRKScene1D):
    """Viscous Burgers u_t + u u_x = ν u_xx (+ a g), parameter ``nu``."""

    linear_params = ("nu",)
    amplitude = 0.5
    space = {
        "n": Choice((16, 24, 32, 48)),
        "nu": Range(0.05, 0.5),
        "substeps": Range(1, 3, integer=True),
        "dealias": Choice((False, True)),
    }

    def __init__(
        self,
        n: int = 32,
        length: float = 2 * np.pi,
        nu: float = 0.1,
        dt: float = 0.05,
        substeps: int = 1,
        dealias: bool = False,
        forcing: np.ndarray | None = None,
        forcing_amplitude: float = 1.0,
    ):
        super().__init__(n, length, dt, (nu,), substeps, dealias, forcing, forcing_amplitude)

    def linear_basis(self) -> list[np.ndarray]:
        return [-self.k**2]

    def check_params(self, p: np.ndarray) -> None:
        validate.number(
            self.name, "nu", p[0], ge=0,
            why="the viscosity ν; ν < 0 is ill-posed: exp(−ν k² Δt) grows without bound",
        )


BURGERS = register_orders(BurgersETDRK, "burgers1d", globals())
