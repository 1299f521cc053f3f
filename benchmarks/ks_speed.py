"""Per-step timings of the Kuramoto–Sivashinsky ETDRK4 solver against its targets and its peer.

KS with N = 128, length 64, Δt = 0.25, ETDRK4, 2/3 dealiasing, float64, one thread (the script
sets NUMBA_NUM_THREADS=1, ADJOINTSIM_THREADS=1 and XLA on one thread before anything loads).
Prints, in µs per step, medians over repeats of the process CPU time (CPU time is steadier than
wall time on a shared machine; the best repeat is printed too, as other jobs on the sibling core
slow whole repeats down; the items are sampled in turn, so that a change of load affects them
alike): the step's 8 real FFTs alone (numpy.fft in numba via rocket-fft, and this package's
packed FFTs), the forward rollout at batch 1 and 64, and forward + gradient (``vjp`` of a
200-step rollout, every state kept: the forward sweep records the tape its adjoint reads). Then
the gradient's cost in forwards, (forward + gradient) / forward, against its target of 2.5.

The peer, exponax (JAX/XLA jit, ``lax.scan`` over the steps, ``vmap`` over the batch, one CPU
thread; the ``peers`` extra), is measured in the same run when it is installed, on the same
scene: its ``KuramotoSivashinskyConservative`` with the 2/3 mask set to keep our modes (the
script prints how far its 200-step state is from ours), forward and ``value_and_grad`` of
½ Σ u², compilation not timed; then how many times faster than it we run, target 2.5.
Otherwise the script says it is not installed and prints no peer figure.
Usage: ``python benchmarks/ks_speed.py [--repeats 9]``.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("ADJOINTSIM_THREADS", "1")

import numpy as np  # noqa: E402
import rocket_fft  # noqa: E402, F401
from numba import njit  # noqa: E402

from adjointsim.bench.work_precision import exponax_rollout, load_exponax  # noqa: E402
from adjointsim.solvers.kuramoto_sivashinsky import KS  # noqa: E402
from adjointsim.spectral import fft1d  # noqa: E402

TARGETS = {  # µs per step
    ("forward", 1): 8.6,
    ("forward", 64): 107.0,
    ("forward+gradient", 1): 17.0,
    ("forward+gradient", 64): 270.0,
}
#: targets: (forward + gradient) / forward at most, and times exponax's speed at least
RATIO_TARGET, PEER_TARGET = 2.5, 2.5
STEPS = 200


@njit(cache=True)
def numpy_ffts(u, reps):
    """``reps`` steps' FFTs alone (4 rfft + 4 irfft, as an ETDRK4 step needs): the lower
    bound of a step's time, which the spectral benchmark reports too."""
    for _ in range(reps):
        for _ in range(4):
            x = np.fft.rfft(u)
            u = np.fft.irfft(x, u.shape[-1])
    return u


@njit(cache=True)
def _packed_ffts(z, nb, fplan, reps):
    m = z.shape[0] // nb
    x, w = np.empty((m + 1) * nb, z.dtype), np.empty((m + 1) * nb, z.dtype)
    t, empty = np.empty_like(z), np.empty(0, z.dtype)
    for _ in range(reps):
        for _ in range(4):
            fft1d.rfft_packed(z, z, 1, x, empty, empty, False, t, w, nb, fplan)
            fft1d.irfft_packed(x, empty, z, w, nb, fplan)


def times(fns: dict, repeats: int) -> dict[str, np.ndarray]:
    """Process CPU seconds of each call, one entry per repeat, after a warm-up call of each
    (which compiles what is compiled on first use); the calls are sampled in turn."""
    for fn in fns.values():
        fn()
    out: dict[str, list[float]] = {key: [] for key in fns}
    for _ in range(repeats):
        for key, fn in fns.items():
            t0 = time.process_time()
            fn()
            out[key].append(time.process_time() - t0)
    return {key: np.array(v) for key, v in out.items()}


