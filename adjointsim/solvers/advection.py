"""Shared scene and kernels of the explicit linear-advection solvers (upwind, Lax–Wendroff).

Equation: u_t + a·∇u = c(t, x) on a periodic box [0, L)^d, d = 1 or 2, with an additive per-step
control c (the correction hook: u_{k+1} = S u_k + Δt c_k). Differentiable parameters: the
velocity components, ``velocity`` in 1D and ``velocity_x``, ``velocity_y`` in 2D.

Both schemes are a fixed linear 3^d-point stencil S u = Σ_o w_o(a) u(· + o), o ∈ {−1, 0, 1}^d,
whose weights a scheme module provides; the compiled kernels below are shared. The adjoint of S
is the mirrored stencil, ū_k = Σ_o w_o ū_{k+1}(· − o), and the velocity cotangent is
ā_d += Σ_o (∂w_o/∂a_d) ⟨ū_{k+1}, u_k(· + o)⟩.

In the kernels a 1D state (B, C, N) is viewed as (B, C, 1, N) (its stencil as the middle row of a
3×3 one) and a 2D state keeps (B, C, Nx, Ny): the last axis is contiguous, so the stencil is one
vectorised pass per output row.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from numba import njit

from .. import validate
from ..stepper import Choice, Range, Stepper


@njit(cache=True, nogil=True)
def advection_forward(states, n, ctrl, dt, w):
    s = states.shape[0]
    for k in range(n):
        stencil(states[k % s], states[(k + 1) % s], w, ctrl, k, dt)


@njit(cache=True, nogil=True)
def advection_adjoint(states, ctrl, cot, cmap, ubar, cbar, pbar, want_p, dt, w, live, dw):
    mirrored = np.ascontiguousarray(w[::-1, ::-1])
    g = np.zeros((3, 3), dtype=pbar.dtype)
    cur, nxt = ubar, np.empty_like(ubar)
    for k in range(states.shape[0] - 1, -1, -1):
        if want_p:
            correlate(cur, states[k], live, g)
        if cbar.shape[0] > 0:
            cbar[k] = dt * cur
        stencil(cur, nxt, mirrored, cot, cmap[k], 1.0)
        cur, nxt = nxt, cur
    if want_p:
        for d in range(dw.shape[0]):
            for r in range(3):
                for q in range(3):
                    pbar[d] += dw[d, r, q] * g[r, q]
    if states.shape[0] % 2 == 1:
        ubar[...] = cur


@njit(cache=True, nogil=True)
def stencil(u, out, w, extra, idx, scale):
    """out[i, j] = Σ_{r,q} w[r, q] u[i + r − 1, j + q − 1] (+ scale·extra[idx] if idx ≥ 0).

    One pass over the three source rows per output row; the ends of the contiguous axis wrap
    around, the interior loop vectorises. Without corner weights (upwind, any 1D stencil) the
    interior skips them: the test is loop-invariant, so the compiler hoists it.
    """
    nb, nc, nx, ny = u.shape
    add = idx >= 0 and extra.shape[0] > 0
    w00, w01, w02 = w[0, 0], w[0, 1], w[0, 2]
    w10, w11, w12 = w[1, 0], w[1, 1], w[1, 2]
    w20, w21, w22 = w[2, 0], w[2, 1], w[2, 2]
    corners = w00 != 0 or w02 != 0 or w20 != 0 or w22 != 0
    for b in range(nb):
        for c in range(nc):
            for i in range(nx):
                row = out[b, c, i]
                a, m, z = u[b, c, (i - 1) % nx], u[b, c, i], u[b, c, (i + 1) % nx]
                for j in range(1, ny - 1):
                    s = w01 * a[j] + w10 * m[j - 1] + w11 * m[j] + w12 * m[j + 1] + w21 * z[j]
                    if corners:
                        s += w00 * a[j - 1] + w02 * a[j + 1] + w20 * z[j - 1] + w22 * z[j + 1]
                    row[j] = s
                for j, jl, jr in ((0, ny - 1, 1), (ny - 1, ny - 2, 0)):
                    row[j] = (
                        w00 * a[jl] + w01 * a[j] + w02 * a[jr]
                        + w10 * m[jl] + w11 * m[j] + w12 * m[jr]
                        + w20 * z[jl] + w21 * z[j] + w22 * z[jr]
                    )
                if add:
                    e = extra[idx, b, c, i]
                    for j in range(ny):
                        row[j] += scale * e[j]


@njit(cache=True, nogil=True)
def correlate(v, u, live, g):
    """g[r, q] += Σ_{i,j} v[i, j] u[i + r − 1, j + q − 1] for the source rows r with live[r]."""
    nb, nc, nx, ny = u.shape
    for b in range(nb):
        for c in range(nc):
            for i in range(nx):
                row = v[b, c, i]
                inner = row[1 : ny - 1]
                for r in range(3):
                    if not live[r]:
                        continue
                    src = u[b, c, (i + r - 1) % nx]
                    gl, gc, gr = _dot3(inner, src[: ny - 2], src[1 : ny - 1], src[2:])
                    g[r, 0] += gl
                    g[r, 1] += gc
                    g[r, 2] += gr
                    g[r, 0] += row[0] * src[ny - 1] + row[ny - 1] * src[ny - 2]
                    g[r, 1] += row[0] * src[0] + row[ny - 1] * src[ny - 1]
                    g[r, 2] += row[0] * src[1] + row[ny - 1] * src[0]


@njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _dot3(x, left, mid, right):
    # Reassociation lets the reductions vectorise; it only reorders the rounding.
    zero = 0.0 * x[0] * mid[0]
    a, b, c = zero, zero, zero
    for j in range(x.shape[0]):
        a += x[j] * left[j]
        b += x[j] * mid[j]
        c += x[j] * right[j]
    return a, b, c


def smooth_noise(rng: np.random.Generator, shape: tuple[int, ...], ndim: int) -> np.ndarray:
    """Periodic Gaussian noise of ``shape`` low-pass filtered over its last ``ndim`` (equal) axes:
    spectrum exp(−|k|²/0.1²), k in cycles per cell, so wavelengths ≳ 6 cells dominate."""
    axes = tuple(range(len(shape) - ndim, len(shape)))
    k = np.fft.fftfreq(shape[-1])
    k2 = sum(np.meshgrid(*(k**2,) * ndim, indexing="ij"))
    spectrum = np.fft.fftn(rng.standard_normal(shape), axes=axes) * np.exp(-k2 / 0.1**2)
    return np.fft.ifftn(spectrum, axes=axes).real


class AdvectionScene(Stepper):
    """Periodic grid and velocity of a 1D or 2D linear-advection problem.

    A scheme subclass supplies :meth:`weights` (the stencil and its velocity derivatives),
    :meth:`max_dt` (its stability limit) and ``stability`` (the limit in words).
    """

    ndim: ClassVar[int]
    stability: ClassVar[str]

    #: smallest n per axis: the stencil's wrap-around along the contiguous axis needs two
    #: points (adjoints checked at n = 2 in tests/test_scene_validation.py)
    min_points: ClassVar[int] = 2

    def _setup(
        self, n: int, length: float, velocity: dict[str, float], dt: float | None, cfl: float
    ) -> None:
        n = validate.integer(self.name, "n", n, ge=self.min_points)
        self.grid_shape = (n,) * self.ndim
        self.channels = 1
        self.control_shape = (1, *self.grid_shape)
        self.length = validate.number(self.name, "length", length, gt=0)
        self.h = self.length / n
        self.param_values = tuple(validate.number(self.name, k, a) for k, a in velocity.items())
        cfl = validate.number(
            self.name, "cfl", cfl, gt=0, le=1, why="dt=None takes cfl × the largest stable Δt"
        )
        if dt is None:
            limit = self.max_dt(np.array(self.param_values))
            if not np.isfinite(limit):
                raise ValueError(
                    f"{self.name}: the velocity is zero, so dt=None (cfl × the largest stable Δt) "
                    "has no time scale; give dt explicitly"
                )
            dt = cfl * limit
        self.dt = validate.number(self.name, "dt", dt, gt=0)
        self.check_params(np.array(self.param_values))

    def nodes(self) -> np.ndarray:
        """Positions x_i = i h of the unknowns along each axis."""
        return self.h * np.arange(self.grid_shape[0])

    def random_state(
        self, rng: np.random.Generator, batch: int = 1, dtype: Any = np.float64
    ) -> np.ndarray:
        """Smooth random field (Gaussian spectrum, wavelengths ≳ 6 h) of unit RMS.

        Resolved waves keep the velocity derivatives well conditioned: both schemes damp grid
        noise within a few steps, which would leave only cancellation in the checks.
        """
        u = smooth_noise(rng, self.state_shape(batch), self.ndim)
        axes = tuple(range(2, 2 + self.ndim))
        return (u / np.sqrt(np.mean(u**2, axis=axes, keepdims=True))).astype(dtype)

    def courant(self, velocity: np.ndarray) -> np.ndarray:
        """Courant numbers ν_d = a_d Δt / h_d (in the dtype of ``velocity``)."""
        return velocity * (self.dt / self.h)

    def max_dt(self, velocity: np.ndarray) -> float:
        raise NotImplementedError

    def weights(self, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The kernels' 3×3 stencil w (dtype of ``velocity``) and ∂w/∂a_d, shape (ndim, 3, 3).

        Index neighbours with :meth:`tap`; a 1D stencil lives in the middle row.
        """
        raise NotImplementedError

    def tap(self, axis: int, step: int) -> tuple[int, int]:
        """Index in the 3×3 stencil of the neighbour ``step`` (±1) cells along ``axis``."""
        # A 1D grid runs along the contiguous (second) stencil axis, like a 2D grid's y.
        return (1, 1 + step) if axis == self.ndim - 1 else (1 + step, 1)

    def check_params(self, p: np.ndarray) -> None:
        limit = self.max_dt(p)
        if self.dt > limit * (1 + 1e-12):
            nu = ", ".join(f"{c:.4g}" for c in self.courant(p))
            raise ValueError(
                f"{self.name}: Δt = {self.dt:.6g} breaks the stability limit {self.stability} "
                f"(Courant numbers ν = a Δt / h = {nu}); the largest stable Δt is {limit:.6g}: "
                f"pass dt ≤ {limit:.6g}, or dt=None with 0 < cfl ≤ 1"
            )

    def _kernel_args(self, p: np.ndarray, dtype: Any) -> tuple:
        w, dw = self.weights(p)
        # Source rows whose taps carry a velocity derivative: the only correlations needed.
        live = (dw != 0).any(axis=(0, 2))
        return w.astype(dtype), live, dw.astype(np.result_type(dtype, np.float64))

    def _view(self, a: np.ndarray) -> np.ndarray:
        if self.ndim == 2:
            return a
        return a.reshape(*a.shape[:-1], 1, a.shape[-1])

    def _forward(self, states, n, ctrl, p):
        w, _, _ = self._kernel_args(p, states.dtype)
        advection_forward(self._view(states), n, self._view(ctrl), self.dt, w)

    def _adjoint(self, states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p):
        w, live, dw = self._kernel_args(p, ubar.dtype)
        advection_adjoint(
            self._view(states), self._view(ctrl), self._view(cot), cmap, self._view(ubar),
            self._view(cbar), pbar, want_p, self.dt, w, live, dw,
        )


