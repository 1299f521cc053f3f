"""Kuramoto–Sivashinsky, Fourier pseudo-spectral with ETDRK1–4 (kernel: :mod:`.spectral1d`).

Continuous:  u_t + u u_x + α u_xx + β u_xxxx = a g(x) on [0, length), periodic; α
             ("anti_diffusion") and β ("hyper_diffusion") are 1 for the standard equation.
Discrete:    û_t = L û − ½ i k · DFT(u²), L = α k² − β k⁴; ``substeps`` ETDRK steps of
             h = Δt/substeps per stored frame, u_{k+1} = S(u_k) + Δt c_k. No dealiasing by
             default (as List et al. and Kassam & Trefethen); ``dealias=True`` applies the 2/3
             rule to the nonlinear term.
Adjoint:     reversed ETDRK stages (see :mod:`.spectral1d`); ᾱ, β̄ from the coefficient
             cotangents and d(coefficient)/dL · (k², −k⁴).
Presets:     :meth:`KuramotoSivashinskyETDRK.kassam_trefethen` (N = 128, length 32π, h = 1/4,
             ETDRK4; initial state from :meth:`kassam_trefethen_state`). List et al.'s scenes
             are the ``ks`` neural-stepper problem's (``adjointsim.train.steppers.ks``).
"""

from __future__ import annotations

import numpy as np

from .. import validate
from ..stepper import Choice, Range
from .spectral1d import ETDRKScene1D, register_orders


class KuramotoSivashinskyETDRK(ETDRKScene1D):
    """Kuramoto–Sivashinsky u_t + u u_x + α u_xx + β u_xxxx = 0, conservative form."""

    linear_params = ("anti_diffusion", "hyper_diffusion")
    space = {
        "n": Choice((16, 24, 32)),
        "length": Range(2 * np.pi, 4 * np.pi),
        "substeps": Range(1, 2, integer=True),
        "dealias": Choice((False, True)),
    }

    def __init__(
        self,
        n: int = 32,
        length: float = 3 * np.pi,
        dt: float = 0.1,
        anti_diffusion: float = 1.0,
        hyper_diffusion: float = 1.0,
        substeps: int = 1,
        dealias: bool = False,
        forcing: np.ndarray | None = None,
        forcing_amplitude: float = 1.0,
    ):
        super().__init__(
            n, length, dt, (anti_diffusion, hyper_diffusion), substeps, dealias, forcing,
            forcing_amplitude,
        )

    def linear_basis(self) -> list[np.ndarray]:
        return [self.k**2, -self.k**4]

    def check_params(self, p: np.ndarray) -> None:
        validate.number(
            self.name, "hyper_diffusion", p[1], gt=0,
            why="the coefficient β of u_xxxx; otherwise the short waves grow like exp(α k² Δt) "
            "without bound",
        )

    @classmethod
    def kassam_trefethen(cls) -> KuramotoSivashinskyETDRK:
        """Kassam & Trefethen's KS: N = 128 on [0, 32π), ETDRK4 with h = 1/4."""
        return KS[4](n=128, length=32 * np.pi, dt=0.25)

    def kassam_trefethen_state(self, dtype: np.dtype | type = np.float64) -> np.ndarray:
        """u0 = cos(x/16)(1 + sin(x/16)) on this grid, shape (1, 1, n)."""
        x = self.nodes()
        return (np.cos(x / 16) * (1 + np.sin(x / 16)))[None, None, :].astype(dtype)


KS = register_orders(KuramotoSivashinskyETDRK, "ks1d", globals())
