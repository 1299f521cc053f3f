"""``chain``: the PBDL book's linear chain (2 masses, coupling 0.2, RK4, Δt = 0.5, 24 steps),
network 4 → 20 ×3 (tanh) → 24; HIG batch 32, lr 1, τ = 1e-10; Adam batch 256, lr 1e-3; GN as
HIG; 100 s budget."""

from __future__ import annotations

from typing import Any, ClassVar

from . import PROBLEMS
from .oscillators import CoupledOscillators


@PROBLEMS.register
class LinearChain(CoupledOscillators):
    """The oscillators' task on the book's linear chain."""

    name = "chain"
    SCENE: ClassVar[dict[str, Any]] = {"n": 2, "dt": 0.5, "stiffness": 1.0,
                                       "linear_coupling": 0.2, "cubic_coupling": 0.0,
                                       "gain": 1.0}
    BUDGET = 100.0
    SETTINGS: ClassVar = {"adam": {"batch": 256, "lr": 1e-3},
                          "hig": {"batch": 32, "lr": 1.0, "tau": 1e-10},
                          "gn": {"batch": 32, "lr": 1.0, "tau": 1e-10}}
    STEPS = 24
    ACTIVATION = "tanh"
