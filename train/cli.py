"""The torch commands of the ``adjointsim`` CLI: data, train, eval, study.

Run them through :func:`adjointsim.cli.main`, the error boundary that turns user errors into
one line; :func:`main` here only parses and dispatches.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import fields
from pathlib import Path

from adjointsim.cli import TORCH_COMMANDS as COMMANDS
from adjointsim.cli import Interrupted, UserError

from .atomic import json_text, write_json


def _at_least(lo: int):
    """An argparse type: an integer ≥ lo."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < lo:
            raise argparse.ArgumentTypeError(f"must be ≥ {lo}, not {value}")
        return value

    return parse


def add_commands(sub: argparse._SubParsersAction) -> None:
    d = sub.add_parser("data", help=COMMANDS["data"])
    d.add_argument("problem", choices=("ks", "kolmogorov"))
    d.add_argument("--size", choices=("tiny", "quick", "full"), default="quick",
                   help="tiny (KS only): seconds, for tests")
    d.add_argument("--seed", type=_at_least(0), default=0)
    d.add_argument("--out", type=Path, default=None, help="default data/PROBLEM-SIZE.h5")
    d.set_defaults(func=_data)

    t = sub.add_parser("train", help=COMMANDS["train"])
    t.add_argument("--config", type=Path, default=None, help="TOML file of TrainConfig keys")
    again = t.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    again.add_argument("--overwrite", action="store_true",
                       help="discard the run already in OUT and start again")
    from .trainer import TrainConfig

    for f in fields(TrainConfig):
        if f.name == "curriculum":
            t.add_argument("--curriculum", type=str, default=None,
                           help='stages "m:lr,m:lr,...", e.g. "1:1e-4,2:1e-5,4:1e-6"')
            continue
        flag = "--" + f.name.replace("_", "-")
        t.add_argument(flag, dest=f.name, type=type(f.default), default=None,
                       help=f"default {f.default!r}")
    t.set_defaults(func=_train)

    e = sub.add_parser("eval", help=COMMANDS["eval"])
    e.add_argument("run", type=Path, help="a training run directory")
    e.add_argument("--data", type=Path, default=None, help="default: the run's dataset")
    e.add_argument("--horizon", type=_at_least(1), default=None,
                   help="12 for KS, 50 for Kolmogorov")
    e.add_argument("--long-steps", type=_at_least(1), default=500,
                   help="length of the rollouts behind correlation time and stability")
    e.set_defaults(func=_eval)

    s = sub.add_parser("study", help=COMMANDS["study"])
    s.add_argument("problem", metavar="NAME", help="ks, kolmogorov, or any study registered in "
                   "train/studies/ (an unknown name lists them)")
    s.add_argument("--quick", action="store_const", const="quick", dest="size",
                   help="a reduced study (minutes); same as --size quick")
    s.add_argument("--size", default="full",
                   help="tiny (seconds, a smoke test of the whole pipeline), quick or full; "
                   "ks also has paper and paper-large (issue 14's protocol, 5 and 2 seeds of "
                   "correction models; hours), other studies their own (an unknown size lists "
                   "them)")
    s.add_argument("--seeds", type=_at_least(1), default=None)
    s.add_argument("--jobs", type=_at_least(1), default=2,
                   help="worker processes of the local cluster (one thread each; default 2)")
    s.add_argument("--cluster", default=None,
                   help="local (default: a Dask cluster of --jobs processes started here), none "
                   "(this process, one cell after another) or a scheduler address "
                   "tcp://HOST:PORT; default $DASK_SCHEDULER_ADDRESS if set, else local")
    s.add_argument("--retries", type=_at_least(0), default=1,
                   help="times a failed cell is run again, resuming from its checkpoint")
    s.add_argument("--out", type=Path, default=None, help="default runs/study-PROBLEM[-SIZE]")
    s.add_argument("--json", type=Path, default=None, help="write one object per model here")
    s.add_argument("--reuse", type=Path, default=None, metavar="ROWS",
                   help="finished rows of an earlier run (its --json or rows.json file, e.g. "
                   "one committed under docs/): those cells are not run again")
    s.add_argument("--no-progress", dest="progress", action="store_false",
                   help="no progress bar")
    s.set_defaults(func=_study, size="full")

    from .hig_problems import add_parser as add_hig

    add_hig(sub, COMMANDS["hig"])

    from .control import add_command

    add_command(sub, COMMANDS["control"])

    from .pinn import add_command as add_pinn

    add_pinn(sub, COMMANDS["pinn"])


