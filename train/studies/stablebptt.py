"""The stabilised-BPTT study: tasks × complexity levels × gradient-flow modes × clipping × seeds.

Each cell trains one controller (:func:`adjointsim.train.control.train_controller`) in its own
run directory and returns its row: ``task``, ``level``, ``mode``, ``clip``, ``seed``,
``test_loss`` (final), the final training loss, the per-epoch test losses and the time. Sizes:

* ``tiny``: two cells of a few seconds (the end-to-end test);
* ``quick``: every registered task (:data:`adjointsim.train.tasks.TASKS`) at its easiest and
  hardest level, modes R/M/S/C, no clipping, one seed, 32 + 32 initial states, a few epochs
  (minutes on 2 cores);
* ``hardest``: the finding of the paper: the hardest level of each task (4 poles, target 5,
  control weight 0.001), modes R/M/C, no clipping, 3 seeds, 64 + 64 initial states, 60 epochs
  (20 for a task whose update costs several times a cart-pole one, ``Task.costly``: quantum);
* ``easiest``: the paper's other finding, that every mode solves the easiest level (1 pole,
  target 3, control weight 1): modes R/M/S/C, otherwise as ``hardest``; the table gives each
  final test loss over the untrained controller's (c = 0);
* ``full``: the paper's settings (Adam 1e-3, 256 + 256 initial states, batch 8), every level,
  modes R/M/S/C, clipping none/value/norm, 3 seeds; epochs sized to about an hour per task on
  2 cores (the paper runs 1000);
* ``paper``: the paper's budget at the hardest cart-pole level (4 poles): 1000 epochs of the
  paper's settings, modes R, M and C and R with norm clipping, 3 seeds;
* ``paper-guidance``: the same for the guidance task at control weight 0.001, at 300 epochs;
* ``budget``: the paper's 1000 epochs for the other two tasks at their hardest levels
  (guidance at control weight 0.001, quantum at target 5), modes R, M and C and R with norm
  clipping, 3 seeds, quantum's closed loop compiled (``compile = "inductor"``; mode C cannot
  be): hours per ensemble on one core, over several sittings (each run resumes
  from its checkpoint; ``adjointsim study stablebptt --size budget --out OUT --so-far``
  tabulates and draws the epochs reached so far).

Cells that differ only in the seed and the clipping train together as one ensemble
(:func:`adjointsim.train.ensemble.train_ensemble`): one task of the runner per ensemble, each
member in its own run directory, equal to its separate run. In the ``budget`` size the modes of
a task take turns of 50 epochs in one task of the runner, so a study stopped in any sitting
compares R, M and C at about the same epoch; on a cluster the runner deals the modes among its
workers (:attr:`adjointsim.runner.Study.turns`), each worker's taking turns.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from adjointsim import engine
from adjointsim.files import pyplot, save_figure, write_text
from adjointsim.run import plot_history, read_history
from adjointsim.runner import Study, in_turns, register_study, runs_show_progress

from ..control import ControlConfig, build_net, evaluate, initial_states, train_controller
from ..ensemble import train_ensemble
from ..tasks import TASKS
from ..unroll import CLIPS, FLOWS

_MODES = ("R", "M", "S", "C")
#: per size: levels per task ("ends" = easiest and hardest, or the levels of named tasks),
#: modes, clips, seeds, samples, epochs (of a task, and of a costly one)
SIZES = {
    "tiny": {"tasks": {"cartpole": (1,)}, "modes": ("R", "C"), "clips": ("none",), "seeds": 1,
             "train": 8, "test": 8, "batch": 4, "epochs": (1, 1)},
    "quick": {"tasks": "ends", "modes": _MODES, "clips": ("none",), "seeds": 1,
              "train": 32, "test": 32, "batch": 8, "epochs": (4, 2)},
    "hardest": {"tasks": "hardest", "modes": ("R", "M", "C"), "clips": ("none",), "seeds": 3,
                "train": 64, "test": 64, "batch": 8, "epochs": (60, 20)},
    # the paper's second finding: at the easiest level every mode solves the task
    "easiest": {"tasks": "easiest", "modes": _MODES, "clips": ("none",), "seeds": 3,
                "train": 64, "test": 64, "batch": 8, "epochs": (60, 20)},
    "full": {"tasks": "all", "modes": _MODES, "clips": CLIPS, "seeds": 3,
             "train": 256, "test": 256, "batch": 8, "epochs": (16, 5)},
    "paper": {"tasks": {"cartpole": (4,)}, "modes": ("R", "M", "C"), "clips": ("none",),
              "extra": (("R", "norm"),), "seeds": 3, "train": 256, "test": 256, "batch": 8,
              "epochs": (1000, 1000)},
    # the guidance task at its hardest control weight, as many epochs as fit in half an hour
    # of 2 cores (the paper: 1000)
    "paper-guidance": {"tasks": {"guidance": (0.001,)}, "modes": ("R", "M", "C"),
                       "clips": ("none",), "extra": (("R", "norm"),), "seeds": 3, "train": 256,
                       "test": 256, "batch": 8, "epochs": (300, 300)},
    # guidance first: an ensemble of it costs about a tenth of a quantum one per epoch
    # the costly task's loop compiled (inductor) where the mode allows: minutes of tracing
    # against hours of updates
    "budget": {"tasks": {"guidance": (0.001,), "quantum": (5,)}, "modes": ("R", "M", "C"),
               "clips": ("none",), "extra": (("R", "norm"),), "seeds": 3, "train": 256,
               "test": 256, "batch": 8, "epochs": (1000, 1000), "turn": 50,
               "compile": "inductor"},
}


def _levels(spec, task: str) -> tuple:
    levels = TASKS.get(task).levels
    if isinstance(spec, dict):
        return spec.get(task, ())
    # "all" puts the hardest and easiest levels first: they hold the paper's findings, so a
    # study stopped early (it resumes) has them before the middle levels
    return {"ends": (levels[0], levels[-1]), "easiest": (levels[0],), "hardest": (levels[-1],),
            "all": (levels[-1], levels[0], *levels[1:-1])}[spec]


def cells(size: str, seeds: int | None) -> list[dict]:
    s = SIZES[size]
    out = []
    for task in TASKS.names():
        for level in _levels(s["tasks"], task):
            variants = [(m, c) for m in s["modes"] for c in s["clips"]] + list(s.get("extra", ()))
            for mode, clip in variants:
                for seed in range(seeds or s["seeds"]):
                    out.append({
                        "id": f"{task}-{level}-{mode}-{clip}-s{seed}",
                        "task": task, "level": level, "mode": mode, "clip": clip,
                        "seed": seed, "epochs": s["epochs"][TASKS.get(task).costly],
                        "train": s["train"],
                        "test": s["test"], "batch": s["batch"],
                        **({"turn": s["turn"]} if "turn" in s else {}),
                        **({"compile": s["compile"]} if "compile" in s and mode != "C"
                           and TASKS.get(task).costly else {}),
                    })
    # level by level across tasks (stable: task order kept within a level)
    out.sort(key=lambda c: _levels(s["tasks"], c["task"]).index(c["level"]))
    return out


def _config(cell: dict, run_dir: Path) -> ControlConfig:
    cfg = ControlConfig(
        task=cell["task"], mode=cell["mode"], clip=cell["clip"], level=cell["level"],
        seed=cell["seed"], epochs=cell["epochs"], train=cell["train"], test=cell["test"],
        batch=cell["batch"], out=str(run_dir), dtype="float32", threads=1,
        compile=cell.get("compile", "off"),
    )
    cfg.validate()
    return cfg


def run_cell(cell: dict, run_dir: Path) -> dict:
    """Train (or resume, or reuse) the cell's controller in ``run_dir``; returns its row."""
    cfg = _config(cell, run_dir)
    result = train_controller(cfg, resume=engine.started(run_dir), progress=runs_show_progress())
    return _row(cell, cfg, result, run_dir)