class Advection1D(AdvectionScene):
    """u_t + a u_x = c on the periodic interval [0, L)."""

    ndim = 1
    param_names = ("velocity",)
    space = {
        "n": Range(8, 48, integer=True),
        # No zero velocity: upwinding switches stencil there (see the scheme modules).
        "velocity": Choice((-1.5, -0.4, 0.3, 1.0)),
        "cfl": Range(0.2, 0.9),
    }

    def __init__(
        self,
        n: int = 32,
        length: float = 1.0,
        velocity: float = 1.0,
        dt: float | None = None,
        cfl: float = 0.5,
    ):
        """``dt`` defaults to ``cfl`` times the scheme's largest stable Δt."""
        self._setup(n, length, {"velocity": velocity}, dt, cfl)


class Advection2D(AdvectionScene):
    """u_t + a_x u_x + a_y u_y = c on the periodic square [0, L)²."""

    ndim = 2
    param_names = ("velocity_x", "velocity_y")
    space = {
        "n": Range(8, 20, integer=True),
        "velocity_x": Choice((-1.0, -0.3, 0.5, 1.2)),
        "velocity_y": Choice((-0.7, 0.2, 0.9)),
        "cfl": Range(0.2, 0.9),
    }

    def __init__(
        self,
        n: int = 16,
        length: float = 1.0,
        velocity_x: float = 1.0,
        velocity_y: float = 0.5,
        dt: float | None = None,
        cfl: float = 0.5,
    ):
        """``dt`` defaults to ``cfl`` times the scheme's largest stable Δt."""
        self._setup(n, length, {"velocity_x": velocity_x, "velocity_y": velocity_y}, dt, cfl)
