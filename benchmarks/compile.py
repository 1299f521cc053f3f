"""Training updates eager against ``torch.compile``: where compiling a loss through a solver pays.

    python benchmarks/compile.py [--quick] [--json PATH] [--backends aot_eager,inductor]

Each task is one training update (the loss of several solver steps through
``adjointsim.train.bridge``, its backward pass, an Adam step), one thread for torch and the
solvers:

* ``ks-correction-wig``: List et al.'s KS correction setup: the 33k ResNet (26 × 8) corrects the
  coarse ``ks1d-etdrk1`` (48 points, dt 1, 2 substeps) after each of m = 3 solver steps, the
  gradient through the solver's adjoint (WIG), batch 16;
* ``cartpole-controller``: a StableBPTT-like controller: the tasks' 11k MLP (100 × 2) picks the
  force of a 4-pole cart-pole from its state at each of 100 steps, one solver call per step
  (mode C's graph: the network sees the state the solver returned), batch 8;
* ``quantum-controller``: the StableBPTT quantum controller (two strided convolutions and a
  linear layer) through 128 Crank–Nicolson steps of ``schrodinger1d-cn``, mode R, batch 8;
* ``quantum-ensemble``: an update of 3 such controllers (seeds) as one ensemble
  (``ControllerEnsemble``: the stacked layers, one solver call per step), the ``compile`` key
  against eager, the way ``stablebptt --size budget`` trains them; ``max_rel_diff`` compares
  the members' first loss and gradient norm (same weights, same batch);
* ``pinn-poisson-epoch``: one full-batch epoch of ``adjointsim pinn``'s Poisson problem (its
  defaults: k = 1, 2500 collocation points, 100 per edge), residual and boundary terms summed,
  the Laplacian by the forward-Laplacian route (numba kernels: run eager, a graph break);
* ``hig-oscillators-adam``: an update of ``adjointsim hig oscillators --optimizer adam`` (what
  the ``compile`` key compiles there): the MLP's controls through 16 steps of the coupled
  oscillators by the bridge, batch 512.

``--jacobian PATH`` also times the Jacobian of an HIG update (oscillators, its batch of 128):
the solver's batched adjoint (:meth:`SolverPhysics.jacobian`, one adjoint call over b·d_y
replicated rollouts) against ``torch.func.vmap(torch.func.jacrev(...))`` through the bridge
operator, and their largest difference.

For each task and backend, a row: ``eager_s`` and ``compiled_s`` (median seconds per update,
process CPU time, after warm-up, the two taken in turn), ``compile_s`` (wall seconds of the
first compiled update, less one eager update: tracing and code generation), ``graph_breaks``
(``torch._dynamo.explain``), ``max_abs_diff`` (the largest difference of the loss and the
gradients, compiled against eager, on the same parameters), ``speedup`` (eager / compiled)
and ``break_even_updates`` (updates after which the compile time is paid back; null when
compiling does not pay).
``aot_eager`` runs torch's own kernels on the traced graph (bit-for-bit the eager numbers);
``inductor`` generates C++ for the network's layers (needs a C++ compiler) and may reorder
their arithmetic (round-off differences).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("TORCHINDUCTOR_COMPILE_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

import adjointsim  # noqa: E402
from adjointsim.files import write_json  # noqa: E402
from adjointsim.nets.mlp import MLP  # noqa: E402
from adjointsim.nets.resnet import ResNet  # noqa: E402
from adjointsim.train import bridge  # noqa: E402
from adjointsim.train.control import ControlConfig, Controller, closed_loop  # noqa: E402
from adjointsim.train.ensemble import ControllerEnsemble  # noqa: E402
from adjointsim.train.hig_problems import adam_loss  # noqa: E402
from adjointsim.train.higs import make_problem as make_hig  # noqa: E402
from adjointsim.train.pinn import PinnConfig  # noqa: E402
from adjointsim.train.pinn import make_problem as make_pinn  # noqa: E402
from adjointsim.train.tasks import get_task  # noqa: E402
from adjointsim.train.unroll import GradientFlow  # noqa: E402


class Task:
    """One update's pieces: the network, the data, and the loss of (network, data)."""

    def __init__(self, name: str, net: torch.nn.Module, data: torch.Tensor,
                 loss: Callable[[torch.Tensor], torch.Tensor], fullgraph: bool = True) -> None:
        self.name, self.net, self.data, self.loss = name, net, data, loss
        #: whether the loss traces into one graph (else its graph breaks run eager)
        self.fullgraph = fullgraph


