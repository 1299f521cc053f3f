"""A correction network trained through the Kuramoto-Sivashinsky solver, from Python.

List et al.'s correction setup: a coarse ETD1 solver (``ks1d-etdrk1``) advances the state and
a small ResNet corrects it after every step; the unrolled loss compares m corrected steps with
reference frames of a finer ETDRK2 solver. With mode WIG the gradient flows back through the
solver's hand-written adjoint (``adjointsim.train.bridge``); NOG stops it there, ONE trains on
single steps. The pieces are the public ones behind ``adjointsim data``, ``adjointsim train``
and ``adjointsim eval``:

    adjointsim.train.data      generate / save / load the reference trajectories (HDF5)
    adjointsim.train.trainer   TrainConfig and train (checkpoints, resume, history)
    adjointsim.train.evaluate  evaluate: relative error, correlation time, stability

It prints the model's relative error over the test rollouts next to the coarse solver's alone.

Run:  python examples/correction_ks.py [--mode ONE|NOG|WIG] [--out DIR] [--tiny]
The default size is the quick study's data and network (about 20 s on 2 cores);
--tiny runs in seconds and only shows that the pipeline works. Without --out, everything is
written to a temporary directory that is removed at the end.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import torch

from adjointsim.train import data
from adjointsim.train.evaluate import evaluate
from adjointsim.train.trainer import TrainConfig, train

#: the quick KS study's settings (``adjointsim study ks --quick``), and a tiny version
SIZES = {
    "quick": {"width": 16, "blocks": 4, "unroll": 3, "epochs": 3, "stride": 1, "lr": 1e-3,
              "lr_decay_every": 64, "batch": 16},
    "tiny": {"width": 4, "blocks": 1, "unroll": 2, "epochs": 1, "stride": 4, "lr": 1e-3,
             "batch": 4},
}


def run(out: Path, size: str, mode: str, seed: int) -> dict:
    path = out / f"ks-{size}.h5"
    data.save(data.generate("ks", size, seed=0, progress=False), path)
    cfg = TrainConfig(problem="ks", data=str(path), out=str(out / f"correction-{mode}"),
                      setup="correction", mode=mode, seed=seed, **SIZES[size])
    # overwrite: running the example again into the same --out starts the run afresh
    model = train(cfg, progress=False, overwrite=True)  # also saves checkpoint.pt, history.csv
    return evaluate(model, data.load(path), horizon=12, dtype=torch.float32,
                    plots=Path(cfg.out))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mode", choices=("ONE", "NOG", "WIG"), default="WIG")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None,
                    help="keep the dataset, the run and its plots here (default: a temporary "
                    "directory, removed at the end)")
    ap.add_argument("--tiny", action="store_true", help="a few seconds, for tests")
    args = ap.parse_args()
    size = "tiny" if args.tiny else "quick"

    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        m = run(out, size, args.mode, args.seed)
        if args.out:
            print(f"dataset, run and plots in {out}")
    print(f"KS correction, mode {args.mode}, {size} size, seed {args.seed}: relative error over "
          "12 steps (mean over the test rollouts)")
    for split in ("interpolation", "extrapolation"):
        print(f"  {split:<14} model {m[split]['rel_error']:.3e}   coarse solver alone "
              f"{m[split]['coarse_rel_error']:.3e}")
    print(f"result: model {m['rel_error']:.3e}, coarse solver alone {m['coarse_rel_error']:.3e} "
          f"(coarse / model = {m['coarse_rel_error'] / m['rel_error']:.1f}); fraction of the "
          f"long rollouts that stay bounded: {m['stable_fraction']:.2f}")
    if args.tiny:
        print("(--tiny only checks that the pipeline runs: these numbers say nothing about the "
              "method; run without --tiny to measure it)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
