"""Inverse problems with ``adjointsim.fit.fit``: scene parameters and an initial state fitted to
observations, each evaluation one rollout and one sweep of the hand-written adjoint, optimised
by scipy's L-BFGS-B. No torch.

1. Kuramoto-Sivashinsky, u_t + u u_x + alpha u_xx + beta u_xxxx = 0 (``ks1d-etdrk4``, N = 64,
   L = 22): alpha and beta recovered from 20 snapshots with 1% noise, starting from 1.3 and
   0.7 (the truth is 1 and 1).
2. Burgers (``burgers1d-rusanov``, the PBDL book's scene): the initial state reconstructed from
   one observation at t = 0.5, with and without a smoothness penalty. The problem is
   ill-posed: a tiny misfit does not make the initial state right, the penalty helps.

The same fits from the command line: ``adjointsim fit --demo ks-params`` and
``adjointsim fit --demo burgers``.

Run:  python examples/inverse_fit.py [--noise 0.01] [--tiny]
Takes about 10 s on 2 cores (--tiny, fewer steps and iterations: about 3 s).
"""

from __future__ import annotations

import argparse

import numpy as np

import adjointsim
from adjointsim.fit import fit
from adjointsim.fit_demos import pbdl_scene, pbdl_state


def ks_parameters(noise: float, steps: int, maxiter: int) -> dict[str, float]:
    scene = adjointsim.get("ks1d-etdrk4")(n=64, length=22.0, dt=0.1)
    u0 = scene.random_state(np.random.default_rng(1234))
    traj = scene.rollout(u0, steps, keep="all")  # the truth: alpha = beta = 1
    every = max(1, steps // 20)
    rng = np.random.default_rng(0)
    obs = {k: traj[k] + noise * float(np.std(traj[1:])) * rng.standard_normal(traj[k].shape)
           for k in range(every, steps + 1, every)}
    result = fit(scene, obs, wrt="params", u0=u0, maxiter=maxiter,
                 params={"anti_diffusion": 1.3, "hyper_diffusion": 0.7},
                 bounds={"hyper_diffusion": (0.05, None)})
    print(f"KS, {len(obs)} snapshots with {noise:.0%} noise: {result.iterations} iterations, "
          f"{result.evaluations} evaluations, {result.seconds:.2f} s, misfit {result.misfit:.3e}")
    errors = {}
    for name, value in result.params.items():
        errors[name] = abs(value - scene.params[name]) / abs(scene.params[name])
        print(f"  {name:<16} fitted {value:.6f}  true {scene.params[name]:.6f}  "
              f"relative error {errors[name]:.2e}")
    return errors


def burgers_state(maxiter: int) -> None:
    scene = pbdl_scene()
    truth = pbdl_state(scene)  # u_0 = -sin(pi x)
    obs = {16: scene.rollout(truth, 16)}  # t = 16 dt = 0.5
    print(f"Burgers, one observation at t = 0.5, initial state from zero, {maxiter} iterations:")
    for smoothness in (0.0, 1e-4):
        result = fit(scene, obs, wrt="state", maxiter=maxiter, smoothness=smoothness,
                     tikhonov=smoothness)
        u0_error = float(np.mean((result.state - truth) ** 2))
        print(f"  smoothness and Tikhonov {smoothness:g}: misfit {result.misfit:.3e}, MSE of "
              f"u_0 against -sin(pi x) {u0_error:.3e} ({result.seconds:.2f} s)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--noise", type=float, default=0.01,
                    help="relative noise on the KS observations (default 0.01)")
    ap.add_argument("--tiny", action="store_true", help="a second or two, for tests")
    args = ap.parse_args()
    errors = ks_parameters(args.noise, 20 if args.tiny else 100, 10 if args.tiny else 200)
    burgers_state(10 if args.tiny else 500)
    print("result: KS parameters recovered to relative errors "
          + ", ".join(f"{k} {v:.2e}" for k, v in errors.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
