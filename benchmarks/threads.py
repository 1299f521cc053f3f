"""Solver threads: every family's forward and forward + gradient on 1, 2, 4, ... threads.

    python benchmarks/threads.py [--repeats 5] [--quick] [--json PATH] [--out DIR]
                                 [--solvers NAME ...] [--batches B ...] [--cores-scaling]

One process, float64, wall-clock time (the threads run side by side), every time the median
over ``--repeats`` samples, the thread counts of one case sampled in turn so that a change of
load affects them alike. For each case (solver, grid size n, rollout length) and batch:

- ``forward_s``: one ``rollout`` of the case's steps (u_n only);
- ``gradient_s``: forward + gradient of ½ Σ u_n²: ``rollout`` and ``vjp`` with parameter
  cotangents and the default storage of every state;
- ``bitwise_equal``: u_n, the state, control and parameter cotangents equal to one thread's,
  to the bit.

Threads 1, 2 and every power of two up to the cores this process may run on (every count
with ``--cores-scaling``); batches 1, 8, 64 and 1024, a batch left out (and said so) where
one forward would exceed :data:`MAX_POINT_STEPS` point-steps or the stored trajectory
:data:`MAX_STORED_BYTES`. Prints a table with the speed-ups over one thread; ``--json PATH``
writes one row per measurement, ``--out DIR`` writes ``threads.json``, ``threads.md`` and
``threads.png`` (speed-up against threads per solver) there.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import adjointsim
from adjointsim import parallel
from adjointsim.bench.work_precision import median_times
from adjointsim.files import pyplot, save_figure, write_json, write_text

BATCHES = (1, 8, 64, 1024)
#: one forward of more point-steps than this (batch × grid points × steps) is left out
MAX_POINT_STEPS = 1 << 28
#: a gradient whose stored trajectory would take more bytes than this is left out
MAX_STORED_BYTES = 1 << 31
#: a timing sample repeats a call until it lasts this long
MIN_TIME = 0.05


@dataclass(frozen=True)
class Case:
    solver: str
    n: int | None  # grid points per axis (None: a system without a grid)
    steps: int
    make: Callable[[], adjointsim.Stepper]


def cases(quick: bool) -> list[Case]:
    """One scene per family: spectral 1D and 2D, stencils 1D and 2D, Burgers (finite volume
    and spectral), Crank–Nicolson (ADI in 2D), Poisson, a control system."""
    def scene(name: str, n: int) -> Callable[[], adjointsim.Stepper]:
        return lambda: adjointsim.get(name).benchmark_scene(n)

    ns = 64 if quick else 128
    s = 4 if quick else 1  # --quick: fewer steps
    return [
        # the spectral benchmark's KS: N = 128, L = 64, Δt = 0.25
        Case("ks1d-etdrk4", 128, 100 // s,
             lambda: adjointsim.get("ks1d-etdrk4")(n=128, length=64.0, dt=0.25)),
        Case("ns2d-etdrk2", ns, 20 // s, scene("ns2d-etdrk2", ns)),
        Case("diffusion1d-ftcs", 256, 100 // s, scene("diffusion1d-ftcs", 256)),
        Case("diffusion2d-ftcs", 128, 20 // s, scene("diffusion2d-ftcs", 128)),
        Case("burgers1d-rusanov", 256, 100 // s, scene("burgers1d-rusanov", 256)),
        Case("burgers1d-etdrk4", 128, 100 // s, scene("burgers1d-etdrk4", 128)),
        Case("diffusion2d-crank-nicolson", 128, 20 // s, scene("diffusion2d-crank-nicolson", 128)),
        Case("poisson2d", 128, 10 // s, scene("poisson2d", 128)),
        Case("cartpole", None, 200 // s, lambda: adjointsim.get("cartpole").default()),
    ]


def thread_counts(every: bool) -> list[int]:
    """1, 2 and the powers of two up to the cores (``every``: each count up to them)."""
    cores = parallel.available_cores()
    if every:
        return sorted({1, 2, *range(1, cores + 1)})
    return sorted({1, 2, *(1 << k for k in range(cores.bit_length()) if 1 << k <= cores)})


def too_large(stepper: adjointsim.Stepper, batch: int, steps: int) -> str | None:
    """Why a batch is left out, or None."""
    points = int(np.prod(stepper.state_shape(batch)))
    if points * steps > MAX_POINT_STEPS:
        return f"{points * steps:.2g} point-steps per forward, over {MAX_POINT_STEPS:.2g}"
    if 8 * points * (steps + 1) > MAX_STORED_BYTES:
        return (f"a stored trajectory of {8 * points * (steps + 1) / 2**30:.1f} GiB, over "
                f"{MAX_STORED_BYTES / 2**30:.0f}")
    return None


def measure(case: Case, batch: int, counts: list[int], repeats: int) -> list[dict]:
    """One row per thread count: times, and whether every output equals one thread's."""
    stepper = case.make()
    rng = np.random.default_rng(batch)
    u0 = stepper.random_state(rng, batch)
    ctrl = (None if stepper.control_shape is None
            else stepper.random_controls(rng, case.steps, batch))

    def forward():
        return stepper.rollout(u0, case.steps, ctrl)

    def gradient():
        last = stepper.rollout(u0, case.steps, ctrl)
        g = stepper.vjp(u0, case.steps, last, ctrl, wrt_params=True)
        params = np.array([g.params[k] for k in stepper.param_names])
        return [a for a in (last, g.state, g.controls, params) if a is not None]

    def on(threads: int, fn: Callable[[], object]) -> Callable[[], object]:
        def call():
            with parallel.using_threads(threads):
                return fn()
        return call

    outputs = {t: on(t, gradient)() for t in counts}
    calls = {(t, what): on(t, fn) for t in counts
             for what, fn in (("forward", forward), ("gradient", gradient))}
    times = median_times(calls, repeats, MIN_TIME, clock=time.perf_counter)
    return [{
        "solver": case.solver, "n": case.n, "steps": case.steps, "batch": batch,
        "threads": t, "forward_s": times[t, "forward"], "gradient_s": times[t, "gradient"],
        "bitwise_equal": all(_same(a, b) for a, b in zip(outputs[t], outputs[counts[0]])),
        **machine(),
    } for t in counts]


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def machine() -> dict:
    """The cores this process may use, the machine's, and the CPU's model name."""
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            model = next((line.split(":", 1)[1].strip() for line in f
                          if line.startswith("model name")), model)
    except OSError:
        pass
    return {"cores": parallel.available_cores(), "cpu_count": os.cpu_count(), "cpu": model}


