"""The ``hig`` study: Adam, Gauss–Newton and half-inverse gradients on every HIG problem, over
seeds, compared at the same wall-clock of updates (``adjointsim study hig [--quick]``).

Each cell is one ``adjointsim hig`` run (:class:`adjointsim.train.hig_problems.HigRun`) in
its own directory (continued where an interrupted study left it); its row holds the final test
loss, the summed update time ``wall_s`` and the test loss at fixed wall-clock ``marks``. The
report tables the median over seeds (and the range) at each mark, says per problem whether HIG
ends below Adam and GN, and draws the loss-versus-time curves, one panel per problem.
"""

from __future__ import annotations

import math
from pathlib import Path
from statistics import median

from adjointsim import engine
from adjointsim.files import pyplot, save_figure, write_text
from adjointsim.run import read_history
from adjointsim.runner import Study, register_study, runs_show_progress

from ..hig_problems import HigConfig, HigRun, loss_at, plot_test_losses
from ..higs import OPTIMIZERS

#: the problems of the quick and full sizes, in the paper's order
PAPER = ("oscillators", "quantum", "poisson", "chain")

#: per size: problems, seeds, time budget per problem (s), wall-clock marks of the table (s)
SIZES = {
    "tiny": {"problems": ("chain", "oscillators"), "seeds": 1,
             "budget": {"chain": 0.2, "oscillators": 0.2}, "marks": (0.1, 0.2), "data": "tiny"},
    "quick": {"problems": PAPER, "seeds": 3,
              "budget": {"oscillators": 20.0, "quantum": 20.0, "poisson": 20.0, "chain": 30.0},
              "marks": (1.0, 2.0, 5.0, 10.0, 20.0, 30.0), "data": "full"},
    # the two problems the quick size does not reproduce, at 15x its budget
    "long": {"problems": ("quantum", "poisson"), "seeds": 3,
             "budget": {"quantum": 300.0, "poisson": 300.0},
             "marks": (1.0, 10.0, 30.0, 100.0, 300.0), "data": "full"},
    "full": {"problems": PAPER, "seeds": 3,
             "budget": {"oscillators": 600.0, "quantum": 600.0, "poisson": 600.0,
                        "chain": 100.0},
             "marks": (1.0, 10.0, 100.0, 300.0, 600.0), "data": "full"},
    # Poisson with HIG and GN at the paper's batch of 64, an hour of update time each: about
    # 10 hours of one core for the 9 cells (seed 0 of each optimizer first)
    "paper-batch": {"problems": ("poisson64",), "seeds": 3, "budget": {"poisson64": 3600.0},
                    "marks": (1.0, 10.0, 30.0, 100.0, 300.0, 1000.0, 3600.0), "data": "full"},
}


def cells(size: str, seeds: int | None) -> list[dict]:
    spec = SIZES[size]
    n = spec["seeds"] if seeds is None else seeds
    # Seed-major: an interrupted study has every problem at some seed before any third seed.
    return [
        {"id": f"{p}-{o}-s{s}", "problem": p, "optimizer": o, "seed": s,
         "budget": spec["budget"][p], "data": spec["data"],
         "marks": [m for m in spec["marks"] if m <= spec["budget"][p]]}
        for s in range(n) for p in spec["problems"] for o in OPTIMIZERS
    ]


def run_cell(cell: dict, run_dir: Path) -> dict:
    cfg = HigConfig(problem=cell["problem"], optimizer=cell["optimizer"], seed=cell["seed"],
                    budget=cell["budget"], size=cell["data"])
    cfg.validate()
    run = HigRun(cfg, Path(run_dir), plots=False)
    result = engine.run(run, resume=engine.RunDir(run).holds(), progress=runs_show_progress())
    history = read_history(Path(run_dir) / "history.csv")
    return {
        "wall_s": result["wall_s"],
        "updates": result["updates"],
        "test_loss": result["test_loss"],
        "diverged": result["diverged"],
        "loss_at": {str(m): loss_at(history, m) for m in cell["marks"]},
    }


def collect(out: Path, size: str, seeds: int | None = None) -> list[dict]:
    """The rows of the cells under the study directory ``out`` that have been evaluated,
    finished or not: ``wall_s``, ``updates`` and ``test_loss`` of the last evaluation (what a
    stopped or running study has reached)."""
    rows = []
    for cell in cells(size, seeds):
        path = Path(out) / cell["id"] / "history.csv"
        history = read_history(path) if path.exists() else []
        if history:
            last = history[-1]
            rows.append({**cell, "wall_s": last["wall_s"], "updates": last["update"],
                         "test_loss": last["test_loss"] if math.isfinite(last["test_loss"])
                         else None, "diverged": not math.isfinite(last["test_loss"]),
                         # the marks it has reached
                         "loss_at": {str(m): loss_at(history, m) for m in cell["marks"]
                                     if m <= last["wall_s"]}})
    return rows


def _problems(rows: list[dict]) -> list[str]:
    """The problems of ``rows``, in the order of the study's cells."""
    return list(dict.fromkeys(r["problem"] for r in rows))


