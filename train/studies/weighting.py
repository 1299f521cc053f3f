"""The ``weighting`` study: every loss-weighting scheme of
:data:`adjointsim.train.weighting.SCHEMES` on the PINN problems of :mod:`adjointsim.train.pinn`
(``adjointsim study weighting --quick``).

A cell is one problem × scheme × seed (× wavenumber k for Poisson), one
:func:`adjointsim.train.pinn.train_run` in its own directory (resumed from its checkpoint when
interrupted). ``epsilon-optimal`` (analytic weights) and ``ntk`` (per-sample residuals) exist
for Poisson only, so the other problems' cells skip them.

Each row holds ``problem``, ``weighting``, ``seed``, ``epochs``, ``k`` (Poisson only) and:

* ``rel_l2``: the problem's accuracy measure, named in ``metric``: for Poisson the relative L2
  error of u on the 100 × 100 grid; for Sobolev the relative L2 error of f on the 100 × 100
  grid; for ks-inverse the relative error of the learned coefficients,
  ‖(α, β) − (1, 1)‖ / ‖(1, 1)‖ (the relative L2 error of u over the trajectory is kept as
  ``u_rel_l2``); null when the run diverged;
* ``wall_s``: the wall-clock seconds of the cell's last attempt (training, evaluation and its
  plots; a resumed cell counts only the part it ran), and ``train_s``, the training time over
  every attempt;
* ``diverged``.

The report writes ``table.md`` (median over seeds [min, max] per problem/k and scheme, the
best median per column in bold, and per column the schemes whose median is below
inverse-Dirichlet's) and ``weighting.png`` (the error against k per scheme; the other problems
in a second panel).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from statistics import median

from adjointsim.files import pyplot, save_figure, write_text
from adjointsim.runner import Study, register_study

from ..pinn import EPOCHS, NEEDS_POISSON, PinnConfig, train_run
from ..weighting import RULES
from .pinn import median_range, rel_l2_of

#: the authors' schedule (Poisson 30,001 epochs) cut to the first 3000, where the lr is 1e-3
REDUCED = 3000
TINY_NET = {"width": 8, "depth": 2, "collocation": 64, "edge_points": 8, "log_every": 5,
            "plot": False}
#: per size: Poisson's epochs per k, the other problems' epochs, schemes, seeds, overrides of
#: the authors' network and point sets
SIZES: dict[str, dict] = {
    "tiny": {"poisson": {1: 6}, "others": {}, "schemes": ("uniform", "inverse-dirichlet"),
             "seeds": 1, "net": TINY_NET},
    # k = 1, 3, 6 rather than 1..6: a cell took 40-58 s (median 43 s, ntk the slowest) on
    # one core of a shared 2-core machine, 25 minutes for the 33 cells; every scheme at
    # every k would take about 50
    "quick": {"poisson": {1: REDUCED, 3: REDUCED, 6: REDUCED}, "others": {},
              "schemes": RULES, "seeds": 1, "net": {}},
    "full": {"poisson": {**{k: REDUCED for k in range(1, 6)}, 6: EPOCHS["poisson"]},
             "others": {"sobolev": EPOCHS["sobolev"], "ks-inverse": EPOCHS["ks-inverse"]},
             "schemes": RULES, "seeds": 3, "net": {}},
}
METRICS = {"poisson": "relative L2 of u on the 100 x 100 grid",
           "sobolev": "relative L2 of f on the 100 x 100 grid",
           "ks-inverse": "relative error of (alpha, beta)"}
#: what every row holds besides its cell's keys
ROW_KEYS = {"rel_l2": float, "metric": str, "diverged": bool, "wall_s": float,
            "train_s": float}


def cells(size: str, seeds: int | None) -> list[dict]:
    """Seed-major, then Poisson by k, then the other problems: an interrupted study has every
    scheme at the first k's and seeds."""
    spec = SIZES[size]
    n = spec["seeds"] if seeds is None else seeds
    out = []
    for s in range(n):
        for k, epochs in spec["poisson"].items():
            out += [{"id": f"poisson-k{k}-{w}-s{s}", "problem": "poisson", "k": k,
                     "weighting": w, "seed": s, "epochs": epochs, **spec["net"]}
                    for w in spec["schemes"]]
        for problem, epochs in spec["others"].items():
            out += [{"id": f"{problem}-{w}-s{s}", "problem": problem, "weighting": w,
                     "seed": s, "epochs": epochs, **spec["net"]}
                    for w in spec["schemes"] if w not in NEEDS_POISSON]
    return out


def run_cell(cell: dict, run_dir: Path) -> dict:
    start = time.perf_counter()
    keys = {k: v for k, v in cell.items() if k not in ("id", "plot")}
    result = train_run(PinnConfig(**keys), Path(run_dir), resume=True, progress=False,
                       plot=cell.get("plot", True))
    row = {"rel_l2": result["rel_l2"], "metric": METRICS[cell["problem"]],
           "diverged": result["diverged"], "train_s": result["seconds"]}
    if cell["problem"] == "ks-inverse":
        c = result["coefficients"]
        err = math.hypot(c["alpha"] - 1.0, c["beta"] - 1.0) / math.sqrt(2.0)
        row.update(rel_l2=err if math.isfinite(err) else None, u_rel_l2=result["rel_l2"],
                   alpha=c["alpha"], beta=c["beta"])
    return {**row, "wall_s": time.perf_counter() - start}


def _column(row: dict) -> str:
    return f"k={row['k']}" if row["problem"] == "poisson" else row["problem"]


