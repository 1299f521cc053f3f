"""Per-call overhead of ``adjointsim.train.bridge.step``: what a closed loop pays per solver call.

    python benchmarks/bridge_overhead.py [--repeats 21] [--calls 200]

A controller calls the solver once per step, so the bridge's fixed cost (validation, array
handling, the autograd node, the adjoint's set-up) is paid every step. Side by side in one run,
for tiny scenes (batch 8, controlled):

* ``fast``: the stepper's fast path alone on prepared arrays (``rollout_prepared`` of one step;
  ``vjp_prepared`` of it over that trajectory): the numerics, the allocation of the states and
  cotangents and the non-finite check of the result, no input checks;
* ``bridge``: ``bridge.step(stepper, u, control)`` with ``u`` and ``control`` requiring grad
  (so the forward keeps what the backward needs), then ``torch.autograd.grad`` of the output;
* ``floor``: the least an autograd bridge over the fast path can cost: a bare
  ``torch.autograd.Function`` whose forward and backward call the same fast path, with no
  checks and no copies (unsafe, for reference only);
* ``torch``: a one-op autograd graph (``u * 1.0`` and its gradient), torch's own per-node and
  engine cost.

Printed: median µs per call over ``--repeats`` round-robin batches of ``--calls`` calls, and the
bridge's overhead per step, forward alone and forward + backward: bridge − fast (everything
above the stepper's fast path, torch's autograd machinery included) and bridge − floor (what the
bridge adds to the cheapest custom autograd node: validation, copies, set-up). Target
(a closed loop calls the solver once per step): ≤ 20 µs per step. Times are CPU time of this
process (see ``_per_call_us``).
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

import adjointsim  # noqa: E402
from adjointsim.train import bridge  # noqa: E402

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
    u_np, _, c_np, p = stepper.prepare(
        stepper.random_state(rng, BATCH), 1, stepper.random_controls(rng, 1, BATCH)
    )
    cot_np = rng.standard_normal((1, *u_np.shape))
    cmap = np.array([-1, 0], dtype=np.int64)  # the cotangent of u_1 only, as check_cotangents
    traj = stepper.rollout_prepared(u_np, 1, c_np, p, keep="all")

    def fast_forward():
        stepper.rollout_prepared(u_np, 1, c_np, p, keep="all")

    def fast_both():
        states = stepper.rollout_prepared(u_np, 1, c_np, p, keep="all")
        stepper.vjp_prepared(u_np, 1, c_np, p, cot_np, cmap, trajectory=states)

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
            return torch.from_numpy(stepper.rollout_prepared(u_np, 1, c_np, p))

        @staticmethod
        def backward(ctx, g):
            r = stepper.vjp_prepared(u_np, 1, c_np, p, g.numpy()[None], cmap, trajectory=traj)
            return torch.from_numpy(r.state), torch.from_numpy(r.controls[0])

    def floor_forward():
        Floor.apply(u, c)

    def floor_both():
        torch.autograd.grad(Floor.apply(u, c), (u, c), cot)

    def torch_forward():
        u * 1.0

    def torch_both():
        torch.autograd.grad(u * 1.0, (u,), cot)

    return {
        "fast": (fast_forward, fast_both),
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
        for ref in ("fast", "floor"):
            fwd = med["bridge", 0] - med[ref, 0]
            both = med["bridge", 1] - med[ref, 1]
            print(
                f"  overhead bridge - {ref}: forward {fwd:.1f} µs, "
                f"forward + backward {both:.1f} µs per step"
            )
        print()


if __name__ == "__main__":
    main()