def _fmt(values: list[float]) -> str:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    if not finite:
        return "diverged"
    text = f"{median(finite):.2e}"
    if len(finite) > 1:
        text += f" [{min(finite):.1e}, {max(finite):.1e}]"
    if len(finite) < len(values):
        text += f" ({len(values) - len(finite)} div.)"
    return text


def _final(row: dict) -> float:
    return math.inf if row["test_loss"] is None else row["test_loss"]


def table(rows: list[dict]) -> str:
    """Median test loss over seeds [min, max] at each wall-clock mark and at the end."""
    lines = []
    for problem in _problems(rows):
        mine = [r for r in rows if r["problem"] == problem]
        if not mine:
            continue
        marks = mine[0]["marks"]
        head = ["optimizer", "seeds"] + [f"@{m:g}s" for m in marks] + ["end", "updates"]
        body = []
        for opt in OPTIMIZERS:
            rs = [r for r in mine if r["optimizer"] == opt]
            if not rs:
                continue
            at = [[r["loss_at"].get(str(m), "-") for r in rs] for m in marks]
            # "-": a mark not reached by a run still going (rows of collect)
            at = [[math.inf if v is None else v for v in col if v != "-"] for col in at]
            body.append([opt, str(len(rs))] + [_fmt(col) if col else "-" for col in at]
                        + [_fmt([_final(r) for r in rs]),
                           f"{median(r['updates'] for r in rs):.0f}"])
        widths = [max(len(x[i]) for x in [head, *body]) for i in range(len(head))]
        lines.append(f"{problem} (budget {mine[0]['budget']:g} s of update time; test loss, "
                     "median over seeds [min, max])")
        for x in [head, *body]:
            lines.append("  ".join(c.ljust(w) for c, w in zip(x, widths)))
        lines.append(_verdict(mine))
        lines.append("")
    return "\n".join(lines)


def _verdict(rows: list[dict]) -> str:
    """HIG against Adam and GN per seed at the last mark every run has reached (the budget,
    once they have finished: the same wall-clock)."""
    reached = [m for m in rows[0]["marks"] if all(str(m) in r["loss_at"] for r in rows)]
    if not reached:
        return ""
    mark = str(reached[-1])
    by = {(r["optimizer"], r["seed"]): r["loss_at"][mark] for r in rows}
    by = {k: math.inf if v is None else v for k, v in by.items()}
    seeds = sorted({r["seed"] for r in rows})
    parts = []
    for other in ("adam", "gn"):
        pairs = [(by[("hig", s)], by[(other, s)]) for s in seeds
                 if ("hig", s) in by and (other, s) in by]
        if pairs:
            wins = sum(h < o for h, o in pairs)
            ratio = median(o / h if h > 0 else math.inf for h, o in pairs)
            parts.append(f"HIG below {other.upper()} in {wins}/{len(pairs)} seeds "
                         f"(median {other.upper()}/HIG = {ratio:.3g})")
    return f"  at @{float(mark):g}s: " + "; ".join(parts) if parts else ""


def report(rows: list[dict], out: Path) -> str:
    text = table(rows)
    write_text(Path(out) / "table.txt", text + "\n")
    plot(rows, Path(out), Path(out) / "hig.png")
    return text


def plot(rows: list[dict], out: Path, path: Path) -> None:
    """Test loss against wall-clock, one panel per problem, one curve per optimizer and seed."""
    plt = pyplot()

    problems = _problems(rows)
    fig, axes = plt.subplots(1, len(problems), figsize=(4.2 * len(problems), 3.4), squeeze=False)
    colors = {"adam": "tab:blue", "gn": "tab:orange", "hig": "tab:green"}
    for ax, problem in zip(axes[0], problems):
        curves: dict[str, list[dict]] = {}
        drawn = []
        for r in sorted((r for r in rows if r["problem"] == problem),
                        key=lambda r: (OPTIMIZERS.index(r["optimizer"]), r["seed"])):
            path_csv = out / r["id"] / "history.csv"
            if not path_csv.exists():
                continue
            hist = [h for h in read_history(path_csv)
                    if h["wall_s"] > 0 and math.isfinite(h["test_loss"])]
            if hist:
                # matplotlib leaves labels that start with "_" out of the legend: one entry
                # per optimizer
                label = r["optimizer"].upper() if r["seed"] == 0 else f"_{r['id']}"
                curves[label] = hist
                drawn.append(r)
        if drawn:  # one colour per optimizer, in the order the curves are drawn
            ax.set_prop_cycle(color=[colors[r["optimizer"]] for r in drawn])
        plot_test_losses(path, curves, problem, ax=ax)
        # a diverging run must not squash the others: clip at 10x the highest start
        start = max([0.0] + [hist[0]["test_loss"] for hist in curves.values()])
        if start > 0:
            ax.set_ylim(top=10 * start)
    save_figure(fig, path, dpi=120)


register_study(Study(name="hig", sizes=tuple(SIZES), cells=cells, run_cell=run_cell,
                     report=report, so_far=collect))
