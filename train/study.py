"""Studies: the grid of setups × unroll modes × seeds of List et al., trained, evaluated and
tabulated (mean ± std per cell), with a plot and an optional JSON file.

Everything a study makes lives under its output directory, and every finished piece (the
dataset, each model's checkpoint and results) is reused, so an interrupted study resumes.
"""

from __future__ import annotations

import json
import multiprocessing
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from . import data as datamod
from .atomic import write_text
from .evaluate import TEST_SPLITS, evaluate
from .trainer import DTYPES, TrainConfig, build_model, describe, load_checkpoint, train

#: per problem: the grid, the evaluation horizon and the training settings per study size
STUDIES = {
    "ks": {
        "setups": ("prediction", "correction"),
        "modes": ("ONE", "NOG", "WIG"),
        "horizon": 12,
        "quick": {"data": "quick", "seeds": 2, "train": {
            "width": 16, "blocks": 4, "unroll": 3, "epochs": 3, "stride": 1, "lr": 1e-3,
            "lr_decay_every": 64, "batch": 16}},
        # For tests: the whole pipeline in seconds.
        "tiny": {"data": "tiny", "seeds": 1, "train": {
            "width": 4, "blocks": 1, "unroll": 2, "epochs": 1, "stride": 4, "lr": 1e-3,
            "batch": 4}},
        "full": {"data": "full", "seeds": 3, "train": {
            "width": 26, "blocks": 8, "unroll": 3, "epochs": 2, "stride": 8, "lr": 1e-3,
            "lr_decay_every": 128, "batch": 16}},
    },
    "kolmogorov": {
        "setups": ("correction",),
        "modes": ("NOG", "WIG"),
        "horizon": 50,
        "quick": {"data": "quick", "seeds": 1, "train": {
            "width": 16, "blocks": 4, "curriculum": [[1, 1e-3], [2, 1e-4], [4, 1e-5]],
            "epochs": 2, "stride": 2, "batch": 8, "correction": "sequential"}},
        "full": {"data": "full", "seeds": 2, "train": {
            "width": 32, "blocks": 6, "curriculum": [[1, 1e-3], [2, 1e-4], [4, 1e-5]],
            "epochs": 2, "stride": 4, "batch": 16, "correction": "sequential"}},
    },
}


def run_study(
    problem: str,
    out: str | Path,
    size: str = "full",
    seeds: int | None = None,
    progress: bool = True,
    jobs: int = 1,
) -> list[dict]:
    """Train and evaluate every cell; returns one row per trained model.

    ``jobs`` > 1 trains that many cells at once in worker processes (one torch thread each),
    showing one progress bar over the cells instead of one per model.
    """
    if problem not in STUDIES:
        raise ValueError(f"unknown study {problem!r}; choose from {sorted(STUDIES)}")
    spec = STUDIES[problem]
    sizes = [k for k in spec if isinstance(spec[k], dict)]
    if size not in sizes:
        raise ValueError(f"unknown study size {size!r}; choose from {sizes}")
    if jobs < 1:
        raise ValueError(f"jobs must be ≥ 1, not {jobs}")
    settings = spec[size]
    out = Path(out)
    data_path = out / f"{problem}-{settings['data']}.h5"
    if not data_path.exists():
        datamod.save(datamod.generate(problem, settings["data"], seed=0, progress=progress),
                     data_path)
    datamod.load(data_path)  # a damaged or stale file fails here, before any training
    cells = [(setup, mode, seed) for setup in spec["setups"] for mode in spec["modes"]
             for seed in range(seeds if seeds is not None else settings["seeds"])]
    todo = [c for c in cells if not _result_path(out, *c).exists()]
    args = [(problem, size, str(data_path), str(out), *c) for c in todo]
    if jobs > 1 and len(todo) > 1:
        context = multiprocessing.get_context("spawn")  # fresh torch/numba state per worker
        with ProcessPoolExecutor(min(jobs, len(todo)), mp_context=context) as pool:
            futures = [pool.submit(_run_cell, *a, progress=False) for a in args]
            for future in tqdm(as_completed(futures), total=len(futures), desc="study cells",
                               disable=not progress, unit="model"):
                future.result()
    else:
        for a in args:
            _run_cell(*a, progress=progress)
    rows = [json.loads(_result_path(out, *c).read_text()) for c in cells]
    write_summary(rows, out, spec["horizon"])
    return rows


