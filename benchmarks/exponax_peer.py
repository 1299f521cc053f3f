"""exponax (JAX/XLA, float64, one CPU thread) as a peer of the spectral solvers.

    python benchmarks/exponax_peer.py [--repeats 7]

Prints exponax's per-step times for the two configurations of ``benchmarks/spectral.py`` (which
imports :func:`prepare` from here), or ``skipped: exponax not installed``. The exponax steppers
are exact twins of our scenes (:func:`adjointsim.bench.work_precision.exponax_twin`: same grid,
Δt, coefficients and dealiasing; exponax evaluates the NS nonlinearity as u·∇ω with 4 inverse +
1 forward FFT per stage, we as ∇·(u ω) with 3 + 2). A rollout is ``lax.scan`` over the steps,
``vmap`` over the batch, ``jit``-compiled once (compilation is not timed); the gradient of the
loss ½ Σ u_n² is ``jax.value_and_grad`` of that rollout, also jit-compiled.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from adjointsim.bench.work_precision import (  # noqa: E402
    exponax_rollout,
    exponax_twin,
    load_exponax,
    median_times,
)
from adjointsim.stepper import Stepper  # noqa: E402


def available() -> bool:
    return load_exponax() is not None


def prepare(stepper: Stepper, u0: np.ndarray, steps: int) -> dict:
    """exponax's twin of ``stepper`` from ``u0`` (B, C, *grid) over ``steps`` steps, compiled:
    the calls to time (``forward``, ``gradient`` = forward + gradient), the last state and the
    gradient of ½ Σ u_steps² (in our sign convention)."""
    jax, _ = load_exponax()
    twin, sign = exponax_twin(stepper)
    run = exponax_rollout(twin, steps)
    forward = jax.jit(run)
    value_and_grad = jax.jit(jax.value_and_grad(lambda u: 0.5 * (run(u) ** 2).sum()))
    x = jax.numpy.asarray(sign * u0)
    return dict(
        forward=lambda: forward(x).block_until_ready(),
        gradient=lambda: jax.block_until_ready(value_and_grad(x)),
        last=sign * np.asarray(forward(x)), grad=sign * np.asarray(value_and_grad(x)[1]),
    )


def measure(stepper: Stepper, u0: np.ndarray, steps: int, repeats: int) -> dict[str, float]:
    """Seconds per step of exponax's forward rollout and of forward + gradient."""
    calls = prepare(stepper, u0, steps)
    times = median_times({k: calls[k] for k in ("forward", "gradient")}, repeats)
    return {k: v / steps for k, v in times.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    if not available():
        print("skipped: exponax not installed")
        return 0
    import exponax
    import jax

    from adjointsim.solvers.kuramoto_sivashinsky import KS
    from adjointsim.solvers.navier_stokes import NavierStokes2DETDRK2

    print(f"exponax {exponax.__version__}, jax {jax.__version__}, XLA_FLAGS="
          f"{os.environ.get('XLA_FLAGS', '')!r}; µs per step (median process CPU time)")
    ks = KS[4](n=128, length=64.0, dt=0.25)
    for batch in (1, 64):
        u0 = ks.random_state(np.random.default_rng(0), batch)
        t = measure(ks, u0, 200, args.repeats)
        print(f"KS ETDRK4 N=128 L=64 dt=0.25 batch {batch:2d}: forward {1e6 * t['forward']:8.1f}"
              f", forward + gradient (200 steps) {1e6 * t['gradient']:8.1f}")
    ns = NavierStokes2DETDRK2(n=128, nu=1e-3, dt=0.005, forcing_wavenumber=6)  # List et al.'s
    u0 = ns.rollout(ns.random_state(np.random.default_rng(0), 1), 200)
    t = measure(ns, u0, 100, args.repeats)
    print(f"NS Kolmogorov 128² ETDRK2 batch 1: forward {1e6 * t['forward']:8.1f}, "
          f"forward + gradient (100 steps) {1e6 * t['gradient']:8.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
