"""Ensembles against separate runs: K members trained in one process, K runs one after another.

    python benchmarks/ensemble.py [--quick] [--json PATH] [--out DIR]

Two tasks, one thread (torch and the solvers), a fixed number of updates per member:
* ``cartpole``: the StableBPTT controller (an 11k-parameter MLP) at 4 poles, mode R, batch 8
  (the updates alone);
* ``ks-correction``: List et al.'s KS correction setup, a 33k ResNet (26 × 8), WIG, m = 3,
  batch 16, through the trainer itself: ``train_ensemble`` against ``train`` per member, each
  timed whole (building the nets, loading the data, the updates, the final checkpoints) on the
  ``tiny`` KS dataset (48 grid points, as the paper's).
For K = 1, 4, 8, 16 members in float32, and K = 4 in float64: the time of the ensemble, the
time of the K separate runs, and the members' largest relative deviation of the parameters
from their separate runs (max |Δθ| / max |θ| per tensor). Target: ≥ 4× at K = 8 for both tasks.
``--out DIR`` writes ``ensemble.json``, ``ensemble.md`` and ``ensemble.png`` there.

    python benchmarks/ensemble.py --routes [--quick] [--json PATH] [--out DIR]

compares two ways to run an ensemble's update, side by side in one run, on the cart-pole
controller (4 poles, mode R, batch 8), for K = 1, 2, 4, 8 members: ``stacked``, the route
:mod:`adjointsim.train.ensemble` takes (the members' layers as batched matrix products, one
solver call per step for all), and ``vmap``, ``torch.func.vmap`` of
``torch.func.grad_and_value`` of one member's whole loss (its net through
``torch.func.functional_call`` over ``torch.func.stack_module_state``'s stacked parameters, the
solver call inside: the bridge's vmap rule makes it one call for all members), with the same
per-member clipping, bookkeeping and stacked Adam step. Each update is timed alone, the three
(a single run's update, stacked, vmap) in turn; the medians give speedup = K × single /
ensemble. The epoch's first update, which also diagnoses cos(g_M, g_R), is left out: every
other update is alike. ``max_rel_diff`` compares the vmap route's members after the timed
updates with the stacked route's. ``--out DIR`` writes ``routes.json`` and ``routes.md``.

    python benchmarks/ensemble.py --convs [--quick] [--json PATH] [--out DIR]

times the convolutional networks' forward and backward pass in an ensemble, side by side in one
run: ``batched``, each 1D convolution one batched matrix product over the members (the route
the ensembles take), against ``vmap`` of ``functional_call`` (the grouped convolutions vmap
makes of them), for List et al.'s KS ResNet (26 × 8, batch 16, 48 points) and the quantum
controller (batch 8, 32 points) at K = 3 and 8. The two alternate; medians; ``max_rel_diff``
compares their outputs and gradients. ``--out DIR`` writes ``convs.json`` and ``convs.md``.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import tempfile
import time
from pathlib import Path

import torch
from torch.func import functional_call, grad_and_value, vmap

from adjointsim import parallel
from adjointsim.files import pyplot, save_figure, write_json, write_text
from adjointsim.train import bridge
from adjointsim.train import control as ctl
from adjointsim.train import data as datamod
from adjointsim.train.checkpoint import load_checkpoint
from adjointsim.train.ensemble import ControllerEnsemble, Stack, train_ensemble
from adjointsim.train.trainer import TrainConfig, train
from adjointsim.train.unroll import Update, clip_update

MEMBERS = (1, 4, 8, 16)
ROUTE_MEMBERS = (1, 2, 4, 8)


def _deviation(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> float:
    return max(float((a[n] - b[n]).abs().max() / b[n].abs().max().clamp(min=1e-30)) for n in b)


def _controllers(members: int, dtype: str, where: Path) -> list[ctl.Controller]:
    """Cart-pole controllers at 4 poles, mode R, one per seed, built (not yet trained)."""
    out = []
    for s in range(members):
        cfg = ctl.ControlConfig(task="cartpole", level=4, mode="R", seed=s, dtype=dtype,
                                out=str(where / f"s{s}"))
        cfg.validate()
        run = ctl.Controller(cfg)
        run.build()
        out.append(run)
    return out


def cartpole(members: int, updates: int, dtype: str, work: Path) -> tuple[float, float, float]:
    """(ensemble seconds, separate seconds, max relative deviation) of ``updates`` minibatch
    updates per member (fewer than an epoch's: no evaluation), through the ensemble's updater
    and through each run's own update."""
    ensemble = ControllerEnsemble(_controllers(members, dtype, work / "ensemble"))
    start = time.perf_counter()
    for _ in range(updates):
        ensemble.update()
    together = time.perf_counter() - start
    ensemble.sync()
    runs = _controllers(members, dtype, work / "separate")
    start = time.perf_counter()
    for run in runs:
        for _ in range(updates):
            run.update()
    separate = time.perf_counter() - start
    return together, separate, max(
        _deviation(*({n: p.detach() for n, p in r.net.named_parameters()} for r in pair))
        for pair in zip(ensemble.members, runs))


def ks_correction(members: int, updates: int, dtype: str, work: Path
                  ) -> tuple[float, float, float]:
    data = work / "ks-tiny.h5"
    if not data.exists():
        datamod.save(datamod.generate("ks", "tiny", seed=0, progress=False), data)
    where = work / f"ks-{dtype}-{members}"

    def cfg(kind: str, seed: int) -> TrainConfig:
        return TrainConfig(data=str(data), out=str(where / kind / f"s{seed}"), mode="WIG",
                           unroll=3, width=26, blocks=8, batch=16, lr=1e-3, epochs=100.0,
                           stride=1, dtype=dtype, seed=seed, max_iterations=updates,
                           checkpoint_every=10**6)

    start = time.perf_counter()
    train_ensemble([cfg("ensemble", s) for s in range(members)], progress=False)
    ensemble = time.perf_counter() - start
    start = time.perf_counter()
    for s in range(members):
        train(cfg("separate", s), progress=False)
    separate = time.perf_counter() - start
    return ensemble, separate, max(
        _deviation(*(load_checkpoint(where / kind / f"s{s}" / "checkpoint.pt",
                                     ("state",))["state"]["model"]
                     for kind in ("ensemble", "separate")))
        for s in range(members))


def vmap_update(ensemble: ControllerEnsemble) -> None:
    """One minibatch update of every member of ``ensemble`` through ``torch.func``: vmap of
    the gradient of one member's closed loop, then the stacked route's per-member clipping,
    record and Adam step (an epoch's first update, its diagnosis, is not covered)."""
    members, stack = ensemble.members, ensemble.stack
    task = members[0].task

    def loss(params: tuple[torch.Tensor, ...], x: torch.Tensor) -> torch.Tensor:
        weights = dict(zip(stack.names, params))
        terms = []
        for t in range(task.steps):
            c = task.control(functional_call(stack.template, weights, (x,)))
            x = bridge.step(task.solver, x, c)
            term = task.step_loss(x, c, t)
            if term is not None:
                terms.append(term)
        return task.total(terms)

    # the stacked tensors themselves (no outer tape: torch.func.grad keeps its own)
    grads, losses = vmap(grad_and_value(loss))(tuple(stack.tensors),
                                               torch.stack([m.batch() for m in members]))
    for k, m in enumerate(members):
        update = Update(clip_update([g[k] for g in grads], m.config.clip))
        ctl.record(m.state, float(losses[k]), update, False)
    stack.adam(list(grads), list(range(len(members))))
    for m in members:
        m.advance(0.0)


def routes(members: int, updates: int, work: Path) -> dict:
    """Per-update medians (seconds) of a single run, the stacked route and the vmap route at
    ``members`` members, timed in turn, and the routes' largest relative deviation."""
    single = _controllers(1, "float32", work / "single")[0]
    stacked = ControllerEnsemble(_controllers(members, "float32", work / "stacked"))
    mapped = ControllerEnsemble(_controllers(members, "float32", work / "vmap"))
    for run in (single, *stacked.members, *mapped.members):
        run.state["step"] = 1  # past the epoch's first update (its diagnosis)
    timed = {"single": single.update, "stacked": stacked.update,
             "vmap": lambda: vmap_update(mapped)}
    times: dict[str, list[float]] = {name: [] for name in timed}
    for _ in range(updates):
        for name, update in timed.items():
            start = time.perf_counter()
            update()
            times[name].append(time.perf_counter() - start)
    stacked.sync()
    mapped.sync()
    med = {name: statistics.median(t) for name, t in times.items()}
    return {"task": "cartpole", "members": members, "updates": updates,
            **{f"{name}_s": v for name, v in med.items()},
            "stacked_speedup": members * med["single"] / med["stacked"],
            "vmap_speedup": members * med["single"] / med["vmap"],
            "max_rel_diff": max(
                _deviation(*({n: p.detach() for n, p in r.net.named_parameters()}
                             for r in pair))
                for pair in zip(mapped.members, stacked.members))}


def _route_line(r: dict) -> str:
    return (f"| {r['task']} | {r['members']} | {r['updates']} | {1e3 * r['single_s']:.1f} | "
            f"{1e3 * r['stacked_s']:.1f} | {1e3 * r['vmap_s']:.1f} | "
            f"{r['stacked_speedup']:.2f} | {r['vmap_speedup']:.2f} | {r['max_rel_diff']:.1e} |")


def compare_routes(updates: int, json_path: Path | None, out: Path | None) -> None:
    head = ("| task | members | updates | single ms | stacked ms | vmap ms | stacked speedup | "
            "vmap speedup | vmap vs stacked max rel diff |\n"
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    print(head, flush=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        routes(1, 2, Path(tmp) / "warm-up")  # compilation and first-call costs
        for k in ROUTE_MEMBERS:
            rows.append(routes(k, updates, Path(tmp) / f"k{k}"))
            print(_route_line(rows[-1]), flush=True)
    if json_path is not None:
        write_json(json_path, rows)
    if out is not None:
        write_json(out / "routes.json", rows)
        write_text(out / "routes.md", head + "\n" + "\n".join(map(_route_line, rows)) + "\n")


def convs(net: torch.nn.Module, members: int, x: torch.Tensor, repeats: int) -> dict:
    """Median seconds of one forward and backward pass of ``members`` copies of ``net`` on
    ``x`` (every member's rows), batched and under vmap, and their largest deviation."""
    torch.manual_seed(0)
    nets = [_fresh(net) for _ in range(members)]
    rows = len(x) // members
    stacks = {"batched": Stack(nets, (1e-3,) * members),
              "vmap": Stack(nets, (1e-3,) * members, batched=False)}
    times: dict[str, list[float]] = {k: [] for k in stacks}
    results = {}
    for i in range(repeats + 2):
        for name, stack in stacks.items():
            start = time.perf_counter()
            leaves = stack.leaves()
            y = stack.net(leaves, rows)(x)
            grads = torch.autograd.grad(y.square().sum(), leaves)
            if i >= 2:  # the first two: warm-up
                times[name].append(time.perf_counter() - start)
            results[name] = [y.detach(), *grads]
    diff = max(float((a - b).abs().max() / b.abs().max())
               for a, b in zip(results["batched"], results["vmap"]))
    batched, plain = (statistics.median(times[k]) for k in ("batched", "vmap"))
    return {"members": members, "batched_s": batched, "vmap_s": plain,
            "speedup": plain / batched, "max_rel_diff": diff}


def _fresh(net: torch.nn.Module) -> torch.nn.Module:
    """A copy of ``net`` with newly drawn weights (each member its own)."""
    out = copy.deepcopy(net)
    for m in out.modules():
        if hasattr(m, "reset_parameters"):
            m.reset_parameters()
    return out


def compare_convs(repeats: int, json_path: Path | None, out: Path | None) -> None:
    from adjointsim.nets.resnet import ResNet
    from adjointsim.train.tasks import get_task

    cases = {"KS ResNet 26x8": (ResNet.preset("small", 2, 1), 16, (2, 48)),
             "quantum controller": (get_task("quantum", 5).net(), 8, (2, 32))}
    head = ("| network | members | batched ms | vmap ms | speedup | max rel diff |\n"
            "|---|---:|---:|---:|---:|---:|")
    print(head, flush=True)
    rows = []
    for name, (net, batch, shape) in cases.items():
        for k in (3, 8):
            x = torch.randn(k * batch, *shape)
            rows.append({"network": name, **convs(net, k, x, repeats)})
            r = rows[-1]
            print(f"| {name} | {k} | {1e3 * r['batched_s']:.2f} | {1e3 * r['vmap_s']:.2f} | "
                  f"{r['speedup']:.2f} | {r['max_rel_diff']:.1e} |", flush=True)
    lines = [head] + [f"| {r['network']} | {r['members']} | {1e3 * r['batched_s']:.2f} | "
                      f"{1e3 * r['vmap_s']:.2f} | {r['speedup']:.2f} | "
                      f"{r['max_rel_diff']:.1e} |" for r in rows]
    if json_path is not None:
        write_json(json_path, rows)
    if out is not None:
        write_json(out / "convs.json", rows)
        write_text(out / "convs.md", "\n".join(lines) + "\n")


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
    parser.add_argument("--quick", action="store_true", help="fewer updates (a minute or two)")
    parser.add_argument("--json", type=Path, default=None, metavar="PATH")
    parser.add_argument("--out", type=Path, default=None, metavar="DIR")
    parser.add_argument("--routes", action="store_true",
                        help="compare the stacked route with torch.func.vmap (cart-pole)")
    parser.add_argument("--convs", action="store_true",
                        help="compare batched convolutions with vmap's (KS ResNet, quantum)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    parallel.set_threads(1)
    if args.routes:
        compare_routes(5 if args.quick else 15, args.json, args.out)
        return
    if args.convs:
        compare_convs(10 if args.quick else 50, args.json, args.out)
        return
    updates = {"cartpole": 2 if args.quick else 6, "ks-correction": 4 if args.quick else 16}
    runs = [(k, "float32") for k in MEMBERS] + [(4, "float64")]
    rows = []
    head = ("| task | dtype | members | updates each | ensemble s | separate s | speedup | "
            "max rel diff |\n|---|---|---:|---:|---:|---:|---:|---:|")
    print(head, flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for task, fn in (("cartpole", cartpole), ("ks-correction", ks_correction)):
            fn(1, 1, "float32", Path(tmp) / "warm-up")  # compilation and first-call costs
            for k, dtype in runs:
                ens, sep, diff = fn(k, updates[task], dtype, Path(tmp))
                rows.append({"task": task, "dtype": dtype, "members": k,
                             "updates": updates[task], "ensemble_s": ens, "separate_s": sep,
                             "max_rel_diff": diff, "speedup": sep / ens})
                print(_line(rows[-1]), flush=True)
    table = head + "\n" + "\n".join(_line(r) for r in rows)
    if args.json is not None:
        write_json(args.json, rows)
    if args.out is not None:
        write_json(args.out / "ensemble.json", rows)
        write_text(args.out / "ensemble.md", table + "\n")
        _plot([r for r in rows if r["dtype"] == "float32"], args.out / "ensemble.png")


def _line(r: dict) -> str:
    return (f"| {r['task']} | {r['dtype']} | {r['members']} | {r['updates']} | "
            f"{r['ensemble_s']:.3f} | {r['separate_s']:.3f} | {r['speedup']:.2f} | "
            f"{r['max_rel_diff']:.1e} |")


if __name__ == "__main__":
    main()
