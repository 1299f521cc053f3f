"""One half-inverse-gradient update, split into its parts, its Jacobian against torch.func,
and the three routes to its direction side by side.

    python benchmarks/hig.py [--problem oscillators] [--repeats 7] [--routes P ...] [--batch B]

Prints the median time of one HIG update on the problem's HIG batch, split into the network
part (the layers' backward for all b·d_y rows), the physics part (the solver's batched adjoint,
one call for all rows), the decomposition (the Gram eigendecomposition, or QR + small SVD, as
``adjointsim.train.hig`` chooses) and the apply, with the physics share (target ≤ 25% on the
oscillators). Then J = ∂y/∂θ from ``HalfInverseGradients.jacobian`` against
``torch.func.jacrev`` through the same RK4 simulator written in plain torch (checked equal to
1e-10 in float64; target ≥ 5x). Last, per problem of ``--routes``: the direction of one update
(derivatives and decomposition) from the Gram matrix of layer factors (the default), from the
Gram matrix of the explicit J, and from QR + SVD of J (up to 1024 rows). Each repetition runs
every candidate once, round-robin, so that load on a shared machine hits them alike.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from torch.func import functional_call, jacrev

from adjointsim.solvers.oscillators import Oscillators
from adjointsim.train.hig import HalfInverseGradients
from adjointsim.train.higs import make_problem


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
    parser.add_argument("--routes", nargs="*", default=["oscillators", "quantum", "poisson"],
                        choices=("oscillators", "quantum", "poisson", "chain"),
                        help="problems whose update is timed by the three routes")
    parser.add_argument("--batch", type=int, default=None,
                        help="batch of the route comparison (default: each problem's HIG batch)")
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
    for name in args.routes:
        routes(name, args.repeats, args.batch)


#: QR + SVD of a larger J takes minutes per update: the comparison leaves it out
SVD_MAX_ROWS = 1024


def routes(name: str, repeats: int, batch: int | None) -> None:
    """The direction of one update of ``name`` (its HIG batch, or ``batch``) by the three routes,
    round-robin: the Gram matrix from layer factors (the default), from the explicit J, and
    QR + SVD of the explicit J."""
    problem = make_problem(name, 0)
    settings = problem.settings["hig"]
    torch.manual_seed(0)
    model = problem.model()
    batch = int(settings["batch"]) if batch is None else batch
    x, c, _ = problem.sample(torch.Generator().manual_seed(0), batch)

    def make(decomposition: str) -> HalfInverseGradients:
        return HalfInverseGradients(model, problem.physics, problem.loss, lr=0.0,
                                    tau=settings["tau"], decomposition=decomposition,
                                    max_jacobian_mb=1e5)

    gram, svd = make("gram"), make("svd")
    deltas: dict[str, torch.Tensor] = {}

    def layers() -> None:
        deltas["layers"] = gram.direction(gram.layer_factors(x, c)[1], g)

    def explicit() -> None:
        deltas["explicit"] = gram.direction(gram.jacobian(x, c)[1], g)

    def qr_svd() -> None:
        deltas["svd"] = svd.direction(svd.jacobian(x, c)[1], g)

    rows = batch * problem.test[2].shape[1]
    g = torch.randn(rows, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    candidates = {"Gram from layer factors": layers, "Gram from J": explicit}
    if rows <= SVD_MAX_ROWS:
        candidates["QR + SVD of J"] = qr_svd
    times: dict[str, list[float]] = {k: [] for k in candidates}
    for f in candidates.values():
        f()  # warm-up
    for _ in range(repeats):
        for k, f in candidates.items():
            t0 = time.perf_counter()
            f()
            times[k].append(time.perf_counter() - t0)
    med = {k: statistics.median(v) for k, v in times.items()}
    base = med["Gram from layer factors"]
    print(f"{name}: the direction of one update (batch {x.shape[0]}, {rows} rows of J, "
          f"τ = {settings['tau']:g}), derivatives and decomposition, median of {repeats}:")
    for k, v in med.items():
        print(f"  {k:<24} {1e3 * v:8.1f} ms  {v / base:5.2f}x")
    ref = deltas.get("svd", deltas["explicit"])
    for k in [k for k in ("layers", "explicit") if deltas[k] is not ref]:
        err = float((deltas[k] - ref).norm() / ref.norm())
        against = "QR + SVD" if "svd" in deltas else "the Gram matrix from J"
        print(f"  direction from {k} against {against}: {err:.1e} relative")

if __name__ == "__main__":
    main()