def ks_correction(batch: int = 16, unroll: int = 3) -> Task:
    torch.manual_seed(0)
    ks = adjointsim.get("ks1d-etdrk1")(n=48, length=2 * np.pi * 8, dt=1.0, substeps=2)
    net = ResNet(1, 1, width=26, blocks=8).double()
    u0 = torch.from_numpy(ks.random_state(np.random.default_rng(0), batch))
    target = torch.from_numpy(ks.random_state(np.random.default_rng(1), batch))

    def loss(u: torch.Tensor) -> torch.Tensor:
        total = u.new_zeros(())
        for _ in range(unroll):
            u = bridge.rollout(ks, u, 1)
            u = u + net(u)
            total = total + (u - target).square().mean()
        return total / unroll

    return Task("ks-correction-wig", net, u0, loss)


def cartpole_controller(batch: int = 8, steps: int = 100) -> Task:
    torch.manual_seed(0)
    cartpole = adjointsim.get("cartpole")(poles=4)
    size = int(np.prod(cartpole.state_shape(1)))
    net = MLP(size, 1, width=100, depth=2)
    x0 = torch.from_numpy(cartpole.random_state(np.random.default_rng(0), batch)).float()

    def loss(x: torch.Tensor) -> torch.Tensor:
        total = x.new_zeros(())
        for _ in range(steps):
            c = net(x.flatten(1))
            x = bridge.step(cartpole, x, c)
            total = total + x.square().mean() + 1e-3 * c.square().mean()
        return total / steps

    return Task("cartpole-controller", net, x0, loss)


def quantum_controller(batch: int = 8) -> Task:
    """The StableBPTT quantum task at its hardest level (target 5): the strided-convolution
    controller through 128 Crank–Nicolson steps, mode R, as ``control quantum`` runs it."""
    task = get_task("quantum", 5, None)
    torch.manual_seed(0)
    net = task.net()
    torch.nn.init.normal_(net[-1].weight, std=0.1)  # a trained-like controller, not c = 0
    x0 = torch.from_numpy(task.initial_states(np.random.default_rng(0), batch)).float()

    def loss(x: torch.Tensor) -> torch.Tensor:
        return closed_loop(task, net, x, GradientFlow("R"))[0]

    return Task("quantum-controller", net, x0, loss)


def pinn_epoch() -> Task:
    problem = make_pinn(PinnConfig(problem="poisson"))
    torch.manual_seed(0)
    net = problem.model()
    terms = problem.terms

    def loss(_: torch.Tensor) -> torch.Tensor:
        losses = problem.losses(net, "taylor", terms)
        return sum(losses[t] for t in terms)

    return Task("pinn-poisson-epoch", net, torch.zeros(()), loss, fullgraph=False)


def hig_adam() -> Task:
    torch.manual_seed(0)
    problem = make_hig("oscillators", 0, "full", {})
    net = problem.model()
    x, c, t = problem.sample(torch.Generator().manual_seed(1),
                             problem.settings["adam"]["batch"])

    def loss(x: torch.Tensor) -> torch.Tensor:
        return adam_loss(problem, net, x, c, t)

    return Task("hig-oscillators-adam", net, x, loss)


TASKS = {"ks-correction-wig": ks_correction, "cartpole-controller": cartpole_controller,
         "quantum-controller": quantum_controller, "pinn-poisson-epoch": pinn_epoch,
         "hig-oscillators-adam": hig_adam}


def _gradients(task: Task, loss_fn: Callable) -> list[torch.Tensor]:
    """The loss and the parameters' gradients (the parameters left untouched)."""
    params = list(task.net.parameters())
    loss = loss_fn(task.data)
    return [loss.detach(), *torch.autograd.grad(loss, params)]


