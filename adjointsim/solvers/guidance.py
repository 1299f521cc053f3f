"""Guidance by repulsion: drivers herd evaders in 2D, explicit Euler (Schnell & Thuerey 2024).

Continuous, with d = ε + |x_i − x_j| (ε = 0.1) for every pair and the reference code's
constants as defaults (a = 15 repulsion, γ_d = 1 and γ_e = 4 damping, k_d = k_e = 0.2):
  drivers   ẍ_i = F_i − γ_d ẋ_i + k_d Σ_{drivers j≠i} (x_i − x_j)/d²,
            F_i = c_i1 (x_i − C) + c_i2 rot90(x_i − C),  C = Σ_evaders x_e (the sum, as coded),
  evaders   ẍ_e = a Σ_drivers (x_e − x_d)/d² − γ_e ẋ_e
                  + k_e Σ_{evaders j≠e} ((0.5/d − 1)/d)(x_e − x_j),
i.e. drivers repel each other and the evaders, evaders keep a spacing near 0.5 among themselves,
and each driver's two control coefficients per step come from the controller.
Discrete (explicit Euler): x' = x + Δt ẋ, ẋ' = ẋ + Δt ẍ(x, ẋ, c), Δt = T/steps = 4/60.
State (B, 4, D + E): channels (x, y, ẋ, ẏ), agents the D drivers then the E evaders. Control
(B, D, 2). Differentiable parameters: ``repulsion`` (a), ``driver_damping`` (γ_d),
``evader_damping`` (γ_e), ``driver_spacing`` (k_d), ``evader_cohesion`` (k_e).
Adjoint: every pair force is φ(ρ) r with r = x_i − x_j, ρ = |r|, so its transpose Jacobian
maps a cotangent f̄ to r̄ = φ f̄ + φ'(ρ) (r·f̄) r/ρ (added to x̄_i, subtracted from x̄_j), with
φ = k/d² (φ' = −2k/d³) or φ = k(0.5/d − 1)/d (φ' = k(d − 1)/d³); the control force is linear in
c and in x_i − C. Choices: rot90(v) = (−v_y, v_x) (counter-clockwise, the paper does not say);
the evader-driver term reads 15·Σ(−1/d²)(x_d − x_e) = 15·Σ(x_e − x_d)/d², a repulsion; the
derivative of |r| is undefined where two agents coincide (never met from the task's states).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

from .. import validate
from ..registry import register
from ..stepper import Range, Stepper

_EPS = 0.1
_SPACING = 0.5


@njit(cache=True, nogil=True, inline="always")
def _pair(rx, ry, k, cohesive):
    """φ(ρ) and φ'(ρ)/ρ of the pair force φ(ρ) r."""
    rho = np.sqrt(rx * rx + ry * ry)
    d = _EPS + rho
    if cohesive:
        return k * (_SPACING / d - 1.0) / d, k * (d - 2.0 * _SPACING) / (d * d * d) / rho
    return k / (d * d), -2.0 * k / (d * d * d) / rho


@njit(cache=True, nogil=True)
def _accelerations(u, c, nd, p, acc):
    """acc (2, D + E) from one state u (4, D + E) and controls c (D, 2) (or empty)."""
    a, gd, ge, kd, ke = p[0], p[1], p[2], p[3], p[4]
    na = u.shape[1]
    cx = 0.0 * u[0, 0]
    cy = 0.0 * u[0, 0]
    for e in range(nd, na):
        cx += u[0, e]
        cy += u[1, e]
    for i in range(nd):
        ax = -gd * u[2, i]
        ay = -gd * u[3, i]
        if c.shape[0] > 0:
            wx = u[0, i] - cx
            wy = u[1, i] - cy
            ax += c[i, 0] * wx - c[i, 1] * wy
            ay += c[i, 0] * wy + c[i, 1] * wx
        for j in range(nd):
            if j != i:
                rx = u[0, i] - u[0, j]
                ry = u[1, i] - u[1, j]
                phi, _ = _pair(rx, ry, kd, False)
                ax += phi * rx
                ay += phi * ry
        acc[0, i] = ax
        acc[1, i] = ay
    for e in range(nd, na):
        ax = -ge * u[2, e]
        ay = -ge * u[3, e]
        for d in range(nd):
            rx = u[0, e] - u[0, d]
            ry = u[1, e] - u[1, d]
            phi, _ = _pair(rx, ry, a, False)
            ax += phi * rx
            ay += phi * ry
        for j in range(nd, na):
            if j != e:
                rx = u[0, e] - u[0, j]
                ry = u[1, e] - u[1, j]
                phi, _ = _pair(rx, ry, ke, True)
                ax += phi * rx
                ay += phi * ry
        acc[0, e] = ax
        acc[1, e] = ay