def exponax_calls(stepper: KS, u0: np.ndarray) -> tuple[dict, float] | None:
    """exponax's forward and forward + gradient of a ``STEPS``-step rollout of its twin of
    ``stepper`` (the calls to time), and the relative difference of its last state from ours;
    None if exponax is not installed."""
    loaded = load_exponax()
    if loaded is None:
        return None
    jax, exponax = loaded
    n = stepper.grid_shape[0]
    # exponax's mask keeps |k| ≤ fraction · n/2 − 1: this fraction keeps our highest mode K
    highest = int(np.flatnonzero(fft1d.dealias_mask(n))[-1])
    alpha, beta = stepper.param_values[:2]
    twin = exponax.stepper.KuramotoSivashinskyConservative(
        1, stepper.length, n, stepper.dt, second_order_scale=alpha, fourth_order_scale=beta,
        dealiasing_fraction=(highest + 1.5) / (n // 2), order=4, num_circle_points=32)
    run = exponax_rollout(twin, STEPS)
    forward = jax.jit(run)
    value_and_grad = jax.jit(jax.value_and_grad(lambda u: 0.5 * (run(u) ** 2).sum()))
    x = jax.numpy.asarray(u0)
    ours = stepper.rollout(u0, STEPS)
    difference = float(np.abs(np.asarray(forward(x)) - ours).max() / np.abs(ours).max())
    return {"exponax forward": lambda: forward(x).block_until_ready(),
            "exponax forward+gradient": lambda: jax.block_until_ready(value_and_grad(x))
            }, difference


def measure(batch: int, repeats: int) -> tuple[dict[str, np.ndarray], float | None]:
    """Seconds per step of each item at ``batch``, one entry per repeat (exponax's too, if it
    is installed), and how far exponax's last state is from ours (None without it)."""
    stepper = KS[4](n=128, length=64.0, dt=0.25, dealias=True)
    rng = np.random.default_rng(0)
    u0 = stepper.random_state(rng, batch)
    cot = rng.standard_normal(u0.shape)
    reps = 2000 if batch == 1 else 100
    rows = np.ascontiguousarray(u0[:, 0, :])
    packed = rng.standard_normal(64 * batch) * 0.1 + 0j
    fplan = fft1d.plan(128)
    per_step = {
        "forward": lambda: stepper.rollout(u0, STEPS),
        "forward+gradient": lambda: stepper.vjp(u0, STEPS, cot),
    }
    peer = exponax_calls(stepper, u0)
    if peer is not None:
        per_step.update(peer[0])
    raw = times(per_step, repeats)
    ffts = times({"ffts_numpy": lambda: numpy_ffts(rows, reps),
                  "ffts_packed": lambda: _packed_ffts(packed, batch, fplan, reps)}, repeats)
    return ({**{k: v / reps for k, v in ffts.items()}, **{k: v / STEPS for k, v in raw.items()}},
            None if peer is None else peer[1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=9)
    args = parser.parse_args()
    loaded = load_exponax()
    peer = ("exponax not installed (pip install 'adjointsim[peers]'): no peer figures"
            if loaded is None else f"exponax {loaded[1].__version__}, jax "
            f"{loaded[0].__version__}, XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    print(f"KS ETDRK4, N = 128, L = 64, dt = 0.25, 2/3 dealiasing, float64, "
          f"NUMBA_NUM_THREADS={os.environ['NUMBA_NUM_THREADS']}, "
          f"ADJOINTSIM_THREADS={os.environ['ADJOINTSIM_THREADS']}; {peer}; µs per step "
          "(CPU time)")
    for batch in (1, 64):
        raw, difference = measure(batch, args.repeats)
        if difference is not None:
            print(f"batch {batch:3d}: exponax's state after {STEPS} steps differs from ours by "
                  f"{difference:.1e} (relative, max norm)")
        for label, reduce in (("median", np.median), ("best", np.min)):
            t = {k: 1e6 * float(reduce(v)) for k, v in raw.items()}
            both = t["forward+gradient"]
            versus = "" if difference is None else (
                f" | exponax forward {t['exponax forward']:7.2f}, forward+gradient "
                f"{t['exponax forward+gradient']:7.2f}: {t['exponax forward+gradient'] / both:.2f}x"
                f" (target ≥ {PEER_TARGET})")
            print(
                f"batch {batch:3d} {label:>6}: 8 FFTs numpy.fft {t['ffts_numpy']:7.2f}, packed "
                f"{t['ffts_packed']:7.2f} | forward {t['forward']:7.2f} "
                f"(target {TARGETS['forward', batch]}) | forward+gradient {both:7.2f} "
                f"(target {TARGETS['forward+gradient', batch]}) | /forward "
                f"{both / t['forward']:.2f} (target ≤ {RATIO_TARGET}){versus}"
            )


if __name__ == "__main__":
    main()
