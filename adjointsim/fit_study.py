"""The ``fit-params`` study: coefficients from solver trajectories with :func:`adjointsim.fit.fit`
(``adjointsim study fit-params``).

Two problems of :func:`adjointsim.fit_demos.demo_problem`, each fitted from a perturbed start with
L-BFGS-B (tol 1e-30, the initial state known):

* ``ks-params``: ``ks1d-etdrk4``, N = 64, L = 22, Δt = 0.1, a smooth random initial state (seed
  1234), observations every 5 steps up to step 100 (t = 10); α = anti_diffusion,
  β = hyper_diffusion (β bounded below by 0.05);
* ``burgers-nu``: the PBDL Burgers scene (N = 128 on [−1, 1], u0 = −sin(πx), Δt = 1/32 in 8
  Rusanov sub-steps), every step up to 32; ν bounded to [0, 0.01].

One cell is one fit: noise-free, and with Gaussian noise of σ = 1 % of the trajectory's standard
deviation on every observed value for each noise seed. The report writes ``fit-params.md`` (the
median relative error over the seeds per problem, parameter and noise), ``fit-params.json`` (one
row per fitted parameter) and ``fit-params.png`` into the study directory. Seconds are wall
seconds of the fit alone (numba compiles in an untimed fit of one iteration first).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .runner import Study, register_study

PROBLEMS = ("ks-params", "burgers-nu")
NOISES = (0.0, 0.01)
TOL = 1e-30
#: per size: problems, noise seeds, the optimiser's iteration limit
SIZES = {
    "tiny": {"problems": PROBLEMS, "seeds": 1, "maxiter": 500},
    "full": {"problems": PROBLEMS, "seeds": 5, "maxiter": 500},
}
#: the keys of a table row (fit-params.json), one per fitted parameter
ROW_KEYS = ("problem", "noise", "seed", "parameter", "true", "start", "fitted", "rel_error",
            "misfit", "iterations", "seconds")


def cells(size: str, seeds: int | None) -> list[dict]:
    """One fit per problem, noise and noise seed (one seed for the noise-free fit)."""
    spec = SIZES[size]
    n = spec["seeds"] if seeds is None else seeds
    return [{"id": f"{p}-noise{noise:g}-s{s}", "problem": p, "noise": noise, "seed": s,
             "maxiter": spec["maxiter"], "tol": TOL}
            for p in spec["problems"] for noise in NOISES for s in range(1 if noise == 0 else n)]


def run_cell(cell: dict, run_dir: Path) -> dict:
    """One fit; per fitted parameter its true, starting and fitted value and relative error."""
    from .fit import fit
    from .fit_demos import demo_problem, demo_scene

    prob = demo_problem(cell["problem"], cell["noise"], cell["seed"])
    scene = demo_scene(cell["problem"])[0]
    obs = {int(k): s for k, s in zip(prob["steps"], prob["states"])}
    given = {"wrt": prob["wrt"], "u0": prob["u0"], "params": prob["params"],
             "bounds": prob.get("bounds")}
    fit(scene, obs, maxiter=1, **given)
    t = time.perf_counter()
    r = fit(scene, obs, tol=cell["tol"], maxiter=cell["maxiter"], **given)
    seconds = time.perf_counter() - t
    true = {k: prob["truth_params"][k] for k in r.wrt}
    return {"true": true, "start": {k: prob["params"][k] for k in r.wrt},
            "fitted": {k: r.params[k] for k in r.wrt},
            "rel_error": {k: abs(r.params[k] - true[k]) / abs(true[k]) for k in r.wrt},
            "misfit": r.misfit, "iterations": r.iterations, "seconds": seconds}


def table_rows(rows: list[dict]) -> list[dict]:
    """The cells' rows as one row per fitted parameter (the keys :data:`ROW_KEYS`)."""
    return [{"problem": r["problem"], "noise": r["noise"], "seed": r["seed"], "parameter": k,
             "true": r["true"][k], "start": r["start"][k], "fitted": r["fitted"][k],
             "rel_error": r["rel_error"][k], "misfit": r["misfit"],
             "iterations": r["iterations"], "seconds": r["seconds"]}
            for r in rows for k in r["fitted"]]


