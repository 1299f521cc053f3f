"""A cart-pole controller trained through the simulator, with gradient-flow mode C.

A controller network reads the cart-pole state, outputs the force, the ``cartpole`` solver
advances one step (its compiled step forward, its hand-written adjoint backward), and the loss
1 - mean cos(theta) at the last of 100 steps judges the swing-up from hanging (Schnell &
Thuerey's task). Mode C (combined) keeps each element of the regular BPTT gradient (R) only
where it agrees in sign with the gradient of mode M, whose network-input path is stopped; both
come from one forward and one backward pass (``adjointsim.train.unroll.GradientFlow``).

The script trains the one-pole swing-up with mode C and, for comparison, with plain BPTT (R),
through ``adjointsim.train.control`` (``ControlConfig``, ``train_controller``: the same run as
``adjointsim control cartpole --poles 1 --mode C``), and prints each final test loss against
the untrained controller's (its last layer starts at zero: no force, the pole keeps hanging).

Run:  python examples/cartpole_controller.py [--poles 1..4] [--out DIR] [--tiny]
The default (64 training and 64 test states, 60 epochs of batch 8, modes C and R) takes about
a minute on 2 cores; --tiny (mode C only, 2 epochs) takes seconds. Without --out the runs go
to a temporary directory, removed at the end.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from adjointsim.train.control import (
    ControlConfig,
    build_net,
    evaluate,
    get_task,
    initial_states,
    train_controller,
)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--poles", type=int, choices=(1, 2, 3, 4), default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None,
                    help="keep the runs here (default: a temporary directory)")
    ap.add_argument("--tiny", action="store_true", help="a few seconds, for tests")
    args = ap.parse_args()
    size = ({"train": 16, "test": 16, "epochs": 2} if args.tiny
            else {"train": 64, "test": 64, "epochs": 60})
    modes = ("C",) if args.tiny else ("C", "R")

    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        results = {}
        for mode in modes:
            cfg = ControlConfig(task="cartpole", level=args.poles, mode=mode, seed=args.seed,
                                batch=8, lr=1e-3, out=str(out / f"cartpole-{mode}"), **size)
            # history.csv, checkpoint.pt, result.json, test_loss.png and rollout.png go to out
            # overwrite: running the example again into the same --out starts afresh
            results[mode] = train_controller(cfg, progress=False, overwrite=True)
        # The untrained controller (zero last layer) on the same test states: the uncontrolled
        # system, the loss every mode starts from.
        task = get_task("cartpole", args.poles)
        _, x_test = initial_states(cfg, task)
        untrained = evaluate(task, build_net(cfg, task), x_test)
        if args.out:
            print(f"runs in {out}")

    print(f"cart-pole, {args.poles} pole(s), {size['epochs']} epochs, seed {args.seed}: final "
          f"test loss (1 - mean cos theta at the last step); untrained {untrained:.4f}")
    for mode, r in results.items():
        print(f"  mode {mode}: {r['test_loss']:.4f} ({r['test_loss'] / untrained:.3f} of the "
              f"untrained loss, {r['parameters']} parameters, {r['seconds']:.1f} s of updates)")
    print("result: final test loss / untrained: " + ", ".join(
        f"{mode} {r['test_loss'] / untrained:.3f}" for mode, r in results.items()))
    if args.tiny:
        print("(--tiny only checks that the pipeline runs: these numbers say nothing about the "
              "method; run without --tiny to measure it)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
