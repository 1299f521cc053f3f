"""``adjointsim bench work-precision SCENE``: error at t_end against run time of the spectral
ETDRK solvers, their NumPy ETDRK4 baseline and (when installed) exponax; a CSV and a log-log
plot in ``--out``."""

from __future__ import annotations

import argparse
from pathlib import Path

from .options import at_least, progress_option, threads_option


def arguments(p: argparse.ArgumentParser) -> None:
    from adjointsim.bench.work_precision import SCENES

    p.add_argument("which", choices=("work-precision",), help="the benchmark")
    p.add_argument("scene", choices=sorted(SCENES),
                   help="; ".join(f"{k}: {v.title}" for k, v in SCENES.items()))
    p.add_argument("--out", type=Path, default=Path("."), metavar="DIR",
                   help="where the CSV and the plot go (default .)")
    p.add_argument("--quick", action="store_true", help="a small sweep (under a minute)")
    p.add_argument("--repeats", type=at_least(1), default=None,
                   help="timing samples per point (default 5, with --quick 3)")
    p.add_argument("--no-exponax", dest="exponax", action="store_false",
                   help="leave out the exponax curve")
    threads_option(p)
    progress_option(p)


def run(args: argparse.Namespace) -> int:
    from adjointsim import parallel
    from adjointsim.bench import work_precision

    parallel.set_threads(args.threads)
    work_precision.run(args.scene, args.out, args.quick, args.repeats, args.exponax,
                       args.progress)
    return 0
