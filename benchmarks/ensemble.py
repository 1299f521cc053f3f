"""Ensembles against separate runs: K members trained in one process, K runs one after another.

    python benchmarks/ensemble.py [--quick] [--json PATH] [--out DIR]

Two tasks, float32, one thread (torch and the solvers), a fixed number of updates per member:
* ``cartpole``: the StableBPTT controller (an 11k-parameter MLP) at 4 poles, mode R, batch 8;
* ``ks-correction``: List et al.'s KS correction setup, a 33k ResNet (26 × 8), WIG, m = 3,
  batch 16.
For K = 1, 4, 8, 16 members: the time of the ensemble's updates, the time of the K separate
runs' updates, and the members' largest relative deviation of the parameters from their
separate runs (max |Δθ| / max |θ| per tensor). Target: ≥ 4× at K = 8 for both tasks.
``--out DIR`` writes ``ensemble.json``, ``ensemble.md`` and ``ensemble.png`` there.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

import adjointsim
from adjointsim import parallel
from adjointsim.files import pyplot, save_figure, write_json, write_text
from adjointsim.nets import ResNet
from adjointsim.train import control as ctl
from adjointsim.train.ensemble import Stack, _control_update
from adjointsim.train.model import NeuralStepper
from adjointsim.train.unroll import GradientFlow, unrolled_loss

MEMBERS = (1, 4, 8, 16)


def _deviation(stack: Stack, nets: list[torch.nn.Module]) -> float:
    worst = 0.0
    for k, net in enumerate(nets):
        for i, (_, p) in enumerate(net.named_parameters()):
            ref = p.detach()
            worst = max(worst, float((stack.tensors[i][k] - ref).abs().max()
                                     / ref.abs().max().clamp(min=1e-30)))
    return worst


def cartpole(members: int, updates: int) -> tuple[float, float, float]:
    """(ensemble seconds, separate seconds, max relative deviation)."""
    cfgs = [ctl.ControlConfig(task="cartpole", poles=4, mode="R", seed=s) for s in range(members)]
    task = ctl.get_task("cartpole", 4)
    data = [ctl.initial_states(c, task)[0] for c in cfgs]
    batches = [[d[u * 8:(u + 1) * 8] for d in data] for u in range(updates)]
    stack = Stack([ctl.build_net(c, task) for c in cfgs], [c.lr for c in cfgs])
    states = [{"epoch": 0, **ctl._fresh_epoch()} for _ in cfgs]
    start = time.perf_counter()
    for u in range(updates):
        _control_update(cfgs, task, stack, batches[u], states, list(range(members)))
        for s in states:
            s["step"] += 1
    ensemble = time.perf_counter() - start
    nets = [ctl.build_net(c, task) for c in cfgs]
    start = time.perf_counter()
    for k, (cfg, net) in enumerate(zip(cfgs, nets)):
        opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
        state = {"epoch": 0, **ctl._fresh_epoch()}
        for u in range(updates):
            ctl._update(cfg, task, net, opt, list(net.parameters()), batches[u][k], state)
            state["step"] += 1
    separate = time.perf_counter() - start
    return ensemble, separate, _deviation(stack, nets)


def _ks_frames(members: int, updates: int, batch: int, m: int) -> torch.Tensor:
    """(updates, members × batch, m + 1, 1, 48): reference windows, each member its own."""
    ref = adjointsim.get("ks1d-etdrk2").list_et_al(1.0)
    rng = np.random.default_rng(0)
    n = updates * members * batch
    u = ref.rollout(ref.random_state(rng, n) * 0.5, 200, keep="all")[-m - 1:]
    frames = torch.from_numpy(np.swapaxes(u, 0, 1).copy()).float()
    return frames.reshape(updates, members * batch, *frames.shape[1:])


def ks_correction(members: int, updates: int) -> tuple[float, float, float]:
    m, batch = 3, 16
    coarse = adjointsim.get("ks1d-etdrk1").list_et_al(1.0, coarse=True)
    frames = _ks_frames(members, updates, batch, m)
    params = torch.ones(members * batch, dtype=torch.float64)
    cond = torch.ones(members * batch)

    def net(seed: int) -> torch.nn.Module:
        torch.manual_seed(seed)
        return ResNet.preset("small", 2, 1)

    stack = Stack([net(s) for s in range(members)], [1e-3] * members)
    start = time.perf_counter()
    for u in range(updates):
        leaves = stack.leaves()
        model = NeuralStepper(stack.net(leaves, batch), "correction", lambda p: coarse)
        flow = GradientFlow("WIG")
        # the mean over every member's rows × K: the sum of the members' own mean losses
        loss = unrolled_loss(model, frames[u], params, cond, flow) * members
        update = flow.backward(loss, leaves)
        stack.adam(update.grads, list(range(members)))
    ensemble = time.perf_counter() - start
    nets = [net(s) for s in range(members)]
    start = time.perf_counter()
    for k, n in enumerate(nets):
        model = NeuralStepper(n, "correction", lambda p: coarse)
        opt = torch.optim.Adam(n.parameters(), lr=1e-3)
        rows = slice(k * batch, (k + 1) * batch)
        for u in range(updates):
            flow = GradientFlow("WIG")
            loss = unrolled_loss(model, frames[u, rows], params[rows], cond[rows], flow)
            flow.backward(loss, list(n.parameters()))
            opt.step()
    separate = time.perf_counter() - start
    return ensemble, separate, _deviation(stack, nets)


def _plot(rows: list[dict], path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for task in dict.fromkeys(r["task"] for r in rows):
        mine = [r for r in rows if r["task"] == task]
        ax.plot([r["members"] for r in mine], [r["speedup"] for r in mine], "o-", label=task)
    ax.axhline(1, color="k", lw=0.5)
    ax.set_xlabel("members K")
    ax.set_ylabel("speedup: K separate runs / ensemble")
    ax.set_xticks(MEMBERS)
    ax.set_title("Ensembles on one thread (float32)", fontsize=9)
    ax.legend(fontsize=8)
    save_figure(fig, path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="fewer updates (under a minute)")
    parser.add_argument("--json", type=Path, default=None, metavar="PATH")
    parser.add_argument("--out", type=Path, default=None, metavar="DIR")
    args = parser.parse_args()
    torch.set_num_threads(1)
    parallel.set_threads(1)
    updates = {"cartpole": 2 if args.quick else 6, "ks-correction": 2 if args.quick else 8}
    rows = []
    head = ("| task | members | updates each | ensemble s | separate s | speedup | "
            "max rel diff |\n|---|---:|---:|---:|---:|---:|---:|")
    print(head, flush=True)
    for task, fn in (("cartpole", cartpole), ("ks-correction", ks_correction)):
        fn(1, 1)  # warm-up: compilation and first-call costs
        for k in MEMBERS:
            ens, sep, diff = fn(k, updates[task])
            rows.append({"task": task, "members": k, "updates": updates[task],
                         "ensemble_s": ens, "separate_s": sep, "max_rel_diff": diff,
                         "speedup": sep / ens})
            print(f"| {task} | {k} | {updates[task]} | {ens:.3f} | {sep:.3f} | "
                  f"{sep / ens:.2f} | {diff:.1e} |", flush=True)
    table = head + "\n" + "\n".join(
        f"| {r['task']} | {r['members']} | {r['updates']} | {r['ensemble_s']:.3f} | "
        f"{r['separate_s']:.3f} | {r['speedup']:.2f} | {r['max_rel_diff']:.1e} |" for r in rows)
    if args.json is not None:
        write_json(args.json, rows)
    if args.out is not None:
        write_json(args.out / "ensemble.json", rows)
        write_text(args.out / "ensemble.md", table + "\n")
        _plot(rows, args.out / "ensemble.png")


if __name__ == "__main__":
    main()
