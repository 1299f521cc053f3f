"""``adjointsim control``: a controller trained through a simulator, resumable."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from .options import (
    THREADS_HELP,
    config_flags,
    overrides,
    run_options,
    seeds_option,
    train_seeds,
    write_result,
)

_HELPS = {
    "mode": "the gradient flow: R (regular BPTT), M, S, N, or C (combined)",
    "clip": "clip each update at 1, by value or by global norm",
    "poles": "cartpole: the number of poles",
    "target": "quantum: the eigenstate to reach",
    "control_weight": "guidance: the weight of the control cost",
    "seed": "random seed of the initial states, the weights and the batch order",
    "epochs": "epochs; --resume continues a run to more",
    "lr": "Adam's learning rate",
    "train": "training initial states",
    "test": "test initial states",
    "batch": "initial states per update",
    "threads": THREADS_HELP,
}


def arguments(p: argparse.ArgumentParser) -> None:
    from adjointsim.train.control import TASKS, ControlConfig

    p.add_argument("task", choices=tuple(TASKS), help="the control problem")
    run_options(p, "runs/control-TASK-MODE")
    config_flags(p, ControlConfig, ControlConfig.ACCEPTED, skip=("task", "out"), helps=_HELPS)
    seeds_option(p)


def run(args: argparse.Namespace) -> int:
    from adjointsim.run import require_checkpoint, run_errors
    from adjointsim.train.control import ControlConfig, get_task, train_controller

    values = overrides(args, ControlConfig)
    if args.out is not None:
        values["out"] = str(args.out)
    cfg = ControlConfig.load(args.config, **values)
    if args.out is None and cfg.out == ControlConfig.out:  # neither flag nor file chose one
        cfg.out = str(Path("runs") / f"control-{cfg.task}-{cfg.mode}")
    out = Path(cfg.out)
    if args.seeds:
        return _ensemble(args, cfg, out)
    if args.resume:
        require_checkpoint(out)
    task = get_task(cfg.task, cfg.level)
    n = sum(p.numel() for p in task.net().parameters())
    print(f"{cfg.task} ({task.knob} {cfg.level}), mode {cfg.mode}, clip {cfg.clip}: "
          f"{n:,} parameters", flush=True)
    with run_errors(out):
        result = train_controller(cfg, resume=args.resume, progress=args.progress,
                                  overwrite=args.overwrite)
    write_result(args, result)
    loss = result["test_loss"]
    loss = f"{loss:.4e}" if loss is not None and math.isfinite(loss) else "not finite"
    print(f"final test loss {loss}; run in {out} (history.csv, test_loss.png, rollout.png)")
    return 0


def _ensemble(args: argparse.Namespace, cfg, out: Path) -> int:
    """``--seeds``: one run per seed in ``out/seedN``, trained as one ensemble."""
    from adjointsim.files import write_json
    from adjointsim.train.ensemble import train_ensemble

    cfgs, results = train_seeds(args, cfg, out,
                                f"{cfg.task} ({cfg.level}), mode {cfg.mode}, clip {cfg.clip}",
                                train_ensemble)
    if args.json is not None:
        write_json(args.json, results)
    for c, r in zip(cfgs, results):
        loss = r["test_loss"]
        loss = f"{loss:.4e}" if loss is not None and math.isfinite(loss) else "not finite"
        print(f"seed {c.seed}: final test loss {loss}; run in {c.out}")
    return 0
