"""Where each scheme stops being stable: the largest Δt at which a long rollout stays bounded,
found by bisection, against the limit the scheme states itself.

For every registered scheme that has a time step and a scene per grid size (``n``, default
coefficients), one cell of the ``stability`` study (:mod:`adjointsim.runner`) finds

- the **stated** limit: the largest Δt its constructor / ``check_params`` accepts (bisection on
  acceptance; none if it accepts every Δt up to the search cap);
- the **found** limit: the largest Δt at which ``steps`` steps from the scene's random state
  plus white noise of 10⁻³ of its size (so that every mode is excited) stay finite and below
  10⁴ × max(1, max|u₀|), with the scheme's own check switched off so that Δt beyond the stated
  limit can be run. Bracketing doubles Δt from the scene's default; bisection (geometric)
  stops at 2 % width (0.01 % for the stated limit).

Verdicts: ``ok`` (stated within −5 %/+100 % of found), ``stated too large`` (the scheme accepts
a Δt that blows up), ``conservative`` (stable up to more than twice the stated limit),
``missing`` (no stated limit, but a finite one found), ``unconditional`` (neither found up to
the cap). Each scheme, grid and coefficient set is one cell of ``adjointsim study stability``
(``--jobs``/``--cluster`` spread them): ``--size full`` sweeps every such scheme on the grids
above, ``quick`` every scheme on two small grids, ``tiny`` two schemes (one without a grid).
"""

from __future__ import annotations

import inspect
import json
import math
import textwrap
from functools import partial
from pathlib import Path

import numpy as np

from . import registry
from .files import log_axis
from .runner import Study, register_study
from .stepper import Stepper

#: per size: the schemes (None: every one with a time step), grid sizes of 1D and 2D scenes,
#: rollout length
SIZES = {
    "tiny": {"schemes": ("advection1d-upwind", "oscillators-rk4"), "1d": (16, 32), "2d": (16,),
             "steps": 200},
    "quick": {"schemes": None, "1d": (16, 32), "2d": (16,), "steps": 200},
    "full": {"schemes": None, "1d": (32, 64, 128, 256), "2d": (16, 32, 64), "steps": 1000},
}
CAP = 2.0**14  # the search stops at this multiple of the scene's default Δt
GROWTH = 1e4
WIDTH = 1.02


def schemes() -> list[str]:
    """Registered schemes that take a time step ``dt``."""
    return [n for n in registry.names()
            if "dt" in inspect.signature(registry.get(n).__init__).parameters]


def _grids(name: str, size: str) -> tuple[int | None, ...]:
    cls = registry.get(name)
    if "n" not in inspect.signature(cls.__init__).parameters or cls.name in ("oscillators-rk4",):
        return (None,)
    return SIZES[size]["2d" if "2d" in name else "1d"]


def _coefficients(name: str) -> list[dict]:
    """The default coefficients, and ν ×10 where the scene has a viscosity/diffusivity ν."""
    nu = inspect.signature(registry.get(name).__init__).parameters.get("nu")
    if nu is None or not isinstance(nu.default, float) or nu.default <= 0:
        return [{}]
    return [{}, {"nu": 10 * nu.default}]


def cells(size: str, seeds: int | None) -> list[dict]:
    """One cell per scheme of the size, coefficient set and grid (no seeds: deterministic)."""
    spec = SIZES[size]
    return [{"id": "-".join([name, *([f"n{n}"] if n else []),
                             *(f"{k}{v:g}" for k, v in coef.items())]),
             "scheme": name, "n": n, "coefficients": coef, "steps": spec["steps"]}
            for name in (spec["schemes"] or schemes()) for coef in _coefficients(name)
            for n in _grids(name, size)]


def _make(cls: type[Stepper], n: int | None, dt: float | None, coef: dict) -> Stepper:
    kwargs = {**coef, **({} if n is None else {"n": n})}
    return cls(**kwargs) if dt is None else cls(**kwargs, dt=dt)


def _accepts(cls: type[Stepper], n: int | None, coef: dict, dt: float) -> bool:
    try:
        _make(cls, n, dt, coef)
    except ValueError:
        return False
    return True


