"""``adjointsim data``: reference trajectories (HDF5) for training."""

from __future__ import annotations

import argparse
from pathlib import Path

from .options import progress_option, seed_option, threads_option


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("problem", choices=("ks", "kolmogorov"))
    p.add_argument("--size", choices=("tiny", "quick", "full"), default="quick",
                   help="tiny (KS only): seconds, for tests; default quick")
    seed_option(p)
    p.add_argument("--out", type=Path, default=None, metavar="PATH",
                   help="the HDF5 file (default data/PROBLEM-SIZE.h5)")
    p.add_argument("--overwrite", action="store_true", help="replace the file at --out")
    threads_option(p)
    progress_option(p)


def run(args: argparse.Namespace) -> int:
    from adjointsim import parallel
    from adjointsim.errors import UserError
    from adjointsim.train import data

    out = args.out or Path("data") / f"{args.problem}-{args.size}.h5"
    if out.is_dir():
        raise UserError(f"--out {out} is a directory; give the path of the HDF5 file to write")
    if out.exists() and not args.overwrite:
        raise UserError(f"{out} exists; pass --overwrite to replace it, or choose another --out")
    parallel.set_threads(args.threads)
    data.save(data.generate(args.problem, args.size, args.seed, progress=args.progress), out)
    print(f"wrote {out}")
    return 0