def _update_seconds(task: Task, loss_fns: list[Callable], updates: int) -> list[float]:
    """Median CPU seconds of one update (loss, backward, Adam step) for each loss function,
    over ``updates`` rounds that run each once in turn (so that a change of load on a shared
    machine hits them alike)."""
    opt = torch.optim.Adam(task.net.parameters(), lr=1e-6)
    times: list[list[float]] = [[] for _ in loss_fns]
    for _ in range(updates):
        for fn, kept in zip(loss_fns, times, strict=True):
            t0 = time.process_time()
            opt.zero_grad(set_to_none=True)
            fn(task.data).backward()
            opt.step()
            kept.append(time.process_time() - t0)
    return [float(np.median(t)) for t in times]


def measure(make: Callable[[], Task], backend: str, updates: int) -> dict:
    task = make()
    explained = torch._dynamo.explain(task.loss)(task.data)
    torch._dynamo.reset()
    compiled = torch.compile(task.loss, fullgraph=task.fullgraph, backend=backend)
    want = _gradients(task, task.loss)
    start = time.perf_counter()
    got = _gradients(task, compiled)  # traces, compiles and runs once
    first_s = time.perf_counter() - start
    diff = max(float((a - b).abs().max()) for a, b in zip(got, want, strict=True))
    _update_seconds(task, [task.loss, compiled], 2)  # warm-up
    eager, fast = _update_seconds(task, [task.loss, compiled], updates)
    compile_s = max(first_s - eager, 0.0)
    saved = eager - fast
    return {
        "task": task.name, "backend": backend, "eager_s": eager, "compiled_s": fast,
        "compile_s": compile_s, "graph_breaks": explained.graph_break_count,
        "max_abs_diff": diff, "speedup": eager / fast,
        "break_even_updates": int(np.ceil(compile_s / saved)) if saved > 0 else None,
        "updates": updates, "dtype": str(task.data.dtype).removeprefix("torch."),
    }


def quantum_ensemble(backend: str, updates: int, members: int = 3) -> dict:
    """An update of the quantum controllers as ``stablebptt --size budget`` trains them: an
    ensemble of ``members`` seeds (target 5, mode R, batch 8, float32) through
    :class:`ControllerEnsemble`, eager against the ``compile`` key's ``backend``, in turn."""
    with tempfile.TemporaryDirectory() as tmp:
        ensembles = {}
        for key in ("off", backend):
            runs = []
            for seed in range(members):
                cfg = ControlConfig(task="quantum", level=5, mode="R", seed=seed,
                                    dtype="float32", compile=key,
                                    out=str(Path(tmp) / key / f"s{seed}"))
                cfg.validate()
                run = Controller(cfg)
                run.build()
                run.state["step"] = 1  # past the epoch's first update (its eager diagnosis)
                # a trained-like controller: at c = 0 the gradient is round-off (about 1e-8)
                with torch.no_grad():
                    rng = torch.Generator().manual_seed(seed)
                    run.net[-1].weight.normal_(0.0, 0.1, generator=rng)
                runs.append(run)
            ensembles[key] = ControllerEnsemble(runs)
        eager, fast = ensembles["off"], ensembles[backend]
        start = time.perf_counter()
        fast.update()  # traces, compiles and runs once
        first_s = time.perf_counter() - start
        times: dict[str, list[float]] = {"off": [], backend: []}
        eager.update()
        for _ in range(updates):  # fewer than an epoch's 32: no evaluation is timed
            for key, ens in ((backend, fast), ("off", eager)):
                t0 = time.process_time()
                ens.update()
                times[key].append(time.process_time() - t0)
        # the first update's loss and gradient norm, from the same weights and batch (later
        # weights drift apart: Adam turns round-off in near-zero gradients into steps of lr)
        diff = max(abs(a.state[k][0] - b.state[k][0]) / abs(a.state[k][0])
                   for a, b in zip(eager.members, fast.members) for k in ("losses", "norms"))
    eager_s, fast_s = (float(np.median(times[k])) for k in ("off", backend))
    compile_s = max(first_s - eager_s, 0.0)
    saved = eager_s - fast_s
    return {
        "task": f"quantum-ensemble-{members}", "backend": backend, "eager_s": eager_s,
        "compiled_s": fast_s, "compile_s": compile_s, "graph_breaks": None,
        "max_rel_diff": diff, "speedup": eager_s / fast_s,
        "break_even_updates": int(np.ceil(compile_s / saved)) if saved > 0 else None,
        "updates": updates, "dtype": "float32",
    }


