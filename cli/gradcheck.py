"""``adjointsim gradcheck``: the dot-product, Taylor and finite-difference tests of the
registered solvers' adjoints."""

from __future__ import annotations

import argparse
import math
import sys
import time

from adjointsim import parallel, registry
from adjointsim.errors import UserError
from adjointsim.files import json_text, write_text

from .options import at_least, json_option, seed_option, threads_option


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("names", nargs="*", help="registered solver names (see --list)")
    p.add_argument("--all", action="store_true", help="check every registered solver")
    p.add_argument("--list", action="store_true", help="print the registered solver names")
    p.add_argument("--steps", type=at_least(1), default=50,
                   help="rollout length, 1 to 100000 (default 50)")
    p.add_argument("--dtype", choices=("float64", "float32"), default="float64",
                   help="default float64")
    seed_option(p)
    threads_option(p)
    json_option(p, "also write the rows here as JSON ('-': print only them)")


def run(args: argparse.Namespace) -> int:
    from adjointsim.check import REF_SAFETY, TOLERANCES, check

    if args.list:
        print("\n".join(registry.names()))
        return 0
    if args.all == bool(args.names):
        raise UserError("name solvers or pass --all (see --list)")
    if args.steps > 100_000:
        raise UserError(f"--steps {args.steps} is more than the 100000 a gradient check needs; "
                        "choose fewer")
    names = registry.names() if args.all else args.names
    parallel.set_threads(args.threads)
    for name in names:
        registry.get(name)  # unknown names fail before any work
    start = time.perf_counter()
    quiet = str(args.json) == "-"
    progress = None
    if not quiet:
        def progress(name: str) -> None:
            print(f"checking {name} ...", file=sys.stderr, flush=True)

    rows = check(names, steps=args.steps, dtype=args.dtype, seed=args.seed, progress=progress)
    ok = all(r.passed for r in rows)
    if args.json is not None:
        text = json_text([r.as_dict() for r in rows])
        if quiet:
            print(text)
            return 0 if ok else 1
        write_text(args.json, text + "\n")
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
