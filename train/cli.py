"""The torch commands of the ``adjointsim`` CLI: data, train, eval, study."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import fields
from pathlib import Path

from adjointsim.cli import TORCH_COMMANDS as COMMANDS


def add_commands(sub: argparse._SubParsersAction) -> None:
    d = sub.add_parser("data", help=COMMANDS["data"])
    d.add_argument("problem", choices=("ks", "kolmogorov"))
    d.add_argument("--size", choices=("quick", "full"), default="quick")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--out", type=Path, default=None, help="default data/PROBLEM-SIZE.h5")
    d.set_defaults(func=_data)

    t = sub.add_parser("train", help=COMMANDS["train"])
    t.add_argument("--config", type=Path, default=None, help="TOML file of TrainConfig keys")
    t.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
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
    e.add_argument("--horizon", type=int, default=None, help="12 for KS, 50 for Kolmogorov")
    e.add_argument("--long-steps", type=int, default=500,
                   help="length of the rollouts behind correlation time and stability")
    e.set_defaults(func=_eval)

    s = sub.add_parser("study", help=COMMANDS["study"])
    s.add_argument("problem", metavar="NAME", help="ks, kolmogorov, or any study registered in "
                   "train/studies/ (an unknown name lists them)")
    s.add_argument("--quick", action="store_const", const="quick", dest="size",
                   help="a reduced study (minutes); same as --size quick")
    s.add_argument("--size", default="full",
                   help="tiny (seconds, a smoke test of the whole pipeline), quick or full")
    s.add_argument("--seeds", type=int, default=None)
    s.add_argument("--jobs", type=int, default=2,
                   help="worker processes of the local cluster (one thread each; default 2)")
    s.add_argument("--cluster", default=None,
                   help="local (default: a Dask cluster of --jobs processes started here), none "
                   "(this process, one cell after another) or a scheduler address "
                   "tcp://HOST:PORT; default $DASK_SCHEDULER_ADDRESS if set, else local")
    s.add_argument("--retries", type=int, default=1,
                   help="times a failed cell is run again, resuming from its checkpoint")
    s.add_argument("--out", type=Path, default=None, help="default runs/study-PROBLEM[-SIZE]")
    s.add_argument("--json", type=Path, default=None, help="write one object per model here")
    s.add_argument("--no-progress", dest="progress", action="store_false",
                   help="no progress bar")
    s.set_defaults(func=_study, size="full")


def _data(args: argparse.Namespace) -> int:
    from . import data

    out = args.out or Path("data") / f"{args.problem}-{args.size}.h5"
    data.save(data.generate(args.problem, args.size, args.seed), out)
    print(f"wrote {out}")
    return 0


def _train(args: argparse.Namespace) -> int:
    from .trainer import TrainConfig, build_model, describe, train

    overrides = {k: v for k, v in vars(args).items() if k not in ("config", "resume", "func",
                                                                  "command")}
    if overrides.get("curriculum"):
        stages = (s.split(":") for s in overrides["curriculum"].split(","))
        overrides["curriculum"] = [[int(m), float(lr)] for m, lr in stages]
    cfg = TrainConfig.load(args.config, **overrides)
    print(f"{cfg.setup}/{cfg.mode}: {describe(build_model(cfg))}", flush=True)
    train(cfg, resume=args.resume)
    print(f"run in {cfg.out}")
    return 0


def _eval(args: argparse.Namespace) -> int:
    from . import data
    from .evaluate import evaluate
    from .studies.list_et_al import STUDIES, load_model
    from .trainer import DTYPES

    model, cfg = load_model(args.run)
    horizon = args.horizon or STUDIES[cfg.problem]["horizon"]
    metrics = evaluate(model, data.load(args.data or cfg.data), horizon, DTYPES[cfg.dtype],
                       args.run, args.long_steps)
    print(json.dumps(metrics, indent=2))
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
                          report=False)
    except runner.CellsFailed as e:
        rows, failed = e.rows, e.failures
    if rows:
        print(runner.get_study(args.problem).report(rows, out.resolve()))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(runner.dumps(rows))
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
    sys.exit(main())
