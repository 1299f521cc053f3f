"""``oscillators``: 2 coupled nonlinear oscillators (``oscillators-rk4``, Δt = 0.125, 96 steps),
x ~ U[0, 1)⁴; the network 4 → 20 ×3 (ReLU) → 96 controls must bring the state back to x; loss
‖y − x‖². Adam batch 512, lr 3e-4; HIG and GN batch 128, lr 1, τ = 1e-6. With another ``n``
in the scene, x and the network's input have 2n entries."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch

from adjointsim.nets.mlp import MLP
from adjointsim.solvers.oscillators import Oscillators

from ..hig import SolverPhysics
from . import DTYPE, PROBLEMS, HigProblem


@PROBLEMS.register
class CoupledOscillators(HigProblem):
    """Controls over ``STEPS`` steps that bring the chain back to where it started."""

    name = "oscillators"
    SOLVER = Oscillators
    SCENE: ClassVar[dict[str, Any]] = {"n": 2, "dt": 0.125, "stiffness": 1.0,
                                       "linear_coupling": 0.0, "cubic_coupling": 1.0,
                                       "gain": 3.0}
    SETTINGS: ClassVar = {"adam": {"batch": 512, "lr": 3e-4},
                          "hig": {"batch": 128, "lr": 1.0, "tau": 1e-6},
                          "gn": {"batch": 128, "lr": 1.0, "tau": 1e-6}}
    #: the rollout's steps (one control each) and the network's activation
    STEPS: ClassVar[int] = 96
    ACTIVATION: ClassVar[str] = "relu"

    def __init__(self, seed: int, size: str = "full", scene: dict[str, Any] | None = None):
        super().__init__(seed, size, scene)
        n = self.solver.n
        rng = np.random.default_rng(seed)
        train = torch.from_numpy(rng.random((self.count, 2 * n)))
        test = torch.from_numpy(rng.random((self.count, 2 * n)))
        self.physics = SolverPhysics(self.solver, self.STEPS, lambda c: c.reshape(-1, 2, n))
        self.train, self.test = (train, train, train), (test, test, test)

    def model(self) -> torch.nn.Module:
        return MLP(2 * self.solver.n, self.STEPS, width=20, depth=3,
                   activation=self.ACTIVATION).to(DTYPE)
