"""``adjointsim hig``: a network trained through a solver with half-inverse gradients,
Gauss-Newton or Adam, for a budget of update time, resumable."""

from __future__ import annotations

import argparse
from pathlib import Path

from .options import (
    COMPILE_HELP,
    THREADS_HELP,
    at_least,
    config_flags,
    overrides,
    run_config,
    run_options,
    scene_of,
    scene_option,
    write_result,
)
from .study import TINY_NOTE

_HELPS = {
    "optimizer": "half-inverse gradients, Gauss-Newton or Adam, each with the problem's batch "
    "size and learning rate",
    "size": "tiny shrinks the data sets (for tests); quick is full",
    "threads": THREADS_HELP,
    "compile": COMPILE_HELP,
}


def arguments(p: argparse.ArgumentParser) -> None:
    from adjointsim.train.hig_problems import HigConfig
    from adjointsim.train.higs import PROBLEMS

    p.add_argument("problem", nargs="?", choices=PROBLEMS.names(), default=None,
                   help="the problem (config key problem; with --resume, the run's)")
    run_options(p, "runs/hig-PROBLEM-OPTIMIZER-seedSEED")
    # budget and max_updates accept None (the problem's budget, no limit), so their flags are
    # spelled here rather than by config_flags
    config_flags(p, HigConfig, HigConfig.ACCEPTED,
                 skip=("problem", "budget", "max_updates", "scene"), helps=_HELPS)
    scene_option(p)
    defaults = ", ".join(f"{name} {kind.BUDGET:g}" for name, kind in PROBLEMS.items())
    p.add_argument("--time-budget", dest="budget", type=float, default=None, metavar="SECONDS",
                   help="seconds of update time, > 0 (config key budget; default per problem: "
                   f"{defaults})")
    p.add_argument("--max-updates", dest="max_updates", type=at_least(1), default=None,
                   metavar="N", help="stop after this many updates (config key max_updates; "
                   "default: no limit)")


def run(args: argparse.Namespace) -> int:
    from adjointsim.train.hig_problems import HigConfig, HigRun, train_run

    values = {**overrides(args, HigConfig), "scene": scene_of(args)}
    cfg = run_config(args, HigRun, HigConfig, values, _default_out)
    out = args.out or _default_out(cfg)
    result = train_run(cfg, out, resume=args.resume, overwrite=args.overwrite,
                       progress=args.progress)
    write_result(args, result)
    loss = result["test_loss"]
    print(f"{cfg.problem}/{cfg.optimizer} seed {cfg.seed}: {result['updates']} updates in "
          f"{result['wall_s']:.1f} s, test loss "
          f"{'diverged' if loss is None else f'{loss:.4g}'}; run in {out}")
    if cfg.size == "tiny":
        print(TINY_NOTE)
    return 0


def _default_out(cfg) -> Path:
    return Path("runs") / f"hig-{cfg.problem}-{cfg.optimizer}-seed{cfg.seed}"