def pack(cell: dict) -> tuple[str, ...]:
    """The keys in which the cells of one runner task differ: seed and clip (one ensemble),
    and the mode (with whether it compiles) too where the modes take turns (one task, an
    ensemble per mode)."""
    return ("seed", "clip", "mode", "compile") if "turn" in cell else ("seed", "clip")


#: an ensemble's epoch in units of one compiled run's: a share of its own (the evaluation and
#: the loop's per-step work, whatever the members), one per compiled run and 2.3 per eager one
#: (mode C cannot compile), as the quantum budget's ensembles of R, M and C measure
_EPOCH_COST = {"ensemble": 2.0, "compiled": 1.0, "eager": 2.3}


def turn_cost(cells: list[dict], run_dirs: list[Path]) -> float:
    """What is left of a mode's ensemble, for dealing the modes among workers: the epochs its
    runs have still to train (from the slowest member's history) times an epoch's cost, so
    that a study resumed in a later sitting deals what remains afresh."""
    kinds = ["compiled" if c.get("compile", "off") != "off" else "eager" for c in cells]
    epoch = _EPOCH_COST["ensemble"] + sum(_EPOCH_COST[k] for k in kinds)
    reached = min(_epochs(d) for d in run_dirs)
    return epoch * max(cells[0]["epochs"] - reached, 0)


