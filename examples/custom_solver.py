"""A solver of your own: a new Stepper with its numba kernel and hand-written adjoint, registered
and verified by the same dot-product, Taylor and finite-difference tests as the built-in ones.

The scheme is a 1D periodic reaction-diffusion (Allen-Cahn) equation, explicit Euler in time:

    u_{k+1} = u_k + dt (nu Lap u_k + r (u_k - u_k^3) + c_k)

with an additive per-step control c_k and two differentiable parameters, nu and r. Its
discrete adjoint, written next to the forward kernel:

    ubar_k  = ubar_{k+1} + dt (nu Lap ubar_{k+1} + r (1 - 3 u_k^2) ubar_{k+1})
    cbar_k  = dt ubar_{k+1}
    nubar  += dt <ubar_{k+1}, Lap u_k>,   rbar += dt <ubar_{k+1}, u_k - u_k^3>

The script registers the class (in this process only), checks it with
``adjointsim.check.check`` exactly as ``adjointsim gradcheck NAME`` checks a built-in solver,
uses it (rollout, vjp with parameter cotangents), and finally checks a copy whose adjoint
forgets the factor 3: every row of that one fails.

Run:  python examples/custom_solver.py [--tiny]
Takes about 2 s on 2 cores once numba has cached the kernels (--tiny too); the first run
compiles them, about 10 s.
"""

from __future__ import annotations

import argparse
import math

import numpy as np
from numba import njit

import adjointsim
from adjointsim import Stepper, validate
from adjointsim.check import check, check_stepper


# ----------------------------------------------------------------------------- the kernels
@njit(cache=True)
def _laplacian(u, out, inv_h2):
    """Periodic centred second difference along the last axis of (B, C, N)."""
    nb, nc, n = u.shape
    for b in range(nb):
        for c in range(nc):
            for i in range(n):
                left, right = u[b, c, (i - 1) % n], u[b, c, (i + 1) % n]
                out[b, c, i] = (left - 2 * u[b, c, i] + right) * inv_h2


@njit(cache=True)
def allen_cahn_forward(states, n, ctrl, p, dt, inv_h2):
    # states (S, B, C, N): u_{k+1} goes into slot (k + 1) % S (S = 2: ping-pong buffer).
    s = states.shape[0]
    lap = np.empty_like(states[0])
    nu, r = p[0], p[1]
    for k in range(n):
        u = states[k % s]
        v = states[(k + 1) % s]
        _laplacian(u, lap, inv_h2)
        for b in range(u.shape[0]):
            for c in range(u.shape[1]):
                for i in range(u.shape[2]):
                    x = u[b, c, i]
                    v[b, c, i] = x + dt * (nu * lap[b, c, i] + r * (x - x * x * x))
        if ctrl.shape[0] > 0:  # a zero-length control axis: the scene runs uncontrolled
            v += dt * ctrl[k]


@njit(cache=True)
def allen_cahn_adjoint(states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p, dt, inv_h2,
                       cubic):
    # Reverses the steps whose inputs are states[0 .. m-1]; on entry ubar is the cotangent of
    # u_m. ``cubic`` is 3 for the true adjoint (the broken copy below passes 1).
    nu, r = p[0], p[1]
    lap = np.empty_like(ubar)
    for k in range(states.shape[0] - 1, -1, -1):
        u = states[k]
        if want_p:
            _laplacian(u, lap, inv_h2)
            pbar[0] += dt * np.sum(lap * ubar)
            pbar[1] += dt * np.sum((u - u * u * u) * ubar)
        if cbar.shape[0] > 0:
            cbar[k] = dt * ubar
        _laplacian(ubar, lap, inv_h2)
        for b in range(u.shape[0]):
            for c in range(u.shape[1]):
                for i in range(u.shape[2]):
                    x, w = u[b, c, i], ubar[b, c, i]
                    ubar[b, c, i] = w + dt * (nu * lap[b, c, i] + r * (1 - cubic * x * x) * w)
        if cmap[k] >= 0:
            ubar += cot[cmap[k]]


