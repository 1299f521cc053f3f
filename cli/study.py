"""``adjointsim study NAME``: a grid of runs on Dask distributed, every cell resumable; an
unknown NAME or size lists the registered ones."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from adjointsim.errors import Interrupted

from .options import at_least, json_option, progress_option

#: every registered study, one line each (a test holds it to the runner's registry)
STUDIES = {
    "ks": "KS neural steppers: prediction/correction x ONE/NOG/WIG",
    "kolmogorov": "the same on 2D Kolmogorov flow",
    "karman": "the same on the cylinder wake (sequential correction)",
    "ks-curves": "learning curves of KS correction, ONE, NOG and WIG",
    "stablebptt": "controllers with the gradient flows R, M, S and C",
    "hig": "half-inverse gradients against Gauss-Newton and Adam",
    "pinn-poisson": "multi-scale Poisson PINN: uniform vs inverse-Dirichlet",
    "pinn-ks-inverse": "KS coefficients learned by a PINN, with loss balancing",
    "weighting": "every loss-weighting scheme on PINNs and guidance",
    "weighting-forgetting": "loss weights when a term of another scale joins",
    "fit-params": "KS coefficients fitted to noisy snapshots",
    "burgers-dp-pinn": "a Burgers initial state: differentiable physics vs PINN",
    "burgers-nu-dp-pinn": "the Burgers viscosity: differentiable physics vs PINN",
    "smoke": "a smoke inflow optimised through the flow's adjoint",
    "stability": "the largest stable time step of every solver",
}


#: printed under a result of size tiny, which can look like a failure
TINY_NOTE = ("size tiny only checks that the pipeline runs: its numbers say nothing about the "
             "methods (a larger --size measures them)")


def arguments(p: argparse.ArgumentParser) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    width = max(map(len, STUDIES))
    p.epilog = "studies:\n" + "\n".join(f"  {name:<{width}}  {text}"
                                          for name, text in STUDIES.items())
    p.add_argument("problem", metavar="NAME", help="the study (listed below)")
    p.add_argument("--quick", action="store_const", const="quick", dest="size",
                   help="a reduced study (minutes); same as --size quick")
    p.add_argument("--size", default="full",
                   help="tiny (seconds, a smoke test of the whole pipeline), quick or full "
                   "(default); some studies have sizes of their own (an unknown size lists "
                   "them)")
    p.add_argument("--seeds", type=at_least(1), default=None,
                   help="seeds per configuration (default: the size's)")
    p.add_argument("--jobs", type=at_least(1), default=2,
                   help="worker processes of the local cluster (one thread each; default 2)")
    p.add_argument("--cluster", default=None,
                   help="local (default: a Dask cluster of --jobs processes started here), none "
                   "(this process, one cell after another) or a scheduler address "
                   "tcp://HOST:PORT; default $DASK_SCHEDULER_ADDRESS if set, else local")
    p.add_argument("--retries", type=at_least(0), default=1,
                   help="times a failed cell is run again, resuming from its checkpoint "
                   "(default 1)")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="the study directory (default runs/study-NAME[-SIZE])")
    json_option(p, "also write one object per cell here")
    p.add_argument("--reuse", type=Path, default=None, metavar="ROWS",
                   help="finished rows of an earlier run (its --json or rows.json file, e.g. "
                   "one committed under docs/results/): those cells are not run again")
    p.add_argument("--so-far", action="store_true",
                   help="run nothing: tabulate and draw what the study directory holds so far, "
                   "unfinished cells too (a running or stopped study; ks-curves, stablebptt, "
                   "hig), the rows in DIR/rows-so-far.json")
    progress_option(p)
    p.set_defaults(size="full")


def run(args: argparse.Namespace) -> int:
    """Every unfinished cell through :func:`adjointsim.runner.run`; exit 1 if any failed (each
    failure is printed with its cell id), after the report of what finished."""
    from adjointsim import runner
    from adjointsim.files import write_json
    from adjointsim.train.studies import load

    load(args.problem)
    suffix = "" if args.size == "full" else f"-{args.size}"
    out = args.out or Path("runs") / f"study-{args.problem}{suffix}"
    if args.so_far:
        rows = runner.so_far(args.problem, out, args.size, args.seeds)
        print(runner.write_report(args.problem, rows, out.resolve()))
        if args.json:
            write_json(args.json, rows)
        return 0
    failed: list[tuple[str, str]] = []
    try:
        rows = runner.run(args.problem, out, args.size, args.seeds, cluster=args.cluster,
                          jobs=args.jobs, retries=args.retries, progress=args.progress,
                          report=False, reuse=args.reuse)
    except runner.CellsFailed as e:
        rows, failed = e.rows, e.failures
    except KeyboardInterrupt:
        raise Interrupted("run the same command again: finished cells are kept and the "
                          "others resume from their checkpoints") from None
    if rows:
        print(runner.write_report(args.problem, rows, out.resolve()))
        if args.size == "tiny":
            print(TINY_NOTE)
    if args.json:
        write_json(args.json, rows)
    for cell_id, error in failed:
        print(f"adjointsim study: cell {cell_id} failed: {error}", file=sys.stderr)
    if failed:
        print(f"adjointsim study: {len(failed)} cell(s) failed, {len(rows)} finished; run the "
              "same command again to retry only the failed ones", file=sys.stderr)
    return 1 if failed else 0
