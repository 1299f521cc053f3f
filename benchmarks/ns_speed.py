"""Speed of the 2D Navier–Stokes ETDRK solvers, and of their peer exponax measured in the same run.

    python benchmarks/ns_speed.py [--n 128] [--steps 100] [--repeats 7] [--orders 2]
                                  [--batch 1] [--threads 1 2] [--cpu]

Kolmogorov reference scene (k_f = 6, Re = 1000, Δt = 0.005·128/n, 2/3 dealiasing), float64,
started from a developed state. Per step, median / minimum over the repeats of:
  forward        rollout(u0, steps)
  fwd+adj        vjp(u0, steps, ū): the forward sweep records the stage fields, the adjoint
                 reads them (the default path)
  fwd+adj (rec)  forward + vjp(..., trajectory=...): the adjoint recomputes the stages
  numpy          the vectorised NumPy forward of tests/references/spectral2d.py
then (fwd+adj) / forward, the gradient's cost in forwards. When exponax is installed (the
``peers`` extra), its exact twin of each scene (benchmarks/exponax_peer.py: JAX/XLA jit on one
CPU thread, from the same state, compilation not timed) is measured in the same run: its
forward and forward + gradient per step (median), and how many times faster than it ours run;
otherwise the script says it is not installed and prints no peer figure. ``--threads``: the
solver thread counts to run (adjointsim.parallel; a batch smaller than the count runs its
transforms on the threads, a larger one splits its rows over them; NUMBA_NUM_THREADS stays 1).
``--cpu`` measures the thread's CPU time instead of wall time: other processes on a shared
machine inflate it much less, but it misses the work of any other thread, so use it with one
thread only (exponax is then timed in process CPU time: XLA may run it on a thread of its own).
Targets at 128², batch 1, ETDRK2: forward ≤ 0.43 ms/step and forward + adjoint ≤ 1.1 ms/step.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))
# the NumPy references live with the tests (tests/references), imported from the repository root
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import exponax_peer  # noqa: E402
import numpy as np  # noqa: E402

import adjointsim.solvers.navier_stokes as ns  # noqa: E402
from adjointsim import get, parallel  # noqa: E402
from tests.references.spectral2d import navier_stokes as numpy_rollout  # noqa: E402


def timings(fn, repeats: int, clock) -> tuple[float, float]:
    fn()
    times = []
    for _ in range(repeats):
        t = clock()
        fn()
        times.append(clock() - t)
    return float(np.median(times)), float(np.min(times))


def measure(stepper: ns.NavierStokes2D, u0: np.ndarray, steps: int, repeats: int,
            clock) -> list:
    cot = np.ones_like(u0)
    traj = stepper.rollout(u0, steps, keep="all")
    forward = timings(lambda: stepper.rollout(u0, steps), repeats, clock)
    taped = timings(lambda: stepper.vjp(u0, steps, cot), repeats, clock)
    recomputed = timings(lambda: stepper.vjp(u0, steps, cot, trajectory=traj), repeats, clock)
    reference = timings(lambda: numpy_rollout(stepper, u0, steps), max(1, repeats // 3), clock)
    rows = [forward, taped, (forward[0] + recomputed[0], forward[1] + recomputed[1]), reference]
    return [(1e3 * med / steps, 1e3 * low / steps) for med, low in rows]


def peer(stepper: ns.NavierStokes2D, u0: np.ndarray, steps: int, repeats: int,
         clock) -> tuple[float, float] | None:
    """exponax's forward and forward + gradient of its twin of ``stepper`` from ``u0``, ms per
    step (median); None if exponax is not installed."""
    if not exponax_peer.available():
        return None
    calls = exponax_peer.prepare(stepper, u0, steps)
    forward, gradient = (timings(calls[k], repeats, clock)[0] for k in ("forward", "gradient"))
    return 1e3 * forward / steps, 1e3 * gradient / steps


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--n", type=int, default=128)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--orders", type=int, nargs="+", default=[2])
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--threads", type=int, nargs="+", default=[1],
                        help="solver thread counts to measure, each in turn")
    parser.add_argument("--cpu", action="store_true", help="thread CPU time instead of wall time")
    args = parser.parse_args()
    clock = time.thread_time if args.cpu else time.perf_counter
    installed = exponax_peer.available()
    print(f"ms/step, median / min ({'CPU' if args.cpu else 'wall'} time); exponax "
          + ("measured alongside" if installed
             else "not installed (pip install 'adjointsim[peers]'): no peer figures"))
    print(f"{'solver':<12} {'grid':>6} {'B':>3} {'thr':>3} {'forward':>15} {'fwd+adj':>15} "
          f"{'fwd+adj (rec)':>15} {'numpy':>15} {'/forward':>8}"
          + (f" {'exponax fwd, grad':>18} {'x exponax fwd, grad':>20}" if installed else ""))
    for order in args.orders:
        cls = get(f"ns2d-etdrk{order}")
        stepper = cls(n=args.n, nu=1e-3, dt=0.005 * 128 / args.n, forcing_wavenumber=6)
        u0 = stepper.rollout(stepper.random_state(np.random.default_rng(0), args.batch), 200)
        theirs = peer(stepper, u0, args.steps, args.repeats,
                      time.process_time if args.cpu else clock)
        for threads in args.threads:
            with parallel.using_threads(threads):
                cells = measure(stepper, u0, args.steps, args.repeats, clock)
            text = " ".join(f"{med:>7.3f} / {low:<5.3f}" for med, low in cells)
            ratio = cells[1][0] / cells[0][0]
            versus = "" if theirs is None else (
                f" {theirs[0]:>8.3f}, {theirs[1]:<8.3f} {theirs[0] / cells[0][0]:>9.2f}, "
                f"{theirs[1] / cells[1][0]:<9.2f}")
            print(f"{stepper.name:<12} {args.n:>5}² {args.batch:>3} {threads:>3} {text} "
                  f"{ratio:>8.2f}{versus}", flush=True)


if __name__ == "__main__":
    main()
