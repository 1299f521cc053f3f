"""Kuramoto–Sivashinsky as List et al. train it: N = 48 on a domain 2π·8·factor, frames 1.0
apart; the reference ETDRK2, the coarse solver ETD1 on the same grid and frame spacing."""

from __future__ import annotations

import numpy as np

import adjointsim
from adjointsim import Stepper

from ..problems import STEPPERS, Problem


@STEPPERS.register
class KuramotoSivashinsky(Problem):
    """KS, N = 48, domain 2π·8·factor: reference ETDRK2 (Δt = 0.5, two sub-steps per frame),
    coarse ETD1 on the same grid and frame spacing; the network sees the factor.

    Left to itself the coarse solver is unstable on the chaotic attractor: exponential Euler
    treats advection explicitly, and at Δt = 0.5 the modes near |k| ≈ 1 grow. From attractor
    states it blows up after a median of 16–32 frames (factor 1.4 → 0.85); in the correction
    setup the network keeps it on track. ``substeps = 4`` would make it stable."""

    name = "ks"
    dims = 1
    train_params = (0.9, 0.95, 1.0, 1.1, 1.2, 1.3)
    test_params = {"interpolation": (0.93, 1.15), "extrapolation": (0.85, 1.40)}
    warmup_frames = 200
    substeps = 1
    sizes = {
        "full": {"frames": 5000, "train_per_param": 6, "test_per_param": 10},
        "quick": {"frames": 400, "train_per_param": 2, "test_per_param": 3},
        "tiny": {"frames": 24, "train_per_param": 1, "test_per_param": 1},
    }
    #: both solvers' grid, frame spacing and ETDRK steps per frame
    SCENE = {"n": 48, "dt": 1.0, "substeps": 2}

    def _solver(self, order: int, param: float) -> Stepper:
        return adjointsim.get(f"ks1d-etdrk{order}")(length=2 * np.pi * 8 * float(param),
                                                    **self.scene)

    def reference(self, param: float) -> Stepper:
        return self._solver(2, param)

    def coarse(self, param: float) -> Stepper:
        return self._solver(1, param)

    def condition(self, param: float) -> float:
        return float(param)

    def initial_states(
        self, rng: np.random.Generator, param: float, count: int, split: str
    ) -> np.ndarray:
        stepper = self.reference(param)
        x = stepper.nodes()  # solver units: x = 2π ξ with ξ ∈ [0, L), L = 8·factor
        length = 8.0 * param
        if split == "train":
            # cos(2πξ) ± a cos(2πξ/L)(1 ± b sin(2πξ/L)), the paper's six smooth states.
            shapes = [
                np.cos(x) + s * a * np.cos(x / length) * (1 + s * b * np.sin(x / length))
                for a, b in ((0.1, 0.1), (0.2, 0.3), (0.3, 0.5))
                for s in (1.0, -1.0)
            ]
            picks = [shapes[i % len(shapes)] for i in range(count)]
        else:
            # Random smooth states: cos(2πξ) (not periodic on the domain unless 8·factor is an
            # integer, like the training states; the warm-up frames smooth the seam away) plus
            # a few random low modes of the domain.
            picks = []
            for _ in range(count):
                modes = np.arange(1, 5)
                amp = rng.normal(0, 0.5, (2, modes.size))
                picks.append(
                    np.cos(x) + (amp[0] @ np.cos(np.outer(modes, x) / length))
                    + (amp[1] @ np.sin(np.outer(modes, x) / length))
                )
        return np.stack(picks)[:, None, :]
