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
    s.add_argument("problem", choices=("ks", "kolmogorov"))
    s.add_argument("--quick", action="store_const", const="quick", dest="size",
                   help="a reduced study (minutes); same as --size quick")
    s.add_argument("--size", choices=("tiny", "quick", "full"), default="full",
                   help="tiny: seconds, a smoke test of the whole pipeline")
    s.add_argument("--seeds", type=int, default=None)
    s.add_argument("--jobs", type=int, default=1,
                   help="models trained at once (one thread each; 2 suits a 2-core machine)")
    s.add_argument("--out", type=Path, default=None, help="default runs/study-PROBLEM[-SIZE]")
    s.add_argument("--json", type=Path, default=None, help="write one object per model here")
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
    from .study import STUDIES, load_model
    from .trainer import DTYPES

    model, cfg = load_model(args.run)
    horizon = args.horizon or STUDIES[cfg.problem]["horizon"]
    metrics = evaluate(model, data.load(args.data or cfg.data), horizon, DTYPES[cfg.dtype],
                       args.run, args.long_steps)
    print(json.dumps(metrics, indent=2))
    return 0


def _study(args: argparse.Namespace) -> int:
    from .study import run_study, table

    suffix = "" if args.size == "full" else f"-{args.size}"
    out = args.out or Path("runs") / f"study-{args.problem}{suffix}"
    rows = run_study(args.problem, out, args.size, args.seeds, jobs=args.jobs)
    print(table(rows))
    print(f"plot: {out / 'study.png'}; per-model results and rollout plots under {out}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="adjointsim")
    add_commands(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