def _groups(rows: list[dict]) -> dict[tuple, list[dict]]:
    groups: dict[tuple, list[dict]] = {}
    for r in table_rows(rows):
        groups.setdefault((r["problem"], r["parameter"], r["noise"]), []).append(r)
    return groups


def table(rows: list[dict]) -> str:
    """Markdown: per problem, parameter and noise the median relative error over the seeds."""
    lines = ["| problem | parameter | true | start | noise | rel. error (median over seeds) "
             "| spread (min – max) | iterations | seconds |", "|---" * 9 + "|"]
    for (demo, k, noise), rs in _groups(rows).items():
        errs = np.array([r["rel_error"] for r in rs])
        spread = "–" if len(rs) == 1 else f"{errs.min():.2g} – {errs.max():.2g}"
        lines.append(f"| {demo} | {k} | {rs[0]['true']:.6g} | {rs[0]['start']:.6g} | "
                     f"{noise:.0%} ({len(rs)} seed{'s' * (len(rs) > 1)}) | "
                     f"{np.median(errs):.2g} | {spread} | "
                     f"{int(np.median([r['iterations'] for r in rs]))} | "
                     f"{np.median([r['seconds'] for r in rs]):.2f} |")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    """The relative error of every fitted parameter, one marker per seed, side by side per
    noise level."""
    from .files import pyplot, save_figure

    fig, ax = pyplot().subplots(figsize=(6, 3.8))
    flat = table_rows(rows)
    names = list(dict.fromkeys(f"{r['problem']}\n{r['parameter']}" for r in flat))
    noises = sorted({r["noise"] for r in flat})
    for j, noise in enumerate(noises):
        mine = [r for r in flat if r["noise"] == noise]
        shift = 0.3 * (j - (len(noises) - 1) / 2)
        ax.plot([names.index(f"{r['problem']}\n{r['parameter']}") + shift for r in mine],
                [max(r["rel_error"], 1e-17) for r in mine], "o", color=f"C{j % 10}",
                alpha=0.7, label=f"{noise:.0%} noise")
    ax.set_xticks(range(len(names)), names, fontsize=8)
    ax.set(yscale="log", ylabel="relative error of the fitted value",
           title="parameter estimation with the adjoints (L-BFGS-B)")
    ax.legend(fontsize=7)
    save_figure(fig, path, dpi=120)


def report(rows: list[dict], out: Path) -> str:
    """``OUT/fit-params.md``, ``OUT/fit-params.json`` and ``OUT/fit-params.png``."""
    from .files import write_json, write_text

    text = table(rows)
    seeds = len({r["seed"] for r in rows if r["noise"]})
    about = (
        "Parameter estimation with `adjointsim.fit` (L-BFGS-B, tol 1e-30, the initial state "
        "known), from `adjointsim study fit-params`.\n\n"
        "* ks-params: `ks1d-etdrk4`, N = 64, L = 22, Δt = 0.1, a smooth random initial state "
        "(seed 1234), observations every 5 steps up to step 100 (t = 10); α = anti_diffusion, "
        "β = hyper_diffusion (β bounded below by 0.05).\n"
        "* burgers-nu: the PBDL Burgers scene (N = 128 on [−1, 1], u0 = −sin(πx), Δt = 1/32 in 8 "
        "Rusanov sub-steps), every step up to 32; ν bounded to [0, 0.01].\n"
        "* Noise: Gaussian, σ = 1% of the trajectory's standard deviation, on every observed "
        f"value; {seeds} noise seed{'s' * (seeds != 1)}.\n\n")
    write_text(out / "fit-params.md", about + text + "\n")
    write_json(out / "fit-params.json", table_rows(rows))
    plot(rows, out / "fit-params.png")
    return text


register_study(Study("fit-params", tuple(SIZES), cells, run_cell, report))