def _result_path(out: Path, setup: str, mode: str, seed: int) -> Path:
    return out / f"{setup}-{mode}-seed{seed}" / "results.json"


def _run_cell(problem: str, size: str, data_path: str, out: str, setup: str, mode: str,
              seed: int, progress: bool) -> None:
    """Train (resuming if a checkpoint exists), evaluate and write one cell's results."""
    spec = STUDIES[problem]
    result_path = _result_path(Path(out), setup, mode, seed)
    cfg = TrainConfig.load(problem=problem, data=data_path, out=str(result_path.parent),
                           setup=setup, mode=mode, seed=seed, **spec[size]["train"])
    model = train(cfg, resume=True, progress=progress)
    if progress:
        print(f"{setup}/{mode}/seed {seed}: {describe(model)}", flush=True)
    metrics = evaluate(model, datamod.load(data_path), spec["horizon"], DTYPES[cfg.dtype],
                       result_path.parent)
    row = {"problem": problem, "setup": setup, "mode": mode, "seed": seed, **metrics}
    write_text(result_path, json.dumps(row, indent=2))


def load_model(run: str | Path):
    """Rebuild a trained model from its run directory."""
    ckpt = load_checkpoint(Path(run) / "checkpoint.pt")
    if not ckpt["state"].get("finished"):
        warnings.warn(
            f"{run} holds an unfinished run (stopped after {ckpt['state']['total']} iterations); "
            "finish it by running its `adjointsim train` command again with --resume, or expect "
            "a partly trained model",
            stacklevel=2,
        )
    model = build_model(TrainConfig(**ckpt["config"]))
    model.load_state_dict(ckpt["model"])
    return model, TrainConfig(**ckpt["config"])


def table(rows: list[dict]) -> str:
    """Mean ± std of the relative error per setup and mode, overall and per test split (with
    the coarse solver's median alone), correlation time and stable fraction."""
    cells: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        cells.setdefault((r["setup"], r["mode"]), []).append(r)
    lines = [f"{'setup':<11} {'mode':<4} {'n':>2}  {'rel. error (mean ± std)':>24}  "
             f"{'interpolation':>13}  {'extrapolation':>13}  {'corr. time':>10}  {'stable':>6}"]
    coarse = next((r for r in rows if r.get("coarse_rel_error") is not None), None)
    for (setup, mode), rs in cells.items():
        e = np.array([r["rel_error"] for r in rs])
        split = [np.mean([r[s]["rel_error"] for r in rs]) for s in TEST_SPLITS]
        ct = np.mean([r["correlation_time"] for r in rs])
        st = np.mean([r["stable_fraction"] for r in rs])
        lines.append(
            f"{setup:<11} {mode:<4} {len(rs):>2}  {np.mean(e):11.3e} ± {np.std(e):10.2e}  "
            f"{split[0]:13.3e}  {split[1]:13.3e}  {ct:10.1f}  {st:6.2f}"
        )
    if coarse is not None:
        lines.append(
            f"{'coarse solver alone (median)':<45}  {coarse['coarse_rel_error']:.3e}  "
            + "  ".join(f"{coarse[s]['coarse_rel_error']:13.3e}" for s in TEST_SPLITS)
        )
    return "\n".join(lines)


def write_summary(rows: list[dict], out: Path, horizon: int) -> None:
    write_text(out / "table.txt", table(rows) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells: dict[str, list[float]] = {}
    for r in rows:
        cells.setdefault(f"{r['setup']}\n{r['mode']}", []).append(r["rel_error"])
    fig, ax = plt.subplots(figsize=(1.3 * len(cells) + 2, 3.8))
    names = list(cells)
    means = [np.mean(cells[k]) for k in names]
    ax.bar(names, means, yerr=[np.std(cells[k]) for k in names], capsize=4, color="#5a8")
    for i, k in enumerate(names):
        ax.scatter([i] * len(cells[k]), cells[k], color="k", s=10, zorder=3)
    coarse = [r["coarse_rel_error"] for r in rows if r.get("coarse_rel_error") is not None]
    if coarse:
        ax.axhline(coarse[0], color="r", lw=1, ls="--", label="coarse solver alone")
        ax.legend()
    ax.set_yscale("log")
    ax.set_ylabel(f"relative error over {horizon} steps")
    fig.tight_layout()
    fig.savefig(out / "study.png", dpi=120)
    plt.close(fig)
