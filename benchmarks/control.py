"""Cost of one controller update through each simulator (stabilised-BPTT tasks).

    python benchmarks/control.py [--repeats 15] [--batch 8] [--dtype float64|float32]
                                 [--tasks cartpole,guidance,quantum]

Side by side in one run, round-robin, medians over ``--repeats`` updates, per task (at its
hardest level: 4 poles, control weight 0.001, target 5; the paper's networks, batch 8):

* ``R``: one update in mode R (forward through the closed loop, one backward pass);
* ``C``: one update in mode C (one forward, two backward passes, sign rule);
* ``torch``: the same R update with the simulator written in plain torch and differentiated by
  autograd (the classes below; the quantum step is Crank–Nicolson by a batched complex solve).
  Before timing, its loss and parameter gradient are checked against the bridge version to
  1e-10 (relative, float64).

Printed: ms per update and the ratios C/R (target ≤ 1.3) and torch/R (> 1 means the
hand-written adjoints win). Then, per task, what C adds: the network's forward + backward on
all steps' inputs stacked (C's one extra pass) against the same rows in per-step passes at the
batch size (as R runs them).
"""

from __future__ import annotations

import argparse
import os
import time
from functools import partial

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from adjointsim.train import control  # noqa: E402
from adjointsim.train.unroll import GradientFlow  # noqa: E402


class TorchCartPole:
    """The cart-pole step of ``adjointsim.solvers.cartpole`` in torch."""

    def __init__(self, s):
        self.dt = s.dt
        self.g, self.m, self.mt, self.ll = s.param_values

    def __call__(self, u, c):
        q, w, f = u[:, 0], u[:, 1], c[:, :1]
        th, om = q[:, 1:], w[:, 1:]
        a = (f + self.m * self.ll * torch.sin(th) * om**2) / self.mt
        alpha = (self.g * torch.sin(th) - torch.cos(th) * a) / (
            self.ll * (4 / 3 - self.m * torch.cos(th) ** 2 / self.mt))
        acc = (f[:, 0] + self.m * self.ll * (torch.sin(th) * om**2
                                              - alpha * torch.cos(th)).sum(dim=1)) / self.mt
        w = w + self.dt * torch.cat([acc[:, None], alpha], dim=1)
        return torch.stack([q + self.dt * w, w], dim=1)


class TorchGuidance:
    """The guidance step of ``adjointsim.solvers.guidance`` in torch (pairwise broadcasting)."""

    def __init__(self, s):
        self.dt, self.nd = s.dt, s.drivers
        self.a, self.gd, self.ge, self.kd, self.ke = s.param_values
        n = s.drivers + s.evaders
        self.off = ~torch.eye(n, dtype=torch.bool)

    def __call__(self, u, c):
        nd = self.nd
        x, v = u[:, :2], u[:, 2:]
        r = x[:, :, :, None] - x[:, :, None, :]  # (B, 2, i, j) = x_i − x_j
        # |r| with a safe square root on the diagonal (masked out below)
        rho2 = (r**2).sum(dim=1)
        rho = torch.sqrt(torch.where(self.off, rho2, torch.ones_like(rho2)))
        d = 0.1 + rho
        zero = torch.zeros_like(d)
        rep = torch.where(self.off, 1 / d**2, zero)
        coh = torch.where(self.off, (0.5 / d - 1) / d, zero)
        drivers = -self.gd * v[:, :, :nd] + self.kd * (r[:, :, :nd, :nd] * rep[:, None, :nd, :nd]
                                                       ).sum(dim=3)
        w = x[:, :, :nd] - x[:, :, nd:].sum(dim=2, keepdim=True)
        rot = torch.stack([-w[:, 1], w[:, 0]], dim=1)
        drivers = drivers + c[:, None, :, 0] * w + c[:, None, :, 1] * rot
        evaders = (-self.ge * v[:, :, nd:]
                   + self.a * (r[:, :, nd:, :nd] * rep[:, None, nd:, :nd]).sum(dim=3)
                   + self.ke * (r[:, :, nd:, nd:] * coh[:, None, nd:, nd:]).sum(dim=3))
        acc = torch.cat([drivers, evaders], dim=2)
        return torch.cat([x + self.dt * v, v + self.dt * acc], dim=1)


class TorchSchrodinger:
    """Crank–Nicolson of ``schrodinger1d-cn`` in torch: a batched complex dense solve."""

    def __init__(self, s):
        n = s.n
        t = np.diag(np.full(n, 2.0)) - np.diag(np.ones(n - 1), 1) - np.diag(np.ones(n - 1), -1)
        self.kin = torch.tensor(s.kinetic * t, dtype=torch.complex128)
        self.x = torch.tensor(s.x, dtype=torch.complex128)
        self.eye = torch.eye(n, dtype=torch.complex128)
        self.half = 0.5j * s.dt

    def __call__(self, u, c):
        cd = torch.complex64 if u.dtype == torch.float32 else torch.complex128
        psi = torch.complex(u[:, 0], u[:, 1])
        h = self.kin.to(cd) + torch.diag_embed(c[:, :1].to(cd) * self.x.to(cd))
        eye = self.eye.to(cd)
        lhs, rhs = eye + self.half * h, eye - self.half * h
        out = torch.linalg.solve(lhs, (rhs @ psi[:, :, None]))[:, :, 0]
        return torch.stack([out.real, out.imag], dim=1)


