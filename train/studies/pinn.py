"""The ``pinn-poisson`` study: the multi-scale Poisson PINN over k × weighting × seeds
(``adjointsim study pinn-poisson [--quick]``), against the authors' reported errors.

Each cell is one ``adjointsim pinn poisson`` run (:func:`train.pinn.train_run`) in its own
directory; its row holds ``k``, ``weighting``, ``seed``, ``epochs`` and the final ``rel_l2``
on the 100 × 100 grid. The report tables the median over seeds [min, max] per k and weighting
next to the authors' figure (30,001 epochs, mean of 5 seeds), says per k whether ID is below
uniform and max/avg, and plots the error against k.
"""

from __future__ import annotations

import math
from pathlib import Path
from statistics import median

import torch

from adjointsim.runner import Study, register_study

from ..atomic import atomic_path, write_text
from ..pinn import REPORTED, PinnConfig, train_run

WEIGHTINGS = ("uniform", "inverse-dirichlet", "max-avg", "fixed")
#: per size: wavenumbers, weightings, seeds, epochs, network and point-set overrides
SIZES = {
    "tiny": {"k": (1, 2), "weightings": ("uniform", "inverse-dirichlet"), "seeds": 1,
             "epochs": 10, "net": {"width": 8, "depth": 2, "collocation": 64,
                                   "edge_points": 8, "log_every": 5, "plot": False}},
    "quick": {"k": (2, 4, 6), "weightings": WEIGHTINGS[:3], "seeds": 1, "epochs": 1000,
              "net": {}},
    # what fits in about an hour on a shared 2-core machine (one process)
    "reduced": {"k": (2, 4, 6), "weightings": WEIGHTINGS[:3], "seeds": 3, "epochs": 1000,
                "net": {}},
    "full": {"k": (1, 2, 3, 4, 5, 6), "weightings": WEIGHTINGS, "seeds": 5, "epochs": 30001,
             "net": {}},
}
SHORT = {"uniform": "uni", "inverse-dirichlet": "id", "max-avg": "maxavg", "fixed": "fixed"}


def cells(size: str, seeds: int | None) -> list[dict]:
    spec = SIZES[size]
    n = spec["seeds"] if seeds is None else seeds
    # Seed-major: an interrupted study has every (k, weighting) at some seed first.
    return [
        {"id": f"k{k}-{SHORT[w]}-s{s}", "k": k, "weighting": w, "seed": s,
         "epochs": spec["epochs"], **spec["net"]}
        for s in range(n) for k in spec["k"] for w in spec["weightings"]
    ]


def run_cell(cell: dict, run_dir: Path) -> dict:
    torch.set_num_threads(1)
    keys = {k: v for k, v in cell.items() if k not in ("id", "plot")}
    cfg = PinnConfig(problem="poisson", **keys)
    result = train_run(cfg, Path(run_dir), resume=True, progress=False,
                       plot=cell.get("plot", True))
    return {"rel_l2": result["rel_l2"], "diverged": result["diverged"],
            "seconds": result["seconds"]}


def _err(row: dict) -> float:
    return math.inf if row.get("rel_l2") is None else row["rel_l2"]


def _fmt(values: list[float]) -> str:
    finite = [v for v in values if math.isfinite(v)]
    if not finite:
        return "diverged"
    text = f"{median(finite):.2e}"
    if len(finite) > 1:
        text += f" [{min(finite):.1e}, {max(finite):.1e}]"
    return text + f" n={len(values)}" + (f" ({len(values) - len(finite)} div.)"
                                         if len(finite) < len(values) else "")


def table(rows: list[dict]) -> str:
    """Median relative L2 over seeds [min, max] per k and weighting, the authors' figure in
    parentheses, and a verdict per k."""
    ks = sorted({r["k"] for r in rows})
    ws = [w for w in WEIGHTINGS if any(r["weighting"] == w for r in rows)]
    epochs = sorted({r["epochs"] for r in rows})
    head = ["k"] + ws
    body = []
    for k in ks:
        line = [str(k)]
        for w in ws:
            errs = [_err(r) for r in rows if r["k"] == k and r["weighting"] == w]
            line.append(f"{_fmt(errs)} ({REPORTED[w][k]:.1e})" if errs else "-")
        body.append(line)
    widths = [max(len(x[i]) for x in [head, *body]) for i in range(len(head))]
    lines = [f"Poisson PINN, relative L2 on the 100 x 100 grid: median [min, max] over n seeds "
             f"after {', '.join(map(str, epochs))} epochs (authors, 30,001 epochs, mean of 5 "
             "seeds, in parentheses)"]
    lines += ["  ".join(c.ljust(wd) for c, wd in zip(x, widths)) for x in [head, *body]]
    lines += [v for k in ks if (v := _verdict(rows, k))]
    return "\n".join(lines)


def _verdict(rows: list[dict], k: int) -> str:
    by = {(r["weighting"], r["seed"]): _err(r) for r in rows if r["k"] == k}
    parts = []
    for other in ("uniform", "max-avg"):
        pairs = [(v, by[(other, s)]) for (w, s), v in by.items()
                 if w == "inverse-dirichlet" and (other, s) in by]
        if pairs:
            wins = sum(i <= o for i, o in pairs)
            parts.append(f"ID at or below {other} in {wins}/{len(pairs)} seeds")
    return f"  k={k}: " + "; ".join(parts) if parts else ""


def plot(rows: list[dict], path: Path) -> None:
    """Relative L2 against k: one marker per run, the median per weighting as a line, the
    authors' figures dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"uniform": "tab:red", "inverse-dirichlet": "tab:blue", "max-avg": "tab:orange",
              "fixed": "tab:green"}
    fig, ax = plt.subplots(figsize=(5.5, 4))
    ks = sorted({r["k"] for r in rows})
    for w, c in colors.items():
        mine = [r for r in rows if r["weighting"] == w and math.isfinite(_err(r))]
        if not mine:
            continue
        ax.scatter([r["k"] for r in mine], [r["rel_l2"] for r in mine], color=c, s=12,
                   alpha=0.6)
        med = [(k, median(_err(r) for r in mine if r["k"] == k)) for k in ks
               if any(r["k"] == k for r in mine)]
        ax.plot(*zip(*med), color=c, label=w)
        ax.plot(ks, [REPORTED[w][k] for k in ks], color=c, ls="--", lw=0.8)
    ax.set(yscale="log", xticks=ks, xlabel="k (ω = kπ)", ylabel="relative L2 error",
           title="Poisson PINN (dashed: authors, 30k epochs)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)


def report(rows: list[dict], out: Path) -> str:
    text = table(rows)
    write_text(Path(out) / "table.txt", text + "\n")
    plot(rows, Path(out) / "pinn-poisson.png")
    return text


register_study(Study(name="pinn-poisson", sizes=tuple(SIZES), cells=cells, run_cell=run_cell,
                     report=report))