# ----------------------------------------------------------------- report
def table(rows: list[dict], skipped: list[str]) -> str:
    """Markdown: per case and batch, the times and the speed-ups over one thread."""
    base = {(r["solver"], r["batch"]): r for r in rows if r["threads"] == 1}
    lines = ["| solver | n | steps | batch | threads | forward ms | speed-up | forward + "
             "gradient ms | speed-up | bitwise equal |", "|---|---:|---:|---:|---:|---:|---:|"
             "---:|---:|---|"]
    for r in rows:
        one = base.get((r["solver"], r["batch"]))
        up = (f"{one['forward_s'] / r['forward_s']:.2f}x" if one else "–",
              f"{one['gradient_s'] / r['gradient_s']:.2f}x" if one else "–")
        lines.append(f"| {r['solver']} | {r['n'] or '–'} | {r['steps']} | {r['batch']} | "
                     f"{r['threads']} | {1e3 * r['forward_s']:.3f} | {up[0]} | "
                     f"{1e3 * r['gradient_s']:.3f} | {up[1]} | "
                     f"{'yes' if r['bitwise_equal'] else 'NO'} |")
    if rows:
        m = rows[0]
        lines.append(f"\n{m['cpu']}; {m['cores']} cores for this process ({m['cpu_count']} on "
                     "the machine); medians of wall-clock time, speed-ups over 1 thread.")
    lines += [f"\nleft out: {s}" for s in skipped]
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    """Speed-up over one thread against threads, per solver at its largest batch measured."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5), sharey=True)
    largest = {}
    for r in rows:
        largest[r["solver"]] = max(largest.get(r["solver"], 0), r["batch"])
    counts = sorted({r["threads"] for r in rows})
    for ax, key, title in ((axes[0], "forward_s", "forward"),
                           (axes[1], "gradient_s", "forward + gradient")):
        ax.plot(counts, counts, "k:", label="ideal")
        for solver, batch in largest.items():
            mine = sorted((r["threads"], r[key]) for r in rows
                          if r["solver"] == solver and r["batch"] == batch)
            one = dict(mine).get(1)
            if one is None:
                continue
            ax.plot([t for t, _ in mine], [one / s for _, s in mine], "o-",
                    label=f"{solver} (batch {batch})")
        ax.set_xscale("log", base=2)
        ax.set_yscale("log", base=2)
        ax.set_xticks(counts, [str(t) for t in counts])
        ax.yaxis.set_major_formatter(plt.FuncFormatter(lambda y, _: f"{y:g}"))
        ax.set_xlabel("solver threads")
        ax.set_title(title)
    axes[0].set_ylabel("speed-up over 1 thread")
    axes[1].legend(fontsize=7)
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=None, help="samples per time (default 5, "
                   "with --quick 3)")
    p.add_argument("--quick", action="store_true",
                   help="fewer steps, NS at 64², batches up to 64")
    p.add_argument("--solvers", nargs="+", default=None, metavar="NAME",
                   help="only these cases' solvers")
    p.add_argument("--batches", nargs="+", type=int, default=None, metavar="B",
                   help=f"default {' '.join(map(str, BATCHES))} (with --quick up to 64)")
    p.add_argument("--cores-scaling", action="store_true",
                   help="every thread count up to the cores, not only the powers of two")
    p.add_argument("--json", type=Path, default=None, metavar="PATH",
                   help="write one row per measurement here")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="write threads.json, threads.md and threads.png here")
    args = p.parse_args(argv)
    repeats = args.repeats or (3 if args.quick else 5)
    batches = args.batches or [b for b in BATCHES if not args.quick or b <= 64]
    chosen = cases(args.quick)
    if args.solvers:
        unknown = set(args.solvers) - {c.solver for c in chosen}
        if unknown:
            p.error(f"no case for {', '.join(sorted(unknown))}; choose from "
                    f"{', '.join(c.solver for c in chosen)}")
        chosen = [c for c in chosen if c.solver in args.solvers]
    counts = thread_counts(args.cores_scaling)
    rows: list[dict] = []
    skipped: list[str] = []
    for case in chosen:
        for batch in batches:
            why = too_large(case.make(), batch, case.steps)
            if why is not None:
                skipped.append(f"{case.solver} at batch {batch}: {why}")
                print(f"skipped {case.solver} batch {batch}: {why}", file=sys.stderr)
                continue
            print(f"{case.solver} batch {batch} ...", file=sys.stderr, flush=True)
            rows.extend(measure(case, batch, counts, repeats))
    text = table(rows, skipped)
    print(text)
    if args.json is not None:
        write_json(args.json, rows)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        write_json(args.out / "threads.json", rows)
        write_text(args.out / "threads.md", text + "\n")
        plot(rows, args.out / "threads.png")
    return 0 if all(r["bitwise_equal"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
