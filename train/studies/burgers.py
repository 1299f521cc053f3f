"""PBDL's Burgers problems, differentiable physics (DP) against a physics-informed network
(:mod:`adjointsim.train.burgers_pinn`), as two studies. Each cell is one run in its own
directory: DP a fit run (``adjointsim fit --demo``), the PINN a training run
(:class:`adjointsim.train.burgers_pinn.BurgersPinnRun`); an interrupted study continues them.

* ``burgers-dp-pinn`` (``adjointsim study burgers-dp-pinn``): the reconstruction of u(·, 0)
  from the state at t = 0.5. Cells: DP (L-BFGS-B from zero) at each iteration limit of the size,
  and the PINN (uniform weights, Adam) for the size's budget of CPU seconds, per seed. The report
  compares the PINN's last logged state within DP's run time and at its budget with DP and the
  book's figure: ``fit-burgers.md``, ``fit-burgers.json`` and ``fit-burgers.png`` (the book's
  side-by-side plots and the misfit over run time). The size ``id-residual`` is the PINN under
  inverse-Dirichlet weighting with the residual as the reference term, the choice that drives
  it to u ≈ 0.
* ``burgers-nu-dp-pinn`` (``adjointsim study burgers-nu-dp-pinn``): the viscosity from every
  step of the PBDL trajectory (:func:`adjointsim.fit_demos.demo_problem` ``burgers-nu``, ν from
  2 ν_true), noise-free and with 1 % noise: DP against the PINN inverse problem (ν learned with
  the network); ``fit-params-pinn.md``, ``fit-params-pinn.json`` and ``fit-params-pinn.png``.

Seconds are CPU seconds of one thread (DP without numba's compilation).
"""

from __future__ import annotations

import math
from pathlib import Path

from adjointsim.files import pyplot, save_figure, write_json, write_text
from adjointsim.runner import Study, register_study

from ..burgers_pinn import BOOK_DP, BurgersPinnConfig, run_dp, run_pinn
from ..threads import use_threads

#: a PINN small enough for a smoke test of the whole pipeline
_TINY_PINN = {"width": 8, "depth": 2, "collocation": 64, "boundary_points": 8, "epochs": 20,
              "log_every": 5}
#: per size: DP iteration limits, the PINN's budget of CPU seconds and its config keys
SIZES = {
    "tiny": {"dp": (3, 10), "budget": 5.0, "pinn": _TINY_PINN},
    "quick": {"dp": (30, 500), "budget": 60.0, "pinn": {}},
    "full": {"dp": (30, 500), "budget": 120.0, "pinn": {}},
    "id-residual": {"dp": (30, 500), "budget": 300.0,
                    "pinn": {"weighting": "inverse-dirichlet", "reference": "residual"}},
}
NU_SIZES = {
    "tiny": {"budget": 5.0, "pinn": _TINY_PINN},
    "full": {"budget": 60.0, "pinn": {}},
}
NOISES = (0.0, 0.01)


# ----------------------------------------------------------------------------- reconstruction
def cells(size: str, seeds: int | None) -> list[dict]:
    """DP per iteration limit (deterministic: no seeds), the PINN per seed."""
    spec = SIZES[size]
    n = 1 if seeds is None else seeds
    return ([{"id": f"dp-{m}", "solver": "dp", "maxiter": m} for m in spec["dp"]]
            + [{"id": f"pinn-s{s}", "solver": "pinn", "seed": s, "budget": spec["budget"],
                **spec["pinn"]} for s in range(n)])


def _pinn(cell: dict, run_dir: Path, demo: str) -> dict:
    """The cell's PINN run: its config and result, with its history."""
    keys = {k: v for k, v in cell.items() if k not in ("id", "solver", "budget")}
    cfg = BurgersPinnConfig(demo=demo, seconds=cell["budget"], **keys)
    return {"pinn_config": cfg.as_dict(), **run_pinn(cfg, run_dir)}


def run_cell(cell: dict, run_dir: Path) -> dict:
    """DP: misfit, MSE of u(·, 0), seconds, its history and curves. PINN: its config, history
    and curves."""
    use_threads(1)
    if cell["solver"] == "dp":
        d = run_dp("burgers", run_dir, maxiter=cell["maxiter"], tol=0.0)
        data = d["data"]
        return {"misfit": d["misfit"], "u0_mse": d["u0_mse"],
                "seconds": d["history"][-1]["cpu_seconds"], "iterations": d["iterations"],
                "history": d["history"], "x": data["x"], "observed": data["observed"][0],
                "true_u0": data["u0"], "predicted": d["predicted"][0],
                "fitted_u0": d["fitted_u0"]}
    p = _pinn(cell, run_dir, "burgers")
    return {k: p[k] for k in ("pinn_config", "history", "x", "predicted", "fitted_u0")}