@njit(cache=True, nogil=True)
def guidance_forward(states, n, ctrl, p, dt, nd):
    s = states.shape[0]
    acc = np.empty((2, states.shape[3]), states.dtype)
    empty = np.empty((0, 2), states.dtype)
    for k in range(n):
        src = states[k % s]
        dst = states[(k + 1) % s]
        for b in range(src.shape[0]):
            c = ctrl[k, b] if ctrl.shape[0] > 0 else empty
            _accelerations(src[b], c, nd, p, acc)
            for i in range(src.shape[2]):
                for x in range(2):
                    v = src[b, 2 + x, i]
                    dst[b, x, i] = src[b, x, i] + dt * v
                    dst[b, 2 + x, i] = v + dt * acc[x, i]


@njit(cache=True, nogil=True, inline="always")
def _pair_adjoint(u, ubar, i, j, k, cohesive, fx, fy):
    """Transpose of the pair force φ(ρ) r, r = x_i − x_j, applied to (fx, fy); returns
    (r·f̄) φ / k, the cotangent of the strength k."""
    rx = u[0, i] - u[0, j]
    ry = u[1, i] - u[1, j]
    # The unit-strength force, so that k = 0 (a switched-off force) still has a cotangent.
    phi1, dphi1 = _pair(rx, ry, 1.0, cohesive)
    rf = rx * fx + ry * fy
    gx = k * (phi1 * fx + dphi1 * rf * rx)
    gy = k * (phi1 * fy + dphi1 * rf * ry)
    ubar[0, i] += gx
    ubar[1, i] += gy
    ubar[0, j] -= gx
    ubar[1, j] -= gy
    return rf * phi1


@njit(cache=True, nogil=True)
def _step_adjoint(u, c, cb, nd, p, dt, ubar, vbar, pbar, want_p):
    """u (4, A): the step's input; ubar (4, A): on entry the output's cotangent, on exit the
    input's. cb (D, 2) receives the controls' cotangent (when not empty)."""
    a, gd, ge, kd, ke = p[0], p[1], p[2], p[3], p[4]
    na = u.shape[1]
    # vbar = Δt · cotangent of the output velocity = cotangent of the acceleration
    for i in range(na):
        for x in range(2):
            vbar[x, i] = dt * ubar[2 + x, i]
            ubar[2 + x, i] += dt * ubar[x, i]
    cx = 0.0 * u[0, 0]
    cy = 0.0 * u[0, 0]
    for e in range(nd, na):
        cx += u[0, e]
        cy += u[1, e]
    sx = 0.0 * cx
    sy = 0.0 * cy
    pa = 0.0 * cx
    pgd = 0.0 * cx
    pge = 0.0 * cx
    pkd = 0.0 * cx
    pke = 0.0 * cx
    for i in range(nd):
        fx = vbar[0, i]
        fy = vbar[1, i]
        pgd -= fx * u[2, i] + fy * u[3, i]
        ubar[2, i] -= gd * fx
        ubar[3, i] -= gd * fy
        if c.shape[0] > 0:
            wx = u[0, i] - cx
            wy = u[1, i] - cy
            if cb.shape[0] > 0:
                cb[i, 0] = fx * wx + fy * wy
                cb[i, 1] = -fx * wy + fy * wx
            # F = c0 w + c1 rot90(w): wbar = c0 f + c1 rot90ᵀ f, rot90ᵀ (fx, fy) = (fy, −fx)
            gx = c[i, 0] * fx + c[i, 1] * fy
            gy = c[i, 0] * fy - c[i, 1] * fx
            ubar[0, i] += gx
            ubar[1, i] += gy
            sx += gx
            sy += gy
        for j in range(nd):
            if j != i:
                pkd += _pair_adjoint(u, ubar, i, j, kd, False, fx, fy)
    for e in range(nd, na):
        fx = vbar[0, e]
        fy = vbar[1, e]
        pge -= fx * u[2, e] + fy * u[3, e]
        ubar[2, e] -= ge * fx
        ubar[3, e] -= ge * fy
        # C = Σ evaders: every evader takes −Σ_i w̄_i
        ubar[0, e] -= sx
        ubar[1, e] -= sy
        for d in range(nd):
            pa += _pair_adjoint(u, ubar, e, d, a, False, fx, fy)
        for j in range(nd, na):
            if j != e:
                pke += _pair_adjoint(u, ubar, e, j, ke, True, fx, fy)
    if want_p:
        pbar[0] += pa
        pbar[1] += pgd
        pbar[2] += pge
        pbar[3] += pkd
        pbar[4] += pke