def _data(args: argparse.Namespace) -> int:
    from . import data

    out = args.out or Path("data") / f"{args.problem}-{args.size}.h5"
    data.save(data.generate(args.problem, args.size, args.seed), out)
    print(f"wrote {out}")
    return 0


def _train(args: argparse.Namespace) -> int:
    from .trainer import TrainConfig, build_model, describe, train

    overrides = {k: v for k, v in vars(args).items()
                 if k not in ("config", "resume", "overwrite", "func", "command")}
    if overrides.get("curriculum"):
        text = overrides["curriculum"]
        try:
            stages = (s.split(":") for s in text.split(","))
            overrides["curriculum"] = [[int(m), float(lr)] for m, lr in stages]
        except ValueError:
            raise UserError(f"--curriculum {text!r} is not a list of stages m:lr, e.g. "
                            '"1:1e-4,2:1e-5"') from None
    cfg = TrainConfig.load(args.config, **overrides)
    print(f"{cfg.setup}/{cfg.mode}: {describe(build_model(cfg))}", flush=True)
    try:
        train(cfg, resume=args.resume, overwrite=args.overwrite)
    except KeyboardInterrupt:
        raise Interrupted(
            f"continue from {Path(cfg.out) / 'checkpoint.pt'} (saved every "
            f"{cfg.checkpoint_every} iterations) by running the same command with --resume"
            + (" instead of --overwrite" if args.overwrite else "")
        ) from None
    print(f"run in {cfg.out}")
    return 0


def _eval(args: argparse.Namespace) -> int:
    from . import data
    from .evaluate import evaluate
    from .studies.list_et_al import STUDIES, load_model
    from .trainer import DTYPES

    if not args.run.is_dir():
        raise FileNotFoundError(f"{args.run} does not exist or is not a directory; give the "
                                "--out directory of an `adjointsim train` run")
    if not (args.run / "checkpoint.pt").exists():
        raise FileNotFoundError(f"{args.run} holds no checkpoint.pt: not a training run, or one "
                                "that saved nothing yet")
    model, cfg = load_model(args.run)
    horizon = STUDIES[cfg.problem]["horizon"] if args.horizon is None else args.horizon
    metrics = evaluate(model, data.load(args.data or cfg.data), horizon, DTYPES[cfg.dtype],
                       args.run, args.long_steps)
    print(json_text(metrics))
    return 0


def _study(args: argparse.Namespace) -> int:
    """Every unfinished cell through :func:`adjointsim.runner.run`; exit 1 if any failed (each
    failure is printed with its cell id), after the report of what finished."""
    from adjointsim import runner

    from .studies import load_all

    load_all()
    suffix = "" if args.size == "full" else f"-{args.size}"
    out = args.out or Path("runs") / f"study-{args.problem}{suffix}"
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
        print(runner.get_study(args.problem).report(rows, out.resolve()))
    if args.json:
        write_json(args.json, rows)
    for cell_id, error in failed:
        print(f"adjointsim study: cell {cell_id} failed: {error}", file=sys.stderr)
    if failed:
        print(f"adjointsim study: {len(failed)} cell(s) failed, {len(rows)} finished; run the "
              "same command again to retry only the failed ones", file=sys.stderr)
    return 1 if failed else 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="adjointsim")
    add_commands(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    from adjointsim.cli import main as cli

    sys.exit(cli())
