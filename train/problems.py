"""The learning problems of List et al.: what the reference and coarse solvers are, which scene
parameters the train and test splits use, how trajectories start and what the network is told.

A problem is a family of scenes indexed by one scalar parameter (the KS domain factor, the
Kolmogorov Reynolds number). The network sees ``condition(param)`` as a constant extra channel.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

import adjointsim
from adjointsim import Stepper


@dataclass(frozen=True)
class Problem:
    name: str
    dims: int
    #: parameter values of the training split and of the named test splits
    train_params: tuple[float, ...]
    test_params: dict[str, tuple[float, ...]]
    #: frames discarded before a trajectory is stored (transients)
    warmup_frames: int
    #: reference solver steps per stored frame (one coarse step spans one frame)
    substeps: int
    #: knobs of the scaled-down versions ("quick": the README's study)
    sizes: dict[str, dict] = field(default_factory=dict)

    # Each problem overrides these four.
    def reference(self, param: float) -> Stepper:
        raise NotImplementedError

    def coarse(self, param: float) -> Stepper:
        raise NotImplementedError

    def initial_states(self, rng: np.random.Generator, param: float, count: int, split: str):
        raise NotImplementedError

    def condition(self, param: float) -> float:
        raise NotImplementedError

    def to_coarse(self, u: np.ndarray) -> np.ndarray:
        """Reference-grid states → coarse grid (identity when the grids agree)."""
        return u

    @property
    def splits(self) -> dict[str, tuple[float, ...]]:
        return {"train": self.train_params, **self.test_params}


class KuramotoSivashinsky(Problem):
    """KS, N = 48, domain 2π·8·factor: reference ETDRK2 (Δt = 0.5, two sub-steps per frame),
    coarse ETD1 on the same grid and frame spacing; the network sees the factor."""

    def reference(self, param: float) -> Stepper:
        return adjointsim.get("ks1d-etdrk2").list_et_al(param)

    def coarse(self, param: float) -> Stepper:
        return adjointsim.get("ks1d-etdrk1").list_et_al(param, coarse=True)

    def condition(self, param: float) -> float:
        return float(param)

    def initial_states(self, rng: np.random.Generator, param: float, count: int, split: str):
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


class Kolmogorov(Problem):
    """2D Kolmogorov flow (k = 6, ν = 1/Re): reference 128² at Δt = 0.005, coarse 32² at
    Δt = 0.02 (one frame = four reference steps), both ETDRK4: ETDRK1/2 blow up on these grids
    once the flow reaches Courant numbers near 1. The network sees Re/1000."""

    coarse_n: int = 32

    def reference(self, param: float) -> Stepper:
        return adjointsim.get("ns2d-etdrk4").kolmogorov_list_et_al(param, "reference")

    def coarse(self, param: float) -> Stepper:
        return adjointsim.get("ns2d-etdrk4").kolmogorov_list_et_al(param, "coarse")

    def condition(self, param: float) -> float:
        return float(param) / 1000.0

    def initial_states(self, rng: np.random.Generator, param: float, count: int, split: str):
        return self.reference(param).random_state(rng, count)

    def to_coarse(self, u: np.ndarray) -> np.ndarray:
        from adjointsim.spectral.fft2d import resample

        return resample(u, self.coarse_n)


PROBLEMS: dict[str, Problem] = {
    "ks": KuramotoSivashinsky(
        name="ks",
        dims=1,
        train_params=(0.9, 0.95, 1.0, 1.1, 1.2, 1.3),
        test_params={"interpolation": (0.93, 1.15), "extrapolation": (0.85, 1.40)},
        warmup_frames=200,
        substeps=1,
        sizes={
            "full": {"frames": 5000, "train_per_param": 6, "test_per_param": 10},
            "quick": {"frames": 400, "train_per_param": 2, "test_per_param": 3},
            "tiny": {"frames": 24, "train_per_param": 1, "test_per_param": 1},
        },
    ),
    "kolmogorov": Kolmogorov(
        name="kolmogorov",
        dims=2,
        train_params=(300.0, 400.0, 500.0, 700.0, 800.0, 900.0),
        test_params={"interpolation": (600.0,), "extrapolation": (1000.0,)},
        warmup_frames=500,
        substeps=4,
        sizes={
            "full": {"frames": 1000, "train_per_param": 2, "test_per_param": 4},
            "quick": {"frames": 120, "train_per_param": 1, "test_per_param": 2},
        },
    ),
}


def get_problem(name: str) -> Problem:
    try:
        return PROBLEMS[name]
    except KeyError:
        raise ValueError(f"unknown problem {name!r}; choose from {sorted(PROBLEMS)}") from None
