"""2D Kolmogorov flow as List et al. train it: forcing sin(6y) in x-momentum, ν = 1/Re, no drag;
a 128² reference and a 32² coarse solver, both ETDRK4."""

from __future__ import annotations

import numpy as np

import adjointsim
from adjointsim import Stepper

from ..problems import STEPPERS, Problem


@STEPPERS.register
class Kolmogorov(Problem):
    """2D Kolmogorov flow (k = 6, ν = 1/Re): reference 128² at Δt = 0.005, coarse 32² at
    Δt = 0.02 (one frame = four reference steps), both ETDRK4: ETDRK1/2 blow up on these grids
    once the flow reaches Courant numbers near 1 (one- and two-stage schemes do not contain the
    imaginary axis; ETDRK3/4 ran 10⁴ steps at Re 300–1000). The network sees Re/1000."""

    name = "kolmogorov"
    dims = 2
    train_params = (300.0, 400.0, 500.0, 700.0, 800.0, 900.0)
    test_params = {"interpolation": (600.0,), "extrapolation": (1000.0,)}
    warmup_frames = 500
    substeps = 4
    sizes = {
        "full": {"frames": 1000, "train_per_param": 2, "test_per_param": 4},
        "quick": {"frames": 120, "train_per_param": 1, "test_per_param": 2},
    }
    #: the reference grid and step, the coarse grid (its step spans one frame: substeps × dt)
    #: and the forcing's wavenumber
    SCENE = {"n": 128, "dt": 0.005, "coarse_n": 32, "forcing_wavenumber": 6}

    def _solver(self, n: int, dt: float, re: float) -> Stepper:
        return adjointsim.get("ns2d-etdrk4")(
            n=n, nu=1.0 / float(re), dt=dt, forcing_wavenumber=self.scene["forcing_wavenumber"],
            forcing_amplitude=1.0)

    def reference(self, param: float) -> Stepper:
        return self._solver(self.scene["n"], self.scene["dt"], param)

    def coarse(self, param: float) -> Stepper:
        try:
            return self._solver(self.scene["coarse_n"], self.substeps * self.scene["dt"], param)
        except (TypeError, ValueError) as e:
            if ": n must" not in str(e):
                raise
            # the solver names its own key, n: the user's is coarse_n
            raise type(e)(f"coarse_n (the coarse solver's n): {e}") from None

    def condition(self, param: float) -> float:
        return float(param) / 1000.0

    def initial_states(
        self, rng: np.random.Generator, param: float, count: int, split: str
    ) -> np.ndarray:
        return self.reference(param).random_state(rng, count)

    def to_coarse(self, u: np.ndarray) -> np.ndarray:
        from adjointsim.spectral.fft2d import resample

        return resample(u, self.scene["coarse_n"])
