"""One half-inverse-gradient update, split into its parts, and its Jacobian against torch.func.

    python benchmarks/hig.py [--problem oscillators] [--repeats 7]

Prints the median time of one HIG update on the problem's HIG batch, split into the Jacobian's
network part (per-sample VJPs through the MLP) and physics part (the solver's batched adjoint,
one call for all b·d_y rows), the decomposition (``svd``: the Gram eigendecomposition or QR + small
SVD, as ``train.hig`` chooses) and the apply, with the physics share
(target ≤ 25% on the oscillators). Then J = ∂y/∂θ from ``HalfInverseGradients.jacobian``
against ``torch.func.jacrev`` through the same RK4 simulator written in plain torch
(checked equal to 1e-10 in float64; target ≥ 5x). Each repetition runs every candidate once,
round-robin, so that load on a shared machine hits them alike.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from torch.func import functional_call, jacrev

from adjointsim.solvers.oscillators import Oscillators
from train.hig import HalfInverseGradients
from train.hig_problems import make_problem


def torch_oscillators(stepper: Oscillators, u0: torch.Tensor, controls: torch.Tensor,
                      steps: int) -> torch.Tensor:
    """The same RK4 chain in plain torch: u0 (b, 2, n), controls (b, steps) -> final state."""
    k, lin, cub, gain = stepper.param_values
    h = stepper.dt

    def slope(z: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        x, v = z[:, 0], z[:, 1]
        d = x[:, 1:] - x[:, :-1]  # bond i joins oscillators i and i + 1
        bond = lin * d + cub * d**3
        a = -k * x + torch.nn.functional.pad(bond, (0, 1)) - torch.nn.functional.pad(bond, (1, 0))
        force = torch.zeros_like(a)
        force[:, -1] = gain * u
        return torch.stack([v, a + force], dim=1)

    y = u0
    for i in range(steps):
        u = controls[:, i]
        k1 = slope(y, u)
        k2 = slope(y + 0.5 * h * k1, u)
        k3 = slope(y + 0.5 * h * k2, u)
        k4 = slope(y + h * k3, u)
        y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return y


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problem", default="oscillators", choices=("oscillators", "chain"))
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    torch.manual_seed(0)
    problem = make_problem(args.problem, 0)
    settings = problem.settings["hig"]
    model = problem.model()
    opt = HalfInverseGradients(model, problem.physics, problem.loss, lr=settings["lr"],
                               tau=settings["tau"])
    x, c, t = problem.sample(torch.Generator().manual_seed(0), int(settings["batch"]))
    stepper, steps = problem.physics.stepper, problem.physics.steps
    params = {k: v.detach() for k, v in model.named_parameters()}

    def ours() -> torch.Tensor:
        return opt.jacobian(x, c)[1]

    def torch_jacrev() -> torch.Tensor:
        def y_of(p: dict) -> torch.Tensor:
            f = functional_call(model, p, (x,))
            return torch_oscillators(stepper, c.reshape(-1, 2, stepper.n), f, steps).reshape(-1)

        parts = jacrev(y_of)(params)
        return torch.cat([parts[k].reshape(parts[k].shape[0], -1) for k in params], dim=1)

    # warm-up (numba cache, torch.func tracing) and the equality check
    j_ours, j_torch = ours(), torch_jacrev()
    err = float((j_ours - j_torch).abs().max() / j_torch.abs().max())
    print(f"{args.problem}: batch {x.shape[0]}, J {tuple(j_ours.shape)} (float64); "
          f"max |J_ours − J_jacrev| / max |J| = {err:.2e}")
    assert err <= 1e-10, "the plain-torch simulator disagrees with the solver"
    opt.step(x, c, t)

    parts: dict[str, list[float]] = {
        k: [] for k in ("network", "physics", "decomposition", "apply")}
    totals, jac_ours, jac_torch = [], [], []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        opt.step(x, c, t)
        totals.append(time.perf_counter() - t0)
        for k in parts:
            parts[k].append(opt.timing[k])
        t0 = time.perf_counter()
        ours()
        jac_ours.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        torch_jacrev()
        jac_torch.append(time.perf_counter() - t0)
    med = {k: statistics.median(v) for k, v in parts.items()}
    total = statistics.median(totals)
    print(f"one HIG update (median of {args.repeats}): {1e3 * total:.1f} ms")
    for k, v in med.items():
        print(f"  {k:<13} {1e3 * v:8.1f} ms  {100 * v / total:5.1f}%")
    share = med["physics"] / total
    print(f"physics part (batched adjoint): {100 * share:.1f}% of the update "
          f"(target ≤ 25%: {'met' if share <= 0.25 else 'NOT met'})")
    a, b = statistics.median(jac_ours), statistics.median(jac_torch)
    print(f"Jacobian: ours {1e3 * a:.1f} ms, torch.func.jacrev through plain-torch RK4 "
          f"{1e3 * b:.1f} ms: {b / a:.1f}x (target ≥ 5x: {'met' if b / a >= 5 else 'NOT met'})")
    # the two decompositions of the same J, side by side
    g = torch.randn(j_ours.shape[0], dtype=j_ours.dtype, generator=torch.Generator().manual_seed(1))
    routes = {name: HalfInverseGradients(model, problem.physics, problem.loss,
                                         tau=settings["tau"], decomposition=name)
              for name in ("svd", "gram")}
    times = {name: [] for name in routes}
    for _ in range(args.repeats):
        for name, o in routes.items():
            t0 = time.perf_counter()
            o.direction(j_ours, g)
            times[name].append(time.perf_counter() - t0)
    d_svd, d_gram = (routes[n].direction(j_ours, g) for n in ("svd", "gram"))
    ts, tg = (statistics.median(times[n]) for n in ("svd", "gram"))
    print(f"decomposition (τ = {settings['tau']:g}): QR + SVD {1e3 * ts:.1f} ms, Gram "
          f"eigendecomposition {1e3 * tg:.1f} ms ({ts / tg:.1f}x); updates differ by "
          f"{float((d_svd - d_gram).norm() / d_svd.norm()):.1e} relative")


if __name__ == "__main__":
    main()
