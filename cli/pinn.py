"""``adjointsim pinn``: physics-informed training with loss balancing, resumable."""

from __future__ import annotations

import argparse
from pathlib import Path

from .options import (
    COMPILE_HELP,
    THREADS_HELP,
    config_flags,
    overrides,
    run_config,
    run_options,
    write_result,
)

_HELPS = {
    "k": "the Poisson wavenumber: ω = kπ",
    "weighting": "how the loss terms are balanced: fixed weights (uniform; the Poisson "
                 "problem's analytic epsilon-optimal, also fixed/analytic), weights from the "
                 "terms' gradients (inverse-dirichlet or id, max-avg or maxavg, gradnorm, ntk), "
                 "from the losses (softadapt, relobralo), or a combined direction (mgda, pcgrad, "
                 "config)",
    "reference": "the inverse-Dirichlet reference term: the problem's (res) or the term of "
                 "largest gradient spread (max)",
    "seed": "draws the points and the initial network (Sobolev: the target too)",
    "lr": "Adam's learning rate (Poisson and Sobolev: × 0.1 at epochs 10k, 20k and 30k)",
    "every": "epochs between weight refreshes",
    "alpha": "the weights' moving-average factor",
    "depth": "hidden layers",
    "collocation": "collocation points (Poisson: drawn from the 100 x 100 grid)",
    "edge_points": "points per boundary edge (ks-inverse: times of the periodicity term)",
    "route": "Δu by the forward Taylor route or nested autograd (Poisson only)",
    "log_every": "epochs between rows of history.csv",
    "threads": THREADS_HELP,
    "compile": COMPILE_HELP,
}


def arguments(p: argparse.ArgumentParser) -> None:
    from adjointsim.train.pinn import PinnConfig
    from adjointsim.train.pinns import PROBLEMS

    problems = PROBLEMS.items()

    def each(key: str) -> str:
        return ", ".join(f"{name} {getattr(cls, key)}" for name, cls in problems)

    p.add_argument("problem", nargs="?", choices=PROBLEMS.names(), default=None,
                   help="the problem (default poisson, or the --config file's; with --resume, "
                   "the run's)")
    run_options(p, "runs/pinn-PROBLEM-kK-WEIGHTING-seedS")
    helps = {**_HELPS, "epochs": f"0: the problem's ({each('epochs')})",
             "width": f"hidden units per layer; 0: the problem's ({each('width')})"}
    config_flags(p, PinnConfig, PinnConfig.ACCEPTED, skip=("problem",), helps=helps)


def run(args: argparse.Namespace) -> int:
    from adjointsim.train import pinn

    cfg = run_config(args, pinn.PinnRun, pinn.PinnConfig, overrides(args, pinn.PinnConfig),
                     _default_out)
    name = _name(cfg)
    out = args.out or _default_out(cfg)
    result = pinn.train_run(cfg, out, resume=args.resume, progress=args.progress,
                            overwrite=args.overwrite)
    write_result(args, result)
    if result["diverged"]:
        print(f"{name} {cfg.weighting}: diverged after {pinn.MAX_SKIPS} non-finite losses in a "
              f"row; run in {out}")
        return 1
    print(f"{name} {cfg.weighting} seed {cfg.seed}: relative L2 "
          f"{result['rel_l2']:.3e} after {cfg.epochs} epochs ({result['seconds']:.0f} s), "
          f"weights {', '.join(f'{k} {v:.3g}' for k, v in result['weights'].items())}"
          + "".join(f", {k} {v:.4g}" for k, v in result["coefficients"].items())
          + f"; run in {out}")
    return 0


def _name(cfg) -> str:
    return f"{cfg.problem}-k{cfg.k}" if cfg.problem == "poisson" else cfg.problem


def _default_out(cfg) -> Path:
    return Path("runs") / f"pinn-{_name(cfg)}-{cfg.weighting}-seed{cfg.seed}"