TORCH_STEPS = {"cartpole": TorchCartPole, "guidance": TorchGuidance,
               "quantum": TorchSchrodinger}


def torch_loss(task, net, x0, step):
    x, terms = x0, []
    for t in range(task.steps):
        c = task.control(net(x))
        x = step(x, c)
        term = task.step_loss(x, c, t)
        if term is not None:
            terms.append(term)
    return task.total(terms)


def setup(name, batch, dtype=torch.float64):
    task = control.get_task(name, control.TASKS.get(name).levels[-1])
    torch.manual_seed(0)
    net = task.net().to(dtype)
    for m in net.modules():  # a trained-looking controller, not the zero-initialised one
        if isinstance(m, torch.nn.Linear | torch.nn.Conv1d):
            m.reset_parameters()
            with torch.no_grad():
                m.weight.mul_(0.3)
    x0 = torch.from_numpy(task.initial_states(np.random.default_rng(0), batch)).to(dtype)
    return task, net, x0


def update_ours(task, net, x0, mode):
    params = list(net.parameters())
    flow = GradientFlow(mode)
    loss = control.closed_loop(task, net, x0, flow)[0]
    return loss, flow.backward(loss, params).grads


def update_torch(task, net, x0, step):
    params = list(net.parameters())
    loss = torch_loss(task, net, x0, step)
    return loss, torch.autograd.grad(loss, params)


def agreement(task, net, x0, step) -> float:
    la, ga = update_ours(task, net, x0, "R")
    lb, gb = update_torch(task, net, x0, step)
    a = torch.cat([la.detach()[None]] + [g.flatten() for g in ga])
    b = torch.cat([lb.detach()[None]] + [g.flatten() for g in gb])
    return float((a - b).norm() / b.norm())


def network_passes(task, net, x0, repeats: int) -> tuple[float, float]:
    """ms of one stacked network forward + backward over steps × batch rows, and of the same
    rows as ``steps`` passes of the batch size."""
    params = list(net.parameters())
    rows = torch.randn(task.steps * x0.shape[0], *x0.shape[1:], dtype=x0.dtype)

    def passes(size):
        for i in range(0, rows.shape[0], size):
            torch.autograd.grad(net(rows[i:i + size]).sum(), params)

    out = []
    for size in (rows.shape[0], x0.shape[0]):
        passes(size)
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            passes(size)
            times.append(time.perf_counter() - t)
        out.append(1e3 * float(np.median(times)))
    return out[0], out[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--tasks", default="cartpole,guidance,quantum")
    ap.add_argument("--dtype", choices=("float64", "float32"), default="float64",
                    help="of the timed updates (the agreement check always runs in float64)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    dtype = getattr(torch, args.dtype)
    print(f"{args.dtype}, batch {args.batch}, one thread; ms per update "
          f"(median of {args.repeats})")
    print(f"{'task':<9} {'steps':>5} {'R':>8} {'C':>8} {'torch':>8} {'C/R':>6} {'torch/R':>8} "
          f"{'agree':>8}")
    passes = {}
    for name in args.tasks.split(","):
        task, net, x0 = setup(name, args.batch)
        step = TORCH_STEPS[name](task.solver)
        err = agreement(task, net, x0, step)
        if not err <= 1e-10:
            raise SystemExit(f"{name}: the torch baseline disagrees with the bridge ({err:.2e})")
        if dtype != torch.float64:
            task, net, x0 = setup(name, args.batch, dtype)
        runs = {"R": partial(update_ours, task, net, x0, "R"),
                "C": partial(update_ours, task, net, x0, "C"),
                "torch": partial(update_torch, task, net, x0, step)}
        for f in runs.values():
            f()  # warm-up (numba compilation, torch caches)
        times = {k: [] for k in runs}
        for _ in range(args.repeats):
            for k, f in runs.items():
                t = time.perf_counter()
                f()
                times[k].append(time.perf_counter() - t)
        med = {k: 1e3 * float(np.median(v)) for k, v in times.items()}
        print(f"{name:<9} {task.steps:>5} {med['R']:8.1f} {med['C']:8.1f} {med['torch']:8.1f} "
              f"{med['C'] / med['R']:6.2f} {med['torch'] / med['R']:8.2f} {err:8.1e}", flush=True)
        passes[name] = network_passes(task, net, x0, args.repeats)
    for name, (stacked, per_step) in passes.items():
        print(f"{name}: network forward + backward, all steps stacked (C's extra pass) "
              f"{stacked:.1f} ms; the same rows in per-step passes {per_step:.1f} ms")


if __name__ == "__main__":
    main()
