"""``adjointsim bench``: benchmarks, error against run time."""

from __future__ import annotations

import argparse


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("which", choices=("work-precision",))
    p.add_argument("rest", nargs=argparse.REMAINDER, help="SCENE [--out DIR] [--quick]")


def run(args: argparse.Namespace) -> int:
    from adjointsim.bench.work_precision import main

    return main(args.rest)
