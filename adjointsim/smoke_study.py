"""The ``smoke`` study: the physics-based deep learning book's "Differentiable Fluid Simulations"
example with the hand-written adjoint of ``incompressible2d-sl`` (``adjointsim study smoke``).

The scene is the book's: a closed box of 32 × 40 cells of side 1 with no-slip walls, no
viscosity, Δt = 1, smoke fed in every step by a disc of radius 3 at an inflow location (0.2 per
step inside it) and lifted by Boussinesq buoyancy (0.5); after n = 20 steps the smoke of the
inflow at (16, 5) is the target. For each other inflow location of the book ((12, 4), (13, 6),
(14, 5)) the initial velocity u_0 is optimised so that its smoke after n steps matches the
target, the smoke's start (empty) and source fixed:

    L(u_0) = ½ Σ_cells (ρ_n(u_0) − ρ*)²   (PhiFlow's ``l2_loss``),

with the gradient from one reverse sweep (:meth:`Stepper.vjp` with the cotangent ρ_n − ρ* on
the density, zero on the velocity). Two optimisers: the book's plain gradient descent (a fixed
step, the physics' ``rate``) and L-BFGS-B. Except at the size ``book``, the initial speed is
bounded by h/Δt (Courant number 1: the first step's backtraces cross at most one cell; neither
the solver nor the book's PhiFlow limits it, and the plume the steps make outruns it): gradient
descent clips to it, L-BFGS-B takes it as bounds.

The size ``book`` takes the book's own numbers where the other sizes keep ours (:data:`BOOK`):
1/3 per step, buoyancy 1, MacCormack advection, free-slip walls, the step's own source lifting
the flow, gradient descent at the book's rate of 1e-3 for its 80 iterations, no bound on u_0;
its report prints the book's losses (:data:`BOOK_LOSSES`) beside ours, summed over the plumes
as the book sums them.

Each cell is one optimisation; its row holds the loss after every iteration with the wall
seconds since the start (numba compiles in an untimed gradient first) and the iterations run
(``iterations_run``: L-BFGS-B stops before the cell's ``iterations`` once its line search finds
no lower point). The report writes ``smoke.md`` (the table), ``smoke.json`` (the rows),
``loss.png`` (loss against iteration and wall time) and ``fields.png`` (per location: the smoke
reached from rest, the target, the smoke reached from the optimised u_0, and the optimised
u_0's speed).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from .runner import Study, register_study

#: the book's inflow locations (cell units): the last one's smoke after n steps is the target
LOCATIONS = ((12.0, 4.0), (13.0, 6.0), (14.0, 5.0), (16.0, 5.0))
OPTIMISERS = ("gd", "lbfgs")
#: the smoke source's disc radius (cells of the book's 32 × 40 grid)
RADIUS = 3.0
#: the scene and optimiser of the sizes tiny, quick and full: the smoke per step inside the
#: disc, the buoyancy, the advection, the side kind of all four walls; ``lift``: whether a
#: step's own source lifts the flow in that step (the solver's buoyancy reads the smoke
#: advected, before the step's source); gradient descent's step (velocity per unit of the
#: loss's gradient); ``bounded``: whether |u_0| is kept within h/Δt
STUDY = {"source": 0.2, "buoyancy": 0.5, "advection": "semi-lagrangian", "walls": "wall",
         "lift": False, "rate": 0.1, "bounded": True}
#: the book's (diffphys-code-ns.ipynb in tum-pbs/pbdl-book at commit 370ee58d,
#: https://physicsbaseddeeplearning.org/diffphys-code-ns.html): INFLOW = 1/3 × the disc per
#: step, the buoyancy force the smoke itself, advect.mac_cormack for the smoke (our MacCormack
#: covers the velocity too, where the book's is semi-Lagrangian), the step's INFLOW in that
#: step's buoyancy, LR = 1e-3 with no bound. Its walls are PhiFlow's extrapolation.ZERO: the
#: ghost value of the tangential velocity is zero, halfway between no-slip (−u) and free slip
#: (+u); free slip, by a small margin, brings our rollout from rest closer to PhiFlow 2.2's.
BOOK = {"source": 1.0 / 3.0, "buoyancy": 1.0, "advection": "maccormack", "walls": "slip",
        "lift": True, "rate": 1e-3, "bounded": False}
#: the book's summed loss over its plumes as its notebook prints it, by optimisation step, each
#: evaluated before that step's update (the source of BOOK, the output of its cell 7)
BOOK_LOSSES = {0: 298.286163, 1: 291.454376, 2: 276.057831, 9: 233.706482, 19: 232.652145,
               29: 178.186951, 39: 176.523254, 49: 169.360931, 59: 167.578674, 69: 175.005310,
               79: 169.943680}
#: per size: the grid (cells across, up), the steps, the locations optimised, the iterations
#: and the physics (STUDY or BOOK)
SIZES: dict[str, dict[str, Any]] = {
    # the book's scene at half the resolution and half the steps, for tests
    "tiny": {"nx": 16, "ny": 20, "steps": 10, "locations": 1, "iterations": 5, **STUDY},
    "quick": {"nx": 32, "ny": 40, "steps": 20, "locations": 3, "iterations": 100, **STUDY},
    "full": {"nx": 32, "ny": 40, "steps": 20, "locations": 3, "iterations": 500, **STUDY},
    # the book's grid, steps and the 80 iterations of its notebook
    "book": {"nx": 32, "ny": 40, "steps": 20, "locations": 3, "iterations": 80, **BOOK},
}


def scene(nx: int, ny: int, physics: dict[str, Any] = STUDY) -> Any:
    """The closed box of ``nx`` × ``ny`` cells of side 32/nx (the book's at 32 × 40) with the
    buoyancy, advection and walls of ``physics`` (:data:`STUDY` or :data:`BOOK`)."""
    from . import get

    return get("incompressible2d-sl")(nx=nx, ny=ny, length=32.0, dt=32.0 / nx, nu=0.0,
                                      boundaries=" ".join([physics["walls"]] * 4), density=True,
                                      buoyancy=physics["buoyancy"],
                                      advection=physics["advection"])


def sources(flow: Any, location: tuple[float, float], steps: int,
            physics: dict[str, Any] = STUDY) -> np.ndarray:
    """The controls of every step (steps, 1, 3, nx + 1, ny + 1): the smoke source, the
    physics' ``source`` per step in the disc of radius RADIUS at ``location`` (in the book's
    32 × 40 units); with ``lift``, the force by which that step's buoyancy reads the smoke with
    the step's source added (the book's order): the buoyancy times the source's amount
    averaged onto the v faces between two cells."""
    from .solvers.incompressible2d import cylinder

    scale = flow.nx / 32.0
    disc = cylinder(flow.nx, flow.ny, (location[0] * scale, location[1] * scale), RADIUS * scale)
    amount = physics["source"] * disc
    c = np.zeros((steps, 1, *flow.control_shape))
    c[:, 0, 2, : flow.nx, : flow.ny] = amount / flow.dt
    if physics["lift"]:
        c[:, 0, 1, : flow.nx, 1: flow.ny] = physics["buoyancy"] * 0.5 * (amount[:, :-1]
                                                                         + amount[:, 1:])
    return c


def cells(size: str, seeds: int | None) -> list[dict]:
    """One optimisation per optimiser and inflow location (``seeds`` does not apply: the
    problem is deterministic)."""
    spec = SIZES[size]
    return [{"id": f"{opt}-loc{k}", "optimiser": opt, "location": list(LOCATIONS[k]), **spec}
            for k in range(spec["locations"]) for opt in OPTIMISERS]


def objective(flow: Any, steps: int, ctrl: np.ndarray, target: np.ndarray
              ) -> tuple[Callable[[np.ndarray], tuple[float, np.ndarray]], np.ndarray, dict]:
    """The loss ½ Σ (ρ_n − ρ*)² of the free velocity entries z of u_0 (the smoke starting
    empty), with its gradient from one reverse sweep; the mask of those entries in the state
    (u at the vertical faces, v at the horizontal ones); and a dict the function keeps its
    last point and loss in (``z``, ``loss``)."""
    nx, ny = flow.nx, flow.ny
    mask = np.zeros(flow.state_shape(1), dtype=bool)
    mask[0, 0, :, :ny] = True
    mask[0, 1, :nx, :] = True
    last: dict[str, Any] = {}

    def loss_and_grad(z: np.ndarray) -> tuple[float, np.ndarray]:
        u0 = np.zeros(mask.shape)
        u0[mask] = z
        traj = flow.rollout(u0, steps, ctrl, keep="all")
        cot = np.zeros_like(u0)
        cot[0, 2] = traj[-1, 0, 2] - target
        g = flow.vjp(u0, steps, {steps: cot}, ctrl, trajectory=traj)
        last.update(z=z.copy(), loss=0.5 * float(np.sum(cot * cot)))
        return last["loss"], g.state[mask]

    return loss_and_grad, mask, last


def run_cell(cell: dict, run_dir: Path) -> dict:
    """One optimisation of u_0; the loss after each iteration and the seconds it took."""
    from scipy.optimize import minimize

    flow = scene(cell["nx"], cell["ny"], cell)
    n, nx, ny = cell["steps"], flow.nx, flow.ny
    rest = np.zeros(flow.state_shape(1))
    target = flow.rollout(rest, n, sources(flow, LOCATIONS[-1], n, cell))[0, 2]
    ctrl = sources(flow, tuple(cell["location"]), n, cell)
    loss_and_grad, mask, last = objective(flow, n, ctrl, target)
    top = flow.h / flow.dt if cell["bounded"] else np.inf  # Courant number 1

    z = np.zeros(int(mask.sum()))
    loss_and_grad(z)  # compile the kernels (cached afterwards) outside the timing
    history: list[dict] = []
    start = time.perf_counter()

    def record(loss: float) -> None:
        history.append({"iteration": len(history), "loss": loss,
                        "seconds": time.perf_counter() - start})

    loss, grad = loss_and_grad(z)
    record(loss)
    if cell["optimiser"] == "gd":
        for _ in range(cell["iterations"]):
            z = np.clip(z - cell["rate"] * grad, -top, top)
            loss, grad = loss_and_grad(z)
            record(loss)
    else:
        best = {"z": z}

        def keep(zk: np.ndarray) -> None:
            # the accepted point is the last one evaluated, except after a backtracking search
            best["z"] = zk.copy()
            record(last["loss"] if np.array_equal(last["z"], zk) else loss_and_grad(zk)[0])

        minimize(loss_and_grad, z, jac=True, method="L-BFGS-B",
                 bounds=[(-top, top)] * z.size if cell["bounded"] else None,
                 callback=keep, options={"maxiter": cell["iterations"], "gtol": 0.0,
                                         "ftol": 0.0})
        z = best["z"]
    u0 = rest.copy()
    u0[mask] = z
    reached = flow.rollout(u0, n, ctrl)[0, 2]
    return {"history": history, "initial_loss": history[0]["loss"],
            "final_loss": history[-1]["loss"], "iterations_run": len(history) - 1,
            "seconds": history[-1]["seconds"], "reduction": history[-1]["loss"]
            / history[0]["loss"], "fields": {
                "from_rest": flow.rollout(rest, n, ctrl)[0, 2, :nx, :ny].tolist(),
                "target": target[:nx, :ny].tolist(), "reached": reached[:nx, :ny].tolist(),
                "speed": _speed(u0[0], nx, ny).tolist()}}


def _speed(u: np.ndarray, nx: int, ny: int) -> np.ndarray:
    """|u| at the cell centres of a staggered velocity (2, nx + 1, ny + 1)."""
    uc = 0.5 * (u[0, :-1, :ny] + u[0, 1:, :ny])
    vc = 0.5 * (u[1, :nx, :-1] + u[1, :nx, 1:])
    return np.hypot(uc, vc)


def table(rows: list[dict]) -> str:
    """Markdown: per optimiser and location the loss at the start and the end, and the time."""
    lines = ["| optimiser | inflow location | loss from rest | final loss | final / start "
             "| iterations | seconds | seconds per iteration |", "|---" * 8 + "|"]
    for r in sorted(rows, key=lambda r: (r["optimiser"], r["location"])):
        its = max(1, r["iterations_run"])
        lines.append(f"| {r['optimiser']} | ({r['location'][0]:g}, {r['location'][1]:g}) | "
                     f"{r['initial_loss']:.4g} | {r['final_loss']:.4g} | {r['reduction']:.3g} | "
                     f"{r['iterations_run']} | {r['seconds']:.2f} | {r['seconds'] / its:.3f} |")
    return "\n".join(lines)


def plot(rows: list[dict], out: Path) -> None:
    """``loss.png``: loss against iteration and against wall seconds, one line per cell (at
    the book's scene also the plumes' summed loss beside the book's); ``fields.png``: per
    location the smoke from rest, the target, the smoke reached from the optimised u_0 (by the
    optimiser that ended lower) and that u_0's speed."""
    from .files import pyplot, save_figure

    plt = pyplot()
    book = is_book(rows)
    fig, axes = plt.subplots(1, 3 if book else 2, figsize=(16.5 if book else 11, 3.8))
    styles = {"gd": "-", "lbfgs": "--"}
    names = {"gd": "gradient descent", "lbfgs": "L-BFGS-B"}
    locations = sorted({tuple(r["location"]) for r in rows})
    for r in sorted(rows, key=lambda r: r["id"]):
        h = r["history"]
        colour = f"C{locations.index(tuple(r['location'])) % 10}"
        label = f"{names[r['optimiser']]}, inflow ({r['location'][0]:g}, {r['location'][1]:g})"
        for ax, x in zip(axes, ("iteration", "seconds")):
            ax.plot([p[x] for p in h], [p["loss"] for p in h], styles[r["optimiser"]],
                    color=colour, label=label)
    for ax, x in zip(axes, ("iteration", "wall seconds")):
        ax.set(yscale="log", xlabel=x, ylabel="loss ½ Σ (ρ_n − ρ*)²")
    axes[0].legend(fontsize=7)
    axes[0].set_title("smoke to the target: loss per iteration")
    axes[1].set_title("loss against wall time (one core)")
    if book:
        for opt in OPTIMISERS:
            total = summed(rows, opt)
            axes[2].plot(list(total), list(total.values()), styles[opt], color="C0",
                         label=f"ours, {names[opt]}")
        axes[2].plot(list(BOOK_LOSSES), list(BOOK_LOSSES.values()), "o", color="C3",
                     label="the book's notebook (PhiFlow)")
        axes[2].set(yscale="log", xlabel="iteration", ylabel="loss summed over the plumes")
        axes[2].set_title("beside the book: the three plumes' summed loss")
        axes[2].legend(fontsize=7)
    save_figure(fig, out / "loss.png", dpi=120)

    shown = {}
    for r in sorted(rows, key=lambda r: r["final_loss"]):
        shown.setdefault(tuple(r["location"]), r)
    fig, axes = plt.subplots(len(shown), 4, figsize=(14, 3.8 * len(shown)), squeeze=False)
    for row_axes, (loc, r) in zip(axes, sorted(shown.items())):
        f = r["fields"]
        lim = max(np.max(f["from_rest"]), np.max(f["target"]), np.max(f["reached"]))
        at = f"({loc[0]:g}, {loc[1]:g})"
        panels = ((f["from_rest"], f"inflow {at}, u_0 = 0: step {r['steps']}", "density ρ", lim),
                  (f["target"], "target ρ*: inflow (16, 5)", "density ρ", lim),
                  (f["reached"], f"inflow {at}, optimised u_0", "density ρ", lim),
                  (f["speed"], f"optimised u_0 ({names[r['optimiser']]})",
                   "|u_0| (cells per step)", None))
        for ax, (data, title, label, vmax) in zip(row_axes, panels):
            im = ax.imshow(np.asarray(data).T, origin="lower", cmap="viridis", vmin=0,
                           vmax=vmax)
            ax.set(title=title, xlabel="cell x", ylabel="cell y")
            ax.title.set_fontsize(9)
            fig.colorbar(im, ax=ax, label=label)
    save_figure(fig, out / "fields.png", dpi=110)


def summed(rows: list[dict], optimiser: str) -> dict[int, float]:
    """The loss summed over the plumes of ``optimiser``'s rows, by iteration (the book's loss:
    its batch of plumes optimised side by side), up to the longest run of ``rows``; a run that
    stopped early (L-BFGS-B, once its line search finds no lower point) stays at its last
    point."""
    histories = [[p["loss"] for p in r["history"]] for r in rows
                 if r["optimiser"] == optimiser]
    if not histories:
        return {}
    return {k: sum(h[min(k, len(h) - 1)] for h in histories)
            for k in range(max(len(r["history"]) for r in rows))}


def is_book(rows: list[dict]) -> bool:
    """Whether ``rows`` ran the book's scene (the physics :data:`BOOK` on its 32 × 40 grid, 20
    steps, all three plumes): only then are their summed losses the book's to compare."""
    return all(all(r[k] == v for k, v in BOOK.items())
               and (r["nx"], r["ny"], r["steps"], r["locations"]) == (32, 40, 20, 3)
               for r in rows)


def beside_book(rows: list[dict]) -> str:
    """Markdown: the book's printed losses (:data:`BOOK_LOSSES`) and ours summed over the
    plumes at the same iterations, each before that iteration's update, and the last of them
    over the first."""
    ours = {opt: summed(rows, opt) for opt in OPTIMISERS}

    def cell(values: dict[int, float], k: int) -> str:
        return f"{values[k]:.1f}" if k in values else "–"

    lines = ["| iteration | book (its notebook) | ours, gradient descent | ours, L-BFGS-B |",
             "|---" * 4 + "|"]
    lines += [f"| {k} | {v:.1f} | {cell(ours['gd'], k)} | {cell(ours['lbfgs'], k)} |"
              for k, v in BOOK_LOSSES.items()]
    last = max(BOOK_LOSSES)

    def ratio(values: dict[int, float]) -> str:
        return f"{values[last] / values[0]:.3g}" if last in values else "–"

    lines.append(f"| {last} / 0 | {BOOK_LOSSES[last] / BOOK_LOSSES[0]:.3g} | "
                 f"{ratio(ours['gd'])} | {ratio(ours['lbfgs'])} |")
    stopped = [f"({r['location'][0]:g}, {r['location'][1]:g}) after {r['iterations_run']}"
               for r in sorted(rows, key=lambda r: r["location"])
               if r["iterations_run"] < r["iterations"]]
    if stopped:
        lines.append(f"\nL-BFGS-B stopped early, its line search finding no lower point: "
                     f"{', '.join(stopped)} iterations; a stopped plume keeps its last loss "
                     "in the sum.")
    return "\n".join(lines)


def report(rows: list[dict], out: Path) -> str:
    """``OUT/smoke.md``, ``OUT/smoke.json``, ``OUT/loss.png`` and ``OUT/fields.png``; at the
    book's scene, with the book's losses beside ours."""
    from .files import write_json, write_text

    r = rows[0]
    text = table(rows)
    if is_book(rows):
        text += ("\n\nBeside the book: the loss summed over the three plumes (the book's "
                 "loss), by iteration, before that iteration's update\n\n" + beside_book(rows))
    bound = "both keep |u_0| ≤ h/Δt" if r["bounded"] else "neither bounds |u_0|"
    lift = ", the step's own source lifting the flow in that step" if r["lift"] else ""
    about = (
        "The smoke of the physics-based deep learning book's \"Differentiable Fluid "
        "Simulations\", reached by optimising the initial velocity with the adjoint of "
        f"`incompressible2d-sl` (`adjointsim study smoke`): a closed box of {r['nx']} × "
        f"{r['ny']} cells with {r['walls']} walls, no viscosity, {r['steps']} steps, "
        f"{r['advection']} advection, smoke {r['source']:.4g} per step in a disc of radius "
        f"{RADIUS:g} (book units), buoyancy {r['buoyancy']:g}{lift}; the target is the smoke "
        f"of the inflow at (16, 5). Gradient descent steps {r['rate']:g} × the gradient; "
        f"L-BFGS-B is scipy's; {bound}. Seconds are wall seconds on one core.\n\n")
    write_text(out / "smoke.md", about + text + "\n")
    write_json(out / "smoke.json", [{k: v for k, v in r.items() if k != "fields"}
                                    for r in rows])
    plot(rows, out)
    return text + f"\nplots: {out / 'loss.png'}, {out / 'fields.png'}"


#: what every finished row holds besides its cell's keys
ROW_KEYS = {"history": list, "initial_loss": float, "final_loss": float, "iterations_run": int,
            "seconds": float, "reduction": float, "fields": dict}

register_study(Study("smoke", tuple(SIZES), cells, run_cell, report, row_keys=ROW_KEYS))
