"""Cost of one misfit-plus-gradient evaluation of a fit, hand-written adjoint vs plain torch.

    python benchmarks/fit.py [--repeats 21] [--batches 1,16]

The problem is PBDL's Burgers reconstruction (:func:`adjointsim.fit_demos.pbdl_scene`: N = 128,
Δt = 1/32 in 5 Rusanov sub-steps, ν = 0.01/π), the misfit at step 16, with the gradient with
respect to the initial state and ν:

* ``adjoint``: :func:`adjointsim.fit.problem`'s objective (forward rollout, the vjp, packing),
  i.e. what the optimiser calls once per evaluation;
* ``torch``: the same scheme written in plain torch (float64) and differentiated by autograd.

Before timing, the two misfits and gradients are checked equal to 1e-10 (relative, float64) at
a generic point (−sin(πx) plus noise: no ties in the Rusanov flux's max). Side by side in one
run, round-robin, one thread, medians of ``--repeats`` evaluations; printed: ms per evaluation
and torch/adjoint (target ≥ 5).
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from adjointsim.fit import problem  # noqa: E402
from adjointsim.fit_demos import PBDL_T_OBS_STEP, pbdl_scene, pbdl_state  # noqa: E402


def torch_misfit(scene, u0: torch.Tensor, nu: torch.Tensor, target: torch.Tensor,
                 steps: int) -> torch.Tensor:
    """The Rusanov scheme of ``adjointsim.solvers.burgers_fv`` (1D, periodic) in torch."""
    tau = scene.dt / scene.substeps
    inv_h = 1.0 / scene.h
    u = u0
    for _ in range(steps):
        for _ in range(scene.substeps):
            east = torch.roll(u, -1, dims=-1)
            west = torch.roll(u, 1, dims=-1)
            alpha = torch.maximum(u.abs(), east.abs())
            flux = 0.25 * (u * u + east * east) - 0.5 * alpha * (east - u)  # face i + ½
            lap = (west - 2.0 * u + east) * inv_h**2
            u = u + tau * nu * lap - tau * inv_h * (flux - torch.roll(flux, 1, dims=-1))
    return ((u - target) ** 2).mean()


def measure(scene, steps: int, batch: int, repeats: int) -> None:
    """One table row: the agreement check, then round-robin timings."""
    rng = np.random.default_rng(batch)
    truth = pbdl_state(scene, batch)
    obs = {steps: scene.rollout(truth, steps)}
    u0 = truth + 0.05 * rng.standard_normal(truth.shape)
    nu0 = 0.8 * scene.params["nu"]
    prob = problem(scene, obs, wrt="state,nu", u0=u0, params={"nu": nu0})
    z = prob.z0

    def adjoint():
        return prob.objective(z)

    ut = torch.tensor(u0, requires_grad=True)
    nut = torch.tensor(nu0, dtype=torch.float64, requires_grad=True)
    target = torch.from_numpy(obs[steps])

    def plain():
        ut.grad = nut.grad = None
        loss = torch_misfit(scene, ut, nut, target, steps)
        loss.backward()
        return float(loss.detach()), ut.grad.numpy().ravel(), float(nut.grad)

    f, g = adjoint()
    ft, gu, gnu = plain()
    # the optimiser works in ν/|ν0|: its gradient entry is |ν0| ∂J/∂ν
    g_torch = np.concatenate([gu, [gnu * abs(nu0)]])
    diff = max(abs(f - ft) / abs(ft),
               float(np.abs(g - g_torch).max() / np.abs(g_torch).max()))
    if diff > 1e-10:
        raise SystemExit(f"batch {batch}: adjoint and torch disagree ({diff:.2e} relative)")
    times: dict[str, list[float]] = {"adjoint": [], "torch": []}
    for _ in range(repeats):
        for name, fn in (("adjoint", adjoint), ("torch", plain)):
            t = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t)
    a, t = (1e3 * float(np.median(times[k])) for k in ("adjoint", "torch"))
    print(f"{batch:>5} {a:>11.3f} {t:>9.3f} {t / a:>14.1f}  {diff:.1e}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=21)
    p.add_argument("--batches", default="1,16")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    scene = pbdl_scene()
    steps = PBDL_T_OBS_STEP
    print(f"one misfit + gradient (u0, nu) of the PBDL Burgers fit, {steps} steps x "
          f"{scene.substeps} sub-steps, N = 128, float64, one thread, median of {args.repeats}")
    print(f"{'batch':>5} {'adjoint ms':>11} {'torch ms':>9} {'torch/adjoint':>14}  max rel. diff")
    for batch in (int(b) for b in args.batches.split(",")):
        measure(scene, steps, batch, args.repeats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
