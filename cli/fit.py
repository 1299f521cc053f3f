"""``adjointsim fit``: inverse problems with the hand-written adjoints."""

from __future__ import annotations

import argparse
from pathlib import Path

from .options import (
    at_least,
    config_flags,
    json_option,
    out_option,
    overrides,
    progress_option,
    run_config,
    scene_of,
    scene_option,
    threads_option,
)

_HELPS = {
    "observations": "HDF5 file: /steps, /states, optional /u0, /controls; attrs scene, config "
                    "(JSON), params (JSON), n (layout above)",
    "demo": "a built-in problem instead of an observation file",
    "wrt": "what to fit, comma-separated: state, controls, params or parameter names "
           "(None: state, or a demo's own choice)",
    "noise": "--demo: relative noise on the observations (0.01 = 1%%)",
    "seed": "--demo: the noise's seed",
    "method": "a gradient-based scipy.optimize method",
    "maxiter": "the optimiser's iteration limit",
    "tol": "scipy minimize's tol",
    "tikhonov": "λ_T of mean((z - z0)^2)",
    "smoothness": "λ_S of mean((D z)^2), D first differences in space (state) / time "
                  "(controls)",
}


def arguments(p: argparse.ArgumentParser) -> None:
    from adjointsim import fit_run
    from adjointsim.fit_run import FitConfig

    p.description = fit_run.__doc__
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("solver", nargs="?", default=None, metavar="SOLVER",
                   help="registered solver name (default: the file's 'scene' attribute)")
    out_option(p, "runs/fit-DEMO, or runs/fit-SOLVER")
    again = p.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true",
                       help="a fit keeps no checkpoint: return the finished fit in --out as it "
                       "is, or start an unfinished one again (an error when --out holds no fit)")
    again.add_argument("--overwrite", action="store_true",
                       help="discard the fit already in --out and run it again")
    p.add_argument("--config", type=Path, default=None, metavar="FILE.toml",
                   help="config keys from a TOML file; flags override them")
    progress_option(p)
    threads_option(p)
    json_option(p, "also write the result (result.json's contents) here")
    p.add_argument("--no-plots", dest="plots", action="store_false",
                   help="no fit.png and history.png")
    skip = ("solver", "scene", "steps", "checkpoint", "bounds", "start")
    config_flags(p, FitConfig, FitConfig.ACCEPTED, skip=skip, helps=_HELPS)
    scene_option(p)
    keys = p.add_argument_group("more FitConfig keys (also accepted in --config)")
    keys.add_argument("--steps", type=at_least(0), default=None,
                      help="rollout length (default: the file's n, else the last observed step)")
    keys.add_argument("--checkpoint", type=at_least(1), default=None,
                      help="states held by the adjoint sweep (default all)")
    keys.add_argument("--bounds", action="append", default=None, metavar="NAME=LO:HI",
                      help="bounds of a fitted parameter, either side may be empty, its start "
                      "inside them (repeat for several; default: a demo's own)")
    keys.add_argument("--start", action="append", default=None, metavar="NAME=VALUE",
                      help="starting (or fixed) value of a parameter (repeat for several)")


def run(args: argparse.Namespace) -> int:
    from adjointsim import parallel
    from adjointsim.files import write_json
    from adjointsim.fit_run import FitConfig, FitRun, run_fit

    parallel.set_threads(args.threads)
    values = {**overrides(args, FitConfig), "scene": scene_of(args)}
    cfg = run_config(args, FitRun, FitConfig, values, _default_out)
    out = args.out or _default_out(cfg)
    summary = run_fit(cfg, out, resume=args.resume, overwrite=args.overwrite,
                      progress=args.progress, plots=args.plots)
    extra = "".join(f", {k} = {v:.3g}" for k, v in summary.items()
                    if k == "u0_mse") + "".join(
        f", rel. error of {k} {v:.2g}" for k, v in summary.get("param_rel_error", {}).items())
    # a result.json of a fit finished before active bounds were reported has none
    active = summary.get("active_bounds", {})
    if active:
        extra += "; on a bound at the end: " + ", ".join(f"{k} ({v})" for k, v in active.items())
    print(f"{summary['scene']}: misfit {summary['start_misfit']:.3g} -> {summary['misfit']:.3g} "
          f"in {summary['iterations']} iterations, {summary['seconds']:.2f} s{extra}; "
          f"{summary['message']}; run in {out}/")
    if args.json:
        write_json(args.json, summary)
    return 0


def _default_out(cfg) -> Path:
    return Path(f"runs/fit-{cfg.demo or cfg.solver or 'fit'}")