def _split(rows: list[dict]) -> tuple[list[dict], list[dict]]:
    dp = sorted((r for r in rows if r["solver"] == "dp"), key=lambda r: r["maxiter"])
    return dp, [r for r in rows if r["solver"] == "pinn"]


def table_rows(rows: list[dict]) -> list[dict]:
    """DP per iteration limit; the PINN at DP's run time (the last logged state within it) and
    at its budget; the book's DP."""
    dp, pinn = _split(rows)
    out = [{"method": f"DP, L-BFGS-B, {d['maxiter']} iterations", "misfit": d["misfit"],
            "u0_mse": d["u0_mse"], "seconds": d["seconds"]} for d in dp]
    for p in pinn:
        history, weighting = p["history"], p["pinn_config"]["weighting"]
        seed = f", seed {p['seed']}" if len(pinn) > 1 else ""
        for budget in sorted({*(d["seconds"] for d in dp[-1:]), history[-1]["seconds"]}):
            h = ([h for h in history if h["seconds"] <= budget] or history[:1])[-1]
            out.append({"method": f"PINN, Adam, {weighting} weights, {h['epoch']} epochs{seed}",
                        "misfit": h["misfit"], "u0_mse": h["u0_mse"], "seconds": h["seconds"]})
    out.append({"method": "book's DP (phiflow/TF, 50 gradient steps)",
                "misfit": BOOK_DP["misfit"], "u0_mse": math.nan, "seconds": BOOK_DP["seconds"]})
    return out


def table(rows: list[dict]) -> str:
    lines = ["| method | misfit (MSE) at t = 0.5 | MSE of u(·, 0) vs −sin(πx) | seconds |",
             "|---|---|---|---|"]
    for r in table_rows(rows):
        u0 = "–" if math.isnan(r["u0_mse"]) else f"{r['u0_mse']:.3g}"
        lines.append(f"| {r['method']} | {r['misfit']:.3g} | {u0} | {r['seconds']:.3g} |")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    """The book's side-by-side plots (t = 0.5, t = 0) and the misfit over run time: DP with
    the most iterations, the first PINN."""
    dp, pinn = _split(rows)
    fig, ax = pyplot().subplots(1, 3, figsize=(14, 3.6))
    if dp:
        d = dp[-1]
        ax[0].plot(d["x"], d["observed"], "k.", ms=3, label="observed")
        ax[1].plot(d["x"], d["true_u0"], "k--", label="true −sin(πx)")
    for r, label, color in ((dp[-1:], "DP", "C0"), (pinn[:1], "PINN", "C1")):
        for row in r:
            ax[0].plot(row["x"], row["predicted"], f"{color}-", label=label)
            ax[1].plot(row["x"], row["fitted_u0"], f"{color}-", label=label)
    for d in dp[-1:]:
        ax[2].loglog([max(h["cpu_seconds"], 1e-4) for h in d["history"]],
                     [h["misfit"] for h in d["history"]], "C0-", label="DP")
    for p in pinn[:1]:
        ax[2].loglog([h["seconds"] for h in p["history"]], [h["misfit"] for h in p["history"]],
                     "C1-", label="PINN")
    ax[0].set(title="t = 0.5 (the observations)", xlabel="x")
    ax[1].set(title="t = 0 (reconstructed)", xlabel="x")
    ax[2].axhline(BOOK_DP["misfit"], color="gray", ls=":", label="book's DP after 132 s")
    ax[2].set(xscale="log", yscale="log", title="misfit at t = 0.5 over run time",
              xlabel="CPU seconds (one thread)", ylabel="MSE")
    for a in ax:
        a.legend(fontsize=7)
    save_figure(fig, path, dpi=100)


def report(rows: list[dict], out: Path) -> str:
    """``OUT/fit-burgers.md``, ``OUT/fit-burgers.json`` (the table's rows, the first PINN's
    config and history, the history of DP with the most iterations) and
    ``OUT/fit-burgers.png``."""
    dp, pinn = _split(rows)
    text = table(rows)
    budget = ", ".join(sorted({f"{p['budget']:g}" for p in pinn})) or "–"
    about = ("PBDL's Burgers reconstruction (observations at t = 0.5 only): `adjointsim study "
             f"burgers-dp-pinn`, the PINN's budget {budget} CPU seconds. CPU seconds of one "
             "thread (DP without numba's compilation); the PINN rows are its last logged state "
             f"(every {pinn[0]['pinn_config']['log_every'] if pinn else '–'} epochs) within "
             "DP's run time and at its budget. Plots: fit-burgers.png.\n\n")
    write_text(out / "fit-burgers.md", about + text + "\n")
    write_json(out / "fit-burgers.json", {
        "rows": table_rows(rows),
        "pinn_config": pinn[0]["pinn_config"] if pinn else None,
        "pinn_history": pinn[0]["history"] if pinn else [],
        "dp_history": dp[-1]["history"] if dp else []})
    plot(rows, out / "fit-burgers.png")
    return text


