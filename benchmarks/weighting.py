"""One full-batch epoch of the Poisson PINN (2500 collocation + 400 boundary points, the
[2, 50×5, 1] tanh network, Adam) under every loss-balancing scheme of
:mod:`adjointsim.train.weighting`, against ``uniform``, side by side in one process.

Rounds go through the schemes in turn; each round times ``--epochs`` epochs (a multiple of the
refresh interval ``every`` = 5, so the schemes that refresh every fifth epoch pay their share)
in CPU time of this one-thread process, which a shared machine's other load disturbs less than
wall-clock. Printed: the median epoch time per scheme, its ratio to uniform and the target of
its class: schemes that need only the losses or one gradient norm per term (on the output
layer) ≤ 1.2x, schemes that need every term's full gradient (or per-sample residual
gradients) ≤ 1.6x at two terms. On the ``taylor`` route (the default) the per-term gradients
are taken one term after another, since its hand-written reverse pass has no batching rule;
``--route autograd`` shows the batched pass.
Run: ``python benchmarks/weighting.py [--rounds 5] [--epochs 10] [--route taylor]``.
"""

from __future__ import annotations

import argparse
import os
import time
from statistics import median

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402

from adjointsim.train.pinn import (  # noqa: E402
    NTK_POINTS,
    PinnConfig,
    make_problem,
    make_weighting,
)
from adjointsim.train.weighting import RULES, SCHEMES  # noqa: E402


def epoch_time(rule: str, route: str, epochs: int, start: int) -> float:
    """Seconds of CPU time per epoch over ``epochs`` epochs from epoch ``start``."""
    cfg = PinnConfig(k=4, weighting=rule, route=route)
    problem = make_problem(cfg)
    model = problem.model()
    params = list(model.parameters())
    opt = torch.optim.Adam(params, lr=cfg.lr)
    w = make_weighting(cfg, problem)
    t0 = time.process_time()
    for epoch in range(start, start + epochs):
        opt.zero_grad(set_to_none=True)
        w.backward(problem.losses(model, route), params, epoch,
                   lambda: problem.residuals(model, route, NTK_POINTS))
        opt.step()
    return (time.process_time() - t0) / epochs


def target(rule: str) -> float:
    scheme = SCHEMES[rule]
    return 1.6 if scheme.needs in ("grads", "residuals") and not scheme.layer else 1.2


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--epochs", type=int, default=10, help="epochs per timed round")
    p.add_argument("--route", default="taylor", choices=("taylor", "autograd"))
    args = p.parse_args()
    torch.set_num_threads(1)
    times: dict[str, list[float]] = {r: [] for r in RULES}
    for rule in times:  # warm-up, and past the first steps' special cases
        epoch_time(rule, args.route, 2, 0)
    for _ in range(args.rounds):
        for rule in times:
            times[rule].append(epoch_time(rule, args.route, args.epochs, 5))
    base = median(times["uniform"])
    print(f"Poisson PINN epoch (2500 + 400 points, [2, 50x5, 1] tanh, route {args.route}), "
          f"1 thread, CPU time, median of {args.rounds} rounds x {args.epochs} epochs")
    print(f"{'scheme':<18} {'needs':<10} {'ms/epoch':>9} {'x uniform':>10} {'target':>7}")
    for rule, ts in times.items():
        t = median(ts)
        needs = "layer" if SCHEMES[rule].layer else SCHEMES[rule].needs or "-"
        print(f"{rule:<18} {needs:<10} {1e3 * t:9.2f} {t / base:10.2f} "
              f"{'' if rule == 'uniform' else f'<= {target(rule)}':>7}")


if __name__ == "__main__":
    main()
