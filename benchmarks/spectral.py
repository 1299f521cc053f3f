"""The spectral solvers side by side with their peers, against their targets.

    python benchmarks/spectral.py [--repeats 9] [--memory-steps 10000] [--quick]

One process, float64, one thread everywhere (NUMBA_NUM_THREADS=1, torch.set_num_threads(1),
XLA flags for one CPU thread), every time the median over ``--repeats`` samples of the process
CPU time (steadier than wall time on a shared machine; all ratios come from the same run).

KS ETDRK4, N = 128, L = 64, Δt = 0.25, smooth random initial states (max |u| = 1), per step:
  forward (200-step rollout) at batch 1 and 64: ours (``ks1d-etdrk4``), vectorised NumPy
  (:class:`adjointsim.bench.work_precision.NumpyETDRK4`), PyTorch eager (torch.fft,
  ``torch_spectral.TorchKS`` under no_grad), exponax (``exponax_peer``: jit, lax.scan, vmap), and
  the lower bound: the step's 8 real FFTs alone (numpy.fft in a numba loop via rocket-fft,
  ``ks_speed.numpy_ffts``);
  forward + gradient of the loss ½ Σ u_200² (200 steps): ours = ``rollout`` + ``vjp`` (the
  cotangent u_200 needs the forward first), PyTorch autograd, jax.value_and_grad through exponax;
  adjoint/forward = (vjp − rollout)/rollout, the adjoint sweep's cost in forward passes. Also
  shown: ``vjp`` alone (a cotangent known up front) and the torch bridge's pipeline,
  ``rollout(keep="all")`` + ``vjp(trajectory=...)``.
NS 128², ETDRK2, batch 1, 100 steps from a developed state of List et al.'s Kolmogorov flow
  (k_f = 6, ν = 10⁻³, Δt = 0.005, 2/3 rule): forward and forward + gradient (rollout + vjp),
  ours against exponax's ``KolmogorovFlowVorticity`` configured as its exact twin.
Memory: ``vjp`` of a 10⁴-step KS rollout (batch 1) without and with ``checkpoint=64``, on a
  fresh stepper: peak traced memory (tracemalloc sees every NumPy allocation, not the scratch
  of the numba kernels), the most states held at once (counted, at every adjoint kernel call,
  over the arrays the checkpointing sweep's frames reference) and the CPU time (median of 3).
Each peer's last state and gradient are compared with ours (relative max difference).
Prints the tables as markdown, the last one the targets with met / not met.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import tracemalloc
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import exponax_peer  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from ks_speed import numpy_ffts  # noqa: E402
from torch_spectral import TorchKS, forward_and_gradient  # noqa: E402

from adjointsim.bench.work_precision import (  # noqa: E402
    XLA_ONE_THREAD,
    NumpyETDRK4,
    median_times,
    relative_error,
)
from adjointsim.solvers.kuramoto_sivashinsky import KS  # noqa: E402
from adjointsim.solvers.navier_stokes import NavierStokes2DETDRK2  # noqa: E402

os.environ.setdefault("XLA_FLAGS", XLA_ONE_THREAD)
torch.set_num_threads(1)

KS_STEPS = 200
NS_STEPS = 100
CHECKPOINT = 64
FFT_LOOPS = 200
MIN_TIME = 0.05


def compare(stepper, u0: np.ndarray, steps: int, peers: dict, repeats: int) -> dict:
    """Time ours (rollout; rollout + vjp for forward + gradient of ½ Σ u_steps²; also vjp alone
    and the torch bridge's way, rollout(keep="all") + vjp(trajectory=...)) and the ``peers``
    (name → dict of calls to time, ``last`` and optionally ``grad``) side by side.

    A peer's ``steps`` says how many steps one of its calls stands for (default ``steps``).
    Returns seconds per step under "<impl> <what>" keys, ``adjoint/forward`` and, per
    implementation, its last state and gradient (for the agreement check).
    """
    last = stepper.rollout(u0, steps)

    def stored():
        trajectory = stepper.rollout(u0, steps, keep="all")
        return stepper.vjp(u0, steps, trajectory[-1], trajectory=trajectory)

    calls = {
        "ours forward": lambda: stepper.rollout(u0, steps),
        "ours vjp": lambda: stepper.vjp(u0, steps, last),
        "ours stored": stored,
    }
    arrays = {"ours": (last, stepper.vjp(u0, steps, last).state)}
    scale = {}
    for name, peer in peers.items():
        for what, fn in peer.items():
            if callable(fn):
                calls[f"{name} {what}"] = fn
                scale[f"{name} {what}"] = peer.get("steps", steps)
        if "last" in peer:
            arrays[name] = (peer["last"], peer.get("grad"))
    times = median_times(calls, repeats, MIN_TIME)
    out = {key: t / scale.get(key, steps) for key, t in times.items()}
    out["ours gradient"] = out["ours forward"] + out["ours vjp"]
    out["adjoint/forward"] = (out["ours vjp"] - out["ours forward"]) / out["ours forward"]
    out["arrays"] = arrays
    return out


def ks_batch(batch: int, repeats: int, with_exponax: bool) -> dict:
    stepper = KS[4](n=128, length=64.0, dt=0.25)
    u0 = stepper.random_state(np.random.default_rng(batch), batch)
    rows = np.ascontiguousarray(u0[:, 0, :])
    numpy_ks = NumpyETDRK4(stepper)
    model = TorchKS(128, 64.0, 0.25)
    u0_t = torch.from_numpy(u0)

    def torch_forward():
        with torch.no_grad():
            return model.rollout(u0_t, KS_STEPS)

    torch_last, torch_grad = forward_and_gradient(model, u0, KS_STEPS)
    peers = {
        # One call runs the 8 FFTs of FFT_LOOPS steps.
        "ffts": {"forward": lambda: numpy_ffts(rows, FFT_LOOPS), "steps": FFT_LOOPS},
        "numpy": {"forward": lambda: numpy_ks.rollout(u0, KS_STEPS),
                  "last": numpy_ks.rollout(u0, KS_STEPS)},
        "torch": {"forward": torch_forward,
                  "gradient": lambda: forward_and_gradient(model, u0, KS_STEPS),
                  "last": torch_last, "grad": torch_grad},
    }
    if with_exponax:
        peers["exponax"] = exponax_peer.prepare(stepper, u0, KS_STEPS)
    return compare(stepper, u0, KS_STEPS, peers, repeats)


def ns_case(repeats: int, with_exponax: bool) -> dict:
    stepper = NavierStokes2DETDRK2(n=128, nu=1e-3, dt=0.005, forcing_wavenumber=6)  # List et al.'s
    u0 = stepper.rollout(stepper.random_state(np.random.default_rng(0), 1), 200)
    peers = {"exponax": exponax_peer.prepare(stepper, u0, NS_STEPS)} if with_exponax else {}
    return compare(stepper, u0, NS_STEPS, peers, repeats)


def states_held(stepper, u0: np.ndarray, steps: int, cot: np.ndarray, checkpoint) -> int:
    """The most states alive at once in ``vjp``: at every adjoint kernel call, the distinct
    arrays of states referenced by the frames of the checkpointing sweep (segment starts, the
    stored segment trajectory, the kernel's inputs), counted in states."""
    size, ndim = u0.size, u0.ndim
    most = 0
    kernel = stepper._adjoint

    def spy(states, *args):
        nonlocal most
        held = {}
        frame = sys._getframe(1)
        while frame is not None:
            if type(frame.f_locals.get("self")).__name__ == "_AdjointSweep":
                for value in frame.f_locals.values():
                    for a in value if isinstance(value, list) else (value,):
                        if isinstance(a, np.ndarray) and a.size and a.shape[-ndim:] == u0.shape:
                            while isinstance(a.base, np.ndarray):
                                a = a.base
                            held[id(a)] = a.size // size
            frame = frame.f_back
        most = max(most, sum(held.values()))
        return kernel(states, *args)

    stepper._adjoint = spy
    try:
        stepper.vjp(u0, steps, cot, checkpoint=checkpoint)
    finally:
        del stepper._adjoint
    return most


def memory_case(steps: int) -> dict:
    def scene():
        return KS[4](n=128, length=64.0, dt=0.25)

    u0 = scene().random_state(np.random.default_rng(0), 1)
    cot = scene().rollout(u0, steps)
    out = {"state_bytes": u0.nbytes}
    for checkpoint in (None, CHECKPOINT):
        scene().vjp(u0, 20, cot, checkpoint=checkpoint)  # load the kernels outside the trace
        seconds = []
        for _ in range(3):
            stepper = scene()
            t0 = time.process_time()
            stepper.vjp(u0, steps, cot, checkpoint=checkpoint)
            seconds.append(time.process_time() - t0)
        # A fresh scene: buffers a stepper keeps between calls count too.
        tracemalloc.start()
        scene().vjp(u0, steps, cot, checkpoint=checkpoint)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        out[checkpoint] = dict(peak=peak, seconds=float(np.median(seconds)),
                               held=states_held(scene(), u0, steps, cot, checkpoint))
    return out


# ----------------------------------------------------------------- report
def fmt(seconds: float | None, unit: float) -> str:
    return "–" if seconds is None else f"{seconds / unit:.{1 if unit < 1e-3 else 3}f}"


def agreement(results: dict, label: str) -> list[str]:
    """Relative max difference of each peer's last state and gradient from ours."""
    arrays = results["arrays"]
    last, grad = arrays["ours"]
    lines = []
    for peer, (p_last, p_grad) in arrays.items():
        if peer == "ours":
            continue
        parts = [f"forward {relative_error(p_last, last):.1e}"]
        if p_grad is not None:
            parts.append(f"gradient {relative_error(p_grad, grad):.1e}")
        lines.append(f"{label}, {peer} vs ours (relative max difference): " + ", ".join(parts))
    return lines


def ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else a / b


def fmt_ratio(a: float | None, b: float | None) -> str:
    r = ratio(a, b)
    return "–" if r is None else f"{r:.2f}×"


def report(ks: dict, ns: dict, mem: dict, note: str) -> str:
    """The markdown tables: timings, memory, and the targets marked met / not met."""
    b1, b64 = ks[1], ks[64]
    us = 1e-6
    lines = [
        "KS ETDRK4, N = 128, L = 64, Δt = 0.25, float64, one thread; µs per step "
        "(median process CPU time)" + note,
        "",
        "| | ours (numba) | NumPy | PyTorch | exponax (JAX) | 8 FFTs alone |",
        "|---|---|---|---|---|---|",
    ]
    for batch, r in ((1, b1), (64, b64)):
        cells = [fmt(r.get(f"{k} forward"), us) for k in ("ours", "numpy", "torch", "exponax",
                                                            "ffts")]
        lines.append(f"| forward, batch {batch} | " + " | ".join(cells) + " |")
    for batch, r in ((1, b1), (64, b64)):
        lines.append(
            f"| forward + gradient ({KS_STEPS} steps), batch {batch} | "
            f"{fmt(r['ours gradient'], us)} (rollout + vjp) | – | "
            f"{fmt(r['torch gradient'], us)} (autograd) | "
            f"{fmt(r.get('exponax gradient'), us)} (jax.grad) | – |"
        )
    lines += [
        "",
        "Ours' forward + gradient by pipeline, µs per step (the ratios: exponax jax.grad / "
        "ours, torch autograd / ours):",
        "",
        "| | rollout + vjp | rollout(keep=\"all\") + vjp(trajectory=…) | vjp alone (cotangent "
        "known up front) |",
        "|---|---|---|---|",
    ]
    for batch, r in ((1, b1), (64, b64)):
        cells = []
        for key in ("ours gradient", "ours stored", "ours vjp"):
            cells.append(
                f"{fmt(r[key], us)} ({fmt_ratio(r.get('exponax gradient'), r[key])}, "
                f"{fmt_ratio(r['torch gradient'], r[key])})"
            )
        lines.append(f"| KS batch {batch} | " + " | ".join(cells) + " |")
    lines.append(
        "| NS 128² | " + " | ".join(
            f"{fmt(ns[key], us)} ({fmt_ratio(ns.get('exponax gradient'), ns[key])})"
            for key in ("ours gradient", "ours stored", "ours vjp")) + " |"
    )
    lines += [
        "",
        f"2D Kolmogorov flow, vorticity form, 128², ETDRK2, batch 1, {NS_STEPS} steps; "
        "ms per step" + note,
        "",
        "| | ours (numba) | exponax (JAX) |",
        "|---|---|---|",
        f"| forward | {fmt(ns['ours forward'], 1e-3)} | "
        f"{fmt(ns.get('exponax forward'), 1e-3)} |",
        f"| forward + gradient | {fmt(ns['ours gradient'], 1e-3)} (rollout + vjp) | "
        f"{fmt(ns.get('exponax gradient'), 1e-3)} (jax.grad) |",
        "",
        f"Memory: vjp of a {mem['steps']}-step KS rollout (N = 128, batch 1, "
        f"{mem['state_bytes']} bytes per state)",
        "",
        "| | states held at once | peak traced memory | CPU time |",
        "|---|---|---|---|",
    ]
    for checkpoint in (None, CHECKPOINT):
        m = mem[checkpoint]
        label = "every state kept" if checkpoint is None else f"checkpoint={checkpoint}"
        lines.append(f"| {label} | {m['held']} | {m['peak'] / 2**20:.1f} MiB | "
                     f"{m['seconds']:.2f} s |")

    def exponax_over_ours(r, what):
        return ratio(r.get(f"exponax {what}"), r[f"ours {what}"]), "exponax/ours"

    targets = [
        ("KS b1 forward ≤ 1.5× the 8 FFTs alone",
         (ratio(b1["ours forward"], b1["ffts forward"]), "ours/FFTs"), 1.5, "≤"),
        ("KS b1 forward ≥ 2.5× faster than exponax", exponax_over_ours(b1, "forward"), 2.5,
         "≥"),
        ("KS b64 forward ≥ 2× faster than exponax", exponax_over_ours(b64, "forward"), 2, "≥"),
        (f"KS b1 forward + adjoint ({KS_STEPS} steps): adjoint/forward ≤ 2",
         (b1["adjoint/forward"], "adjoint/forward"), 2, "≤"),
        (f"KS b64 forward + adjoint ({KS_STEPS} steps): adjoint/forward ≤ 2",
         (b64["adjoint/forward"], "adjoint/forward"), 2, "≤"),
        ("KS b1 forward + gradient ≥ 2.5× faster than jax.grad through exponax",
         exponax_over_ours(b1, "gradient"), 2.5, "≥"),
        ("KS b64 forward + gradient ≥ 2.5× faster than jax.grad through exponax",
         exponax_over_ours(b64, "gradient"), 2.5, "≥"),
        ("KS b1 forward + gradient ≥ 15× faster than torch autograd",
         (ratio(b1["torch gradient"], b1["ours gradient"]), "torch/ours"), 15, "≥"),
        ("KS b64 forward + gradient ≥ 15× faster than torch autograd",
         (ratio(b64["torch gradient"], b64["ours gradient"]), "torch/ours"), 15, "≥"),
        ("NS 128² ETDRK2 forward ≥ 1.5× faster than exponax", exponax_over_ours(ns, "forward"),
         1.5, "≥"),
        ("NS 128² ETDRK2 forward + adjoint ≥ 2× faster than exponax's gradient",
         exponax_over_ours(ns, "gradient"), 2, "≥"),
        (f"{mem['steps']}-step adjoint with checkpointing holds ≤ {CHECKPOINT} states",
         (mem[CHECKPOINT]["held"], "states"), CHECKPOINT, "≤"),
    ]
    lines += ["", "| target | measured | |", "|---|---|---|"]
    for text, (value, what), bound, sense in targets:
        if value is None:
            lines.append(f"| {text} | – ({what}) | not measured |")
            continue
        met = value <= bound if sense == "≤" else value >= bound
        shown = f"{value:.0f}" if what == "states" else f"{value:.2f}"
        lines.append(f"| {text} | {shown} ({what}) | {'met' if met else 'NOT met'} |")
    others = [
        ("KS b64 ours/FFTs", ratio(b64["ours forward"], b64["ffts forward"])),
        ("KS NumPy/ours forward b1", ratio(b1["numpy forward"], b1["ours forward"])),
        ("b64", ratio(b64["numpy forward"], b64["ours forward"])),
        ("KS torch/ours forward b1", ratio(b1["torch forward"], b1["ours forward"])),
        ("b64", ratio(b64["torch forward"], b64["ours forward"])),
        ("NS adjoint/forward", ns["adjoint/forward"]),
    ]
    lines += ["", "Other ratios: " + "; ".join(f"{k} {v:.2f}" for k, v in others)]
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--memory-steps", type=int, default=None,
                        help="rollout length of the memory case (default 10000, quick 2000)")
    parser.add_argument("--quick", action="store_true",
                        help="3 repeats and a 2000-step memory case (a smoke run)")
    args = parser.parse_args()
    repeats = 3 if args.quick else args.repeats
    memory_steps = args.memory_steps or (2000 if args.quick else 10_000)
    with_exponax = exponax_peer.available()
    note = "" if with_exponax else " (exponax: skipped: exponax not installed)"
    if not with_exponax:
        print("exponax: skipped: exponax not installed")
    t0 = time.perf_counter()
    ks = {}
    for batch in (1, 64):
        print(f"KS batch {batch} ...", file=sys.stderr, flush=True)
        ks[batch] = ks_batch(batch, repeats, with_exponax)
    print("NS 128² ...", file=sys.stderr, flush=True)
    ns = ns_case(repeats, with_exponax)
    print("memory ...", file=sys.stderr, flush=True)
    mem = memory_case(memory_steps)
    mem["steps"] = memory_steps
    lines = []
    for batch in (1, 64):
        lines += agreement(ks[batch], f"KS batch {batch}")
    lines += agreement(ns, "NS 128²")
    print("\n".join(lines))
    print()
    print(report(ks, ns, mem, note))
    versions = f"numpy {np.__version__}, torch {torch.__version__}"
    if with_exponax:
        import exponax
        import jax

        versions += f", jax {jax.__version__}, exponax {exponax.__version__}"
    print(f"\n{versions}; NUMBA_NUM_THREADS={os.environ['NUMBA_NUM_THREADS']}, "
          f"torch threads {torch.get_num_threads()}, XLA_FLAGS={os.environ['XLA_FLAGS']!r}; "
          f"{repeats} repeats; {time.perf_counter() - t0:.0f} s wall")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