def _bounded(cls: type[Stepper], n: int | None, coef: dict, dt: float, steps: int) -> bool:
    unchecked = type(cls.__name__, (cls,), {"check_params": lambda self, p: None})
    try:
        scene = _make(unchecked, n, dt, coef)
    except ValueError:
        return False  # refused for another reason than the stability check
    rng = np.random.default_rng(0)
    u = scene.random_state(rng)
    u = u + 1e-3 * max(float(np.abs(u).max()), 1e-12) * rng.standard_normal(u.shape)
    bound = GROWTH * max(1.0, float(np.abs(u).max()))
    done = 0
    with np.errstate(all="ignore"):
        while done < steps:
            chunk = min(100, steps - done)
            try:
                u = scene.rollout(u, chunk)
            except (FloatingPointError, ValueError):  # non-finite state
                return False
            if not np.abs(u).max() <= bound:
                return False
            done += chunk
    return True


def _largest(ok, start: float, cap: float, width: float = WIDTH) -> tuple[float | None, int]:
    """The largest Δt with ``ok(Δt)`` (monotone assumed), from ``start`` within ×/÷ ``cap``;
    None if ok up to ``start·cap``. Returns (Δt, evaluations)."""
    evals = 1
    lo = hi = start
    if ok(start):
        while True:
            hi = lo * 2
            evals += 1
            if hi > start * cap:
                return None, evals
            if not ok(hi):
                break
            lo = hi
    else:
        while True:
            lo = hi / 2
            evals += 1
            if lo < start / cap:
                return 0.0, evals
            if ok(lo):
                break
            hi = lo
    while hi / lo > width:
        mid = math.sqrt(lo * hi)
        evals += 1
        lo, hi = (mid, hi) if ok(mid) else (lo, mid)
    return lo, evals


def run_cell(cell: dict, run_dir: Path) -> dict:
    """Stated and found limits of one scheme on one grid."""
    cls = registry.get(cell["scheme"])
    n, coef = cell["n"], cell.get("coefficients", {})
    default = _make(cls, n, None, coef)
    base = default.dt
    stated, _ = _largest(partial(_accepts, cls, n, coef), base, CAP, width=1.0001)  # no rollouts
    found, evals = _largest(partial(_bounded, cls, n, coef, steps=cell["steps"]), base, CAP)
    return {"default_dt": base, "params": {k: float(v) for k, v in default.params.items()},
            "stated": stated, "found": found, "rollouts": evals, "verdict": verdict(stated, found)}


def verdict(stated: float | None, found: float | None) -> str:
    if found is None:
        return "unconditional" if stated is None else "conservative"
    if stated is None:
        return "missing"
    if stated > found * 1.05:
        return "stated too large"
    if found > 2 * stated:
        return "conservative"
    return "ok"


def _fmt(x: float | None) -> str:
    return "none" if x is None else f"{x:.4g}"


def table(rows: list[dict]) -> str:
    """Markdown table: one row per scheme, coefficients and grid."""
    lines = ["| scheme | n | parameters | default Δt | stated limit | largest stable Δt | "
             "found/stated | verdict |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ratio = (f"{r['found'] / r['stated']:.2f}" if r["found"] is not None and r["stated"]
                 else "–")
        params = ", ".join(f"{k}={v:g}" for k, v in r["params"].items())
        found = (f"≥ {r['default_dt'] * CAP:.3g} (cap)" if r["found"] is None
                 else _fmt(r["found"]))
        note = (", **default Δt unstable**" if r["found"] is not None
                and r["found"] < r["default_dt"] else "")
        lines.append(f"| {r['scheme']} | {r['n'] or '–'} | {params} | {r['default_dt']:.4g} | "
                     f"{_fmt(r['stated'])} | {found} | {ratio} | {r['verdict']}{note} |")
    return "\n".join(lines)


def _family(scheme: str) -> str:
    return scheme.rsplit("-", 1)[0] if "etdrk" in scheme else scheme.split("-")[0]


