"""``ks-curves``: learning curves of List et al.'s KS correction (ResNet 26×8) for ONE, NOG and
WIG: the test error measured along the way, to see whether, and after how many updates, the
paper's ordering WIG < NOG < ONE appears.

**The paper's number of updates** (:func:`paper_updates`, from the dataset): 6 domain sizes × 6
initial states = 36 training trajectories of 5000 frames. NOG and WIG train on windows of
m + 1 = 4 frames, 4997 per trajectory, batch 16, for 80 epochs: 36 · 4997 // 16 = 11,243
updates per epoch, 899,440 in all. ONE takes batch and epochs × m (the reference's rule):
36 · 4999 // 48 = 3749 per epoch × 240 epochs = 899,760.

**Settings** (size ``paper``): the paper's network, unroll 3, batch 16 and every window (stride
1); Adam at the paper's rate 1e-4, held: the paper's 80-epoch re-runs lower it on plateaus of
the loss, which its epochs of 11,243 updates make rare early on (a deviation: the plateau
rule's patience is not given); 8 epochs, a tenth of the paper's updates. The test error every
1000 updates is the study tables' ``rel_error`` (12 steps, 40 test rollouts).

The seeds of a mode train as one ensemble. In one process (``--cluster none``) the three
ensembles take turns of ``chunk`` updates, the one furthest behind first
(:func:`adjointsim.runner.in_turns`), so every curve advances together: a study stopped at any
time has every mode at about the same update. On a cluster the runner deals the modes among
its workers (:attr:`adjointsim.runner.Study.turns`): with two, one worker trains a mode while
the other's two take turns; with three, each has its own. Each member
keeps its curve in ``curve.csv`` of its run directory; run again, the study continues every
run from its checkpoint. The curves so far, finished or not, are tabulated and drawn by
``adjointsim study ks-curves --size paper --out OUT --so-far``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from adjointsim.engine import RESULT, started
from adjointsim.files import log_axis, pyplot, save_figure, write_json, write_text
from adjointsim.run import read_history
from adjointsim.runner import Study, in_turns, register_study, runs_show_progress

from .. import data as datamod
from ..ensemble import train_ensemble
from ..trainer import TrainConfig, plan

MODES = ("ONE", "NOG", "WIG")
#: the paper's epochs (its re-runs with longer training)
PAPER_EPOCHS = 80
#: the paper's mean relative errors of the 26×8 correction models (80-epoch re-runs)
PAPER_ERRORS = {"ONE": 1.9e-3, "NOG": 8.8e-4, "WIG": 1.5e-4}
#: per size: the dataset, seeds, updates per turn of each mode's ensemble, and the training
SIZES = {
    "paper": {"data": "full", "seeds": 3, "chunk": 1000, "train": {
        "width": 26, "blocks": 8, "unroll": 3, "epochs": 8, "stride": 1, "lr": 1e-4,
        "lr_decay": 1.0, "batch": 16, "eval_every": 1000, "checkpoint_every": 1000}},
    # for tests: the whole pipeline in seconds
    "tiny": {"data": "tiny", "seeds": 2, "chunk": 4, "train": {
        "width": 4, "blocks": 1, "unroll": 2, "epochs": 2, "stride": 4, "lr": 1e-3,
        "lr_decay": 1.0, "batch": 4, "eval_every": 2}},
}


def cells(size: str, seeds: int | None) -> list[dict]:
    n = SIZES[size]["seeds"] if seeds is None else seeds
    return [{"id": f"correction-{mode}-seed{seed}", "size": size, "mode": mode, "seed": seed}
            for mode in MODES for seed in range(n)]


def prepare(size: str, out: Path) -> dict:
    """The dataset, made once and shared by every cell (the ``ks`` study's, seed 0)."""
    path = out / f"ks-{SIZES[size]['data']}.h5"
    if not path.exists():
        datamod.save(datamod.generate("ks", SIZES[size]["data"], seed=0), path)
    datamod.load(path)  # a damaged or stale file fails here, before any training
    return {"data": str(path.resolve())}


def config(cell: dict, run_dir: Path) -> TrainConfig:
    return TrainConfig.load(problem="ks", data=cell["data"], out=str(run_dir),
                            setup="correction", mode=cell["mode"], seed=cell["seed"],
                            **SIZES[cell["size"]]["train"])


def paper_updates(mode: str, split: datamod.Split) -> int:
    """The updates of the paper's run of ``mode`` on the training split ``split``: every
    window, batch 16, unroll 3, :data:`PAPER_EPOCHS` epochs (ONE: batch and epochs × 3)."""
    cfg = TrainConfig(mode=mode, unroll=3, batch=16, epochs=PAPER_EPOCHS, stride=1)
    return sum(s["iterations"]
               for s in plan(cfg, lambda length: len(datamod.windows(split, length, 1))))


def run_group(cells: list[dict], run_dirs: list[Path]) -> list[dict]:
    """Train the cells' models, the seeds of a mode as one ensemble, the modes taking turns of
    ``chunk`` updates (each resumes its runs from their checkpoints); returns their rows."""
    groups: dict[str, list[TrainConfig]] = {}
    for cell, run_dir in zip(cells, run_dirs):
        groups.setdefault(cell["mode"], []).append(config(cell, run_dir))
    split = datamod.load(cells[0]["data"]).splits["train"]
    # each mode's planned updates, counted once (in_turns asks at every turn)
    totals = {g[0].mode: sum(s["iterations"] for s in plan(g[0], lambda length, c=g[0]: len(
        datamod.windows(split, length, c.stride)))) for g in groups.values()}

    def total(group: list[TrainConfig]) -> int:
        return totals[group[0].mode]

    def reached(group: list[TrainConfig]) -> int:
        if all((Path(c.out) / RESULT).exists() for c in group):
            return total(group)
        return min(_reached(Path(c.out)) for c in group)

    def advance(group: list[TrainConfig], to: int) -> None:
        train_ensemble(group, resume=any(started(c.out) for c in group),
                       progress=runs_show_progress(), until=to)

    in_turns(list(groups.values()), reached, total, SIZES[cells[0]["size"]]["chunk"], advance)
    return [row(cell, run_dir) for cell, run_dir in zip(cells, run_dirs)]


def run_cell(cell: dict, run_dir: Path) -> dict:
    """One cell alone: its mode's ensemble of one."""
    return run_group([cell], [run_dir])[0]


def _curve(run_dir: Path) -> list[dict]:
    path = run_dir / "curve.csv"
    return read_history(path) if path.exists() else []


def _reached(run_dir: Path) -> int:
    """The last evaluation point of the run in ``run_dir`` (0: none yet)."""
    curve = _curve(run_dir)
    return int(curve[-1]["updates"]) if curve else 0


#: the share of the updates, back from a point, over which the table's last line and the
#: plot's bold curves take each seed's median error (a constant width on the plot's log axis)
TAIL = 0.25


def row(cell: dict, run_dir: Path) -> dict:
    """The cell's row: its curve (updates, test error) as far as it has gone, the last point's
    values and the paper's updates of its mode."""
    curve = _curve(run_dir)
    split = datamod.load(cell["data"]).splits["train"]
    return {**cell, "updates": int(curve[-1]["updates"]) if curve else 0,
            "paper_updates": paper_updates(cell["mode"], split),
            "rel_error": float(curve[-1]["rel_error"]) if curve else None,
            "curve": [[int(p["updates"]), float(p["rel_error"])] for p in curve]}


def collect(out: Path, size: str = "paper", seeds: int | None = None) -> list[dict]:
    """The rows of the cells under the study directory ``out`` that have started, finished or
    not (what a stopped study has reached)."""
    data = str((out / f"ks-{SIZES[size]['data']}.h5").resolve())
    return [row({**cell, "data": data}, out / cell["id"]) for cell in cells(size, seeds)
            if _curve(out / cell["id"])]


def points(rows: list[dict]) -> list[dict]:
    """One row per evaluation point: mode, seed, updates, paper_updates, rel_error."""
    return [{"mode": r["mode"], "seed": r["seed"], "updates": u,
             "paper_updates": r["paper_updates"], "rel_error": e}
            for r in rows for u, e in r["curve"]]


def _by_mode(rows: list[dict]) -> dict[str, dict[int, dict[int, float]]]:
    """mode → updates → seed → rel_error."""
    out: dict[str, dict[int, dict[int, float]]] = {}
    for p in points(rows):
        out.setdefault(p["mode"], {}).setdefault(p["updates"], {})[p["seed"]] = (
            math.inf if p["rel_error"] is None else p["rel_error"])
    return out


def table(rows: list[dict]) -> str:
    """Per mode and evaluation point reached by every seed of every mode: the mean ± std of the
    test error over seeds, and on how many seeds the paper's ordering WIG < NOG < ONE holds."""
    by = _by_mode(rows)
    modes = [m for m in MODES if m in by]
    seeds = sorted({r["seed"] for r in rows})
    common = sorted(set.intersection(*(
        {u for u, s in by[m].items() if len(s) == len(seeds)} for m in modes))) if modes else []
    paper = {r["mode"]: r["paper_updates"] for r in rows}
    marks = _marks(common)
    lines = [f"{'updates':>8} {'% paper':>7}  "
             + "  ".join(f"{m + ' (mean ± std)':>21}" for m in modes) + "  WIG<NOG<ONE (seeds)"]
    for u in marks:
        cols = []
        for m in modes:
            e = np.array([by[m][u][s] for s in seeds])
            with np.errstate(invalid="ignore"):  # a blown-up seed's inf: inf ± nan
                cols.append(f"{np.mean(e):10.3e} ± {np.std(e):8.2e}")
        order = sum(by["WIG"][u][s] < by["NOG"][u][s] < by["ONE"][u][s] for s in seeds) \
            if set(MODES) <= set(modes) else 0
        pct = 100 * u / max(paper.values())
        lines.append(f"{u:>8} {pct:7.2f}  " + "  ".join(f"{c:>21}" for c in cols)
                     + f"  {order}/{len(seeds)}")
    for m in modes:  # a study still going: each mode's last point, reached or not by the others
        last = max(u for u, v in by[m].items() if len(v) == len(seeds))
        e = np.array([by[m][last][s] for s in seeds])
        with np.errstate(invalid="ignore"):
            lines.append(f"{m} at its last point, {last} updates: {np.mean(e):.3e} ± "
                         f"{np.std(e):.2e}")
    if len(common) > 1 and set(MODES) <= set(modes):
        lines.append(_window_line(by, seeds, trailing(common, len(common) - 1)))
    lines.append("paper (80 epochs):  " + "  ".join(f"{m} {PAPER_ERRORS[m]:.1e}" for m in modes))
    lines.append("paper updates: " + ", ".join(f"{m} {paper[m]:,}" for m in modes))
    return "\n".join(lines)


def trailing(updates: list[int], k: int) -> list[int]:
    """The evaluation points of ``updates`` (sorted) from ``(1 − TAIL)`` of ``updates[k]`` up
    to it."""
    return [u for u in updates[: k + 1] if u >= (1 - TAIL) * updates[k]]


def _window_line(by: dict[str, dict[int, dict[int, float]]], seeds: list[int],
                 window: list[int]) -> str:
    """Each seed's median error over the evaluation points ``window``, then mean ± std over
    seeds, and the paper's ordering on those medians: one 12-step evaluation scores the weights
    of a single update at the held learning rate and moves by tens of percent from one point to
    the next; the median of several is not pulled by one spike."""
    avg = {m: {s: float(np.median([by[m][u][s] for u in window])) for s in seeds} for m in MODES}
    cols = [f"{m} {np.mean(list(avg[m].values())):.3e} ± {np.std(list(avg[m].values())):.2e}"
            for m in MODES]
    order = sum(avg["WIG"][s] < avg["NOG"][s] < avg["ONE"][s] for s in seeds)
    return (f"each seed's median over its last {len(window)} points ({window[0]}–{window[-1]} "
            "updates), mean ± std over seeds: " + ", ".join(cols)
            + f"; WIG<NOG<ONE {order}/{len(seeds)}")


def _marks(updates: list[int]) -> list[int]:
    """About 12 of the evaluation points, spread evenly on a log scale, and the last."""
    if len(updates) <= 12:
        return updates
    picks = {updates[int(i)] for i in np.unique(np.geomspace(1, len(updates), 12).astype(int) - 1)}
    return sorted(picks | {updates[-1]})


def plot(rows: list[dict], path: Path) -> None:
    """Test error against updates, log-log: each seed thin, bold the mean over seeds of each
    seed's median over the last :data:`TAIL` of its updates, the paper's 80-epoch figure
    dashed, one colour per mode."""
    plt = pyplot()
    by = _by_mode(rows)
    colours = {"ONE": "tab:blue", "NOG": "tab:orange", "WIG": "tab:green"}
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for mode in (m for m in MODES if m in by):
        pts = {u: s for u, s in by[mode].items() if u > 0}
        seeds = sorted({s for v in pts.values() for s in v})
        for seed in seeds:
            us = sorted(u for u in pts if seed in pts[u])
            ax.plot(us, [pts[u][seed] for u in us], color=colours[mode], lw=0.7, alpha=0.5)
        full = sorted(u for u in pts if len(pts[u]) == len(seeds))
        if full:  # markers: a curve of one point so far shows too
            # as the table's last line: a single evaluation's spike does not move it
            running = [np.mean([np.median([pts[v][s] for v in trailing(full, k)])
                                for s in seeds]) for k in range(len(full))]
            ax.plot(full, running, color=colours[mode], lw=2, marker="o", ms=3,
                    label=f"{mode}, {len(seeds)} seeds' median over the last {TAIL:.0%} updates")
        ax.axhline(PAPER_ERRORS[mode], color=colours[mode], ls="--", lw=1,
                   label=f"{mode}, paper (80 epochs)")
    paper = max(r["paper_updates"] for r in rows)
    ax.set_xscale("log")
    log_axis(ax)
    ax.set_xlabel(f"update (the paper's run: {paper:,})")
    ax.set_ylabel("test relative error over 12 steps")
    ax.set_title("KS correction, ResNet 26×8: test error along the training", fontsize=10)
    ax.legend(fontsize=7, ncol=2)
    save_figure(fig, path, dpi=120)


def report(rows: list[dict], out: Path) -> str:
    """``ks-curves.json`` (one row per evaluation point), ``ks-curves.txt`` (the table) and
    ``ks-curves.png`` (the curves) in ``out``."""
    out = Path(out)
    text = table(rows)
    write_json(out / "ks-curves.json", points(rows))
    write_text(out / "ks-curves.txt", text + "\n")
    plot(rows, out / "ks-curves.png")
    return text + f"\nrows {out / 'ks-curves.json'}, curves {out / 'ks-curves.png'}"


register_study(Study(
    name="ks-curves", sizes=tuple(SIZES), cells=cells, run_cell=run_cell, report=report,
    prepare=prepare,
    row_keys={"updates": int, "paper_updates": int, "rel_error": float, "curve": list},
    pack=("seed", "mode"), run_group=run_group, turns=("mode",), so_far=collect,
))
