"""Shared scene of the finite-difference diffusion solvers (FTCS, backward Euler, Crank–Nicolson).

Equation: u_t = ν Δu + a g(x) + c(t, x) on a box, periodic, homogeneous Dirichlet or homogeneous
Neumann boundaries (see :mod:`adjointsim.grid`), with an optional fixed forcing profile g of
amplitude a and an additive per-step control c (the correction hook: u_{k+1} = S(u_k) + Δt c_k).
Differentiable parameters: ``nu``, and ``forcing`` (the amplitude a) when g is given.
"""

from __future__ import annotations

import numpy as np

from .. import validate
from ..grid import BOUNDARIES, boundary_code, spacing
from ..stepper import Choice, Range, Stepper


class DiffusionScene(Stepper):
    """Grid, boundary, coefficients and forcing of a 1D or 2D diffusion problem."""

    ndim: int
    space = {
        "n": Range(6, 24, integer=True),
        "bc": Choice(("periodic", "dirichlet", "neumann")),
        "nu": Range(0.05, 1.0),
    }

    #: smallest n per boundary condition: one periodic or Neumann point has a zero Laplacian
    #: (ν would do nothing); one Dirichlet point is a valid grid
    min_points = {"periodic": 2, "dirichlet": 1, "neumann": 2}

    def __init__(
        self,
        n: int = 32,
        length: float = 1.0,
        nu: float = 0.1,
        dt: float | None = None,
        bc: str = "periodic",
        forcing: np.ndarray | None = None,
        forcing_amplitude: float = 1.0,
    ):
        """``dt=None`` takes :meth:`default_dt`. ``forcing``: a profile g of shape (1, *grid),
        scaled by the parameter ``forcing_amplitude``."""
        bc = validate.choice(self.name, "bc", bc, tuple(BOUNDARIES))
        n = validate.integer(
            self.name, "n", n, ge=self.min_points[bc],
            why=f"the smallest grid of this scheme with {bc} boundaries",
        )
        self.bc_code = boundary_code(bc)
        self.bc = bc
        self.grid_shape = (n,) * self.ndim
        self.channels = 1
        self.control_shape = (1, *self.grid_shape)
        self.length = validate.number(self.name, "length", length, gt=0)
        nu = validate.number(self.name, "nu", nu)
        amplitude = validate.number(self.name, "forcing_amplitude", forcing_amplitude)
        self.h = spacing(n, self.length, bc)
        self.inv_h2 = (1.0 / self.h**2, 1.0 / self.h**2 if self.ndim == 2 else 0.0)
        self.dt = (
            validate.number(self.name, "dt", dt, gt=0) if dt is not None else self.default_dt(nu)
        )
        if forcing is None:
            self.forcing = np.zeros((0, 1, 1))
            self.param_names, self.param_values = ("nu",), (nu,)
        else:
            g = validate.array(self.name, "forcing", forcing, (1, *self.grid_shape))
            self.forcing = self.as_2d(g)
            self.param_names = ("nu", "forcing")
            self.param_values = (nu, amplitude)
        self.check_params(np.array(self.param_values))

    def default_dt(self, nu: float) -> float:
        """Δt the scheme uses when none is given."""
        return 0.4 * self.h**2 / (nu * self.ndim)

    def as_2d(self, a: np.ndarray) -> np.ndarray:
        """View an array whose trailing axes are the grid as (..., Nx, Ny); 1D grids get Ny = 1."""
        nx, ny = (*self.grid_shape, 1)[:2]
        return a.reshape(*a.shape[: a.ndim - self.ndim], nx, ny)
