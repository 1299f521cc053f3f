"""Per-call overhead of ``adjointsim.train.bridge.step``: what a closed loop pays per solver call.

    python benchmarks/bridge_overhead.py [--repeats 21] [--calls 200]

A controller calls the solver once per step, so the bridge's fixed cost (validation, array
handling, the autograd node, the adjoint's set-up) is paid every step. Side by side in one run,
for tiny scenes (batch 8, controlled):

* ``kernel``: the stepper's numba kernels alone (``_forward`` one step; ``_adjoint`` of it),
  on preallocated arrays: the floor;
* ``bridge``: ``bridge.step(stepper, u, control)`` with ``u`` and ``control`` requiring grad
  (so the forward keeps what the backward needs), then ``torch.autograd.grad`` of the output;
* ``floor``: the least any Python autograd bridge can cost: a bare ``torch.autograd.Function``
  whose forward and backward call the same kernels on preallocated arrays, with no checks, no
  copies and no allocation (unsafe, for reference only);
* ``torch``: a one-op autograd graph (``u * 1.0`` and its gradient), torch's own per-node and
  engine cost.

Printed: median µs per call over ``--repeats`` round-robin batches of ``--calls`` calls, and the
bridge's overhead per step, forward alone and forward + backward: bridge − kernel (everything
above the numerics, torch's autograd machinery included) and bridge − floor (what the bridge
adds to the cheapest possible custom autograd node: validation, copies, set-up). Target
(issue 9): ≤ 20 µs per step. Times are CPU time of this process (see ``_per_call_us``).
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from adjointsim.train import bridge  # noqa: E402

import adjointsim  # noqa: E402

BATCH = 8
SCENES = {
    "schrodinger1d-cn (32 points)": lambda: adjointsim.get("schrodinger1d-cn")(n=32),
    "diffusion1d-ftcs (16 points)": lambda: adjointsim.get("diffusion1d-ftcs")(n=16),
}


def _per_call_us(fn, calls: int, repeats: int) -> float:
    """Median over ``repeats`` batches of the mean CPU time per call, in µs.

    CPU time of this process, not wall time: on a shared machine the wall clock also counts the
    time other processes hold the core, which swamps differences of a few µs.
    """
    fn()  # compile / warm up
    times = []
    for _ in range(repeats):
        t0 = time.process_time()
        for _ in range(calls):
            fn()
        times.append((time.process_time() - t0) / calls * 1e6)
    return float(np.median(times))


def _candidates(stepper) -> dict:
    rng = np.random.default_rng(0)
    u_np = stepper.random_state(rng, BATCH)
    c_np = stepper.random_controls(rng, 1, BATCH)
    p = stepper.param_array(None, np.float64)
    states = np.empty((2, *u_np.shape))
    states[0] = u_np
    inputs = np.ascontiguousarray(states[:1])
    cot_np = rng.standard_normal((1, *u_np.shape))
    cmap = np.array([-1, 0], dtype=np.int64)
    ubar, cbar = np.zeros_like(u_np), np.zeros_like(c_np)
    pbar = np.zeros(len(stepper.param_names))

    def kernel_forward():
        stepper._forward(states, 1, c_np, p)

    def kernel_both():
        stepper._forward(states, 1, c_np, p)
        ubar[:] = cot_np[0]
        stepper._adjoint(inputs, c_np, p, cot_np, cmap[:1], ubar, cbar, pbar, False)

    u = torch.from_numpy(u_np).requires_grad_()
    c = torch.from_numpy(c_np[0]).requires_grad_()
    cot = torch.from_numpy(cot_np[0])

    def bridge_forward():
        bridge.step(stepper, u, c)

    def bridge_both():
        torch.autograd.grad(bridge.step(stepper, u, c), (u, c), cot)

    class Floor(torch.autograd.Function):
        @staticmethod
        def forward(ctx, u, c):
            stepper._forward(states, 1, c_np, p)
            return torch.from_numpy(states[1])

        @staticmethod
        def backward(ctx, g):
            ubar[:] = g.numpy()
            stepper._adjoint(inputs, c_np, p, cot_np, cmap[:1], ubar, cbar, pbar, False)
            return torch.from_numpy(ubar), torch.from_numpy(cbar[0])

    def floor_forward():
        Floor.apply(u, c)

    def floor_both():
        torch.autograd.grad(Floor.apply(u, c), (u, c), cot)

    def torch_forward():
        u * 1.0

    def torch_both():
        torch.autograd.grad(u * 1.0, (u,), cot)

    return {
        "kernel": (kernel_forward, kernel_both),
        "bridge": (bridge_forward, bridge_both),
        "floor": (floor_forward, floor_both),
        "torch": (torch_forward, torch_both),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=21)
    parser.add_argument("--calls", type=int, default=200)
    args = parser.parse_args()
    torch.set_num_threads(1)
    for label, make in SCENES.items():
        stepper = make()
        cands = _candidates(stepper)
        # Round-robin, so that load changes on the shared machine hit every candidate alike.
        samples: dict[tuple[str, int], list[float]] = {}
        for _ in range(args.repeats):
            for name, fns in cands.items():
                for i, fn in enumerate(fns):
                    samples.setdefault((name, i), []).append(_per_call_us(fn, args.calls, 1))
        med = {k: float(np.median(v)) for k, v in samples.items()}
        print(f"{label}, batch {BATCH}, one controlled step, median µs per call:")
        print(f"  {'':8s} {'forward':>10s} {'fwd+bwd':>10s}")
        for name in cands:
            print(f"  {name:8s} {med[name, 0]:10.1f} {med[name, 1]:10.1f}")
        for ref in ("kernel", "floor"):
            fwd = med["bridge", 0] - med[ref, 0]
            both = med["bridge", 1] - med[ref, 1]
            print(
                f"  overhead bridge - {ref}: forward {fwd:.1f} µs, "
                f"forward + backward {both:.1f} µs per step"
            )
        print()


if __name__ == "__main__":
    main()
