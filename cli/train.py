"""``adjointsim train``: a neural time-stepper trained through a solver, resumable."""

from __future__ import annotations

import argparse
from pathlib import Path

from adjointsim.errors import UserError

from .options import (
    COMPILE_HELP,
    THREADS_HELP,
    config_flags,
    overrides,
    run_config,
    run_options,
    scene_of,
    scene_option,
    seeds_option,
    train_seeds,
    write_result,
)

_HELPS = {
    "mode": "the unrolling schedule ONE, or a gradient flow (WIG, NOG; R, M, S, N, C)",
    "setup": "the network predicts the next state, or corrects the coarse solver's",
    "curriculum": 'stages "m:lr,m:lr,...", e.g. "1:1e-4,2:1e-5,4:1e-6"',
    "max_iterations": "stop after this many iterations in total, unfinished: continue with "
                      "--resume (0: no limit)",
    "correction": "how a correction is applied: parallel û' = S(û) + Δt·f(û), sequential "
                  "ũ = S(û), û' = ũ + f(ũ)",
    "unroll": "steps m unrolled per window; the loss is their mean error",
    "lr_decay": "factor on the learning rate every --lr-decay-every iterations",
    "stride": "frames between two windows' starts (1: every window; 8: an eighth of them)",
    "warmup": "steps the network takes from a window's start before the loss, without "
              "gradient (pushforward)",
    "truncate": "cut the gradient every k unrolled steps (truncated BPTT; 0: never)",
    "spike_factor": "skip an update whose gradient norm exceeds this multiple of the running "
                    "mean",
    "rollback": "back to the best weights at half the learning rate when the median loss "
                "rises above this multiple of the best (0: off, else > 1)",
    "checkpoint_every": "iterations between two checkpoints (and history writes)",
    "eval_every": "updates between measurements of the test error (curve.csv; 0: none)",
    "eval_horizon": "steps of those measurements",
    "threads": THREADS_HELP,
    "compile": COMPILE_HELP,
}


def arguments(p: argparse.ArgumentParser) -> None:
    from adjointsim.train.trainer import TrainConfig

    run_options(p, "runs/ks")
    config_flags(p, TrainConfig, TrainConfig.ACCEPTED, skip=("out", "scene"), helps=_HELPS)
    scene_option(p)
    seeds_option(p)


def run(args: argparse.Namespace) -> int:
    from adjointsim.train.trainer import StepperRun, TrainConfig, build_model, describe, train

    values = overrides(args, TrainConfig)
    values["scene"] = scene_of(args)  # must agree with the dataset's scene
    if args.out is not None:
        values["out"] = str(args.out)
    if values.get("curriculum"):
        text = values["curriculum"]
        try:
            stages = (s.split(":") for s in text.split(","))
            values["curriculum"] = [[int(m), float(lr)] for m, lr in stages]
        except ValueError:
            raise UserError(f"--curriculum {text!r} is not a list of stages m:lr, e.g. "
                            '"1:1e-4,2:1e-5"') from None
    # a run stopped by --max-iterations goes on to its end unless a new cap is given
    cfg = run_config(args, StepperRun, TrainConfig, values, lambda c: Path(c.out),
                     fresh=("max_iterations",))
    out = Path(cfg.out)
    if args.seeds:
        from adjointsim.train.ensemble import train_ensemble

        cfgs, _ = train_seeds(args, cfg, out,
                              f"{cfg.setup}/{cfg.mode}: {describe(build_model(cfg))}",
                              train_ensemble)
        results = [_result(c) for c in cfgs]
        if args.json is not None:
            from adjointsim.files import write_json

            write_json(args.json, results)
        for c, r in zip(cfgs, results):
            print(f"seed {c.seed}: final loss {_loss(r)}; run in {c.out}")
        return 0
    print(f"{cfg.setup}/{cfg.mode}: {describe(build_model(cfg))}", flush=True)
    train(cfg, resume=args.resume, progress=args.progress, overwrite=args.overwrite)
    write_result(args, _result(cfg))
    print(f"run in {out}")
    return 0


def _result(cfg) -> dict:
    """A finished run's result.json; for a run stopped by --max-iterations, its recorded
    config with the iterations, skipped updates and final loss so far."""
    import json

    from adjointsim.run import read_history, read_result

    out = Path(cfg.out)
    if (out / "result.json").exists():
        return read_result(out / "result.json")
    history = read_history(out / "history.csv") if (out / "history.csv").exists() else []
    return {**json.loads((out / "config.json").read_text()), "iterations": len(history),
            "skipped": sum(h["skipped"] for h in history),
            "final_loss": history[-1]["loss"] if history else None}


def _loss(result: dict) -> str:
    loss = result["final_loss"]
    return "none yet" if loss is None else f"{loss:.4e}"