def _columns(rows: list[dict]) -> list[str]:
    ks = sorted({r["k"] for r in rows if r["problem"] == "poisson"})
    others = [p for p in METRICS if p != "poisson" and any(r["problem"] == p for r in rows)]
    return [f"k={k}" for k in ks] + others


def _schemes(rows: list[dict]) -> list[str]:
    return [w for w in RULES if any(r["weighting"] == w for r in rows)]


def _medians(rows: list[dict]) -> dict[tuple[str, str], float]:
    """The median error per (column, scheme) over seeds; inf where every seed diverged."""
    groups: dict[tuple[str, str], list[float]] = {}
    for r in rows:
        groups.setdefault((_column(r), r["weighting"]), []).append(rel_l2_of(r))
    return {key: median(v for v in errs if math.isfinite(v))
            if any(math.isfinite(v) for v in errs) else math.inf
            for key, errs in groups.items()}


def table(rows: list[dict]) -> str:
    """A Markdown table: median over seeds [min, max] per column (Poisson's k, then the other
    problems) and scheme, the best median per column in bold; then per column the schemes
    below inverse-Dirichlet."""
    cols, schemes, med = _columns(rows), _schemes(rows), _medians(rows)
    best = {c: min((v for (cc, _), v in med.items() if cc == c), default=math.inf)
            for c in cols}
    lines = ["| scheme | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for w in schemes:
        cells_ = []
        for c in cols:
            errs = [rel_l2_of(r) for r in rows if _column(r) == c and r["weighting"] == w]
            text = median_range(errs, count=False) if errs else "-"
            cells_.append(f"**{text}**" if errs and med[(c, w)] == best[c] < math.inf
                          else text)
        lines.append(f"| {w} | " + " | ".join(cells_) + " |")
    seeds = len({r["seed"] for r in rows})
    epochs = {c: sorted({r["epochs"] for r in rows if _column(r) == c}) for c in cols}
    notes = [f"Median over {seeds} seed{'s' * (seeds > 1)}"
             + (" [min, max]" if seeds > 1 else "") + "; epochs per column: "
             + ", ".join(f"{c}: {'/'.join(map(str, e))}" for c, e in epochs.items())
             + ". Measures: " + "; ".join(f"{p}: {m}" for p, m in METRICS.items()
                                          if any(r["problem"] == p for r in rows)) + "."]
    for c in cols:
        ref = med.get((c, "inverse-dirichlet"))
        if ref is None:
            continue
        below = [w for w in schemes if med.get((c, w), math.inf) < ref]
        notes.append(f"- {c}: below inverse-dirichlet ({ref:.2e}): "
                     + (", ".join(f"{w} ({med[(c, w)]:.2e})" for w in below) or "none"))
    return "\n".join(lines + [""] + notes)


#: one colour and marker per scheme, fixed so that plots of different runs compare
STYLE = {w: (f"C{i}" if i < 10 else "black", "os^vD<>ph*X"[i % 11])
         for i, w in enumerate(RULES)}


def plot(rows: list[dict], path: Path) -> None:
    """Poisson's error against k, one line (median over seeds) and one marker per run per
    scheme, log y; the other problems, if any, in a second panel (one column each)."""
    others = [c for c in _columns(rows) if not c.startswith("k=")]
    fig, axes = pyplot().subplots(1, 1 + bool(others), figsize=(6 + 4 * bool(others), 4.5),
                                  squeeze=False)
    med = _medians(rows)
    ax = axes[0][0]
    poisson = [r for r in rows if r["problem"] == "poisson"]
    ks = sorted({r["k"] for r in poisson})
    for w in _schemes(poisson):
        color, marker = STYLE[w]
        mine = [r for r in poisson if r["weighting"] == w and math.isfinite(rel_l2_of(r))]
        ax.scatter([r["k"] for r in mine], [r["rel_l2"] for r in mine], color=color, s=10,
                   alpha=0.5, marker=marker)
        line = [(k, med[(f"k={k}", w)]) for k in ks
                if math.isfinite(med.get((f"k={k}", w), math.inf))]
        if line:
            ax.plot(*zip(*line), color=color, marker=marker, ms=4, label=w)
    if poisson:
        ax.set(yscale="log", xticks=ks, xlabel="wavenumber k (ω = kπ)",
               ylabel="relative L2 error of u", title="Poisson PINN")
        ax.legend(fontsize=7, ncol=2)
    if others:
        ax = axes[0][1]
        schemes = _schemes(rows)
        for j, w in enumerate(schemes):
            color, marker = STYLE[w]
            # side by side within a problem's column, so that equal errors stay visible
            shift = 0.6 * (j / max(len(schemes) - 1, 1) - 0.5)
            pts = [(i + shift, rel_l2_of(r)) for i, c in enumerate(others) for r in rows
                   if _column(r) == c and r["weighting"] == w and math.isfinite(rel_l2_of(r))]
            if pts:
                ax.scatter(*zip(*pts), color=color, marker=marker, s=16, label=w)
        ax.set(yscale="log", xticks=range(len(others)), xlim=(-0.5, len(others) - 0.5),
               xticklabels=[f"{c}\n({METRICS[c]})" for c in others], xlabel="problem",
               ylabel="error (see tick label)", title="Sobolev and KS inverse")
        ax.tick_params(axis="x", labelsize=7)
        ax.legend(fontsize=7, ncol=2)
    save_figure(fig, path, dpi=120)


def report(rows: list[dict], out: Path) -> str:
    text = table(rows)
    write_text(Path(out) / "table.md", text + "\n")
    plot(rows, Path(out) / "weighting.png")
    return text


register_study(Study(name="weighting", sizes=tuple(SIZES), cells=cells, run_cell=run_cell,
                     report=report, row_keys=ROW_KEYS))