def run_group(cells: list[dict], run_dirs: list[Path]) -> list[dict]:
    """Train (or resume, or reuse) the cells' controllers, those differing only in seed and
    clip as one ensemble; where the cells take turns (``turn`` epochs), the ensembles advance
    in turns, the one furthest behind first, so that a stopped study has every mode at about
    the same epoch. Returns the cells' rows."""
    cfgs = [_config(c, d) for c, d in zip(cells, run_dirs)]
    groups: dict[str, list[int]] = {}
    for i, c in enumerate(cells):
        groups.setdefault(c["mode"], []).append(i)

    def reached(group: list[int]) -> int:
        return min(_epochs(cfgs[i].out) for i in group)

    def advance(group: list[int], to: int) -> None:
        train_ensemble([cfgs[i] for i in group], resume=True, progress=runs_show_progress(),
                       until=to)

    if "turn" in cells[0]:
        in_turns(list(groups.values()), reached, lambda g: cfgs[g[0]].epochs, cells[0]["turn"],
                 advance)
    results: list[dict] = [{}] * len(cells)
    for group in groups.values():
        for i, result in zip(group, train_ensemble([cfgs[i] for i in group], resume=True,
                                                   progress=runs_show_progress())):
            results[i] = result
    return [_row(*args) for args in zip(cells, cfgs, results, run_dirs)]


def _history(run_dir: Path | str) -> list[dict]:
    """The history rows (one per epoch trained) of the run in ``run_dir``; none if it has
    not started."""
    path = Path(run_dir) / "history.csv"
    return read_history(path) if path.exists() else []


def _epochs(run_dir: Path | str) -> int:
    """The epochs the run in ``run_dir`` has trained."""
    history = _history(run_dir)
    return int(history[-1]["epoch"]) if history else 0


def _row(cell: dict, cfg: ControlConfig, result: dict, run_dir: Path) -> dict:
    history = read_history(Path(run_dir) / "history.csv")
    # the untrained controller outputs c = 0 (zero last layer): the uncontrolled loss
    task = cfg.make_task()
    untrained = evaluate(task, build_net(cfg, task), initial_states(cfg, task)[1])
    return {**cell, "test_loss": result["test_loss"], "train_loss": result["train_loss"],
            "untrained_test_loss": untrained,
            "seconds": result["seconds"], "test_history": [h["test_loss"] for h in history],
            "config": cfg.as_dict()}


def collect(out: Path, size: str, seeds: int | None = None) -> list[dict]:
    """The rows of the cells under the study directory ``out`` that have trained an epoch,
    finished or not (what a stopped or running study has reached), compared at one epoch per
    task and level: ``epochs``, the last epoch every started cell of the task and level has
    reached, with ``test_loss`` and ``train_loss`` at that epoch; ``epochs_reached`` is the
    cell's own and ``test_history`` its whole curve."""
    rows, histories = [], []
    for cell in cells(size, seeds):
        history = _history(Path(out) / cell["id"])
        if history:
            rows.append(cell)
            histories.append(history)
    common: dict[tuple, int] = {}
    for cell, history in zip(rows, histories):
        key = (cell["task"], cell["level"])
        common[key] = min(common.get(key, len(history)), len(history))
    out_rows = []
    for cell, history in zip(rows, histories):
        at = history[common[(cell["task"], cell["level"])] - 1]
        out_rows.append({**cell, "epochs": int(at["epoch"]),
                         "epochs_reached": int(history[-1]["epoch"]),
                         "epochs_planned": cell["epochs"], "test_loss": at["test_loss"],
                         "train_loss": at["train_loss"],
                         "test_history": [h["test_loss"] for h in history]})
    return out_rows