def hig_jacobian(repeats: int) -> dict:
    """The HIG Jacobian ∂y/∂f of the oscillators' batch, by the batched adjoint and by
    ``vmap(jacrev)`` through the bridge: median CPU seconds of each and their difference."""
    problem = make_hig("oscillators", 0, "full", {})
    torch.manual_seed(0)
    net, physics = problem.model(), problem.physics
    x, c, _ = problem.sample(torch.Generator().manual_seed(1), problem.settings["hig"]["batch"])
    with torch.no_grad():
        f = net(x)

    def single(fi: torch.Tensor, ci: torch.Tensor) -> torch.Tensor:
        return physics(fi[None], ci[None])[0]

    def by_jacrev() -> torch.Tensor:
        return torch.func.vmap(torch.func.jacrev(single))(f, c)

    routes = {"batched-adjoint": lambda: physics.jacobian(f, c)[1], "jacrev": by_jacrev}
    got = {name: fn() for name, fn in routes.items()}  # warm-up, and the values compared
    times: dict[str, list[float]] = {name: [] for name in routes}
    for _ in range(repeats):
        for name, fn in routes.items():
            t0 = time.process_time()
            fn()
            times[name].append(time.process_time() - t0)
    med = {name: float(np.median(t)) for name, t in times.items()}
    scale = float(got["batched-adjoint"].abs().max())
    return {"task": "hig-oscillators-jacobian", "batch": int(f.shape[0]),
            "shape": list(got["batched-adjoint"].shape),
            "adjoint_s": med["batched-adjoint"], "jacrev_s": med["jacrev"],
            "jacrev_over_adjoint": med["jacrev"] / med["batched-adjoint"],
            "max_abs_diff": float((got["jacrev"] - got["batched-adjoint"]).abs().max()),
            "max_abs": scale, "repeats": repeats}


def merged(path: str, rows: list[dict]) -> list[dict]:
    """The rows already at ``path`` with those of the same task and backend replaced by
    ``rows`` (a run of some tasks keeps the others' rows)."""
    try:
        with open(path) as f:
            kept = json.load(f)
    except FileNotFoundError:
        kept = []
    new = {(r["task"], r.get("backend")) for r in rows}
    return [r for r in kept if (r["task"], r.get("backend")) not in new] + rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="5 timed updates, not 21")
    parser.add_argument("--json", type=str, default=None, help="write the rows there")
    parser.add_argument("--backends", default="aot_eager,inductor")
    parser.add_argument("--tasks", default=",".join([*TASKS, "quantum-ensemble"]),
                        help="comma-separated; none: only --jacobian")
    parser.add_argument("--jacobian", type=str, default=None,
                        help="also compare the HIG Jacobian's two routes; their row goes there")
    args = parser.parse_args()
    torch.set_num_threads(1)
    updates = 5 if args.quick else 21
    rows = []
    for name in filter(None, args.tasks.split(",")):
        for backend in args.backends.split(","):
            row = (quantum_ensemble(backend, updates) if name == "quantum-ensemble"
                   else measure(TASKS[name], backend, updates))
            rows.append(row)
            even = row["break_even_updates"]
            print(
                f"{row['task']:22s} {backend:10s} eager {row['eager_s'] * 1e3:8.1f} ms  "
                f"compiled {row['compiled_s'] * 1e3:8.1f} ms  x{row['speedup']:.2f}  "
                f"compile {row['compile_s']:6.1f} s  breaks {row['graph_breaks'] or '-'}  "
                f"max|diff| {row.get('max_abs_diff', row.get('max_rel_diff')):.1e}  "
                f"pays after {'never' if even is None else f'{even} updates'}",
                flush=True,
            )
    if args.json:
        write_json(args.json, merged(args.json, rows))
    if args.jacobian:
        row = hig_jacobian(5 if args.quick else 21)
        print(f"{row['task']:22s} batch {row['batch']} J {row['shape']}: batched adjoint "
              f"{row['adjoint_s'] * 1e3:.1f} ms, vmap(jacrev) {row['jacrev_s'] * 1e3:.1f} ms "
              f"(x{row['jacrev_over_adjoint']:.2f}), max|diff| {row['max_abs_diff']:.1e} of "
              f"max|J| {row['max_abs']:.1e}", flush=True)
        write_json(args.jacobian, [row])


if __name__ == "__main__":
    main()
