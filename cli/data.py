"""``adjointsim data``: reference trajectories (HDF5) for training."""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

from adjointsim.run import Config

from .options import progress_option, scene_of, scene_option, seed_option, threads_option


@dataclass
class DataConfig(Config):
    """What ``--config`` may hold for ``adjointsim data``: the ``[scene]`` table."""

    scene: dict = field(default_factory=dict)

    ACCEPTED: ClassVar[dict] = {"scene": "the problem's scene keys"}


def arguments(p: argparse.ArgumentParser) -> None:
    from adjointsim.train.problems import PROBLEMS

    p.add_argument("problem", choices=tuple(PROBLEMS))
    p.add_argument("--size", choices=("tiny", "quick", "full"), default="quick",
                   help="tiny (KS only): seconds, for tests; default quick")
    seed_option(p)
    p.add_argument("--out", type=Path, default=None, metavar="PATH",
                   help="the HDF5 file (default data/PROBLEM-SIZE.h5)")
    p.add_argument("--overwrite", action="store_true", help="replace the file at --out")
    p.add_argument("--config", type=Path, default=None, metavar="FILE.toml",
                   help="a [scene] table of the problem's solver keys; --scene overrides it")
    scene_option(p)
    threads_option(p)
    progress_option(p)


def run(args: argparse.Namespace) -> int:
    from adjointsim import parallel
    from adjointsim.errors import UserError
    from adjointsim.train import data
    from adjointsim.train.problems import get_problem

    out = args.out or Path("data") / f"{args.problem}-{args.size}.h5"
    if out.is_dir():
        raise UserError(f"--out {out} is a directory; give the path of the HDF5 file to write")
    if out.exists() and not args.overwrite:
        raise UserError(f"{out} exists; pass --overwrite to replace it, or choose another --out")
    # a folder that cannot be written fails now, not after the data are made
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f"cannot make the folder {out.parent} ({e.strerror}); choose another "
                        "--out") from None
    if not os.access(out.parent, os.W_OK | os.X_OK):
        raise UserError(f"cannot write into {out.parent}; choose another --out")
    problem = get_problem(args.problem, DataConfig.load(args.config, scene=scene_of(args)).scene)
    parallel.set_threads(args.threads)
    data.save(data.generate(problem, args.size, args.seed, progress=args.progress), out)
    print(f"wrote {out}")
    return 0
