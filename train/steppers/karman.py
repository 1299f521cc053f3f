"""The Kármán vortex street behind a cylinder, as the physics-based deep learning book's
"Reducing Numerical Errors with Deep Learning" trains a correction (solver-in-the-loop, Um et
al. 2020): a fine reference solve, and the same solver on a 4x coarser grid as the source.

Both are ``incompressible2d-sl``: a channel of 2 × 1 with a uniform inflow of speed 1 on the
left, an outflow on the right, free-slip walls at the bottom and top and a cylinder of
diameter ¼ centred half a height from the inflow; the scene parameter is the Reynolds number
Re = U D / ν (U = 1, D = ¼). The coarse solver's step spans one frame (``substeps`` reference
steps), so it is 4x coarser in space and time. On its grid the cylinder is 4 cells across and
the semi-Lagrangian advection's numerical viscosity (about U h / 2) dominates the physical one:
the source solver's wake sheds late, weakly and at its own frequency, which is the error the
network learns to correct.
"""

from __future__ import annotations

import numpy as np

from adjointsim import Stepper
from adjointsim.solvers.incompressible2d import MAX_COURANT, Incompressible2D

from ..problems import STEPPERS, Problem

#: the channel's length (its height is 1), the cylinder's diameter and the inflow speed
LENGTH, DIAMETER, SPEED = 2.0, 0.25, 1.0


class TooFastError(FloatingPointError):
    """A state the model made moves beyond the source solver's Courant limit: the model's
    rollout blew up (training skips the update, evaluation marks the rollout)."""


class Source(Incompressible2D):
    """The source solver as the correction runs it. The solver itself limits no state's speed
    (its own flows may outrun h/Δt); a state the model made that fast is counted as a blow-up
    of the model's rollout, like a non-finite one, and raised as one: the correction left the
    flows it was trained on, and the source's backtraces start to jump cells."""

    def check_state(self, u: np.ndarray, what: str = "u0") -> np.ndarray:
        u = np.asarray(u)
        if u.ndim == 4 and u.shape[0] and u.shape[1] >= 2:
            courant = self.courant_number(u)
            if courant > MAX_COURANT:
                raise TooFastError(f"{self.name}: the model's state moves at up to "
                                   f"{courant * self.h / self.dt:.3g}, beyond the source "
                                   f"solver's limit h/dt = {MAX_COURANT * self.h / self.dt:.3g}")
        return super().check_state(u, what)


@STEPPERS.register
class Karman(Problem):
    """The cylinder wake at Re = U D / ν: reference 128 × 64 cells at Δt = 1/160, source
    32 × 16 at Δt = 1/40 (one frame = four reference steps, Courant number 0.4 at the inflow
    speed on both grids). Trajectories start from the inflow speed everywhere with a random
    cross-flow of 0.1 (which breaks the symmetry) and drop 400 frames (t = 10: the street is
    established, shedding about every 1.25). The state is the velocity (u, v) on the staggered
    grid; the network sees Re/1000."""

    name = "karman"
    dims = 2
    channels = 2
    padding = "replicate"
    train_params = (100.0, 200.0, 400.0, 800.0)
    test_params = {"interpolation": (300.0,), "extrapolation": (1000.0,)}
    warmup_frames = 400
    substeps = 4
    sizes = {
        "full": {"frames": 600, "train_per_param": 2, "test_per_param": 2},
        "quick": {"frames": 200, "train_per_param": 1, "test_per_param": 1},
        "tiny": {"frames": 24, "train_per_param": 1, "test_per_param": 1},
    }
    #: the reference grid's cells across the channel (twice as many along it) and step, and
    #: the source grid's cells across (its step spans one frame: substeps × dt)
    SCENE = {"n": 64, "dt": 1 / 160, "coarse_n": 16}

    def _solver(self, kind: type[Incompressible2D], n: int, dt: float, re: float) -> Stepper:
        return kind(nx=2 * n, ny=n, length=LENGTH, dt=dt, nu=SPEED * DIAMETER / float(re),
                    boundaries="inflow outflow slip slip", inflow_speed=SPEED,
                    obstacle="cylinder")

    def reference(self, param: float) -> Stepper:
        return self._solver(Incompressible2D, self.scene["n"], self.scene["dt"], param)

    def coarse(self, param: float) -> Stepper:
        n, coarse_n = self.scene["n"], self.scene["coarse_n"]
        if not (isinstance(coarse_n, int) and coarse_n >= 1 and n % coarse_n == 0):
            raise ValueError(f"coarse_n (the source grid's cells across) must be a positive "
                             f"integer that divides n = {n}, got {coarse_n!r}")
        try:
            return self._solver(Source, coarse_n, self.substeps * self.scene["dt"], param)
        except (TypeError, ValueError) as e:
            # the solver names its own keys (nx, dt): the user's are coarse_n and dt
            raise type(e)(f"the source solver (coarse_n = {coarse_n}, dt = substeps × dt): "
                          f"{e}") from None

    def condition(self, param: float) -> float:
        return float(param) / 1000.0

    def initial_states(
        self, rng: np.random.Generator, param: float, count: int, split: str
    ) -> np.ndarray:
        solver = self.reference(param)
        nx, ny = solver.nx, solver.ny
        u = np.zeros(solver.state_shape(count))
        u[:, 0, :, :ny] = SPEED
        u[:, 1, :nx, 1:ny] = 0.1 * SPEED * rng.standard_normal((count, nx, ny - 1))
        return u

    def to_coarse(self, u: np.ndarray) -> np.ndarray:
        """The reference velocity restricted to the source grid by face fluxes: a coarse face
        takes the mean of the fine faces it covers, so the coarse field's divergence in a cell
        is the mean of the fine divergences inside it (zero, away from the cylinder)."""
        r = self.scene["n"] // self.scene["coarse_n"]
        b, _, nx1, ny1 = u.shape
        nx, ny = (nx1 - 1) // r, (ny1 - 1) // r
        out = np.zeros((b, 2, nx + 1, ny + 1), dtype=u.dtype)
        out[:, 0, :, :ny] = u[:, 0, ::r, : ny * r].reshape(b, nx + 1, ny, r).mean(-1)
        out[:, 1, :nx, :] = u[:, 1, : nx * r, ::r].reshape(b, nx, r, ny + 1).mean(2)
        return out
