"""``adjointsim eval``: errors, correlation time and stability of a trained run, with plots
and ``metrics.json`` written beside them."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .options import at_least, threads_option


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", type=Path, help="a training run directory")
    p.add_argument("--data", type=Path, default=None, help="default: the run's dataset")
    p.add_argument("--horizon", type=at_least(1), default=None,
                   help="steps of the error rollouts (default 12 for KS, 50 for Kolmogorov)")
    p.add_argument("--long-steps", type=at_least(1, 1_000_000), default=500,
                   help="length of the rollouts behind correlation time and stability "
                   "(default 500)")
    threads_option(p, 1)


def run(args: argparse.Namespace) -> int:
    from adjointsim.errors import UserError
    from adjointsim.files import json_text, write_json
    from adjointsim.run import holds_run
    from adjointsim.train import data
    from adjointsim.train.evaluate import evaluate
    from adjointsim.train.studies.neural_steppers import STUDIES
    from adjointsim.train.threads import use_threads
    from adjointsim.train.trainer import DTYPES, TrainConfig, load_model

    if not args.run.is_dir():
        raise FileNotFoundError(f"{args.run} does not exist or is not a directory; give the "
                                "--out directory of an `adjointsim train` run")
    # a run of a version before the scene key is one too
    if not holds_run(args.run, TrainConfig().as_dict(), ("scene",)):
        raise UserError(f"{args.run} holds no run of `adjointsim train` (no config.json of its "
                        "keys); eval evaluates neural time-steppers trained by that command")
    if not (args.run / "checkpoint.pt").exists():
        raise FileNotFoundError(f"{args.run} holds no checkpoint.pt: not a training run, or one "
                                "that saved nothing yet")
    use_threads(args.threads)
    model, cfg = load_model(args.run)
    horizon = STUDIES[cfg.problem]["horizon"] if args.horizon is None else args.horizon
    metrics = evaluate(model, data.load(args.data or cfg.data), horizon, DTYPES[cfg.dtype],
                       args.run, args.long_steps)
    write_json(args.run / "metrics.json", metrics)
    print(json_text(metrics))
    print(f"wrote {args.run / 'metrics.json'}", file=sys.stderr)  # stdout stays JSON
    return 0
