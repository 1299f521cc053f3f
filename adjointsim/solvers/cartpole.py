"""Cart-pole with several poles on one cart, semi-implicit Euler (Schnell & Thuerey 2024).

Continuous (the reference code's multi-pole extension of the classic cart-pole; θ = 0 is
upright, θ = π hanging): per pole i = 1..P, with force F on the cart,
    A_i = (F + m l sinθ_i θ̇_i²)/M,
    θ̈_i = (g sinθ_i − cosθ_i A_i) / (l (4/3 − m cos²θ_i / M)),
    ẍ   = (F + m l Σ_i (sinθ_i θ̇_i² − θ̈_i cosθ_i)) / M,
g gravity, m pole mass, M total mass (kept at its value whatever P, as in the reference code),
l the pole's half length. Discrete (semi-implicit Euler, velocities first):
    θ̇_i' = θ̇_i + Δt θ̈_i,  ẋ' = ẋ + Δt ẍ,  θ_i' = θ_i + Δt θ̇_i',  x' = x + Δt ẋ'.
State (B, 2, 1 + P): channel 0 the positions (x, θ_1..θ_P), channel 1 their velocities; the
control is the force, shape (B, 1), one per step. Differentiable parameters: ``gravity``,
``pole_mass``, ``total_mass``, ``length``.
Adjoint: the transpose of the step's Jacobian, written out by the chain rule through the
intermediate quantities (A_i, the denominator D_i, θ̈_i, ẍ) in reverse order; see
``_step_adjoint``. Choices: the paper's equations are taken literally (M does not grow with
the number of poles; the poles interact only through the cart).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

from .. import validate
from ..registry import register
from ..stepper import Range, Stepper


@njit(cache=True, nogil=True, inline="always")
def _accelerations(q, w, force, p, alpha):
    """θ̈ into ``alpha``; returns ẍ. q, w: positions and velocities (1 + P,)."""
    g, m, mt, ll = p[0], p[1], p[2], p[3]
    total = 0.0 * q[0]
    for i in range(1, q.shape[0]):
        s = np.sin(q[i])
        c = np.cos(q[i])
        a = (force + m * ll * s * w[i] * w[i]) / mt
        alpha[i] = (g * s - c * a) / (ll * (4.0 / 3.0 - m * c * c / mt))
        total += s * w[i] * w[i] - alpha[i] * c
    return (force + m * ll * total) / mt


@njit(cache=True, nogil=True)
def cartpole_forward(states, n, ctrl, p, dt):
    s = states.shape[0]
    alpha = np.empty(states.shape[3], states.dtype)
    for k in range(n):
        src = states[k % s]
        dst = states[(k + 1) % s]
        for b in range(src.shape[0]):
            force = ctrl[k, b, 0] if ctrl.shape[0] > 0 else 0.0 * src[b, 0, 0]
            acc = _accelerations(src[b, 0], src[b, 1], force, p, alpha)
            alpha[0] = acc
            for i in range(src.shape[2]):
                w = src[b, 1, i] + dt * alpha[i]
                dst[b, 1, i] = w
                dst[b, 0, i] = src[b, 0, i] + dt * w


@njit(cache=True, nogil=True)
def _step_adjoint(q, w, force, p, dt, qbar, wbar, pbar, want_p, alpha):
    """Replace (qbar, wbar), the cotangents of the step's output, by those of its input;
    returns the force's cotangent and adds the parameters' to ``pbar``."""
    g, m, mt, ll = p[0], p[1], p[2], p[3]
    acc = _accelerations(q, w, force, p, alpha)
    # positions: q' = q + dt w'  ->  w'bar += dt q'bar (q'bar passes to q unchanged)
    for i in range(q.shape[0]):
        wbar[i] += dt * qbar[i]
    # velocities: w' = w + dt acc  ->  accbar = dt w'bar (w'bar passes to w unchanged)
    abar = dt * wbar[0]
    fbar = abar / mt
    # ẍ = (F + m l Σ)/M
    lam = abar * m * ll / mt
    total = 0.0 * abar
    gbar = 0.0 * abar
    mbar = 0.0 * abar
    mtbar = -abar * acc / mt
    lbar = 0.0 * abar
    for i in range(1, q.shape[0]):
        s = np.sin(q[i])
        c = np.cos(q[i])
        wi = w[i]
        a = (force + m * ll * s * wi * wi) / mt
        den = ll * (4.0 / 3.0 - m * c * c / mt)
        num = g * s - c * a
        al = num / den
        total += s * wi * wi - al * c
        # Σ term: s w² − θ̈ c
        sbar = lam * wi * wi
        cbar = -lam * al
        wb = lam * 2.0 * s * wi
        albar = -lam * c + dt * wbar[i]
        # θ̈ = num / den
        numbar = albar / den
        denbar = -albar * al / den
        # num = g s − c a
        gbar += numbar * s
        sbar += numbar * g
        cbar += -numbar * a
        abar_i = -numbar * c
        # den = l (4/3 − m c²/M)
        lbar += denbar * (4.0 / 3.0 - m * c * c / mt)
        mbar += -denbar * ll * c * c / mt
        mtbar += denbar * ll * m * c * c / (mt * mt)
        cbar += -denbar * ll * 2.0 * m * c / mt
        # a = (F + m l s w²)/M
        fbar += abar_i / mt
        mbar += abar_i * ll * s * wi * wi / mt
        lbar += abar_i * m * s * wi * wi / mt
        sbar += abar_i * m * ll * wi * wi / mt
        wb += abar_i * m * ll * s * 2.0 * wi / mt
        mtbar += -abar_i * a / mt
        qbar[i] += sbar * c - cbar * s
        wbar[i] += wb
    if want_p:
        pbar[0] += gbar
        pbar[1] += mbar + abar * ll * total / mt
        pbar[2] += mtbar
        pbar[3] += lbar + abar * m * total / mt
    return fbar


@njit(cache=True, nogil=True)
def cartpole_adjoint(states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p, dt):
    alpha = np.empty(ubar.shape[2], ubar.dtype)
    for k in range(states.shape[0] - 1, -1, -1):
        for b in range(ubar.shape[0]):
            force = ctrl[k, b, 0] if ctrl.shape[0] > 0 else 0.0 * ubar[b, 0, 0]
            fb = _step_adjoint(states[k, b, 0], states[k, b, 1], force, p, dt,
                               ubar[b, 0], ubar[b, 1], pbar, want_p, alpha)
            if cbar.shape[0] > 0:
                cbar[k, b, 0] = fb
        if cmap[k] >= 0:
            ubar += cot[cmap[k]]


@register
class CartPole(Stepper):
    """``poles`` (1..4) poles on one cart pushed by a force; the paper's constants by default."""

    name = "cartpole"
    point_cost = 9.0
    space = {
        "poles": Range(1, 4, integer=True),
        "dt": Range(0.005, 0.02),
        "gravity": Range(5.0, 15.0),
        "pole_mass": Range(0.05, 0.3),
        "total_mass": Range(0.8, 2.0),
        "length": Range(0.3, 1.0),
    }

    def __init__(
        self,
        poles: int = 2,
        dt: float = 0.01,
        gravity: float = 9.8,
        pole_mass: float = 0.1,
        total_mass: float = 1.1,
        length: float = 0.5,
    ):
        self.poles = validate.integer(self.name, "poles", poles, ge=1, le=4)
        dt = validate.number(self.name, "dt", dt, gt=0)
        gravity = validate.number(self.name, "gravity", gravity)
        for arg, v in (("pole_mass", pole_mass), ("total_mass", total_mass), ("length", length)):
            validate.number(self.name, arg, v, gt=0)
        self.grid_shape = (1 + self.poles,)
        self.channels = 2
        self.control_shape = (1,)
        self.dt = float(dt)
        self.param_names = ("gravity", "pole_mass", "total_mass", "length")
        self.param_values = (float(gravity), float(pole_mass), float(total_mass), float(length))
        self.check_params(np.array(self.param_values))

    def check_params(self, p: np.ndarray) -> None:
        g, m, mt, ll = (float(v) for v in p)
        if not (m > 0 and mt > 0 and ll > 0):
            raise ValueError(
                f"{self.name}: pole_mass, total_mass and length must be > 0, "
                f"not {m}, {mt}, {ll}"
            )
        if not m / mt < 4.0 / 3.0:
            raise ValueError(
                f"{self.name}: pole_mass / total_mass = {m / mt:.3g} must stay below 4/3 "
                "(the pole equation's denominator vanishes there)"
            )

    @classmethod
    def benchmark_scene(cls, n: int) -> Stepper:
        # A size knob, not the pole count: any integer picks the nearest of 1 .. 4 poles.
        return cls(poles=min(4, max(1, validate.integer(cls.name, "n", n))))

    def random_state(
        self, rng: np.random.Generator, batch: int = 1, dtype: Any = np.float64
    ) -> np.ndarray:
        """The task's initial states: x, ẋ, θ̇ ~ U[−1, 1], θ = π + U[−1, 1]·π/6 (hanging)."""
        u = rng.uniform(-1.0, 1.0, self.state_shape(batch))
        u[:, 0, 1:] = np.pi + u[:, 0, 1:] * np.pi / 6
        return u.astype(dtype)

    def _forward(self, states, n, ctrl, p):
        cartpole_forward(states, n, ctrl, p, self.dt)

    def _adjoint(self, states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p):
        cartpole_adjoint(states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p, self.dt)
