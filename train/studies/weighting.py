"""The ``weighting`` study: every loss-weighting scheme of
:data:`adjointsim.train.weighting.SCHEMES` on the PINN problems of :mod:`adjointsim.train.pinns`
and on a differentiable-physics loss, the guidance task of :mod:`adjointsim.train.control`
(``adjointsim study weighting --quick``).

A cell is one problem × scheme × seed (× wavenumber k for Poisson): one
:func:`adjointsim.train.pinn.train_cell` or, for ``guidance``, one
:func:`adjointsim.train.control.train_controller` (gradient flow R, r_c = 1, its terms
``tracking`` and ``control``), in its own directory (resumed from its checkpoint when
interrupted). A problem's cells take the schemes it offers: ``epsilon-optimal`` (analytic
weights) and ``ntk`` (per-sample residuals) exist for Poisson only.

Each row holds ``problem``, ``weighting``, ``seed``, ``epochs``, ``k`` (Poisson only) and:

* ``rel_l2``: the problem's accuracy measure, named in ``metric``: for Poisson the relative L2
  error of u on the 100 × 100 grid; for Sobolev the relative L2 error of f on the 100 × 100
  grid; for ks-inverse the relative error of the learned coefficients,
  ‖(α, β) − (1, 1)‖ / ‖(1, 1)‖ (the relative L2 error of u over the trajectory is kept as
  ``u_rel_l2``, the data loss at the end of each phase as ``data_by_phase``); for guidance the
  final test tracking loss, the mean over steps of mean_e |x_e|² on the test states (the
  whole test loss and its control term are kept as ``test_loss`` and ``control``); null when
  the run diverged;
* ``wall_s``: the wall-clock seconds of the cell's last attempt (training, evaluation and its
  plots; a resumed cell counts only the part it ran), and ``train_s``, the training time over
  every attempt;
* ``diverged``.

The report writes ``table.md``, one table per problem (median over seeds [min, max] per
scheme, and per k for Poisson; the best median per column in bold, and per column the schemes
whose median is below inverse-Dirichlet's), and one plot per problem: ``weighting.png``
(Poisson: the error against k per scheme) and ``weighting-<problem>.png`` (each seed's error
per scheme).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from statistics import median

from adjointsim import engine
from adjointsim.files import pyplot, save_figure, write_text
from adjointsim.runner import Study, register_study, runs_show_progress

from ..control import ControlConfig, train_controller
from ..pinn import PinnConfig, train_cell
from ..pinns import PROBLEMS
from ..weighting import GENERIC, RULES
from .pinn import median_range, rel_l2_of

#: the authors' schedule (Poisson 30,001 epochs) cut to the first 3000, where the lr is 1e-3
REDUCED = 3000
TINY_NET = {"width": 8, "depth": 2, "collocation": 64, "edge_points": 8, "log_every": 5,
            "plot": False}
#: per size: Poisson's epochs per k, the other problems' epochs, schemes, seeds (Poisson's
#: and the other problems'), overrides of the authors' network and point sets, and the
#: guidance task's training and test initial states
SIZES: dict[str, dict] = {
    "tiny": {"poisson": {1: 6}, "others": {"sobolev": 3, "ks-inverse": 3, "guidance": 1},
             "schemes": ("uniform", "inverse-dirichlet"), "seeds": (1, 1), "net": TINY_NET,
             "control": {"train": 8, "test": 8}},
    # k = 1, 3, 6 rather than 1..6: a cell took 40-58 s (median 43 s, ntk the slowest) on
    # one core of a shared 2-core machine, 25 minutes for the 33 cells; every scheme at
    # every k would take about 50. The other problems with reduced schedules (Sobolev 100
    # epochs, ks-inverse 200 per phase, guidance 20 epochs of 64 initial states), so that
    # their 3 seeds take about half an hour
    "quick": {"poisson": {1: REDUCED, 3: REDUCED, 6: REDUCED},
              "others": {"sobolev": 100, "ks-inverse": 600, "guidance": 20},
              "schemes": RULES, "seeds": (1, 3), "net": {},
              "control": {"train": 64, "test": 64}},
    # k = 6 on the authors' schedule, every scheme: about 7 minutes a cell here. 5 seeds, but
    # 3 (``few_seeds``) for the schemes whose median over 3 seeds is more than 2x
    # inverse-Dirichlet's; NTK, at 2.1x with seeds from 0.005 to 0.05, gets 5
    "k6": {"poisson": {6: PROBLEMS.get("poisson").epochs}, "others": {}, "schemes": RULES,
           "seeds": (5, 0), "few_seeds": (3, ("mgda", "gradnorm", "softadapt", "relobralo")),
           "net": {}, "control": {}},
    # the rest of the Poisson table: k = 1..5 on the reduced schedule, every scheme (about
    # 45 s a cell; --seeds 1 is the first sitting's 55 cells)
    "reduced": {"poisson": {k: REDUCED for k in range(1, 6)}, "others": {}, "schemes": RULES,
                "seeds": (3, 0), "net": {}, "control": {}},
    # Sobolev trained well past the quick size's 100 epochs (inverse-Dirichlet: relative L2
    # 0.74 at 200 epochs, 0.035 at 1400), about 6 minutes a cell here
    "sobolev": {"poisson": {}, "others": {"sobolev": 1500}, "schemes": RULES,
                "seeds": (0, 1), "net": {}, "control": {}},
    "full": {"poisson": {**{k: REDUCED for k in range(1, 6)}, 6: PROBLEMS.get("poisson").epochs},
             "others": {"sobolev": PROBLEMS.get("sobolev").epochs,
                        "ks-inverse": PROBLEMS.get("ks-inverse").epochs, "guidance": 100},
             "schemes": RULES, "seeds": (3, 3), "net": {},
             "control": {"train": 256, "test": 256}},
}
METRICS = {"poisson": "relative L2 of u on the 100 x 100 grid",
           "sobolev": "relative L2 of f on the 100 x 100 grid",
           "ks-inverse": "relative error of (alpha, beta)",
           "guidance": "final test tracking loss"}
TITLES = {"poisson": "Poisson PINN", "sobolev": "Sobolev training",
          "ks-inverse": "KS inverse problem (sequential)",
          "guidance": "guidance controller (differentiable physics)"}
#: what every row holds besides its cell's keys
ROW_KEYS = {"rel_l2": float, "metric": str, "diverged": bool, "wall_s": float,
            "train_s": float}


def cells(size: str, seeds: int | None) -> list[dict]:
    """Seed-major, then Poisson by k, then the other problems: an interrupted study has every
    scheme at the first k's and seeds. ``seeds`` replaces the size's seed counts, its
    per-scheme ``few_seeds`` included."""
    spec = SIZES[size]
    n_poisson, n_others = spec["seeds"] if seeds is None else (seeds, seeds)
    n_few, few = spec.get("few_seeds", (0, ())) if seeds is None else (0, ())
    out = []
    for s in range(max(n_poisson, n_others)):
        for k, epochs in spec["poisson"].items() if s < n_poisson else ():
            out += [{"id": f"poisson-k{k}-{w}-s{s}", "problem": "poisson", "k": k,
                     "weighting": w, "seed": s, "epochs": epochs, **spec["net"]}
                    for w in spec["schemes"] if s < n_few or w not in few]
        for problem, epochs in spec["others"].items() if s < n_others else ():
            extra = spec["control"] if problem == "guidance" else spec["net"]
            out += [{"id": f"{problem}-{w}-s{s}", "problem": problem, "weighting": w,
                     "seed": s, "epochs": epochs, **extra}
                    for w in spec["schemes"] if w in offered(problem)]
    return out


def offered(problem: str) -> tuple[str, ...]:
    """The schemes a problem offers: a PINN problem's own, the guidance task's the generic
    ones."""
    return GENERIC if problem == "guidance" else PROBLEMS.get(problem).schemes()


def run_cell(cell: dict, run_dir: Path) -> dict:
    start = time.perf_counter()
    keys = {k: v for k, v in cell.items() if k not in ("id", "plot", "problem")}
    if cell["problem"] == "guidance":
        cfg = ControlConfig(task="guidance", mode="R", out=str(run_dir), **keys)
        result = train_controller(cfg, resume=engine.started(run_dir),
                                  progress=runs_show_progress())
        track = result["test_terms"]["tracking"]
        return {"rel_l2": track if math.isfinite(track) else None,
                "metric": METRICS["guidance"], "diverged": not math.isfinite(track),
                "train_s": result["seconds"], "test_loss": result["test_loss"],
                "control": result["test_terms"]["control"], "weights": result["weights"],
                "wall_s": time.perf_counter() - start}
    keys["problem"] = cell["problem"]
    result = train_cell(PinnConfig(**keys), run_dir, cell.get("plot", True))
    row = {"rel_l2": result["rel_l2"], "metric": METRICS[cell["problem"]],
           "diverged": result["diverged"], "train_s": result["seconds"]}
    if cell["problem"] == "ks-inverse":
        c = result["coefficients"]
        err = math.hypot(c["alpha"] - 1.0, c["beta"] - 1.0) / math.sqrt(2.0)
        row.update(rel_l2=err if math.isfinite(err) else None, u_rel_l2=result["rel_l2"],
                   alpha=c["alpha"], beta=c["beta"],
                   data_by_phase=[p["data"] for p in result["phases"]])
    return {**row, "wall_s": time.perf_counter() - start}


def _column(row: dict) -> str:
    return f"k={row['k']}" if row["problem"] == "poisson" else row["problem"]


def _problems(rows: list[dict]) -> list[str]:
    return [p for p in METRICS if any(r["problem"] == p for r in rows)]


def _columns(rows: list[dict]) -> list[str]:
    ks = sorted({r["k"] for r in rows if r["problem"] == "poisson"})
    return [f"k={k}" for k in ks] + [p for p in _problems(rows) if p != "poisson"]


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


def _seeds(rows: list[dict]) -> str:
    """How many seeds each scheme has: "3 seeds", or "3-5 seeds" where they differ."""
    n = sorted({len({r["seed"] for r in rows if r["weighting"] == w}) for w in _schemes(rows)})
    return f"{n[0]}{f'-{n[-1]}' * (len(n) > 1)} seed{'s' * (n[-1] > 1)}"


def _problem_table(rows: list[dict]) -> list[str]:
    """One problem's rows as a Markdown table (median over seeds [min, max] per column and
    scheme, the best median per column in bold) and its notes."""
    cols, schemes, med = _columns(rows), _schemes(rows), _medians(rows)
    counts = {len({r["seed"] for r in rows if r["weighting"] == w}) for w in schemes}
    best = {c: min((v for (cc, _), v in med.items() if cc == c), default=math.inf)
            for c in cols}
    lines = ["| scheme | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for w in schemes:
        cells_ = []
        for c in cols:
            errs = [rel_l2_of(r) for r in rows if _column(r) == c and r["weighting"] == w]
            text = median_range(errs, count=len(counts) > 1) if errs else "-"
            cells_.append(f"**{text}**" if errs and med[(c, w)] == best[c] < math.inf
                          else text)
        lines.append(f"| {w} | " + " | ".join(cells_) + " |")
    epochs = {c: sorted({r["epochs"] for r in rows if _column(r) == c}) for c in cols}
    notes = [f"Median over {_seeds(rows)}" + (" [min, max]" if max(counts) > 1 else "")
             + (" (n: how many)" if len(counts) > 1 else "") + "; epochs: "
             + ", ".join(f"{c}: {'/'.join(map(str, e))}" for c, e in epochs.items()) + "."]
    for c in cols:
        ref = med.get((c, "inverse-dirichlet"))
        if ref is None:
            continue
        below = [w for w in schemes if med.get((c, w), math.inf) < ref]
        notes.append(f"- {c}: below inverse-dirichlet ({ref:.2e}): "
                     + (", ".join(f"{w} ({med[(c, w)]:.2e})" for w in below) or "none"))
    return lines + [""] + notes


def table(rows: list[dict]) -> str:
    """One Markdown table per problem, under a heading naming its accuracy measure: the
    median over seeds [min, max] per scheme (and per k for Poisson), the best median per
    column in bold; then per column the schemes below inverse-Dirichlet."""
    parts = []
    for p in _problems(rows):
        parts += [f"## {TITLES[p]}: {METRICS[p]}", "",
                  *_problem_table([r for r in rows if r["problem"] == p]), ""]
    return "\n".join(parts).rstrip()


#: one colour and marker per scheme, fixed so that plots of different runs compare
STYLE = {w: (f"C{i}" if i < 10 else "black", "os^vD<>ph*X"[i % 11])
         for i, w in enumerate(RULES)}


def plot_poisson(rows: list[dict], path: Path) -> None:
    """Poisson's error against k, one line (median over seeds) and one marker per run per
    scheme, log y."""
    fig, ax = pyplot().subplots(figsize=(6, 4.5))
    med = _medians(rows)
    ks = sorted({r["k"] for r in rows})
    for w in _schemes(rows):
        color, marker = STYLE[w]
        mine = [r for r in rows if r["weighting"] == w and math.isfinite(rel_l2_of(r))]
        ax.scatter([r["k"] for r in mine], [r["rel_l2"] for r in mine], color=color, s=10,
                   alpha=0.5, marker=marker)
        line = [(k, med[(f"k={k}", w)]) for k in ks
                if math.isfinite(med.get((f"k={k}", w), math.inf))]
        if line:
            ax.plot(*zip(*line), color=color, marker=marker, ms=4, label=w)
    ax.set(yscale="log", xticks=ks, xlabel="wavenumber k (ω = kπ)",
           ylabel=METRICS["poisson"], title=TITLES["poisson"])
    ax.legend(fontsize=7, ncol=2)
    save_figure(fig, path, dpi=120)


def plot_problem(rows: list[dict], path: Path) -> None:
    """One column's error per scheme (a problem, or Poisson at one k): each seed a marker,
    the median a bar, log y."""
    problem, column = rows[0]["problem"], _column(rows[0])
    schemes = _schemes(rows)
    fig, ax = pyplot().subplots(figsize=(1.0 + 0.6 * len(schemes), 4.0))
    med = _medians(rows)
    for i, w in enumerate(schemes):
        color, marker = STYLE[w]
        errs = [rel_l2_of(r) for r in rows if r["weighting"] == w]
        finite = [e for e in errs if math.isfinite(e)]
        ax.scatter([i] * len(finite), finite, color=color, marker=marker, s=18, zorder=3)
        if math.isfinite(med[(column, w)]):
            ax.hlines(med[(column, w)], i - 0.3, i + 0.3, color=color, lw=2)
    at = f", k = {rows[0]['k']}, {rows[0]['epochs']} epochs" if problem == "poisson" else ""
    ax.set(yscale="log", xticks=range(len(schemes)), xlim=(-0.5, len(schemes) - 0.5),
           ylabel=METRICS[problem],
           title=f"{TITLES[problem]}{at}, {_seeds(rows)} (bar: median)")
    ax.set_xticklabels(schemes, rotation=45, ha="right", fontsize=8)
    ax.title.set_fontsize(9)
    save_figure(fig, path, dpi=120)


def report(rows: list[dict], out: Path) -> str:
    text = table(rows)
    write_text(Path(out) / "table.md", text + "\n")
    for p in _problems(rows):
        mine = [r for r in rows if r["problem"] == p]
        if p == "poisson" and len({r["k"] for r in mine}) > 1:
            plot_poisson(mine, Path(out) / "weighting.png")
        elif p == "poisson":
            plot_problem(mine, Path(out) / "weighting.png")
        else:
            plot_problem(mine, Path(out) / f"weighting-{p}.png")
    return text


register_study(Study(name="weighting", sizes=tuple(SIZES), cells=cells, run_cell=run_cell,
                     report=report, row_keys=ROW_KEYS))


# ----------------------------------------------------------------------------- forgetting
#: the ``weighting-forgetting`` study's variants of training: ID as Maddu et al. give it (α = 0.5,
#: the problem's reference), without the moving average (α = 1), and with the largest spread
#: as the reference (the same ratios λ_k s_k, a different overall scale); uniform
VARIANTS = {"uniform": {"weighting": "uniform"},
            "id": {"weighting": "inverse-dirichlet"},
            "id-alpha1": {"weighting": "inverse-dirichlet", "alpha": 1.0},
            "id-max": {"weighting": "inverse-dirichlet", "reference": "max"}}
#: per size: each sequential problem's epochs (three equal phases) and overrides, seeds
FORGETTING: dict[str, dict] = {
    "tiny": {"problems": {"sequential": 6, "ks-inverse": 6}, "seeds": 1, "net": TINY_NET},
    # 500 epochs per phase, 1000 points for the synthetic problem: about 1 CPU-minute a cell
    "quick": {"problems": {"sequential": 1500, "ks-inverse": 1500}, "seeds": 1,
              "net": {"collocation": 1000}},
    "full": {"problems": {"sequential": PROBLEMS.get("sequential").epochs,
                          "ks-inverse": PROBLEMS.get("ks-inverse").epochs}, "seeds": 3,
             "net": {}},
}


def forgetting_cells(size: str, seeds: int | None) -> list[dict]:
    spec = FORGETTING[size]
    n = spec["seeds"] if seeds is None else seeds
    return [{"id": f"{problem}-{v}-s{s}", "problem": problem, "variant": v, "seed": s,
             "epochs": epochs, **VARIANTS[v], **spec["net"]}
            for s in range(n) for problem, epochs in spec["problems"].items()
            for v in VARIANTS]


def forgetting_cell(cell: dict, run_dir: Path) -> dict:
    start = time.perf_counter()
    keys = {k: v for k, v in cell.items() if k not in ("id", "plot", "variant")}
    result = train_cell(PinnConfig(**keys), run_dir, cell.get("plot", True))
    phases = result["phases"]
    terms = [t for t in phases[-1]["active"]]
    row = {"rel_l2": result["rel_l2"], "diverged": result["diverged"],
           "data_by_phase": [p["data"] for p in phases],
           "spreads_by_phase": [{t: p[f"spread/{t}"] for t in terms} for p in phases],
           "weights": result["weights"], "train_s": result["seconds"]}
    if cell["problem"] == "ks-inverse":
        c = result["coefficients"]
        row["coef_err"] = math.hypot(c["alpha"] - 1.0, c["beta"] - 1.0) / math.sqrt(2.0)
    return {**row, "wall_s": time.perf_counter() - start}


def forgetting_table(rows: list[dict]) -> str:
    """Per problem and variant (median over seeds): the data loss at the end of each phase,
    its growth over phases 2 and 3, and the spread of each joining term over data's when it
    joins (at the end of the phase before)."""
    lines = []
    for problem in dict.fromkeys(r["problem"] for r in rows):
        mine = [r for r in rows if r["problem"] == problem and not r["diverged"]]
        terms = list(mine[0]["spreads_by_phase"][0]) if mine else []
        head = ["variant", "data after 1", "after 2", "after 3", "2 / 1", "3 / 2",
                *(f"s_{t} / s_data at join" for t in terms[1:]), "rel. L2 of u"]
        if problem == "ks-inverse":
            head.append("coefficient error")
        lines += [f"## {problem}", "", "| " + " | ".join(head) + " |",
                  "|---" * len(head) + "|"]
        for v in VARIANTS:
            group = [r for r in mine if r["variant"] == v]
            if not group:
                continue

            def med(f, group=group):
                return f"{median(f(r) for r in group):.2e}"

            d = [lambda r, i=i: r["data_by_phase"][i] for i in range(3)]
            cols = [med(d[0]), med(d[1]), med(d[2]),
                    med(lambda r: r["data_by_phase"][1] / r["data_by_phase"][0]),
                    med(lambda r: r["data_by_phase"][2] / r["data_by_phase"][1])]
            cols += [med(lambda r, i=i, t=t: r["spreads_by_phase"][i - 1][t]
                         / r["spreads_by_phase"][i - 1]["data"])
                     for i, t in enumerate(terms[1:], start=1)]
            cols.append(med(lambda r: r["rel_l2"]))
            if problem == "ks-inverse":
                cols.append(med(lambda r: r["coef_err"]))
            lines.append(f"| {v} | " + " | ".join(cols) + " |")
        seeds = len({r["seed"] for r in mine})
        epochs = sorted({r["epochs"] for r in mine})
        lines += ["", f"Median over {seeds} seed{'s' * (seeds > 1)}; "
                  f"{'/'.join(map(str, epochs))} epochs in three equal phases.", ""]
    return "\n".join(lines).rstrip()


def forgetting_plot(rows: list[dict], path: Path) -> None:
    """The data loss at the end of each phase per variant (each seed a line), one panel per
    problem, log y."""
    problems = list(dict.fromkeys(r["problem"] for r in rows))
    fig, axes = pyplot().subplots(1, len(problems), figsize=(5 * len(problems), 4),
                                  squeeze=False)
    for ax, problem in zip(axes[0], problems):
        for i, v in enumerate(VARIANTS):
            group = [r for r in rows if r["problem"] == problem and r["variant"] == v
                     and not r["diverged"]]
            for j, r in enumerate(group):
                ax.plot(range(1, len(r["data_by_phase"]) + 1), r["data_by_phase"],
                        color=f"C{i}", marker="o", ms=4, label=v if j == 0 else None)
        terms = ("data", "+ grad (×1e-3)", "+ lap (×1e3)") if problem == "sequential" \
            else ("data", "+ periodic", "+ residual")
        ax.set(yscale="log", xticks=(1, 2, 3), xticklabels=terms, ylabel="data loss",
               title=f"{problem}: the data loss at the end of each phase")
        ax.title.set_fontsize(9)
        ax.legend(fontsize=8)
    save_figure(fig, path, dpi=120)


def forgetting_report(rows: list[dict], out: Path) -> str:
    text = forgetting_table(rows)
    write_text(Path(out) / "table.md", text + "\n")
    forgetting_plot(rows, Path(out) / "forgetting.png")
    return text


def forgetting_row_keys(cell: dict) -> dict[str, type]:
    """What a row holds besides its cell's keys: ks-inverse's also the coefficient error."""
    keys = {"rel_l2": float, "diverged": bool, "data_by_phase": list,
            "spreads_by_phase": list, "weights": dict, "wall_s": float, "train_s": float}
    return keys | {"coef_err": float} if cell["problem"] == "ks-inverse" else keys


register_study(Study(name="weighting-forgetting", sizes=tuple(FORGETTING),
                     cells=forgetting_cells, run_cell=forgetting_cell,
                     report=forgetting_report, row_keys=forgetting_row_keys))