register_study(Study("burgers-dp-pinn", tuple(SIZES), cells, run_cell, report))


# ----------------------------------------------------------------------------- viscosity
def nu_cells(size: str, seeds: int | None) -> list[dict]:
    """Per noise and seed (of the noise and the PINN): DP, then the PINN."""
    spec = NU_SIZES[size]
    n = 1 if seeds is None else seeds
    return [cell for noise in NOISES for s in range(n) for cell in (
        {"id": f"dp-noise{noise:g}-s{s}", "solver": "dp", "noise": noise, "seed": s},
        {"id": f"pinn-noise{noise:g}-s{s}", "solver": "pinn", "noise": noise, "seed": s,
         "budget": spec["budget"], **spec["pinn"]})]


def nu_run_cell(cell: dict, run_dir: Path) -> dict:
    """The fitted ν, its relative error and the CPU seconds; the PINN's ν over its training."""
    use_threads(1)
    if cell["solver"] == "dp":
        d = run_dp("burgers-nu", run_dir, cell["noise"], cell["seed"], tol=1e-30)
        nu = d["params"]["nu"]
        true_nu = d["data"]["nu"]
        return {"method": "DP (adjointsim.fit)", "nu": nu, "rel_error": abs(nu / true_nu - 1),
                "true_nu": true_nu, "seconds": d["history"][-1]["cpu_seconds"]}
    p = _pinn(cell, run_dir, "burgers-nu")
    history = p["history"]
    h = history[-1]
    return {"method": f"PINN, ν learned ({h['epoch']} epochs)", "nu": h["nu"],
            "rel_error": abs(h["nu"] / p["true_nu"] - 1), "true_nu": p["true_nu"],
            "seconds": h["seconds"],
            "history": [{"seconds": g["seconds"], "nu": g["nu"]} for g in history]}


NU_ROW_KEYS = ("method", "noise", "nu", "rel_error", "seconds")


def nu_table(rows: list[dict]) -> str:
    lines = ["The viscosity ν = 0.01/π of the PBDL Burgers trajectory (all 32 steps observed, "
             "N = 128), from ν = 0.02/π: `adjointsim study burgers-nu-dp-pinn` (CPU seconds, "
             "one thread).", "",
             "| method | noise | fitted ν | rel. error | seconds |", "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['method']} | {r['noise']:.0%} | {r['nu']:.8g} | "
                     f"{r['rel_error']:.2g} | {r['seconds']:.3g} |")
    return "\n".join(lines)


def nu_plot(rows: list[dict], path: Path) -> None:
    """ν over CPU seconds: the PINN's training (lines), DP's fit (markers), the truth."""
    fig, ax = pyplot().subplots(figsize=(6, 3.8))
    noises = sorted({r["noise"] for r in rows})
    for r in rows:
        color = f"C{noises.index(r['noise']) % 10}"
        label = f"{'PINN' if r['solver'] == 'pinn' else 'DP'}, {r['noise']:.0%} noise"
        if r["solver"] == "pinn":
            ax.plot([h["seconds"] for h in r["history"]], [h["nu"] for h in r["history"]],
                    "-", color=color, label=label)
        else:
            ax.plot([max(r["seconds"], 1e-4)], [r["nu"]], "o", color=color, label=label)
    ax.axhline(rows[0]["true_nu"], color="k", ls="--", lw=0.8, label="true ν")
    ax.set(xscale="log", yscale="log", xlabel="CPU seconds (one thread)", ylabel="ν",
           title="Burgers viscosity: DP against the PINN inverse problem")
    ax.legend(fontsize=7)
    save_figure(fig, path, dpi=120)


def nu_report(rows: list[dict], out: Path) -> str:
    """``OUT/fit-params-pinn.md``, ``OUT/fit-params-pinn.json`` (one row per cell, the keys
    :data:`NU_ROW_KEYS`) and ``OUT/fit-params-pinn.png``."""
    text = nu_table(rows)
    write_text(out / "fit-params-pinn.md", text + "\n")
    write_json(out / "fit-params-pinn.json", [{k: r[k] for k in NU_ROW_KEYS} for r in rows])
    nu_plot(rows, out / "fit-params-pinn.png")
    return text


register_study(Study("burgers-nu-dp-pinn", tuple(NU_SIZES), nu_cells, nu_run_cell, nu_report))
