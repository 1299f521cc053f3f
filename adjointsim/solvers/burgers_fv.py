"""Viscous Burgers, conservative finite volumes with the Rusanov flux, explicit Euler (periodic).

Continuous:  u_t + (u²/2)_x = ν u_xx + c                       (1D)
             u_t + (u²/2)_x + (u²/2)_y = ν Δu + c               (2D, scalar u)
Discrete:    one step of Δt is ``substeps`` explicit sub-steps of τ = Δt / substeps,
             u ← u − τ Σ_d (F_{d,+½} − F_{d,−½}) / h_d + τ ν Δ_h u,
             F(u_L, u_R) = (u_L² + u_R²)/4 − (α/2)(u_R − u_L),  α = max(|u_L|, |u_R|),
             then u_{k+1} = u + Δt c_k. Δ_h is the periodic 3/5-point Laplacian
             (:func:`adjointsim.grid.laplacian`). With a velocity bound u_max ≥ max|u| the update
             is monotone if τ (u_max Σ_d 1/h_d + 2ν Σ_d 1/h_d²) ≤ 1: the maximum principle then
             keeps |u| ≤ u_max (without controls), so the stability check is made once, on the
             scene, from u_max.
Adjoint:     per sub-step, in reverse: ū = v̄ + τ ν Δ_h v̄ + Σ_faces F̄ ∂F/∂u,
             F̄_{d,+½} = (τ/h_d)(v̄_R − v̄_L);  ν̄ += τ ⟨Δ_h v̄, u⟩ (Δ_h symmetric);  c̄_k = Δt ū_{k+1}.
             The sub-step inputs are recomputed from the stored step input. ∂α/∂u takes the branch
             of the larger |u| (at |u_L| = |u_R| the flux is differentiable when u_L = u_R and not
             when u_L = −u_R, a sonic point).

A 1D state (B, C, N) runs as (B, C, 1, N) so that its only axis is the contiguous one.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

from .. import validate
from ..grid import PERIODIC, laplacian
from ..registry import register
from ..stepper import Choice, Range, Stepper
from .advection import smooth_noise

#: the most substeps a step takes when dt alone sets them: beyond it a dt is a slip of units
MAX_SUBSTEPS = 100_000


@njit(cache=True, nogil=True)
def burgers_forward(states, n, ctrl, p, dt, substeps, inv_hx, inv_hy, inv_hx2, inv_hy2):
    s = states.shape[0]
    lap = np.empty_like(states[0])
    scratch = np.empty((2, states.shape[-1]), dtype=states.dtype)
    bufs = np.empty((min(substeps - 1, 2),) + states.shape[1:], dtype=states.dtype)
    tau = dt / substeps
    for k in range(n):
        cur = states[k % s]
        out = states[(k + 1) % s]
        for m in range(substeps):
            dst = out if m == substeps - 1 else bufs[m % 2]
            rusanov_step(cur, dst, lap, scratch, p[0], tau, inv_hx, inv_hy, inv_hx2, inv_hy2)
            cur = dst
        if ctrl.shape[0] > 0:
            _add(out, ctrl[k], dt)


@njit(cache=True, nogil=True)
def burgers_adjoint(
    states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p,
    dt, substeps, inv_hx, inv_hy, inv_hx2, inv_hy2,
):
    lap = np.empty_like(ubar)
    scratch = np.empty((3, ubar.shape[-1]), dtype=ubar.dtype)
    inputs = np.empty((substeps - 1,) + ubar.shape, dtype=ubar.dtype)
    cur, nxt = ubar, np.empty_like(ubar)
    tau = dt / substeps
    nu = p[0]
    for k in range(states.shape[0] - 1, -1, -1):
        if cbar.shape[0] > 0:
            cbar[k] = dt * cur
        for m in range(1, substeps):
            prev = states[k] if m == 1 else inputs[m - 2]
            rusanov_step(
                prev, inputs[m - 1], lap, scratch, nu, tau, inv_hx, inv_hy, inv_hx2, inv_hy2
            )
        for m in range(substeps - 1, -1, -1):
            u = states[k] if m == 0 else inputs[m - 1]
            rusanov_step_adjoint(
                u, cur, nxt, lap, scratch, nu, tau, inv_hx, inv_hy, inv_hx2, inv_hy2
            )
            if want_p:
                pbar[0] += tau * _dot(u, lap)
            cur, nxt = nxt, cur
        if cmap[k] >= 0:
            _add(cur, cot[cmap[k]], 1.0)
    if (states.shape[0] * substeps) % 2 == 1:
        ubar[...] = cur


@njit(cache=True, nogil=True)
def rusanov_step(u, v, lap, scratch, nu, tau, inv_hx, inv_hy, inv_hx2, inv_hy2):
    """v = u − τ Σ_d (F_{+½} − F_{−½}) / h_d + τ ν Δ_h u; each face flux is evaluated once."""
    laplacian(u, lap, inv_hx2, inv_hy2, PERIODIC)
    nb, nc, nx, ny = u.shape
    cx, cy, dn = tau * inv_hx, tau * inv_hy, tau * nu
    west, fy = scratch[0], scratch[1]
    for b in range(nb):
        for c in range(nc):
            if nx > 1:
                last, first = u[b, c, nx - 1], u[b, c, 0]
                for j in range(ny):
                    west[j] = _rusanov(last[j], first[j])
            for i in range(nx):
                ui, vi, li = u[b, c, i], v[b, c, i], lap[b, c, i]
                for j in range(ny):
                    vi[j] = ui[j] + dn * li[j]
                if nx > 1:
                    east = u[b, c, (i + 1) % nx]
                    for j in range(ny):
                        f = _rusanov(ui[j], east[j])
                        vi[j] -= cx * (f - west[j])
                        west[j] = f
                if ny > 1:
                    ul, ur = ui[: ny - 1], ui[1:]
                    for j in range(ny - 1):
                        fy[j] = _rusanov(ul[j], ur[j])
                    fy[ny - 1] = _rusanov(ui[ny - 1], ui[0])
                    vi[0] -= cy * (fy[0] - fy[ny - 1])
                    rest, east_flux, west_flux = vi[1:], fy[1:], fy[: ny - 1]
                    for j in range(ny - 1):
                        rest[j] -= cy * (east_flux[j] - west_flux[j])


@njit(cache=True, nogil=True)
def rusanov_step_adjoint(u, vbar, ubar, lap, scratch, nu, tau, inv_hx, inv_hy, inv_hx2, inv_hy2):
    """ubar = (∂v/∂u)ᵀ vbar for the sub-step from u; leaves Δ_h vbar in ``lap``."""
    laplacian(vbar, lap, inv_hx2, inv_hy2, PERIODIC)
    nb, nc, nx, ny = u.shape
    cx, cy, dn = tau * inv_hx, tau * inv_hy, tau * nu
    # carry: the share of the current cell in its west face's cotangent.
    carry, gl, gr = scratch[0], scratch[1], scratch[2]
    for b in range(nb):
        for c in range(nc):
            if nx > 1:
                last, first = u[b, c, nx - 1], u[b, c, 0]
                vlast, vfirst = vbar[b, c, nx - 1], vbar[b, c, 0]
                for j in range(ny):
                    _, dr = _rusanov_grad(last[j], first[j])
                    carry[j] = cx * (vfirst[j] - vlast[j]) * dr
            for i in range(nx):
                ui, vi, ub, li = u[b, c, i], vbar[b, c, i], ubar[b, c, i], lap[b, c, i]
                for j in range(ny):
                    ub[j] = vi[j] + dn * li[j]
                if nx > 1:
                    ip = (i + 1) % nx
                    ue, ve = u[b, c, ip], vbar[b, c, ip]
                    for j in range(ny):
                        dl, dr = _rusanov_grad(ui[j], ue[j])
                        fbar = cx * (ve[j] - vi[j])
                        ub[j] += fbar * dl + carry[j]
                        carry[j] = fbar * dr
                if ny > 1:
                    # Face j+½ sends fbar·∂F/∂u_L to cell j (gl) and fbar·∂F/∂u_R to j+1 (gr).
                    ul, ur, vl, vr = ui[: ny - 1], ui[1:], vi[: ny - 1], vi[1:]
                    for j in range(ny - 1):
                        dl, dr = _rusanov_grad(ul[j], ur[j])
                        fbar = cy * (vr[j] - vl[j])
                        gl[j] = fbar * dl
                        gr[j] = fbar * dr
                    dl, dr = _rusanov_grad(ui[ny - 1], ui[0])
                    fbar = cy * (vi[0] - vi[ny - 1])
                    gl[ny - 1] = fbar * dl
                    gr[ny - 1] = fbar * dr
                    ub[0] += gl[0] + gr[ny - 1]
                    rest, from_west, from_east = ub[1:], gr[: ny - 1], gl[1:]
                    for j in range(ny - 1):
                        rest[j] += from_east[j] + from_west[j]


@njit(cache=True, nogil=True, inline="always")
def _mag(x):
    return x if x.real >= 0 else -x


@njit(cache=True, nogil=True, inline="always")
def _rusanov(a, b):
    ma, mb = _mag(a), _mag(b)
    alpha = ma if ma.real >= mb.real else mb
    return 0.25 * (a * a + b * b) - 0.5 * alpha * (b - a)


@njit(cache=True, nogil=True, inline="always")
def _rusanov_grad(a, b):
    """(∂F/∂u_L, ∂F/∂u_R), with ∂α/∂u on the branch of the larger |u|."""
    ma, mb = _mag(a), _mag(b)
    half_jump = 0.5 * (b - a)
    if ma.real >= mb.real:
        da = 0.5 * (a + ma) - (half_jump if a.real >= 0 else -half_jump)
        db = 0.5 * (b - ma)
    else:
        da = 0.5 * (a + mb)
        db = 0.5 * (b - mb) - (half_jump if b.real >= 0 else -half_jump)
    return da, db


@njit(cache=True, nogil=True)
def _dot(x, y):
    nb, nc, nx, ny = x.shape
    acc = 0.0 * x[0, 0, 0, 0] * y[0, 0, 0, 0]
    for b in range(nb):
        for c in range(nc):
            for i in range(nx):
                for j in range(ny):
                    acc += x[b, c, i, j] * y[b, c, i, j]
    return acc


@njit(cache=True, nogil=True)
def _add(out, x, scale):
    nb, nc, nx, ny = out.shape
    for b in range(nb):
        for c in range(nc):
            for i in range(nx):
                for j in range(ny):
                    out[b, c, i, j] += scale * x[b, c, i, j]


class BurgersScene(Stepper):
    """Periodic box [start, start + L)^d of N cells per axis, viscosity, velocity bound."""

    ndim: int
    default_n: int
    #: smallest cells per axis: the periodic flux and Laplacian loops need a neighbour
    #: distinct from the cell itself (adjoints checked at n = 2 in tests/test_scene_validation.py)
    min_points = 2
    param_names = ("nu",)

    def __init__(
        self,
        n: int | None = None,
        length: float = 2.0,
        start: float = -1.0,
        nu: float = 0.05,
        dt: float | None = None,
        substeps: int | None = 1,
        amplitude: float = 1.0,
        umax: float | None = None,
        cfl: float = 0.5,
    ):
        """``n`` defaults to ``default_n``; ``amplitude`` scales :meth:`random_state`; ``umax``
        (default: ``amplitude``) bounds |u| for the stability check. ``dt=None`` takes ``cfl``
        times the largest stable Δt; ``substeps=None`` the fewest sub-steps that make ``dt``
        stable."""
        name = self.name
        n = self.default_n if n is None else validate.integer(name, "n", n, ge=self.min_points)
        self.grid_shape = (n,) * self.ndim
        self.channels = 1
        self.control_shape = (1, *self.grid_shape)
        self.length = validate.number(name, "length", length, gt=0)
        self.start = validate.number(name, "start", start)
        self.h = self.length / n
        self.amplitude = validate.number(name, "amplitude", amplitude, gt=0)
        self.umax = (
            self.amplitude if umax is None
            else validate.number(name, "umax", umax, gt=0, why="the bound on |u|")
        )
        nu = validate.number(name, "nu", nu, ge=0)
        self.param_values = (nu,)
        if substeps is not None:
            substeps = validate.integer(name, "substeps", substeps, ge=1)
        cfl = validate.number(
            name, "cfl", cfl, gt=0, le=1, why="dt=None takes cfl × the largest stable Δt"
        )
        if dt is None:
            self.substeps = 1 if substeps is None else substeps
            self.dt = cfl * self.substeps / self._rate(nu)
        else:
            self.dt = validate.number(name, "dt", dt, gt=0)
            fewest = max(1, math.ceil(self.dt * self._rate(nu)))
            if substeps is None and fewest > MAX_SUBSTEPS:
                raise ValueError(
                    f"{name}: dt = {self.dt:g} needs {fewest:,} substeps to stay stable (the "
                    f"largest stable substep is {1 / self._rate(nu):.4g}), more than the "
                    f"{MAX_SUBSTEPS:,} chosen unasked; choose a smaller dt, or pass substeps")
            self.substeps = fewest if substeps is None else substeps
        self.check_params(np.array(self.param_values))

    def _rate(self, nu: float) -> float:
        """1/τ_max: u_max Σ_d 1/h_d + 2ν Σ_d 1/h_d²."""
        return self.ndim * (self.umax / self.h + 2 * nu / self.h**2)

    def check_params(self, p: np.ndarray) -> None:
        validate.number(self.name, "nu", p[0], ge=0, why="the viscosity ν")
        tau = self.dt / self.substeps
        number = tau * self._rate(p[0])
        if number > 1 + 1e-12:
            raise ValueError(
                f"{self.name}: τ (u_max Σ_d 1/h_d + 2ν Σ_d 1/h_d²) = {number:.4g} exceeds the "
                f"stability limit 1 (τ = Δt/substeps, u_max = {self.umax:g}, ν = {p[0]:.4g}); "
                f"the largest stable Δt is {self.substeps / self._rate(p[0]):.6g} with "
                f"substeps={self.substeps} (or use substeps ≥ {math.ceil(number * self.substeps)})"
            )

    def nodes(self) -> np.ndarray:
        """Cell centres x_i = start + (i + ½) h along each axis."""
        return self.start + self.h * (np.arange(self.grid_shape[0]) + 0.5)

    def random_state(
        self, rng: np.random.Generator, batch: int = 1, dtype: Any = np.float64
    ) -> np.ndarray:
        """Smooth random field, values in ±[0.3, 0.8]·amplitude, sign alternating over the batch.

        A definite sign per field keeps sonic points (u_L = −u_R, where the Rusanov flux is not
        differentiable) out of gradient checks; both signs are covered over a batch of two.
        """
        u = smooth_noise(rng, self.state_shape(batch), self.ndim)
        axes = tuple(range(2, 2 + self.ndim))
        u /= np.max(np.abs(u), axis=axes, keepdims=True)
        sign = np.where(np.arange(batch) % 2 == 0, 1.0, -1.0).reshape(-1, 1, *(1,) * self.ndim)
        return (sign * self.amplitude * (0.55 + 0.25 * u)).astype(dtype)

    def random_controls(
        self, rng: np.random.Generator, n: int, batch: int = 1, dtype: Any = np.float64
    ) -> np.ndarray:
        """Random controls that move u by at most 0.2·amplitude over the n steps.

        With :meth:`random_state` (0.3 ≤ |u|/amplitude ≤ 0.8) this keeps |u| ≤ u_max, the bound
        the stability check relies on, and the sign of u. Order-one controls would not.
        """
        shape = (n, batch, *self.control_shape)
        # A part common to all steps adds up coherently, so the controls move the state by more
        # than a random walk of n tiny kicks would.
        common = rng.uniform(-1.0, 1.0, (1, batch, *self.control_shape))
        scale = 0.1 * self.amplitude / (max(n, 1) * self.dt)
        return (scale * (common + rng.uniform(-1.0, 1.0, shape))).astype(dtype)

    def _view(self, a: np.ndarray) -> np.ndarray:
        if self.ndim == 2:
            return a
        return a.reshape(*a.shape[:-1], 1, a.shape[-1])

    def _args(self) -> tuple:
        # In the (1, N) view of a 1D grid its axis is the second one.
        inv_h, inv_h2 = 1.0 / self.h, 1.0 / self.h**2
        if self.ndim == 1:
            return (self.dt, self.substeps, 0.0, inv_h, 0.0, inv_h2)
        return (self.dt, self.substeps, inv_h, inv_h, inv_h2, inv_h2)

    def _forward(self, states, n, ctrl, p):
        burgers_forward(self._view(states), n, self._view(ctrl), p, *self._args())

    def _adjoint(self, states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p):
        burgers_adjoint(
            self._view(states), self._view(ctrl), p, self._view(cot), cmap, self._view(ubar),
            self._view(cbar), pbar, want_p, *self._args(),
        )


@register
class BurgersRusanov1D(BurgersScene):
    name = "burgers1d-rusanov"
    ndim = 1
    default_n = 32
    space = {
        "n": Range(16, 48, integer=True),
        "nu": Range(0.05, 0.2),
        "amplitude": Range(0.5, 1.5),
        "substeps": Choice((1, 2, 3)),
        "cfl": Range(0.3, 0.9),
    }


@register
class BurgersRusanov2D(BurgersScene):
    name = "burgers2d-rusanov"
    ndim = 2
    default_n = 16
    space = {
        "n": Range(8, 20, integer=True),
        "nu": Range(0.05, 0.2),
        "amplitude": Range(0.5, 1.5),
        "substeps": Choice((1, 2, 3)),
        "cfl": Range(0.3, 0.9),
    }
