"""The ``adjointsim`` command line: ``gradcheck`` here; the torch commands live in ``train``."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Sequence

from . import registry


def _gradcheck(args: argparse.Namespace) -> int:
    from .check import REF_SAFETY, TOLERANCES, check

    if args.list:
        print("\n".join(registry.names()))
        return 0
    if args.all == bool(args.names):
        print("gradcheck: name solvers or pass --all (see --list)", file=sys.stderr)
        return 2
    if args.steps < 1:
        print(f"adjointsim gradcheck: --steps must be a positive integer, not {args.steps}",
              file=sys.stderr)
        return 2
    names = registry.names() if args.all else args.names
    for name in names:
        registry.get(name)  # unknown names fail before any work
    start = time.perf_counter()
    progress = None
    if not args.json:
        def progress(name: str) -> None:
            print(f"checking {name} ...", file=sys.stderr, flush=True)

    rows = check(names, steps=args.steps, dtype=args.dtype, seed=args.seed, progress=progress)
    ok = all(r.passed for r in rows)
    if args.json:
        print(json.dumps([r.as_dict() for r in rows], allow_nan=False))
        return 0 if ok else 1
    tol = TOLERANCES[args.dtype]
    print(
        f"{args.dtype}, {args.steps} steps, seed {args.seed}; pass if dot-product rel. error <= "
        f"max({tol['dot']:g}, {REF_SAFETY:g} x its reference's error estimate 'ref', which must be "
        f"<= {tol['dot_ref']:g}), Taylor rate >= {tol['rate']:g} or remainder/eps^2 growing "
        f"<= 2x over its last two halvings, central-FD rel. error <= max({tol['fd']:g}, "
        f"{REF_SAFETY:g} x 'ref' <= {tol['fd_ref']:g}; an undecidable 'ref' is only noted when "
        "the exact complex-step dot-product test and the Taylor test passed)"
    )
    width = max(len(r.solver) for r in rows) if rows else 6
    print(f"{'solver':<{width}}  {'wrt':<16} {'dot_rel_err':>11} {'ref':>8} {'taylor_rate':>11} "
          f"{'fd_rel_err':>10} {'ref':>8}  result")

    def num(v: float | None, spec: str, w: int) -> str:
        return f"{v:{w}{spec}}" if v is not None and math.isfinite(v) else f"{'-':>{w}}"

    for r in rows:
        print(f"{r.solver:<{width}}  {r.wrt:<16} {num(r.dot_rel_err, '.2e', 11)} "
              f"{num(r.dot_ref_err, '.1e', 8)} {num(r.taylor_rate, '.3f', 11)} "
              f"{num(r.fd_rel_err, '.2e', 10)} {num(r.fd_ref_err, '.1e', 8)}  "
              + (f"pass{f' ({r.reason})' if r.reason else ''}" if r.passed
                 else f"FAIL: {r.reason}"))
    failed = sum(not r.passed for r in rows)
    print(f"{len(rows) - failed} passed, {failed} failed in {time.perf_counter() - start:.1f} s")
    return 0 if ok else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="adjointsim", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    g = sub.add_parser(
        "gradcheck",
        help="verify the discrete adjoints (dot-product, Taylor and finite-difference tests)",
    )
    g.add_argument("names", nargs="*", help="registered solver names (see --list)")
    g.add_argument("--all", action="store_true", help="check every registered solver")
    g.add_argument("--list", action="store_true", help="print the registered solver names")
    g.add_argument("--steps", type=int, default=50, help="rollout length, >= 1 (default 50)")
    g.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--json", action="store_true", help="print only a JSON list of rows")
    g.set_defaults(func=_gradcheck)
    b = sub.add_parser("bench", help="benchmarks: work-precision sweeps (error vs run time)")
    b.add_argument("which", choices=("work-precision",))
    b.add_argument("rest", nargs=argparse.REMAINDER, help="SCENE [--out DIR] [--quick]")
    b.set_defaults(func=_bench)
    st = sub.add_parser("stability", help="largest stable Δt per scheme and grid (bisection on "
                        "long rollouts) against each scheme's stated limit; table and plot")
    st.add_argument("names", nargs="*", help="registered solver names (see gradcheck --list)")
    st.add_argument("--all", action="store_true", help="every scheme with a time step")
    st.add_argument("--size", choices=("tiny", "full"), default="full")
    st.add_argument("--jobs", type=int, default=2, help="local worker processes (default 2)")
    st.add_argument("--cluster", default=None, help="local, none or tcp://HOST:PORT, as for "
                    "`adjointsim study` (default $DASK_SCHEDULER_ADDRESS, else local)")
    st.add_argument("--retries", type=int, default=1)
    st.add_argument("--out", default=None, help="default runs/stability[-SIZE]")
    st.add_argument("--json", default=None, help="also write the rows here")
    st.set_defaults(func=_stability)
    from .fit_cli import add_arguments as fit_arguments

    fit_arguments(sub.add_parser("fit", help="fit initial state, controls and coefficients to "
                                 "observations (HDF5) with the adjoints; --demo, --study params"))
    return parser


def _bench(args: argparse.Namespace) -> int:
    from .bench.work_precision import main as work_precision

    return work_precision(args.rest)


def _stability(args: argparse.Namespace) -> int:
    from .stability import command

    return command(args.names, args.all, args.size, args.jobs, args.cluster, args.retries,
                   args.out, args.json)


#: commands that need torch; they live in the ``train`` package and load only when used
TORCH_COMMANDS = {
    "data": "generate reference trajectories (HDF5)",
    "train": "train a neural stepper (ONE/NOG/WIG or R/M/S/N/C, prediction/correction)",
    "eval": "evaluate a trained run: errors, correlation time, stability, plots",
    "study": "a grid of runs on Dask (ks, kolmogorov, stablebptt, hig, pinn-poisson, stability)",
    "hig": "train through a solver with half-inverse gradients, Gauss-Newton or Adam",
    "control": "train a controller through a simulator (cartpole, guidance, quantum; R/M/S/N/C)",
    "pinn": "physics-informed training with loss balancing (uniform, inverse-Dirichlet, max/avg)",
}


class UserError(ValueError):
    """A mistake in what the user gave (arguments, config, files): the CLI prints the message
    on one line and exits 2. A ValueError, so library callers can catch it as one."""


class ConfigTypeError(UserError, TypeError):
    """A config value of the wrong type (the message names the key, the value and the type)."""


class DamagedFileError(UserError):
    """A file whose checksum does not match its contents (the message says how to recover)."""


class Interrupted(KeyboardInterrupt):
    """Ctrl-C, carrying what a command's user should do to continue (its ``args[0]``)."""


