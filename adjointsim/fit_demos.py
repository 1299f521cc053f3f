"""The built-in problems of ``adjointsim fit --demo``, and the PBDL Burgers scene they share with
the DP-against-PINN comparison (NumPy only).

* ``burgers``: PBDL's Burgers reconstruction (Thuerey et al., *Physics-based Deep Learning*):
  the initial state −sin(πx) fitted from zero to the state at step 16 (t = 0.5) of the PBDL
  scene (:data:`PBDL_SCENE`);
* ``ks-params``: the Kuramoto–Sivashinsky coefficients α (``anti_diffusion``) and β
  (``hyper_diffusion``, bounded below by 0.05) from every 5th step up to 100 of ``ks1d-etdrk4``
  (N = 64, L = 22, Δt = 0.1) from a smooth random state (seed 1234), started at 1.3 and 0.7;
* ``burgers-nu``: the viscosity ν ∈ [0, 0.01], started at 0.02/π, from every step up to 32 of
  the PBDL scene in 8 sub-steps a step.

Each demo's scene is its solver's keywords (:data:`SCENES`), which a fit's ``scene`` table
overrides key by key.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from . import scenes
from .errors import UserError
from .stepper import Stepper

#: the step of the PBDL scene observed by the reconstruction (t = 16 Δt = 0.5)
PBDL_T_OBS_STEP = 16
#: The PBDL Burgers scene: 128 cells on [−1, 1], ν = 0.01/π, Δt = 1/32 (32 steps reach t = 1).
#: One Δt breaks the explicit limit (Courant number 2 alone), so each step takes the fewest
#: stable sub-steps (``substeps`` None); the velocity bound u_max = 2 of the stability check
#: (5 sub-steps, where |u| ≤ 1 takes 3) keeps an optimiser's trial initial states up to |u| = 2
#: stable.
PBDL_SCENE: dict[str, Any] = {"n": 128, "length": 2.0, "start": -1.0, "nu": 0.01 / np.pi,
                              "dt": 1 / 32, "substeps": None, "umax": 2.0}
#: per demo: its solver and the scene's keywords
SCENES: dict[str, tuple[str, dict[str, Any]]] = {
    "burgers": ("burgers1d-rusanov", PBDL_SCENE),
    "ks-params": ("ks1d-etdrk4", {"n": 64, "length": 22.0, "dt": 0.1}),
    "burgers-nu": ("burgers1d-rusanov", {**PBDL_SCENE, "substeps": 8}),
}
DEMOS = tuple(SCENES)


def pbdl_scene(**changes: Any) -> Stepper:
    """The PBDL Burgers scene (:data:`PBDL_SCENE`) with ``changes`` over its keywords."""
    return scenes.build("burgers1d-rusanov", {**PBDL_SCENE, **changes})


def pbdl_state(scene: Any, batch: int = 1, dtype: Any = np.float64) -> np.ndarray:
    """The PBDL initial state u_0 = −sin(π x) at the cell centres of ``scene``, shape
    (batch, 1, N)."""
    u = -np.sin(np.pi * scene.nodes())
    return np.broadcast_to(u, scene.state_shape(batch)).astype(dtype)


def demo_scene(name: str, scene: dict[str, Any] | None = None) -> tuple[Stepper, dict[str, Any]]:
    """Demo ``name``'s solver and its keywords, ``scene`` over the demo's own; a key or value
    the solver refuses is a ValueError naming it."""
    if name not in SCENES:
        raise UserError(f"unknown demo {name!r}; choose from {', '.join(DEMOS)}")
    solver, defaults = SCENES[name]
    config = {**defaults, **(scene or {})}
    return scenes.build(solver, config), config


def demo_problem(name: str, noise: float = 0.0, seed: int = 0,
                 scene: dict[str, Any] | None = None) -> dict[str, Any]:
    """A built-in problem as the contents of an observation file (see
    :mod:`adjointsim.fit_run`), in its scene with ``scene`` over it, with relative Gaussian
    noise ``noise`` · std(states) drawn from ``seed`` on the observations."""
    stepper, config = demo_scene(name, scene)
    if name == "burgers":
        u0 = pbdl_state(stepper)
        traj = stepper.rollout(u0, 32, keep="all")
        steps = [PBDL_T_OBS_STEP]
        out = {"wrt": "state", "truth_u0": u0, "u0": None, "params": {}}
    elif name == "ks-params":
        u0 = stepper.random_state(np.random.default_rng(1234))
        traj = stepper.rollout(u0, 100, keep="all")
        steps = list(range(5, 101, 5))
        out = {"wrt": "params", "u0": u0,
               "params": {"anti_diffusion": 1.3, "hyper_diffusion": 0.7},
               "bounds": {"hyper_diffusion": (0.05, None)}}
    else:
        u0 = pbdl_state(stepper)
        traj = stepper.rollout(u0, 32, keep="all")
        steps = list(range(1, 33))
        out = {"wrt": "nu", "u0": u0, "params": {"nu": 0.02 / np.pi}, "bounds": {"nu": (0, 0.01)}}
    states = traj[steps].copy()
    if noise:
        rng = np.random.default_rng(seed)
        states += noise * float(np.std(traj[1:])) * rng.standard_normal(states.shape)
    return {"scene": stepper.name, "config": config, "steps": np.array(steps),
            "states": states, "truth_params": dict(stepper.params), **out}
