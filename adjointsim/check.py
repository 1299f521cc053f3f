"""Gradient verification: dot-product test, Taylor test and central finite differences.

For every registered solver and every differentiated input (the initial state, the controls,
each scene parameter) the checker draws a rollout and cotangents w_k on a random subset K of its
states (always including the last one) and compares the hand-written adjoint against:

* a **dot-product test**: ⟨J v, w⟩ against ⟨v, Jᵀ w⟩. ``J v`` is the complex-step derivative
  Im F(x + i h v) / h of the same compiled kernels (exact to round-off, no cancellation), or a
  sixth-order Richardson-extrapolated central difference for solvers that cannot run complex arrays;
* a **Taylor test** on the quadratic functional Φ = Σ_K ⟨w_k, u_k⟩ + ½‖u_k‖²: the remainder
  |Φ(x + εδ) − Φ(x) − ε⟨∇Φ, δ⟩| must fall as ε², i.e. rate ≈ 2 between successive ε;
* a **central finite difference** of Φ along a random direction.

In float32 the adjoint runs in float32 while the references (tangent, Φ) run the float64
kernels from the same float32 inputs: the check then measures the float32 adjoint's own
error, not the round-off of a float32 finite difference.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from . import registry
from .stepper import Stepper

#: thresholds per dtype: dot-product rel. error, Taylor rate, central-FD rel. error
TOLERANCES: dict[str, dict[str, float]] = {
    "float64": {"dot": 1e-10, "rate": 1.9, "fd": 1e-6},
    "float32": {"dot": 1e-4, "rate": 1.8, "fd": 2e-2},
}
_H_COMPLEX_STEP = 1e-100
_EPS_TAYLOR = 1e-3
_EPS_FD = 1e-5


@dataclass(frozen=True)
class CheckResult:
    """One row of ``adjointsim gradcheck``."""

    solver: str
    wrt: str
    dot_rel_err: float
    taylor_rate: float
    fd_rel_err: float
    passed: bool

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def check_stepper(
    stepper: Stepper,
    steps: int = 50,
    dtype: str = "float64",
    seed: int = 0,
    batch: int = 2,
) -> list[CheckResult]:
    """Check the adjoint of ``stepper`` for its state, controls and every scene parameter."""
    if dtype not in TOLERANCES:
        raise ValueError(f"dtype must be one of {sorted(TOLERANCES)}, not {dtype!r}")
    rng = np.random.default_rng(seed)
    real = np.dtype(dtype)
    u0 = stepper.random_state(rng, batch, real)
    ctrl = (
        stepper.random_controls(rng, steps, batch, real)
        if stepper.control_shape is not None
        else stepper._check_controls(None, steps, u0)
    )
    p = np.array(stepper.param_values, dtype=real)
    subset = sorted({steps, *rng.choice(steps + 1, size=min(3, steps + 1), replace=False).tolist()})
    w = {k: stepper.random_state(rng, batch, real) for k in subset}

    inputs: list[tuple[str, np.ndarray, np.ndarray]] = [
        ("state", u0, stepper.random_state(rng, batch, real))
    ]
    if stepper.control_shape is not None:
        # Controls enter as Δt c: scale the direction so the state moves by O(1) per unit ε.
        direction = stepper.random_controls(rng, steps, batch, real) / real.type(stepper.dt)
        inputs.append(("controls", ctrl, direction))
    for i, name in enumerate(stepper.param_names):
        direction = np.zeros_like(p)
        direction[i] = abs(p[i]) if p[i] != 0 else 1.0
        inputs.append((name, p, direction))

    def run(x: np.ndarray, which: str) -> np.ndarray:
        args = {"state": u0, "controls": ctrl, "params": p}
        args["params" if which not in ("state", "controls") else which] = x
        u, c, q = args["state"], args["controls"], args["params"]
        dt = np.result_type(u, c, q, np.float64)
        return stepper._run(u.astype(dt), steps, c.astype(dt), q.astype(dt), keep_all=True)

    def linear(traj: np.ndarray) -> Any:
        return sum(np.sum(w[k] * traj[k]) for k in subset)

    def magnitude(traj: np.ndarray) -> float:
        return float(sum(np.sum(np.abs(w[k] * traj[k])) for k in subset))

    def quadratic_magnitude(traj: np.ndarray) -> float:
        return magnitude(traj) + float(sum(0.5 * np.sum(traj[k] ** 2) for k in subset))

    def quadratic(traj: np.ndarray) -> float:
        return float(sum(np.sum(w[k] * traj[k]) + 0.5 * np.sum(traj[k] ** 2) for k in subset))

    def gradient(cot: dict[int, np.ndarray], which: str) -> np.ndarray:
        g = stepper._vjp(
            u0, steps, np.ascontiguousarray(ctrl), p,
            *stepper._check_cotangents(cot, steps, u0),
            which not in ("state", "controls"), None, stepper.control_shape is not None,
        )
        if which == "state":
            return g.state
        if which == "controls":
            return g.controls
        return np.array([g.params[k] for k in stepper.param_names])

    base = run(u0, "state")
    quad_cot = {k: w[k] + base[k] for k in subset}
    rows = []
    tol = TOLERANCES[dtype]
    for which, x, delta in inputs:
        grad_lin = gradient(w, which)
        grad_quad = gradient(quad_cot, which)
        x, delta = x.astype(np.float64), delta.astype(np.float64)
        adj = float(np.sum(grad_lin * delta))
        tangent, noise = _tangent(stepper, run, linear, magnitude, x, delta, which)
        dot_err = abs(tangent - adj) / max(abs(tangent), abs(adj), noise, 1e-300)

        def phi(e: float, x=x, delta=delta, which=which) -> float:
            return quadratic(run(x + e * delta, which))

        phi0 = quadratic(base)
        slope = float(np.sum(grad_quad * delta))
        rate = _taylor_rate(phi, phi0, slope, _EPS_TAYLOR)
        e = _EPS_FD
        fd = (phi(e) - phi(-e)) / (2 * e)
        # Central differences cannot resolve slopes below the round-off of Φ, taken as
        # 100 eps Σ|terms of Φ|, divided by ε.
        noise = 100 * np.finfo(np.float64).eps * quadratic_magnitude(base) / e
        fd_err = abs(fd - slope) / max(abs(fd), abs(slope), noise, 1e-300)
        passed = bool(dot_err <= tol["dot"] and rate >= tol["rate"] and fd_err <= tol["fd"])
        rows.append(CheckResult(stepper.name, which, dot_err, rate, fd_err, passed))
    return rows


def _tangent(
    stepper: Stepper,
    run: Callable[[np.ndarray, str], np.ndarray],
    linear: Callable[[np.ndarray], Any],
    magnitude: Callable[[np.ndarray], float],
    x: np.ndarray,
    delta: np.ndarray,
    which: str,
) -> tuple[float, float]:
    """Directional derivative of the linear functional and its round-off level: complex step
    (no cancellation), else Richardson-extrapolated central differences."""
    if stepper.complex_step:
        z = x + 1j * _H_COMPLEX_STEP * delta
        return float(np.imag(linear(run(z, which))) / _H_COMPLEX_STEP), 0.0
    h = 1e-2

    def central(e: float) -> float:
        plus, minus = linear(run(x + e * delta, which)), linear(run(x - e * delta, which))
        return (float(plus) - float(minus)) / (2 * e)

    # Two Richardson levels cancel the h² and h⁴ terms: the error is O(h⁶) + round-off / h.
    d1, d2, d4 = central(h), central(h / 2), central(h / 4)
    # Round-off of the differences: eps Σ|w_k u_k| / (h/4), amplified 64/45 by the weights.
    noise = 64 / 45 * np.finfo(np.float64).eps * magnitude(run(x, which)) / (h / 4)
    return (64.0 * d4 - 20.0 * d2 + d1) / 45.0, noise


def _taylor_rate(
    phi: Callable[[float], float], phi0: float, slope: float, eps0: float
) -> float:
    """Median observed order of the first-order Taylor remainder over halving ε."""
    floor = 10 * np.finfo(np.float64).eps * max(abs(phi0), 1.0)
    eps = eps0 * 0.5 ** np.arange(6)
    rem = np.array([abs(phi(e) - phi0 - e * slope) for e in eps])
    good = rem > floor
    rates = [np.log2(rem[i] / rem[i + 1]) for i in range(len(eps) - 1) if good[i] and good[i + 1]]
    return float(np.median(rates)) if rates else float("nan")


def check(
    names: Iterable[str] | None = None,
    steps: int = 50,
    dtype: str = "float64",
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> list[CheckResult]:
    """Check the default scene of each named registered solver (all of them by default)."""
    rows: list[CheckResult] = []
    for name in names if names is not None else registry.names():
        if progress:
            progress(name)
        rows.extend(check_stepper(registry.get(name).default(), steps, dtype, seed))
    return rows