def report(rows: list[dict], out: Path) -> str:
    """``OUT/stability.md`` (table) and ``OUT/stability.png``: per scheme family, the largest
    stable Δt against the grid size (markers; triangles: stable up to the search cap) and the
    stated limit (dashed); the schemes without a grid size (none, or an ``n`` that counts
    something else, as the oscillators') side by side in one more panel."""
    from adjointsim.files import pyplot, save_figure, write_text

    text = table(rows)
    write_text(out / "stability.md", text + "\n")
    plt = pyplot()

    families: dict[str, list[dict]] = {}
    gridless: list[dict] = []
    for r in rows:
        if r["n"]:
            families.setdefault(_family(r["scheme"]), []).append(r)
        else:
            gridless.append(r)
    panels = len(families) + bool(gridless)
    if not panels:
        return text
    cols = min(4, panels)
    nrows = -(-panels // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.2 * cols, 3.3 * nrows), squeeze=False)
    for ax, (family, rs) in zip(axes.flat, sorted(families.items())):
        lines = sorted({(r["scheme"], json.dumps(r.get("coefficients", {}))) for r in rs})
        for k, (scheme, coef) in enumerate(lines):
            pts = sorted((r["n"], r["found"], r["stated"], r["default_dt"] * CAP) for r in rs
                         if r["scheme"] == scheme
                         and json.dumps(r.get("coefficients", {})) == coef)
            label = " ".join([scheme.removeprefix(family).strip("-") or scheme,
                              *(f"{key}={v:g}" for key, v in json.loads(coef).items())])
            ns = np.array([p[0] for p in pts], dtype=float)
            found = np.array([np.nan if p[1] is None else p[1] for p in pts])
            capped = np.array([p[3] if p[1] is None else np.nan for p in pts])
            stated = np.array([np.nan if p[2] is None else p[2] for p in pts])
            color = f"C{k % 10}"
            ax.plot(ns, found, "o-", color=color, label=label, ms=4)
            ax.plot(ns, capped, "^", color=color, ms=6)
            ax.plot(ns, stated, "--", color=color, lw=1)
        ax.set(xscale="log", title=family, xlabel="grid size n", ylabel="largest stable Δt")
        log_axis(ax)
        grid = sorted({r["n"] for r in rs})
        ax.set_xticks(grid, [str(g) for g in grid])
        ax.xaxis.set_minor_locator(plt.NullLocator())
        ax.legend(fontsize=6)
    if gridless:
        _plot_gridless(axes.flat[len(families)], gridless)
    for ax in axes.flat[panels:]:
        ax.axis("off")
    # wrapped to the figure's width (about 0.55 em a character): one panel is 4.2 inches
    chars = int(fig.get_figwidth() * 72 / (0.55 * 10))
    fig.suptitle(textwrap.fill("largest Δt with a bounded rollout (circles; triangles: bounded "
                               "up to the search cap), stated limit (dashed)", chars),
                 fontsize=10)
    save_figure(fig, out / "stability.png", dpi=100)
    return text


def _plot_gridless(ax, rows: list[dict]) -> None:
    """One column per scheme and coefficient set: found (circle; triangle at the cap) and
    stated (bar) limits."""
    rows = sorted(rows, key=lambda r: (r["scheme"], json.dumps(r.get("coefficients", {}))))
    for k, r in enumerate(rows):
        color = f"C{k % 10}"
        if r["found"] is None:
            ax.plot(k, r["default_dt"] * CAP, "^", color=color, ms=6)
        else:
            ax.plot(k, r["found"], "o", color=color, ms=5)
        if r["stated"] is not None:
            ax.plot(k, r["stated"], "_", color=color, ms=16, mew=1.5)
    names = [" ".join([r["scheme"], *(f"{key}={v:g}" for key, v in
                                      r.get("coefficients", {}).items())]) for r in rows]
    ax.set_xticks(range(len(rows)), names, rotation=20 if len(rows) > 2 else 0, ha="right"
                  if len(rows) > 2 else "center", fontsize=8)
    ax.set_xlim(-0.6, len(rows) - 0.4)
    ax.set(title="without a grid size", xlabel="scheme (stated limit: bar)",
           ylabel="largest stable Δt")
    log_axis(ax)


register_study(Study("stability", tuple(SIZES), cells, run_cell, report))
