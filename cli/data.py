"""``adjointsim data``: reference trajectories (HDF5) for training."""

from __future__ import annotations

import argparse
from pathlib import Path

from .options import seed_option


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("problem", choices=("ks", "kolmogorov"))
    p.add_argument("--size", choices=("tiny", "quick", "full"), default="quick",
                   help="tiny (KS only): seconds, for tests; default quick")
    seed_option(p)
    p.add_argument("--out", type=Path, default=None, metavar="PATH",
                   help="the HDF5 file (default data/PROBLEM-SIZE.h5)")


def run(args: argparse.Namespace) -> int:
    from adjointsim.train import data

    out = args.out or Path("data") / f"{args.problem}-{args.size}.h5"
    data.save(data.generate(args.problem, args.size, args.seed), out)
    print(f"wrote {out}")
    return 0