def table(rows: list[dict]) -> str:
    """Final test loss per task, level, mode and clip (mean ± std over seeds) and, where the
    rows hold it, its mean ratio to the untrained (uncontrolled) test loss."""
    groups: dict[tuple, list[float]] = {}
    ratios: dict[tuple, list[float]] = {}
    for r in rows:
        key = (r["task"], r["level"], r["mode"], r["clip"])
        loss = r["test_loss"] if r["test_loss"] is not None else float("nan")
        groups.setdefault(key, []).append(loss)
        if r.get("untrained_test_loss"):
            ratios.setdefault(key, []).append(loss / r["untrained_test_loss"])
    lines = [f"{'task':<9} {'level':>6} {'mode':<4} {'clip':<5} {'n':>2}  "
             "final test loss (mean ± std)" + ("   / untrained" if ratios else "")]
    order = {m: i for i, m in enumerate(FLOWS)}
    for (task, level, mode, clip), v in sorted(
            groups.items(), key=lambda kv: (TASKS.names().index(kv[0][0]), str(kv[0][1]),
                                            kv[0][3], order[kv[0][2]])):
        v = np.array(v, dtype=float)
        ratio = ratios.get((task, level, mode, clip))
        lines.append(f"{task:<9} {level!s:>6} {mode:<4} {clip:<5} {len(v):>2}  "
                     f"{np.nanmean(v):.4e} ± {np.nanstd(v):.2e}"
                     + (f"   {np.nanmean(ratio):.3f}" if ratio else ""))
    return "\n".join(lines)


def summary(rows: list[dict]) -> str:
    """One line per task, level and clip: each mode's final test loss (mean over seeds) and,
    in brackets, its mean ratio to the untrained loss; then on how many seeds C ends below R
    and below M (paired by seed)."""
    cell = {(r["task"], r["level"], r["clip"], r["mode"], r["seed"]): r for r in rows}
    keys = sorted({k[:3] for k in cell}, key=lambda k: (TASKS.names().index(k[0]),
                                                        TASKS.get(k[0]).levels.index(k[1]), k[2]))
    modes = [m for m in FLOWS if any(k[3] == m for k in cell)]
    lines = [f"{'task':<9} {'level':>6} {'clip':<5} "
             + " ".join(f"{m:<17}" for m in modes) + "  C<R   C<M"]
    for task, level, clip in keys:
        entries, final = [], {}
        for m in modes:
            rs = [r for k, r in cell.items() if k[:4] == (task, level, clip, m)]
            final[m] = {r["seed"]: r["test_loss"] for r in rs if r["test_loss"] is not None}
            if not final[m]:
                entries.append(f"{'-':<17}")
                continue
            ratio = [r["test_loss"] / r["untrained_test_loss"] for r in rs
                     if r["test_loss"] is not None and r.get("untrained_test_loss")]
            text = f"{np.mean(list(final[m].values())):.3g}"
            entries.append(f"{text + (f' [{np.mean(ratio):.3f}]' if ratio else ''):<17}")
        wins = []
        for other in ("R", "M"):
            paired = [s for s in final.get("C", {}) if s in final.get(other, {})]
            below = sum(final["C"][s] < final[other][s] for s in paired)
            wins.append(f"{below}/{len(paired)}" if paired else "-")
        lines.append(f"{task:<9} {level!s:>6} {clip:<5} " + " ".join(entries)
                     + f"  {wins[0]:<5} {wins[1]}")
    return "\n".join(lines)


def report(rows: list[dict], out: Path) -> str:
    """Table (``table.txt``: the summary, then every group) and per task the test-loss
    curves (``stablebptt-TASK.png``; with several levels, one file per level,
    ``stablebptt-TASK-LEVEL.png``, and the final loss against the level,
    ``stablebptt-TASK-levels.png``)."""
    out = Path(out)
    text = summary(rows) + "\n\n" + table(rows)
    if any("epochs_reached" in r for r in rows):
        text = _reached(rows) + "\n\n" + text
    write_text(out / "table.txt", text + "\n")
    for task in TASKS.names():
        mine = [r for r in rows if r["task"] == task]
        levels = sorted({r["level"] for r in mine}, key=TASKS.get(task).levels.index)
        for level in levels:
            name = f"stablebptt-{task}" + (f"-{level}" if len(levels) > 1 else "")
            _plot_curves([r for r in mine if r["level"] == level], out / f"{name}.png")
        if len(levels) > 1:
            _plot_levels(mine, levels, out / f"stablebptt-{task}-levels.png")
    return text


