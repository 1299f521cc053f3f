"""``adjointsim control``: a controller trained through a simulator, resumable."""

from __future__ import annotations

import argparse
from pathlib import Path

from .options import (
    COMPILE_HELP,
    THREADS_HELP,
    config_flags,
    overrides,
    resumed,
    run_options,
    scene_of,
    scene_option,
    seeds_option,
    train_seeds,
    write_result,
)

_HELPS = {
    "mode": "the gradient flow: R (regular BPTT), M, S, N, or C (combined)",
    "clip": "clip each update at 1, by value or by global norm",
    "level": "the task's level, also its own flag (below); default: its easiest",
    "seed": "random seed of the initial states, the weights and the batch order",
    "epochs": "epochs; --resume continues a run to more",
    "lr": "Adam's learning rate",
    "train": "training initial states",
    "test": "test initial states",
    "batch": "initial states per update",
    "weighting": "how the loss's terms are balanced (a task of several terms)",
    "threads": THREADS_HELP,
    "compile": COMPILE_HELP,
}


def _flag(key: str) -> str:
    return "--" + key.replace("_", "-")


def arguments(p: argparse.ArgumentParser) -> None:
    from adjointsim.train.control import TASKS, ControlConfig

    p.add_argument("task", nargs="?", choices=tuple(TASKS.names()), default=None,
                   help="the control problem (with --resume, the run's)")
    run_options(p, "runs/control-TASK-MODE")
    config_flags(p, ControlConfig, ControlConfig.ACCEPTED, skip=("task", "out", "scene"),
                 helps=_HELPS)
    levels = p.add_argument_group("each task's level (the config key 'level')")
    for name, cls in TASKS.items():
        levels.add_argument(_flag(cls.key), dest=f"level_{name}", default=None,
                            type=type(cls.levels[0]), choices=cls.levels,
                            metavar="{" + ",".join(map(str, cls.levels)) + "}",
                            help=f"{name}: {cls.about}")
    scene_option(p)
    seeds_option(p)


def _level(args: argparse.Namespace, task: str) -> float | None:
    """The level a task's own flag gives (None: none); another task's flag is refused."""
    from adjointsim.errors import UserError
    from adjointsim.train.control import TASKS

    given = {name: getattr(args, f"level_{name}") for name in TASKS.names()
             if getattr(args, f"level_{name}") is not None}
    for name in given:
        if name != task:
            raise UserError(f"option '{TASKS.get(name).key}': applies to the {name} task, not "
                            f"{task}")
    if given and args.level is not None:
        raise UserError(f"--level and {_flag(TASKS.get(task).key)} give the same key: pass one")
    return given.get(task)


def run(args: argparse.Namespace) -> int:
    from adjointsim.errors import UserError
    from adjointsim.train.control import TASKS, ControlConfig, Controller, train_controller

    values = overrides(args, ControlConfig)
    values["scene"] = scene_of(args)
    if args.out is not None:
        values["out"] = str(args.out)
    recorded = resumed(args, lambda: _out(ControlConfig.load(args.config, **values)),
                       Controller, ControlConfig)
    task = args.task or (recorded or {}).get("task")
    if task is None:
        raise UserError(f"the task is needed: adjointsim control TASK ({', '.join(TASKS.names())}"
                        "); a run is continued without it by --resume --out DIR")
    level = _level(args, task)
    if level is not None:
        values["level"] = level
    cfg = ControlConfig.load(args.config, recorded=recorded, **values)
    out = args.out if args.out is not None else _out(cfg)
    cfg.out = str(out)
    if args.seeds:
        return _ensemble(args, cfg, out)
    task = cfg.make_task()
    n = sum(p.numel() for p in task.net().parameters())
    print(f"{cfg.task} ({task.key} {cfg.level}), mode {cfg.mode}, clip {cfg.clip}: "
          f"{n:,} parameters", flush=True)
    result = train_controller(cfg, resume=args.resume, progress=args.progress,
                              overwrite=args.overwrite)
    write_result(args, result)
    return _report(result, out, "final test loss")


def _out(cfg) -> Path:
    """The run directory: the config's, else one named by the task and the mode."""
    from adjointsim.train.control import ControlConfig

    if cfg.out == ControlConfig.out:  # neither flag nor file chose one
        return Path("runs") / f"control-{cfg.task}-{cfg.mode}"
    return Path(cfg.out)


def _report(result: dict, out: Path, what: str) -> int:
    """The final test loss and the run's files, as written; 1 for a diverged run."""
    files = ", ".join(n for n in ("history.csv", "test_loss.png", "rollout.png")
                      if (out / n).exists())
    if result["diverged"]:
        print(f"{what} not finite: the controller diverged (the simulator blew up under it; "
              f"try a lower --lr or --clip); run in {out} ({files})")
        return 1
    print(f"{what} {result['test_loss']:.4e}; run in {out} ({files})")
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
    return max(_report(r, Path(c.out), f"seed {c.seed}: final test loss")
               for c, r in zip(cfgs, results))