#: one line and exit 2 for these; anything else (a bare KeyError too) is a bug and keeps its
#: traceback (``ADJOINTSIM_TRACEBACK=1`` shows it for these too)
USER_ERRORS = (UserError, ValueError, registry.UnknownSolverError, OSError)


def main(argv: Sequence[str] | None = None) -> int:
    """The one error boundary of every command: user errors print ``adjointsim CMD: message``
    and exit 2, Ctrl-C exits 130 with how to continue, genuine bugs raise."""
    argv = list(sys.argv[1:] if argv is None else argv)
    command = argv[0] if argv else ""
    try:
        if command in TORCH_COMMANDS:
            from train.cli import main as train_main

            return train_main(argv)
        parser = build_parser()
        parser.epilog = "torch commands (see adjointsim COMMAND --help): " + "; ".join(
            f"{k}: {v}" for k, v in TORCH_COMMANDS.items()
        )
        args = parser.parse_args(argv)
        return args.func(args)
    except KeyboardInterrupt as e:
        hint = e.args[0] if e.args else "files are written atomically, so run the command again"
        print(f"adjointsim {command}: interrupted; {hint}", file=sys.stderr)
        return 130
    except USER_ERRORS as e:
        if os.environ.get("ADJOINTSIM_TRACEBACK"):
            raise
        message = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
        print(f"adjointsim {command}: {' '.join(str(message).split())}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
