"""Per-step timings of the Kuramoto–Sivashinsky ETDRK4 solver against its targets and peers.

KS with N = 128, length 64, Δt = 0.25, ETDRK4, 2/3 dealiasing, float64, one thread (the script
sets NUMBA_NUM_THREADS=1 and ADJOINTSIM_THREADS=1 before anything loads). Prints, in µs per
step, medians over repeats of the process CPU time (CPU time is steadier than wall time on a
shared machine; the best repeat is printed too, as other jobs on the sibling core slow whole
repeats down): the step's 8 real FFTs alone (numpy.fft in numba via rocket-fft, and this
package's packed FFTs), the forward rollout at batch 1 and 64, and forward + gradient (``vjp``
of a 200-step rollout, every state kept: the forward sweep records the tape its adjoint reads).
Then the gradient's cost in forwards, (forward + gradient) / forward, against its target of 2.5,
and how many times faster than exponax's forward + gradient on this kind of machine (JAX/XLA
jit, one CPU core: 43.5 µs per step at batch 1, 676 µs at batch 64) it runs, target 2.5.
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

from adjointsim.solvers.kuramoto_sivashinsky import KS  # noqa: E402
from adjointsim.spectral import fft1d  # noqa: E402

TARGETS = {  # µs per step
    ("forward", 1): 8.6,
    ("forward", 64): 107.0,
    ("forward+gradient", 1): 17.0,
    ("forward+gradient", 64): 270.0,
}
#: exponax 0.2 (JAX/XLA jit, vmap), forward + gradient of a 200-step rollout, µs per step
EXPONAX_GRADIENT = {1: 43.5, 64: 676.0}
#: targets: (forward + gradient) / forward at most, and times exponax's speed at least
RATIO_TARGET, PEER_TARGET = 2.5, 2.5
STEPS = 200


@njit(cache=True)
def _numpy_ffts(u, reps):
    # 4 rfft + 4 irfft per step, as an ETDRK4 step needs
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


def times(fn, repeats: int) -> np.ndarray:
    fn()
    out = []
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        out.append(time.process_time() - t0)
    return np.array(out)


def measure(batch: int, repeats: int) -> dict[str, np.ndarray]:
    """Seconds per step of each item at ``batch``, one entry per repeat."""
    stepper = KS[4](n=128, length=64.0, dt=0.25, dealias=True)
    rng = np.random.default_rng(0)
    u0 = stepper.random_state(rng, batch)
    cot = rng.standard_normal(u0.shape)
    reps = 2000 if batch == 1 else 100
    rows = np.ascontiguousarray(u0[:, 0, :])
    packed = rng.standard_normal(64 * batch) * 0.1 + 0j
    fplan = fft1d.plan(128)
    return {
        "ffts_numpy": times(lambda: _numpy_ffts(rows, reps), repeats) / reps,
        "ffts_packed": times(lambda: _packed_ffts(packed, batch, fplan, reps), repeats) / reps,
        "forward": times(lambda: stepper.rollout(u0, STEPS), repeats) / STEPS,
        "forward+gradient": times(lambda: stepper.vjp(u0, STEPS, cot), repeats) / STEPS,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=9)
    args = parser.parse_args()
    print(f"KS ETDRK4, N = 128, L = 64, dt = 0.25, 2/3 dealiasing, float64, "
          f"NUMBA_NUM_THREADS={os.environ['NUMBA_NUM_THREADS']}, "
          f"ADJOINTSIM_THREADS={os.environ['ADJOINTSIM_THREADS']}; µs per step (CPU time)")
    for batch in (1, 64):
        raw = measure(batch, args.repeats)
        for label, reduce in (("median", np.median), ("best", np.min)):
            t = {k: 1e6 * float(reduce(v)) for k, v in raw.items()}
            both = t["forward+gradient"]
            print(
                f"batch {batch:3d} {label:>6}: 8 FFTs numpy.fft {t['ffts_numpy']:7.2f}, packed "
                f"{t['ffts_packed']:7.2f} | forward {t['forward']:7.2f} "
                f"(target {TARGETS['forward', batch]}) | forward+gradient {both:7.2f} "
                f"(target {TARGETS['forward+gradient', batch]}) | /forward "
                f"{both / t['forward']:.2f} (target ≤ {RATIO_TARGET}) | exponax "
                f"{EXPONAX_GRADIENT[batch]:.1f}: {EXPONAX_GRADIENT[batch] / both:.2f}x "
                f"(target ≥ {PEER_TARGET})"
            )


if __name__ == "__main__":
    main()
