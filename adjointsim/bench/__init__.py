"""Benchmarks shipped with the package, behind ``adjointsim bench``.

``work-precision`` (:mod:`.work_precision`): error against run time of the spectral ETDRK
solvers, their NumPy ETDRK4 baseline and (when installed) exponax. Nothing here imports torch
or jax at module level; the peer libraries load inside the functions that use them.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

COMMANDS = {
    "work-precision": "error vs run time of the spectral ETDRK solvers (CSV + log-log PNG)",
}


def main(argv: Sequence[str] | None = None) -> int:
    """``adjointsim bench COMMAND ...``: dispatch to the command's own ``main(argv)``."""
    parser = argparse.ArgumentParser(prog="adjointsim bench", description=__doc__.splitlines()[0])
    parser.add_argument("command", choices=sorted(COMMANDS), help="; ".join(
        f"{k}: {v}" for k, v in COMMANDS.items()))
    parser.add_argument("args", nargs=argparse.REMAINDER, help="the command's own arguments")
    args = parser.parse_args(argv)
    from . import work_precision

    return work_precision.main(args.args)