# ----------------------------------------------------------------------------- the stepper
class AllenCahn1D(Stepper):
    """Periodic 1D Allen-Cahn, u_t = nu u_xx + r (u - u^3) + c, explicit Euler."""

    name = "allen-cahn1d-euler"
    space = {"n": adjointsim.Range(8, 64, integer=True), "nu": adjointsim.Range(0.01, 0.1)}

    def __init__(self, n: int = 64, length: float = 2 * math.pi, nu: float = 0.05,
                 r: float = 1.0, dt: float | None = None):
        n = validate.integer(self.name, "n", n, ge=3, why="the centred stencil needs 3 points")
        length = validate.number(self.name, "length", length, gt=0)
        nu = validate.number(self.name, "nu", nu, ge=0)
        r = validate.number(self.name, "r", r, ge=0)
        self.h = length / n
        self.inv_h2 = 1.0 / self.h**2
        # 0.4 / (nu / h^2 + r): inside the diffusion limit 1/2 and the reaction's time scale.
        default = 0.4 / (nu * self.inv_h2 + r) if nu * self.inv_h2 + r > 0 else 0.1
        self.dt = validate.number(self.name, "dt", default if dt is None else dt, gt=0)
        self.grid_shape, self.channels, self.control_shape = (n,), 1, (1, n)
        self.param_names, self.param_values = ("nu", "r"), (nu, r)
        self.check_params(np.array(self.param_values))

    def check_params(self, p: np.ndarray) -> None:
        number = float(p[0].real) * self.dt * self.inv_h2
        if number > 0.5:
            raise ValueError(f"{self.name}: nu dt / h^2 = {number:.3g} exceeds the explicit "
                             f"limit 1/2; pass dt <= {0.5 / (float(p[0].real) * self.inv_h2):.4g}")

    @classmethod
    def benchmark_scene(cls, n: int) -> AllenCahn1D:
        return cls(n=n)

    def random_state(self, rng, batch=1, dtype=np.float64):
        # A few low Fourier modes: smooth and of order one, as the Taylor test likes.
        x = np.arange(self.grid_shape[0]) * self.h
        k = np.arange(1, 5)
        a, b = rng.normal(0, 0.5, (2, batch, 1, k.size))
        u = a @ np.cos(np.outer(k, x)) + b @ np.sin(np.outer(k, x))
        return u.astype(dtype)

    def _forward(self, states, n, ctrl, p):
        allen_cahn_forward(states, n, ctrl, p, self.dt, self.inv_h2)

    _cubic = 3.0

    def _adjoint(self, states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p):
        allen_cahn_adjoint(states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p, self.dt,
                           self.inv_h2, self._cubic)


class BrokenAllenCahn1D(AllenCahn1D):
    """The same scheme with a wrong adjoint: d(u^3)/du taken as u^2 instead of 3 u^2."""

    name = "allen-cahn1d-broken"
    _cubic = 1.0


def print_rows(rows) -> None:
    def num(v, spec):
        return format(v, spec) if v is not None and math.isfinite(v) else "-"

    print(f"{'solver':<20} {'wrt':<8} {'dot_rel_err':>11} {'taylor_rate':>11} {'fd_rel_err':>10}"
          "  result")
    for r in rows:
        print(f"{r.solver:<20} {r.wrt:<8} {num(r.dot_rel_err, '11.2e')} "
              f"{num(r.taylor_rate, '11.3f')} {num(r.fd_rel_err, '10.2e')}  "
              + ("pass" if r.passed else f"FAIL: {r.reason.split(';')[0]}"))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tiny", action="store_true", help="a few steps only (seconds, for tests)")
    args = ap.parse_args()
    steps = 5 if args.tiny else 100

    # Registration makes the class visible to everything that iterates over the registry
    # (adjointsim.get, adjointsim.check.check, the benchmarks), in this process only.
    adjointsim.register(AllenCahn1D)
    scene = adjointsim.get("allen-cahn1d-euler")(n=64, nu=0.05, r=1.0)

    # Use it like any built-in solver: a rollout, then the gradient of a loss on u_n.
    u0 = scene.random_state(np.random.default_rng(0), batch=4)
    un = scene.rollout(u0, steps)
    g = scene.vjp(u0, steps, {-1: un}, wrt_params=True)  # d(0.5 |u_n|^2) / d(u0, nu, r)
    print(f"{scene.name}: {steps} steps of dt = {scene.dt:.4g}, |u_n| = {np.linalg.norm(un):.4f}")
    print(f"d(0.5 |u_n|^2)/d nu = {g.params['nu']:.6g}, d/d r = {g.params['r']:.6g}")

    rows = check(["allen-cahn1d-euler"], steps=steps)
    print_rows(rows)
    broken = check_stepper(BrokenAllenCahn1D(), steps=steps)
    print_rows(broken)
    ok = all(r.passed for r in rows) and not any(r.passed for r in broken)
    print(f"result: {sum(r.passed for r in rows)}/{len(rows)} rows of the new solver pass; "
          f"{sum(not r.passed for r in broken)}/{len(broken)} rows of the broken adjoint fail")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
