"""Diffusion, implicit θ-schemes: backward Euler (θ = 1) and Crank–Nicolson (θ = 1/2).

Continuous:  u_t = ν Δu + a g + c.   f_k = a g + c_k,  X = Δt ν δ²_x / h²,  Y = Δt ν δ²_y / h².
1D:          (I − θX) u_{k+1} = (I + (1−θ)X) u_k + Δt f_k.
2D (ADI):    (I − θX) u* = (I + (1−θ)Y) u_k + θ Δt f_k,
             (I − θY) u_{k+1} = (I + (1−θ)X) u* + (1−θ) Δt f_k,
             i.e. (I − θX)(I − θY) u_{k+1} = (I + (1−θ)X)(I + (1−θ)Y) u_k + Δt f_k (X, Y commute):
             Peaceman–Rachford for θ = 1/2 (second order), the LOD (Yanenko) splitting of
             backward Euler for θ = 1 (first order). Unconditionally stable for ν ≥ 0.
A step is a chain of half steps  dst = T⁻¹ (E src + w Δt f_k)  with T = I − θ Z (tridiagonal along
the implicit axis, Z = X or Y; :mod:`adjointsim.tridiagonal`) and E = I + (1−θ) Z' along the
explicit axis (the same one in 1D, the other one in 2D); w = 1 in 1D, θ and 1 − θ in 2D.
Adjoint, half steps in reverse order:  r̄ = T⁻ᵀ dst̄,  src̄ = Eᵀ r̄ (δ² is symmetric),
             c̄_k += w Δt r̄,  ā += w Δt ⟨r̄, g⟩,
             ν̄ += (1−θ)(Δt/h²) ⟨r̄, δ²' src⟩ + θ (Δt/h²) ⟨r̄, δ² dst⟩   (from T̄ = −r̄ dstᵀ);
the half-step state u*, and u_{k+1} of a segment's last step, are recomputed for ν̄ only."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from numba import njit

from .. import validate
from ..grid import NEUMANN, PERIODIC, ghost
from ..registry import register
from ..tridiagonal import factor, solve, solve_rows, transpose
from .diffusion import DiffusionScene


@njit(cache=True, nogil=True)
def theta_forward(states, n, ctrl, p, dt, theta, inv_hx2, inv_hy2, bc, g):
    s = states.shape[0]
    sc, _, fx, fy = _setup(states[0], p, dt, theta, inv_hx2, inv_hy2, bc, False)
    ustar = np.empty_like(states[0])
    for k in range(n):
        _step(states[k % s], ustar, states[(k + 1) % s], sc, fx, fy, ctrl, k, p, g, bc)


@njit(cache=True, nogil=True)
def theta_adjoint(
    states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p, dt, theta, inv_hx2, inv_hy2, bc, g
):
    m = states.shape[0]
    halves = 2 if ubar.shape[3] > 1 else 1
    sc, dnu, fx, fy = _setup(ubar, p, dt, theta, inv_hx2, inv_hy2, bc, False)
    _, _, fxt, fyt = _setup(ubar, p, dt, theta, inv_hx2, inv_hy2, bc, True)
    cur, other = ubar, np.empty_like(ubar)
    swapped = False
    ustar, last, lap = np.empty_like(ubar), np.empty_like(ubar), np.empty_like(ubar)
    for k in range(m - 1, -1, -1):
        u = states[k]
        unext = last
        if want_p:
            # ν̄ needs every half step's input and output.
            if k + 1 < m:
                unext = states[k + 1]
                if halves == 2:
                    _half_step(u, ustar, 0, sc, fx, ctrl, k, p, g, bc)
            else:
                _step(u, ustar, last, sc, fx, fy, ctrl, k, p, g, bc)
        for h in range(halves - 1, -1, -1):
            src = u if h == 0 else ustar
            dst = unext if h == halves - 1 else ustar
            ft = fxt if h == 0 else fyt
            if _half_step_adjoint(cur, other, lap, src, dst, h, halves, sc, dnu, ft, cbar, k,
                                  pbar, want_p, g, bc):
                cur, other, swapped = other, cur, not swapped
        if cmap[k] >= 0:
            cur += cot[cmap[k]]
    if swapped:
        ubar[:] = cur


@njit(cache=True, nogil=True)
def _setup(like, p, dt, theta, inv_hx2, inv_hy2, bc, adjoint):
    """Multipliers and factorised implicit matrices of the x and y half steps.

    sc = [θΔtν/hx², θΔtν/hy², (1−θ)Δtν/hx², (1−θ)Δtν/hy², w_0 Δt, w_1 Δt] with the source
    weights w = (1,) in 1D and (θ, 1−θ) in 2D; dnu = ∂sc[:4]/∂ν. The adjoint factorises the
    transposed matrices. Everything is float64 (complex128 under complex step) whatever the
    state's precision: float32 coefficients would perturb the operator itself, e.g. the column
    sums that conserve the mean, by O(ε) at every step, a drift far above float32 round-off.
    """
    nx, ny = like.shape[2], like.shape[3]
    two_d = ny > 1
    dnu = np.array([theta * dt * inv_hx2, theta * dt * inv_hy2,
                    (1 - theta) * dt * inv_hx2, (1 - theta) * dt * inv_hy2])
    sc = np.zeros(6) + _zero64(like)
    sc[:4] = dnu * p[0]
    sc[4] = theta * dt if two_d else dt
    sc[5] = (1 - theta) * dt
    cx, cy = _matrix(sc, 0, bc), _matrix(sc, 1, bc)
    if adjoint:
        cx, cy = transpose(cx), transpose(cy)
    fx = factor(cx, nx, bc == PERIODIC)
    fy = factor(cy, ny, bc == PERIODIC) if two_d else fx
    return sc, dnu, fx, fy


@njit(cache=True, nogil=True)
def _matrix(sc, axis, bc):
    """Coefficients of I − s δ², s = sc[axis] (see :mod:`adjointsim.tridiagonal`)."""
    s = sc[axis]
    coef = np.empty(5, dtype=sc.dtype)
    coef[0] = -s
    coef[1] = 1 + 2 * s
    coef[2] = -s
    # The Neumann ghost mirrors its neighbour; Dirichlet ghosts vanish, periodic ones wrap.
    coef[3] = 1 + s if bc == NEUMANN else 1 + 2 * s
    coef[4] = coef[3]
    return coef


@njit(cache=True, nogil=True)
def _step(u, ustar, v, sc, fx, fy, ctrl, k, p, g, bc):
    """u → v; in 2D the half-step state u* is left in ``ustar``."""
    if v.shape[3] > 1:
        _half_step(u, ustar, 0, sc, fx, ctrl, k, p, g, bc)
        _half_step(ustar, v, 1, sc, fy, ctrl, k, p, g, bc)
    else:
        _half_step(u, v, 0, sc, fx, ctrl, k, p, g, bc)


@njit(cache=True, nogil=True, inline="always")
def _explicit_axis(h, halves):
    # 1D: explicit and implicit along x; 2D half step h: implicit along h, explicit along 1 − h.
    return 1 - h if halves == 2 else 0


@njit(cache=True, nogil=True)
def _half_step(src, dst, h, sc, f, ctrl, k, p, g, bc):
    """Half step h: dst = T⁻¹ (E src + w_h Δt (a g + c_k)), T implicit along axis h."""
    e = _explicit_axis(h, 2 if src.shape[3] > 1 else 1)
    _explicit(src, dst, 1.0, sc[2 + e], e, bc)
    w = sc[4 + h]
    if w != 0:
        if g.shape[0] > 0:
            wa = w * p[1]
            for b in range(dst.shape[0]):
                _add_scaled(dst[b], wa, g)
        if ctrl.shape[0] > 0:
            _add_scaled(dst, w, ctrl[k])
    _solve_along(f, dst, h)


@njit(cache=True, nogil=True)
def _half_step_adjoint(r, out, lap, src, dst, h, halves, sc, dnu, ft, cbar, k, pbar, want_p, g,
                       bc):
    """Reverse half step h: r ← T⁻ᵀ r, then Eᵀ r goes to ``out`` (returns True) or, when
    E = I, stays in ``r`` (returns False). ``lap`` is scratch space."""
    e = _explicit_axis(h, halves)
    w = sc[4 + h]
    _solve_along(ft, r, h)
    if want_p:
        _explicit(dst, lap, 0.0, 1.0, h, bc)
        pbar[0] += dnu[h] * _dot(r, lap)
        if dnu[2 + e] != 0:
            _explicit(src, lap, 0.0, 1.0, e, bc)
            pbar[0] += dnu[2 + e] * _dot(r, lap)
        if g.shape[0] > 0:
            for b in range(r.shape[0]):
                pbar[1] += w * _dot(r[b], g)
    if cbar.shape[0] > 0:
        if h == halves - 1:
            cbar[k] = 0
        _add_scaled(cbar[k], w, r)
    if sc[2 + e] == 0:
        return False
    _explicit(r, out, 1.0, sc[2 + e], e, bc)
    return True


@njit(cache=True, nogil=True)
def _explicit(src, out, a, s, axis, bc):
    """out = a src + s δ² src along ``axis`` (0: x, 1: y) of (B, C, Nx, Ny) arrays."""
    nb, nc, nx, ny = src.shape
    if s == 0:
        _copy_scaled(src, out, a)
    elif ny == 1:
        # 1D grids run as rows, so that the inner loops go along the grid.
        _explicit_rows(src.reshape(1, nb * nc, nx), out.reshape(1, nb * nc, nx), a, s, bc)
    elif axis == 0:
        _explicit_middle(src.reshape(nb * nc, nx, ny), out.reshape(nb * nc, nx, ny), a, s, bc)
    else:
        _explicit_rows(src.reshape(nb * nc, nx, ny), out.reshape(nb * nc, nx, ny), a, s, bc)


@njit(cache=True, nogil=True)
def _explicit_rows(src, out, a, s, bc):
    """Along the last axis of (L, M, n) arrays."""
    nl, nm, n = src.shape
    for lo in range(nl):
        for m in range(nm):
            u, o = src[lo, m], out[lo, m]
            o[0] = a * u[0] + s * (ghost(u[0], u[n - 1], bc) - 2 * u[0] + u[1])
            for j in range(1, n - 1):
                o[j] = a * u[j] + s * (u[j - 1] - 2 * u[j] + u[j + 1])
            o[n - 1] = a * u[n - 1] + s * (u[n - 2] - 2 * u[n - 1] + ghost(u[n - 1], u[0], bc))


@njit(cache=True, nogil=True)
def _explicit_middle(src, out, a, s, bc):
    """Along the middle axis of (L, n, M) arrays, the M columns side by side."""
    nl, n, nm = src.shape
    for lo in range(nl):
        u, o = src[lo], out[lo]
        for m in range(nm):
            o[0, m] = a * u[0, m] + s * (ghost(u[0, m], u[n - 1, m], bc) - 2 * u[0, m] + u[1, m])
        for i in range(1, n - 1):
            for m in range(nm):
                o[i, m] = a * u[i, m] + s * (u[i - 1, m] - 2 * u[i, m] + u[i + 1, m])
        for m in range(nm):
            o[n - 1, m] = a * u[n - 1, m] + s * (
                u[n - 2, m] - 2 * u[n - 1, m] + ghost(u[n - 1, m], u[0, m], bc)
            )


@njit(cache=True, nogil=True)
def _solve_along(f, u, axis):
    nb, nc, nx, ny = u.shape
    if ny == 1:
        solve_rows(f, u.reshape(1, nb * nc, nx))
    elif axis == 0:
        solve(f, u.reshape(nb * nc, nx, ny))
    else:
        solve_rows(f, u.reshape(nb * nc, nx, ny))


@njit(cache=True, nogil=True)
def _copy_scaled(src, out, a):
    x, o = src.reshape(-1), out.reshape(-1)
    for i in range(o.size):
        o[i] = a * x[i]


@njit(cache=True, nogil=True)
def _add_scaled(out, w, x):
    """out += w x for C-ordered arrays of the same shape."""
    o, y = out.reshape(-1), x.reshape(-1)
    for i in range(o.size):
        o[i] += w * y[i]


@njit(cache=True, nogil=True, inline="always")
def _zero64(x):
    """Zero in float64, or complex128 for complex ``x``."""
    return np.zeros(1, dtype=x.dtype)[0] + 0.0


@njit(cache=True, nogil=True, fastmath={"reassoc"})
def _dot(r, x):
    """Σ r x over C-ordered arrays of the same shape, in float64 (complex128); reassociation
    lets the sum vectorise instead of waiting on one accumulator."""
    a, y = r.reshape(-1), x.reshape(-1)
    acc = _zero64(r)
    for i in range(a.size):
        acc += a[i] * y[i]
    return acc


class _ThetaDiffusion(DiffusionScene):
    theta: ClassVar[float]
    #: the (cyclic) Thomas solver needs two unknowns per axis
    min_points = {"periodic": 2, "dirichlet": 2, "neumann": 2}

    def default_dt(self, nu: float) -> float:
        """Δt = L²/(1000 ν), a fixed fraction of the domain diffusion time, independent of the
        grid (4x the 2D FTCS limit at n = 32, 65x at n = 256); ν = 0 uses the ν = 1 value."""
        return 1e-3 * self.length**2 / (nu if nu > 0 else 1.0)

    def check_params(self, p: np.ndarray) -> None:
        validate.number(
            self.name, "nu", p[0], ge=0,
            why="backward diffusion is ill-posed; for ν ≥ 0 the scheme is unconditionally "
            "stable: the largest stable Δt is unbounded",
        )

    def _args(self, dtype):
        return (self.dt, self.theta, *self.inv_h2, self.bc_code, self.forcing.astype(dtype))

    def _forward(self, states, n, ctrl, p):
        theta_forward(self.as_2d(states), n, self.as_2d(ctrl), p, *self._args(states.dtype))

    def _adjoint(self, states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p):
        theta_adjoint(
            self.as_2d(states), self.as_2d(ctrl), p, self.as_2d(cot), cmap, self.as_2d(ubar),
            self.as_2d(cbar), pbar, want_p, *self._args(ubar.dtype),
        )


@register
class BackwardEulerDiffusion1D(_ThetaDiffusion):
    name = "diffusion1d-backward-euler"
    ndim = 1
    theta = 1.0


@register
class CrankNicolsonDiffusion1D(_ThetaDiffusion):
    name = "diffusion1d-crank-nicolson"
    ndim = 1
    theta = 0.5


@register
class BackwardEulerDiffusion2D(_ThetaDiffusion):
    name = "diffusion2d-backward-euler"
    ndim = 2
    theta = 1.0


@register
class CrankNicolsonDiffusion2D(_ThetaDiffusion):
    name = "diffusion2d-crank-nicolson"
    ndim = 2
    theta = 0.5