@njit(cache=True, nogil=True)
def guidance_adjoint(states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p, dt, nd):
    vbar = np.empty((2, ubar.shape[2]), ubar.dtype)
    empty = np.empty((0, 2), ubar.dtype)
    for k in range(states.shape[0] - 1, -1, -1):
        for b in range(ubar.shape[0]):
            c = ctrl[k, b] if ctrl.shape[0] > 0 else empty
            cb = cbar[k, b] if cbar.shape[0] > 0 else empty
            _step_adjoint(states[k, b], c, cb, nd, p, dt, ubar[b], vbar, pbar, want_p)
        if cmap[k] >= 0:
            ubar += cot[cmap[k]]


@register
class Guidance(Stepper):
    """``drivers`` agents steered by two coefficients each herd ``evaders`` to the origin."""

    name = "guidance"
    point_cost = 120.0  # every agent feels every other
    space = {
        "drivers": Range(1, 3, integer=True),
        "evaders": Range(1, 5, integer=True),
        "dt": Range(0.02, 0.0667),
        "repulsion": Range(5.0, 20.0),
        "driver_damping": Range(0.5, 2.0),
        "evader_damping": Range(2.0, 6.0),
        "driver_spacing": Range(0.1, 0.5),
        "evader_cohesion": Range(0.1, 0.5),
    }

    def __init__(
        self,
        drivers: int = 2,
        evaders: int = 4,
        dt: float = 4.0 / 60.0,
        repulsion: float = 15.0,
        driver_damping: float = 1.0,
        evader_damping: float = 4.0,
        driver_spacing: float = 0.2,
        evader_cohesion: float = 0.2,
    ):
        self.drivers = validate.integer(self.name, "drivers", drivers, ge=1)
        self.evaders = validate.integer(self.name, "evaders", evaders, ge=1)
        dt = validate.number(self.name, "dt", dt, gt=0)
        for arg, v in (("repulsion", repulsion), ("driver_damping", driver_damping),
                       ("evader_damping", evader_damping), ("driver_spacing", driver_spacing),
                       ("evader_cohesion", evader_cohesion)):
            validate.number(self.name, arg, v, ge=0)
        self.grid_shape = (self.drivers + self.evaders,)
        self.channels = 4
        self.control_shape = (self.drivers, 2)
        self.dt = float(dt)
        self.param_names = ("repulsion", "driver_damping", "evader_damping", "driver_spacing",
                            "evader_cohesion")
        self.param_values = tuple(float(v) for v in (repulsion, driver_damping, evader_damping,
                                                       driver_spacing, evader_cohesion))
        self.check_params(np.array(self.param_values))

    def check_params(self, p: np.ndarray) -> None:
        if p.min() < 0:
            bad = ", ".join(f"{k} = {v!r}" for k, v in zip(self.param_names, p.tolist()) if v < 0)
            raise ValueError(f"{self.name}: parameters must be ≥ 0, got {bad}")

    @classmethod
    def benchmark_scene(cls, n: int) -> Stepper:
        # A size knob: any integer below 1 still gives one evader.
        return cls(evaders=max(1, validate.integer(cls.name, "n", n)))

    def random_state(
        self, rng: np.random.Generator, batch: int = 1, dtype: Any = np.float64
    ) -> np.ndarray:
        """The task's initial states: drivers uniform in the annulus 3 ≤ r ≤ 4, evaders around
        one centre uniform in the annulus 1 ≤ r ≤ 2 with U[−0.5, 0.5]² offsets; at rest."""
        u = np.zeros(self.state_shape(batch))
        u[:, :2, : self.drivers] = _annulus(rng, 3.0, 4.0, (batch, self.drivers))
        centre = _annulus(rng, 1.0, 2.0, (batch, 1))
        offsets = rng.uniform(-0.5, 0.5, (batch, 2, self.evaders))
        u[:, :2, self.drivers :] = centre + offsets
        return u.astype(dtype)

    def _forward(self, states, n, ctrl, p):
        guidance_forward(states, n, ctrl, p, self.dt, self.drivers)

    def _adjoint(self, states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p):
        guidance_adjoint(states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p, self.dt,
                         self.drivers)


def _annulus(rng: np.random.Generator, r0: float, r1: float, shape: tuple) -> np.ndarray:
    """Points uniform in area in r0 ≤ r ≤ r1, shape (*shape[:1], 2, *shape[1:])."""
    r = np.sqrt(rng.uniform(r0**2, r1**2, shape))
    phi = rng.uniform(0.0, 2.0 * np.pi, shape)
    return np.stack([r * np.cos(phi), r * np.sin(phi)], axis=1)
