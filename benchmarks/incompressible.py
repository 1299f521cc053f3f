"""Speed of the staggered-grid incompressible Navier–Stokes solver: forward and gradient.

    python benchmarks/incompressible.py [--n 32 64] [--batch 1] [--steps 50] [--repeats 7]
                                        [--checkpoint 8] [--viscosity explicit] [--cpu]
                                        [--json PATH]

Scene: ``incompressible2d-sl``'s benchmark scene at size n, the wake of a cylinder in a channel
of 2n × n cells (inflow left, outflow right, free-slip walls) with an advected smoke density and
buoyancy, float64, one solver thread, started from the flow after 20 steps (``--viscosity
implicit``: the same scene with backward-Euler viscosity; key ``viscosity``). Per row, median
wall time (``--cpu``: the thread's CPU time, which other processes on a shared machine inflate
much less) over the repeats, which run the three in turn, of
  forward_s               rollout(u0, steps)
  gradient_s              vjp(u0, steps, ū, wrt_params=True): the forward sweep and the
                          adjoint, every state kept
  gradient_checkpoint_s   the same holding at most ``--checkpoint`` states (binomial
                          checkpointing: the memory stays flat in the number of steps)
and ``peak_mib``, the largest memory (tracemalloc) the checkpointed gradient allocates,
for ``steps`` and for 4 × ``steps`` (``peak_mib_4x``). The optional peer, PhiFlow on the CPU
(``pip install phiflow``; its twin of the scene in ``phiflow_peer.py``), runs the same scene
from the same state in the same rounds (keys ``peer``, ``peer_forward_s``, ``peer_gradient_s``,
and ``peer_rel_diff``: the relative L2 difference of its velocity after ``steps`` steps from
ours, which says the twin is the same flow); ``--peer-repeats`` rounds (it is slow), and
without PhiFlow the script says so and writes no peer keys.
``--json PATH`` writes the rows as a JSON list.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import time
import tracemalloc
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import phiflow_peer  # noqa: E402

from adjointsim import get, parallel  # noqa: E402

NAME = "incompressible2d-sl"


def median_times(fns: list, repeats: int, clock) -> list[float]:
    """The median time of each of ``fns`` over ``repeats`` rounds that run them in turn: a
    change of load on a shared machine then reaches all of them alike, not one more than the
    others (the ratios stay fair)."""
    for fn in fns:
        fn()  # compiled (or loaded from the cache) and warm before the clock starts
    times = [[] for _ in fns]
    for _ in range(repeats):
        for fn, kept in zip(fns, times):
            t = clock()
            fn()
            kept.append(clock() - t)
    return [float(np.median(kept)) for kept in times]


def peak_mib(fn) -> float:
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        fn()
        return (tracemalloc.get_traced_memory()[1] - base) / 2**20
    finally:
        tracemalloc.stop()


def row(n: int, batch: int, steps: int, repeats: int, checkpoint: int, viscosity: str,
        clock, peer_repeats: int = 0) -> dict:
    stepper = get(NAME).benchmark_scene(n, viscosity=viscosity)
    rng = np.random.default_rng(0)
    u0 = stepper.rollout(np.zeros(stepper.state_shape(batch)), 20)
    u0[:, 2] = stepper.random_state(rng, batch)[:, 2]
    w = rng.standard_normal(u0.shape)

    def gradient(k: int, budget: int | None) -> None:
        stepper.vjp(u0, k, w, wrt_params=True, checkpoint=budget)

    forward_s, gradient_s, checkpoint_s = median_times(
        [lambda: stepper.rollout(u0, steps), lambda: gradient(steps, None),
         lambda: gradient(steps, checkpoint)], repeats, clock)
    return {
        "solver": NAME, "nx": stepper.nx, "ny": stepper.ny, "batch": batch, "steps": steps,
        "viscosity": viscosity,
        "forward_s": forward_s,
        "gradient_s": gradient_s,
        "gradient_checkpoint_s": checkpoint_s,
        "checkpoint": checkpoint,
        "peak_mib": peak_mib(lambda: gradient(steps, checkpoint)),
        "peak_mib_4x": peak_mib(lambda: gradient(4 * steps, checkpoint)),
        "state_mib": u0.nbytes / 2**20,
        **(peer_keys(stepper, u0, w, steps, peer_repeats, clock)
           if peer_repeats and batch == 1 and viscosity == "explicit" else {}),
    }


def peer_keys(stepper, u0: np.ndarray, w: np.ndarray, steps: int, repeats: int,
              clock) -> dict:
    """PhiFlow's figures on the same scene (its twin in ``phiflow_peer``)."""
    from importlib.metadata import version

    peer = phiflow_peer.prepare(stepper, u0, w, steps)
    forward_s, gradient_s = median_times([peer["forward"], peer["gradient"]], repeats, clock)
    ours, theirs = stepper.rollout(u0, steps)[:, :2], peer["last"]()[:, :2]
    return {"peer": f"phiflow {version('phiflow')} (torch, jit_compile, scipy-direct)",
            "peer_forward_s": forward_s, "peer_gradient_s": gradient_s,
            "peer_rel_diff": float(np.linalg.norm(theirs - ours) / np.linalg.norm(ours))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("--n", type=int, nargs="+", default=[32, 64],
                        help="channel heights (the channel is 2n × n cells)")
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--checkpoint", type=int, default=8)
    parser.add_argument("--viscosity", choices=("explicit", "implicit"), default="explicit")
    parser.add_argument("--peer-repeats", type=int, default=3,
                        help="rounds of the PhiFlow peer, where installed (0: none)")
    parser.add_argument("--cpu", action="store_true", help="thread CPU time instead of wall time")
    parser.add_argument("--json", type=Path, help="write the rows here")
    args = parser.parse_args()
    peer_repeats = args.peer_repeats
    if importlib.util.find_spec("phi") is None:
        print("PhiFlow is not installed: no peer figures (pip install phiflow to add them)")
        peer_repeats = 0
    elif args.batch != 1 or args.viscosity != "explicit":
        print("the PhiFlow twin is of batch 1 and explicit viscosity: no peer figures")
    rows = []
    with parallel.using_threads(1):
        for n in args.n:
            r = row(n, args.batch, args.steps, args.repeats, args.checkpoint, args.viscosity,
                    time.thread_time if args.cpu else time.perf_counter, peer_repeats)
            rows.append(r)
            print(f"{r['solver']} {r['nx']}×{r['ny']} B={r['batch']} {r['steps']} steps, "
                  f"{r['viscosity']} viscosity: "
                  f"forward {r['forward_s']:.3f} s, gradient {r['gradient_s']:.3f} s "
                  f"({r['gradient_s'] / r['forward_s']:.2f}× forward), checkpointed "
                  f"{r['gradient_checkpoint_s']:.3f} s, peak {r['peak_mib']:.1f} MiB "
                  f"({4 * r['steps']} steps: {r['peak_mib_4x']:.1f} MiB; one state "
                  f"{r['state_mib']:.2f} MiB)", flush=True)
            if "peer" in r:
                print(f"  {r['peer']}: forward {r['peer_forward_s']:.3f} s "
                      f"({r['peer_forward_s'] / r['forward_s']:.0f}× ours), gradient "
                      f"{r['peer_gradient_s']:.3f} s "
                      f"({r['peer_gradient_s'] / r['gradient_s']:.0f}× ours); its velocity "
                      f"after {r['steps']} steps differs from ours by "
                      f"{r['peer_rel_diff']:.1%} (relative L2)", flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
