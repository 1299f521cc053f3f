"""One full-batch epoch of the Poisson PINN (2500 collocation + 400 boundary points, the
[2, 50×5, 1] tanh network, Adam, ID weighting as configured) with Δu from the forward Taylor
route (nets/taylor.py) against nested reverse-mode autograd, side by side in one process.

Rounds alternate the two routes; each round times ``--epochs`` epochs in CPU time of this
(one-thread) process, which a shared machine's other load disturbs less than wall-clock; the
median epoch time per route and the ratio are printed. A profiled epoch lists the forward
route's matrix products (torch's mm/addmm calls), which are replayed alone on warm buffers:
their time bounds the speed-up the route could reach if everything else cost nothing. Timing
the forward Laplacian alone splits the epoch into it and the rest (the boundary term, the
weighting, Adam), and the last line says how fast the Laplacian would have to be for 3x.
Run: ``python benchmarks/pinn.py [--rounds 7]``.
"""

from __future__ import annotations

import argparse
import os
import time
from statistics import median

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from weighting import epoch_time  # noqa: E402  (the one timed epoch, beside this file)

from adjointsim.train.pinn import PinnConfig, make_problem  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--epochs", type=int, default=20, help="epochs per timed round")
    p.add_argument("--weighting", default="inverse-dirichlet")
    args = p.parse_args()
    torch.set_num_threads(1)
    times = {"taylor": [], "autograd": []}
    for route in times:  # warm-up
        epoch_time(args.weighting, route, 2, 0)
    for _ in range(args.rounds):
        for route in times:
            times[route].append(epoch_time(args.weighting, route, args.epochs, 0))
    t_f, t_a = median(times["taylor"]), median(times["autograd"])
    print(f"Poisson PINN epoch (2500 + 400 points, [2, 50x5, 1] tanh, {args.weighting}), "
          f"1 thread, CPU time, median of {args.rounds} rounds x {args.epochs} epochs")
    print(f"  forward Taylor : {1e3 * t_f:7.2f} ms/epoch  {1 / t_f:7.1f} epochs/s")
    print(f"  nested autograd: {1e3 * t_a:7.2f} ms/epoch  {1 / t_a:7.1f} epochs/s")
    print(f"  speed-up       : {t_a / t_f:.2f}x")
    floor, inside, lap, rest, elementwise = split("taylor", args.weighting)
    print(f"  matrix products: {1e3 * floor:7.2f} ms/epoch for the forward Taylor route's "
          f"products alone, each replayed on warm buffers ({1e3 * inside:.2f} ms of them in "
          "the forward Laplacian)")
    print(f"  bound          : {t_a / floor:.2f}x if all but those products were free")
    print(f"  split          : the forward Laplacian alone (forward + reverse) {1e3 * lap:.2f} "
          f"ms/epoch, the rest of the epoch {1e3 * rest:.2f} ms")
    print(f"  3x needs       : the forward Laplacian in ≤ {1e3 * (t_a / 3 - rest):.2f} ms/epoch "
          f"(its products alone: {1e3 * inside:.2f} ms)")
    low = inside + elementwise + rest
    print(f"  floor          : {1e3 * low:.2f} ms/epoch = the Laplacian's products "
          f"{1e3 * inside:.2f} + its tanh and one write of each array its layers must write "
          f"{1e3 * elementwise:.2f} (warm) + the rest {1e3 * rest:.2f}: at most {t_a / low:.2f}x")


_LAPLACIAN = ("_ForwardLaplacian", "_ForwardLaplacianBackward")


def split(route: str, weighting: str,
          epochs: int = 10) -> tuple[float, float, float, float, float]:
    """Seconds per epoch: the route's matrix products alone, all and those inside the forward
    Laplacian's Function (the mm/addmm calls of a profiled round, by shape, each replayed on
    preallocated inputs and outputs, so without allocation or page faults; median of 5
    repeats); then, unprofiled, the forward Laplacian alone (forward and reverse, as in the
    epoch) and the rest of the epoch; last, the Laplacian's element-wise floor
    (:func:`elementwise_floor`)."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        epoch_time(weighting, route, 2, 0)
    calls: dict[tuple, int] = {}
    for e in prof.events():
        if e.name not in ("aten::mm", "aten::addmm"):
            continue
        n = 2 if e.name == "aten::mm" else 3  # (an out= tensor comes after)
        parent, inside = e.cpu_parent, False
        while parent is not None and not inside:
            inside, parent = parent.name in _LAPLACIAN, parent.cpu_parent
        key = (e.name, tuple(tuple(s) for s in e.input_shapes[:n]), inside)
        calls[key] = calls.get(key, 0) + 1
    floor = inside_floor = 0.0
    for (name, shapes, inside), count in calls.items():
        op = torch.mm if name == "aten::mm" else torch.addmm
        args = [torch.rand(s) for s in shapes]
        out = torch.empty(shapes[-2][0], shapes[-1][1])
        reps = []
        for _ in range(5):
            t0 = time.perf_counter()
            for _ in range(20):
                op(*args, out=out)
            reps.append((time.perf_counter() - t0) / 20)
        t = median(reps) * count / 2
        floor += t
        inside_floor += t if inside else 0.0
    problem = make_problem(PinnConfig(k=4, weighting=weighting, route=route))
    model = problem.model()
    params = list(model.parameters())
    lap, whole = [], []
    for _ in range(5):
        t0 = time.process_time()
        for _ in range(epochs):
            res = model.laplacian(problem.x_col, route) - problem.f_col
            torch.autograd.grad((res**2).mean(), params)
        lap.append((time.process_time() - t0) / epochs)
        whole.append(epoch_time(weighting, route, epochs, 0))
    return (floor, inside_floor, median(lap), median(whole) - median(lap),
            elementwise_floor(model, *problem.x_col.shape))


def elementwise_floor(model: torch.nn.Module, n: int, dirs: int) -> float:
    """Seconds per epoch that no fusing of the forward Laplacian's element-wise work removes
    (n points, derivatives along dirs axes): tanh of each hidden layer's (n, width)
    pre-activations, and one write pass (a copy, warm)
    per array the layers must produce: forward, the D first-order and the second-order
    streams; reverse, the cotangents of the D + 2 pre-activation streams (the first layer's
    value stream only: its other streams are the same for every point)."""
    widths = [m.out_features for m in model.modules() if isinstance(m, torch.nn.Linear)][:-1]
    arrays = {w: (torch.rand(n, w).numpy(), torch.empty(n, w).numpy()) for w in widths}
    reps = []
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(20):
            for i, w in enumerate(widths):
                src, dst = arrays[w]
                np.tanh(src, out=dst)
                for _ in range(dirs + 1 + (1 if i == 0 else dirs + 2)):
                    np.copyto(dst, src)
        reps.append((time.perf_counter() - t0) / 20)
    return median(reps)


if __name__ == "__main__":
    main()
