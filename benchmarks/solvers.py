"""Forward and adjoint speed of every registered solver, against its vectorised NumPy version.

    python benchmarks/solvers.py [--steps 100] [--repeats 5] [--names NAME ...] [--csv PATH]

For each solver: 1D grids at N = 256 and 2D grids at 128², batch 1 and 64, a rollout of
``--steps`` steps. Prints per-step medians of the forward rollout, of the adjoint sweep alone
(the backward kernels over a stored trajectory) and of the whole ``vjp`` (forward with storage
plus adjoint), the ratios adjoint/forward, and the speed-up over NumPy measured in the same run.
Targets: adjoint/forward ≤ 2.5 and numba ≥ 5x faster than NumPy at batch 1.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
# the NumPy references live with the tests (tests/references), imported from the repository root
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

import adjointsim  # noqa: E402
from tests.references import all_rollouts  # noqa: E402

SIZES = {1: 256, 2: 128}


def median_time(fn, repeats: int) -> float:
    fn()  # warm-up: compilation and caches
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def bench(name: str, batch: int, steps: int, repeats: int, numpy_rollouts: dict) -> dict:
    cls = adjointsim.get(name)
    ndim = len(cls.default().grid_shape)
    stepper = cls.benchmark_scene(SIZES[ndim])
    rng = np.random.default_rng(0)
    u0 = stepper.random_state(rng, batch)
    u0, _, ctrl, p = stepper.prepare(u0, steps)
    traj = stepper.rollout_prepared(u0, steps, ctrl, p, keep="all")
    cot, cmap = stepper.check_cotangents(np.ones_like(u0), steps, u0)

    def adjoint():
        stepper.vjp_prepared(u0, steps, ctrl, p, cot, cmap, trajectory=traj)

    fwd = median_time(lambda: stepper.rollout(u0, steps), repeats)
    adj = median_time(adjoint, repeats)
    vjp = median_time(lambda: stepper.vjp(u0, steps, np.ones_like(u0)), repeats)
    row = {
        "solver": name,
        "grid": "x".join(map(str, stepper.grid_shape)),
        "batch": batch,
        "forward_us": 1e6 * fwd / steps,
        "adjoint_us": 1e6 * adj / steps,
        "vjp_us": 1e6 * vjp / steps,
        "adjoint/forward": adj / fwd,
        "numpy_us": float("nan"),
        "speedup": float("nan"),
    }
    if name in numpy_rollouts:
        ref = numpy_rollouts[name]
        np.testing.assert_allclose(
            ref(stepper, u0, steps), stepper.rollout(u0, steps), rtol=1e-8, atol=1e-10
        )
        t_np = median_time(lambda: ref(stepper, u0, steps), max(1, repeats // 2))
        row["numpy_us"] = 1e6 * t_np / steps
        row["speedup"] = t_np / fwd
    return row


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64])
    parser.add_argument("--names", nargs="+", default=None)
    parser.add_argument("--csv", type=Path, default=None)
    args = parser.parse_args()
    numpy_rollouts = all_rollouts()
    names = args.names or adjointsim.names()
    header = (f"{'solver':<28} {'grid':>8} {'B':>3} {'fwd µs/step':>11} {'adj µs/step':>11} "
              f"{'vjp µs/step':>11} {'adj/fwd':>7} {'numpy µs':>9} {'numba/numpy':>11}")
    print(header)
    rows = []
    for name in names:
        for batch in args.batches:
            r = bench(name, batch, args.steps, args.repeats, numpy_rollouts)
            rows.append(r)
            print(f"{r['solver']:<28} {r['grid']:>8} {r['batch']:>3} {r['forward_us']:11.2f} "
                  f"{r['adjoint_us']:11.2f} {r['vjp_us']:11.2f} {r['adjoint/forward']:7.2f} "
                  f"{r['numpy_us']:9.1f} {r['speedup']:10.1f}x", flush=True)
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)


if __name__ == "__main__":
    main()