def _reached(rows: list[dict]) -> str:
    """Rows of a study still running: per task and level, the epoch its losses are compared
    at and the epochs each mode and clip has reached (fewest over seeds)."""
    lines = []
    for task, level in dict.fromkeys((r["task"], r["level"]) for r in rows):
        mine = [r for r in rows if (r["task"], r["level"]) == (task, level)]
        reached: dict[str, int] = {}
        for r in mine:
            key = f"{r['mode']}/{r['clip']}"
            reached[key] = min(reached.get(key, r["epochs_reached"]), r["epochs_reached"])
        lines.append(f"{task} {level}: compared at epoch {mine[0]['epochs']} of "
                     f"{mine[0]['epochs_planned']}; reached "
                     + ", ".join(f"{k} {v}" for k, v in reached.items()))
    return "\n".join(lines)


_COLORS = {"R": "tab:blue", "M": "tab:orange", "S": "tab:green", "N": "tab:purple",
           "C": "tab:red"}


def _plot_curves(rows: list[dict], path: Path) -> None:
    """Test loss over epochs, mean over seeds: a curve per mode and clip."""
    task, level = rows[0]["task"], rows[0]["level"]
    runs: dict[tuple, list[list[float]]] = {}
    for r in rows:
        runs.setdefault((r["mode"], r["clip"]), []).append(r["test_history"])
    order = {m: i for i, m in enumerate(FLOWS)}
    curves = {}
    for (mode, clip), hs in sorted(runs.items(), key=lambda kv: (order[kv[0][0]], kv[0][1])):
        n = min(len(h) for h in hs)
        mean = np.nanmean(np.array([h[:n] for h in hs], dtype=float), axis=0)
        clip_txt = "" if clip == "none" else f", clip {clip}"
        curves[f"{mode}{clip_txt} (n={len(hs)})"] = [
            {"epoch": e + 1, "test_loss": float(v)} for e, v in enumerate(mean)]
    plot_history(path, curves, "epoch", "test_loss", "epoch", "test loss",
                 title=f"{task}, {TASKS.get(task).key.replace('_', ' ')} {level}: test loss, "
                 "mean over seeds")


def _plot_levels(rows: list[dict], levels: list, path: Path) -> None:
    """Final test loss over the untrained one against the level: a panel per clip, a line
    per mode (mean ± std over seeds)."""
    plt = pyplot()
    clips = [c for c in CLIPS if any(r["clip"] == c for r in rows)]
    fig, axes = plt.subplots(1, len(clips), figsize=(3.6 * len(clips), 3.4), squeeze=False,
                             sharey=True)
    task = rows[0]["task"]
    for ax, clip in zip(axes[0], clips):
        for mode in FLOWS:
            ratio = [[r["test_loss"] / r["untrained_test_loss"] for r in rows
                      if (r["level"], r["mode"], r["clip"]) == (level, mode, clip)
                      and r["test_loss"] is not None and r.get("untrained_test_loss")]
                     for level in levels]
            if not any(ratio):
                continue
            x = [i for i, v in enumerate(ratio) if v]
            ax.errorbar(x, [np.mean(ratio[i]) for i in x], yerr=[np.std(ratio[i]) for i in x],
                        marker="o", capsize=3, label=mode, color=_COLORS[mode])
        ax.set_xticks(range(len(levels)), [str(v) for v in levels])
        ax.set_xlabel(TASKS.get(task).key.replace("_", " "))
        ax.set_yscale("log")
        ax.set_title(f"clip {clip}", fontsize=9)
    axes[0][0].set_ylabel("final test loss / untrained")
    axes[0][0].legend(fontsize=8)
    fig.suptitle(f"{task}: final test loss against the level (mean ± std over seeds)",
                 fontsize=9)
    save_figure(fig, path, dpi=110)


register_study(Study(
    name="stablebptt",
    sizes=tuple(SIZES),
    cells=cells,
    run_cell=run_cell,
    report=report,
    pack=pack,
    run_group=run_group,
    turns=("mode",),
    turn_cost=turn_cost,
    so_far=collect,
))
