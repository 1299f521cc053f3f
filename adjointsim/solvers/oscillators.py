"""A chain of coupled oscillators with a control force on the last one, RK4 in time.

Continuous (N oscillators in a chain with free ends, neighbours j = i ± 1):
    ẋ_i = v_i,
    v̇_i = −k x_i + Σ_j [ℓ (x_j − x_i) + c (x_j − x_i)³] + g u(t) δ_{i,N−1},
with the differentiable parameters k (``stiffness``), ℓ (``linear_coupling``), c
(``cubic_coupling``) and g (``gain``). Defaults: the nonlinear oscillators of the half-inverse
gradients paper (Schnell, Holl & Thuerey 2022: k = 1, ℓ = 0, c = 1, g = 3, Δt = 0.125);
:meth:`Oscillators.linear_chain` is the PBDL book's linear chain (k = 1, ℓ = 0.2, c = 0, g = 1,
Δt = 0.5).
Discrete: the state is (x, v) as two channels, shape (B, 2, N); classical RK4 with the control
u_k held over the step, y_{k+1} = y_k + Δt/6 (K1 + 2K2 + 2K3 + K4), K_s = F(Z_s, u_k),
Z_1 = y_k, Z_2 = y_k + Δt/2 K1, Z_3 = y_k + Δt/2 K2, Z_4 = y_k + Δt K3.
Adjoint (reverse of the stages, recomputed from the stored y_k): with ȳ_{k+1} given,
    K̄_1 = K̄_4 = Δt/6 ȳ_{k+1},  K̄_2 = K̄_3 = Δt/3 ȳ_{k+1},  ȳ_k = ȳ_{k+1};
    for s = 4 .. 1:  Z̄_s = (∂F/∂Z)ᵀ K̄_s,  ȳ_k += Z̄_s,  K̄_{s−1} += a_s Z̄_s  (a = Δt/2, Δt/2, Δt),
where (∂F/∂Z)ᵀ(w_x, w_v) = (x̄, w_x) with x̄_m = −k w_v,m + Σ_j (ℓ + 3c (x_j − x_m)²)(w_v,j − w_v,m);
ū_k = g Σ_s K̄_s[v_{N−1}] and the parameters collect Σ_s ⟨K̄_s[v], ∂a/∂p⟩ likewise.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

from .. import validate
from ..registry import register
from ..stepper import Range, Stepper

#: RK4's stability interval on the imaginary axis: |λ Δt| ≤ 2√2 for an undamped oscillation
RK4_IMAGINARY_LIMIT = 2.0 * np.sqrt(2.0)


@njit(cache=True, nogil=True)
def _accel(x, u, p, out):
    """out_i = −k x_i + Σ_j [ℓ d + c d³] (d = x_j − x_i) + g u δ_{i,N−1}."""
    n = x.shape[0]
    for i in range(n):
        a = -p[0] * x[i]
        if i > 0:
            d = x[i - 1] - x[i]
            a += p[1] * d + p[2] * d * d * d
        if i < n - 1:
            d = x[i + 1] - x[i]
            a += p[1] * d + p[2] * d * d * d
        out[i] = a
    out[n - 1] += p[3] * u


@njit(cache=True, nogil=True)
def _stages(y, u, p, h, zs, ks):
    """Stage inputs Z_s (zs[s]) and slopes K_s (ks[s]) of one RK4 step from y (2, N)."""
    for s in range(4):
        a = 0.0 if s == 0 else (h if s == 3 else 0.5 * h)
        for c in range(2):
            for i in range(y.shape[1]):
                zs[s, c, i] = y[c, i] + a * ks[s - 1, c, i] if s > 0 else y[c, i]
        for i in range(y.shape[1]):
            ks[s, 0, i] = zs[s, 1, i]
        _accel(zs[s, 0], u, p, ks[s, 1])


@njit(cache=True, nogil=True)
def oscillators_forward(states, n, ctrl, p, h):
    s_ring = states.shape[0]
    nb, _, nx = states.shape[1:]
    zs = np.empty((4, 2, nx), states.dtype)
    ks = np.empty((4, 2, nx), states.dtype)
    for k in range(n):
        for b in range(nb):
            u = ctrl[k, b, 0] if ctrl.shape[0] > 0 else 0.0 * p[0]
            y = states[k % s_ring, b]
            _stages(y, u, p, h, zs, ks)
            out = states[(k + 1) % s_ring, b]
            for c in range(2):
                for i in range(nx):
                    out[c, i] = y[c, i] + h / 6.0 * (
                        ks[0, c, i] + 2.0 * ks[1, c, i] + 2.0 * ks[2, c, i] + ks[3, c, i]
                    )


@njit(cache=True, nogil=True)
def oscillators_adjoint(states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p, h):
    m = states.shape[0]
    nb, _, nx = ubar.shape
    zs = np.empty((4, 2, nx), ubar.dtype)
    ks = np.empty((4, 2, nx), ubar.dtype)
    kbar = np.empty((4, 2, nx), ubar.dtype)
    weights = (h / 6.0, h / 3.0, h / 3.0, h / 6.0)
    for k in range(m - 1, -1, -1):
        for b in range(nb):
            u = ctrl[k, b, 0] if ctrl.shape[0] > 0 else 0.0 * p[0]
            _stages(states[k, b], u, p, h, zs, ks)
            yb = ubar[b]
            for s in range(4):
                for c in range(2):
                    for i in range(nx):
                        kbar[s, c, i] = weights[s] * yb[c, i]
            u_acc = 0.0 * yb[0, 0]
            for s in range(3, -1, -1):
                a = 0.0 if s == 0 else (h if s == 3 else 0.5 * h)
                x = zs[s, 0]
                wv = kbar[s, 1]
                for i in range(nx):
                    # Z̄ = (∂F/∂Z)ᵀ K̄_s: velocity part w_x, position part x̄
                    xb = -p[0] * wv[i]
                    if i > 0:
                        d = x[i - 1] - x[i]
                        xb += (p[1] + 3.0 * p[2] * d * d) * (wv[i - 1] - wv[i])
                    if i < nx - 1:
                        d = x[i + 1] - x[i]
                        xb += (p[1] + 3.0 * p[2] * d * d) * (wv[i + 1] - wv[i])
                    vb = kbar[s, 0, i]
                    yb[0, i] += xb
                    yb[1, i] += vb
                    if s > 0:
                        kbar[s - 1, 0, i] += a * xb
                        kbar[s - 1, 1, i] += a * vb
                u_acc += wv[nx - 1]
                if want_p:
                    for i in range(nx):
                        pbar[0] -= wv[i] * x[i]
                        if i > 0:
                            d = x[i - 1] - x[i]
                            pbar[1] += wv[i] * d
                            pbar[2] += wv[i] * d * d * d
                        if i < nx - 1:
                            d = x[i + 1] - x[i]
                            pbar[1] += wv[i] * d
                            pbar[2] += wv[i] * d * d * d
                    pbar[3] += wv[nx - 1] * u
            if cbar.shape[0] > 0:
                cbar[k, b, 0] = p[3] * u_acc
        if cmap[k] >= 0:
            ubar += cot[cmap[k]]


@register
class Oscillators(Stepper):
    """``n`` oscillators in a chain with linear and cubic nearest-neighbour coupling, a control
    force g·u on the last one, classical RK4. State (B, 2, n): positions, then velocities."""

    name = "oscillators-rk4"
    space = {
        "n": Range(1, 6, integer=True),
        "dt": Range(0.05, 0.25),
        "stiffness": Range(0.5, 2.0),
        "linear_coupling": Range(0.0, 0.5),
        "cubic_coupling": Range(0.0, 1.5),
        "gain": Range(0.5, 3.0),
    }
    control_shape = (1,)
    param_names = ("stiffness", "linear_coupling", "cubic_coupling", "gain")

    def __init__(
        self,
        n: int = 2,
        dt: float = 0.125,
        stiffness: float = 1.0,
        linear_coupling: float = 0.0,
        cubic_coupling: float = 1.0,
        gain: float = 3.0,
    ):
        name = self.name
        self.n = validate.integer(name, "n", n, ge=1, why="the number of oscillators")
        self.grid_shape = (self.n,)
        self.channels = 2
        self.dt = validate.number(name, "dt", dt, gt=0)
        values = (stiffness, linear_coupling, cubic_coupling, gain)
        self.param_values = tuple(
            validate.number(name, k, v) for k, v in zip(self.param_names, values)
        )
        self.check_params(np.array(self.param_values))

    @classmethod
    def linear_chain(cls) -> Oscillators:
        """The PBDL book's HIG demo: 2 masses, linear coupling 0.2, Δt = 0.5, unit gain."""
        return cls(n=2, dt=0.5, stiffness=1.0, linear_coupling=0.2, cubic_coupling=0.0, gain=1.0)

    @classmethod
    def benchmark_scene(cls, n: int) -> Stepper:
        return cls(n=n)

    def check_params(self, p: np.ndarray) -> None:
        # Highest frequency of the linear part: ω² = k + 4ℓ (the chain's shortest mode); the
        # cubic term adds an amplitude-dependent stiffness no static check can bound.
        omega = float(np.sqrt(max(p[0].real, 0.0) + 4.0 * abs(p[1].real)))
        if omega * self.dt > RK4_IMAGINARY_LIMIT:
            raise ValueError(
                f"{self.name}: dt = {self.dt:g} is beyond RK4's stability limit for the linear "
                f"frequency ω = √(k + 4ℓ) = {omega:.4g}: dt must be ≤ 2√2/ω = "
                f"{RK4_IMAGINARY_LIMIT / omega:.4g}"
            )

    def random_state(
        self, rng: np.random.Generator, batch: int = 1, dtype: Any = np.float64
    ) -> np.ndarray:
        """Positions and velocities uniform in [0, 1), as in the HIG paper's data."""
        return rng.random(self.state_shape(batch)).astype(dtype)

    def _forward(self, states, n, ctrl, p):
        oscillators_forward(states, n, ctrl, p, self.dt)

    def _adjoint(self, states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p):
        oscillators_adjoint(states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p, self.dt)
