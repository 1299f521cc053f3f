"""``adjointsim fit``: fit a scene's rollout to observations stored in HDF5 (NumPy only).

Observation file layout (``--observations FILE.h5``)::

    /steps      int (K,)                      the observed step numbers k (0 = u_0)
    /states     float (K, B, C, *grid)        the observed states d_k
    /u0         float (B, C, *grid)           optional: the initial state (fixed), or the
                                              starting guess when it is fitted (default zero)
    /controls   float (n, B, *control_shape)  optional: the controls, fixed or starting guess
    /truth/u0, /truth/controls                optional: the true values, for error reports
    attrs: scene   the registry name (must match SCENE)
           config  JSON of the scene's constructor keywords, e.g. {"n": 128, "nu": 0.003}
           params  optional JSON {parameter: value}: fixed values or starting guesses
           truth_params  optional JSON {parameter: value}: the true values, for error reports
           n       optional rollout length (default: the last observed step)

A run directory (``--out``, default ``runs/fit-SCENE``) receives ``history.csv`` (per iteration:
misfit, regularisation, objective, gradient norm, evaluations, seconds), ``result.json``
(fitted parameters, misfit, errors against the truth when the file has it, optimiser message),
``fitted.h5`` (fitted u0, controls and the predicted observed states, same layout), and the plots
``fit.png`` (fitted against observed states) and ``history.png`` (misfit and gradient norm per
iteration). All files are written atomically; a finished run is not overwritten without
``--overwrite``. A fit is restarted, not resumed, after an interruption (it takes seconds).

``--demo burgers`` (PBDL's Burgers reconstruction), ``--demo ks-params`` (KS α, β) and
``--demo burgers-nu`` write their observation file into the run directory and fit it;
``--study params`` runs the parameter-estimation table (0% and 1% noise, 5 noise seeds).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from . import registry

if TYPE_CHECKING:  # scipy loads only when a fit runs, not with every `adjointsim` command
    from .fit import FitResult

DEMOS = ("burgers", "ks-params", "burgers-nu")
PBDL_T_OBS_STEP = 16


# ----------------------------------------------------------------------------- built-in problems
def pbdl_scene():
    """The PBDL Burgers scene (N = 128 on [−1, 1], ν = 0.01/π, Δt = 1/32) with a velocity bound
    of 2 for the stability check (5 sub-steps instead of :meth:`pbdl`'s 3), so that the
    optimiser's trial initial states up to |u| = 2 stay stable."""
    cls = registry.get("burgers1d-rusanov")
    return cls(n=128, length=2.0, start=-1.0, nu=0.01 / np.pi, dt=1 / 32, substeps=None, umax=2)


def demo_problem(name: str, noise: float = 0.0, seed: int = 0) -> dict[str, Any]:
    """A built-in problem as the contents of an observation file (see the module doc), with
    relative Gaussian noise ``noise`` · std(states) drawn from ``seed`` on the observations."""
    if name == "burgers":
        scene = pbdl_scene()
        config = {"n": 128, "length": 2.0, "start": -1.0, "nu": 0.01 / np.pi, "dt": 1 / 32,
                  "substeps": None, "umax": 2.0}
        u0 = scene.pbdl_state()
        traj = scene.rollout(u0, 32, keep="all")
        steps = [PBDL_T_OBS_STEP]
        out = {"wrt": "state", "truth_u0": u0, "u0": None, "params": {}}
    elif name == "ks-params":
        config = {"n": 64, "length": 22.0, "dt": 0.1}
        scene = registry.get("ks1d-etdrk4")(**config)
        u0 = scene.random_state(np.random.default_rng(1234))
        traj = scene.rollout(u0, 100, keep="all")
        steps = list(range(5, 101, 5))
        out = {"wrt": "params", "u0": u0,
               "params": {"anti_diffusion": 1.3, "hyper_diffusion": 0.7},
               "bounds": {"hyper_diffusion": (0.05, None)}}
    elif name == "burgers-nu":
        scene = registry.get("burgers1d-rusanov")(
            n=128, length=2.0, start=-1.0, nu=0.01 / np.pi, dt=1 / 32, substeps=8, umax=2)
        config = {"n": 128, "length": 2.0, "start": -1.0, "nu": 0.01 / np.pi, "dt": 1 / 32,
                  "substeps": 8, "umax": 2.0}
        u0 = scene.pbdl_state()
        traj = scene.rollout(u0, 32, keep="all")
        steps = list(range(1, 33))
        out = {"wrt": "nu", "u0": u0, "params": {"nu": 0.02 / np.pi}, "bounds": {"nu": (0, 0.01)}}
    else:
        raise ValueError(f"unknown demo {name!r}; choose from {', '.join(DEMOS)}")
    states = traj[steps].copy()
    if noise:
        rng = np.random.default_rng(seed)
        states += noise * float(np.std(traj[1:])) * rng.standard_normal(states.shape)
    return {"scene": scene.name, "config": config, "steps": np.array(steps), "states": states,
            "truth_params": dict(scene.params), **out}


def write_observations(path: str | Path, prob: dict[str, Any]) -> None:
    """An observation file (module doc) for ``prob`` as made by :func:`demo_problem`."""
    import h5py

    from adjointsim.files import atomic_path

    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["scene"] = prob["scene"]
        f.attrs["config"] = json.dumps(prob["config"])
        if prob.get("params"):
            f.attrs["params"] = json.dumps(prob["params"])
        f.attrs["truth_params"] = json.dumps(prob["truth_params"])
        f["steps"] = prob["steps"]
        f["states"] = prob["states"]
        if prob.get("u0") is not None:
            f["u0"] = prob["u0"]
        if prob.get("truth_u0") is not None:
            f["truth/u0"] = prob["truth_u0"]


def read_observations(path: str | Path, scene_name: str | None) -> dict[str, Any]:
    """The checked contents of an observation file: scene, steps, states and the optional
    entries (module doc)."""
    import h5py

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"observation file {path} does not exist")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise ValueError(f"{path} is not a readable HDF5 file ({e})") from None
    with f:
        for key in ("steps", "states"):
            if key not in f:
                raise ValueError(f"{path} has no dataset /{key} (see `adjointsim fit --help` "
                                 "for the layout)")
        name = f.attrs.get("scene", scene_name)
        if name is None:
            raise ValueError(f"{path} names no scene (attribute 'scene'); give SCENE")
        name = str(name)
        if scene_name is not None and scene_name != name:
            raise ValueError(f"{path} holds observations of {name!r}, not {scene_name!r}")

        def attr_json(key: str) -> dict:
            if key not in f.attrs:
                return {}
            try:
                value = json.loads(f.attrs[key])
            except (TypeError, json.JSONDecodeError):
                raise ValueError(f"{path}: attribute {key!r} is not JSON") from None
            if not isinstance(value, dict):
                raise ValueError(f"{path}: attribute {key!r} must be a JSON object")
            return value

        out = {"scene": name, "config": attr_json("config"), "params": attr_json("params"),
               "truth_params": attr_json("truth_params"),
               "steps": np.asarray(f["steps"][()]), "states": np.asarray(f["states"][()]),
               "n": int(f.attrs["n"]) if "n" in f.attrs else None}
        for key in ("u0", "controls", "truth/u0", "truth/controls"):
            out[key] = np.asarray(f[key][()]) if key in f else None
    steps, states = out["steps"], out["states"]
    if steps.ndim != 1 or steps.dtype.kind not in "iu":
        raise ValueError(f"{path}: /steps must be a 1D integer array, not {steps.dtype} "
                         f"of shape {steps.shape}")
    if states.shape[:1] != steps.shape:
        raise ValueError(f"{path}: /states has {states.shape[0] if states.ndim else 0} "
                         f"states for {len(steps)} steps")
    if len(set(steps.tolist())) != len(steps):
        raise ValueError(f"{path}: /steps names a step twice")
    for key in ("params", "truth_params"):
        for name, value in out[key].items():
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"{path}: attribute {key!r}: {name} must be a number, "
                                 f"not {value!r}")
    for key in ("states", "u0", "controls", "truth/u0", "truth/controls"):
        if out[key] is not None:
            if out[key].dtype.kind not in "iuf":
                raise ValueError(f"{path}: /{key} has dtype {out[key].dtype}; expected real "
                                 "numbers")
            out[key] = out[key].astype(np.float64)
    return out


def make_scene(name: str, config: dict):
    cls = registry.get(name)
    try:
        return cls(**config)
    except TypeError as e:
        raise ValueError(f"the scene config {config} does not fit {name}: {e}") from None


# ----------------------------------------------------------------------------- the run
def _history_csv(history: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(history[0]))
    w.writeheader()
    w.writerows(history)
    return buf.getvalue()


def plot_fit(path: Path, scene, obs: dict[int, np.ndarray], result: FitResult,
             truth_u0: np.ndarray | None) -> None:
    """Fitted against observed states (first batch element and channel) at up to four observed
    steps, and the fitted initial state against the truth when it is known."""
    from adjointsim.files import pyplot, save_figure

    plt = pyplot()
    steps = list(obs)
    shown = steps if len(steps) <= 4 else [steps[int(i)] for i in
                                           np.linspace(0, len(steps) - 1, 4).round()]
    panels = len(shown) + (truth_u0 is not None)
    fig, axes = plt.subplots(1, panels, figsize=(4.2 * panels, 3.3), squeeze=False)
    dt = getattr(scene, "dt", 1.0)
    x = scene.nodes() if hasattr(scene, "nodes") and len(scene.grid_shape) == 1 else None
    for ax, k in zip(axes.flat, shown):
        o, p = obs[k][0, 0], result.predicted[k][0, 0]
        if o.ndim == 2:
            ax.imshow(np.concatenate([o, p, o - p], axis=1), cmap="RdBu_r")
            ax.set_title(f"step {k}: observed | fitted | difference", fontsize=8)
            ax.axis("off")
            continue
        xs = np.arange(o.size) if x is None else x
        ax.plot(xs, o.ravel(), ".", ms=3, label="observed")
        ax.plot(xs, p.ravel(), "-", lw=1, label="fitted")
        ax.set(title=f"step {k} (t = {k * dt:.3g})", xlabel="x")
        ax.legend(fontsize=7)
    if truth_u0 is not None:
        ax = axes.flat[-1]
        t, f_ = truth_u0[0, 0], result.state[0, 0]
        if t.ndim == 2:
            ax.imshow(np.concatenate([t, f_], axis=1), cmap="RdBu_r")
            ax.axis("off")
        else:
            xs = np.arange(t.size) if x is None else x
            ax.plot(xs, t.ravel(), "k--", lw=1, label="true u0")
            ax.plot(xs, f_.ravel(), "-", lw=1, label="fitted u0")
            ax.legend(fontsize=7)
        ax.set_title("initial state", fontsize=9)
    fig.suptitle(f"{scene.name}: fitted {', '.join(result.wrt)}, misfit {result.misfit:.3g}",
                 fontsize=10)
    save_figure(fig, path, dpi=100)


def plot_history(path: Path, history: list[dict], title: str) -> None:
    from adjointsim.files import pyplot, save_figure

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.5))
    it = [h["iteration"] for h in history]
    ax.semilogy(it, [max(h["misfit"], 1e-300) for h in history], label="misfit")
    ax.semilogy(it, [max(h["grad_norm"], 1e-300) for h in history], label="gradient norm")
    ax.set(xlabel="iteration", title=title)
    ax.legend()
    save_figure(fig, path, dpi=100)


def _pairs(items: list[str] | None, what: str) -> dict[str, str]:
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"{what} takes NAME=VALUE, not {item!r}")
        out[key.strip()] = value.strip()
    return out


def _number(text: str, what: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"{what}: {text!r} is not a number") from None
    if not math.isfinite(v):
        raise ValueError(f"{what}: {text!r} must be finite")
    return v


def _bounds(items: list[str] | None) -> dict[str, tuple[float | None, float | None]]:
    out = {}
    for key, value in _pairs(items, "--bounds").items():
        lo, sep, hi = value.partition(":")
        if not sep:
            raise ValueError(f"--bounds takes NAME=LO:HI (either side may be empty), not "
                             f"{key}={value}")
        out[key] = (None if not lo else _number(lo, f"--bounds {key}"),
                    None if not hi else _number(hi, f"--bounds {key}"))
    return out


def run_fit(obs_file: Path, scene_name: str | None, out: Path, args: argparse.Namespace,
            progress: bool = True) -> dict[str, Any]:
    """Fit the observation file, write the run directory, return result.json's contents."""
    from adjointsim.files import atomic_path, write_json, write_text

    from .fit import fit, parse_wrt

    data = read_observations(obs_file, scene_name)
    scene = make_scene(data["scene"], data["config"])
    wrt = args.wrt or "state"
    parse_wrt(scene, wrt)  # an unknown entry fails before anything runs
    params = {**data["params"], **{k: _number(v, f"--start {k}")
                                   for k, v in _pairs(args.start, "--start").items()}}
    obs = {int(k): s for k, s in zip(data["steps"], data["states"])}
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=args.maxiter, desc=f"fit {scene.name}", unit="it")

    def tick(row: dict) -> None:
        if bar is not None and row["iteration"]:
            bar.update(1)
            bar.set_postfix(misfit=f"{row['misfit']:.3g}", grad=f"{row['grad_norm']:.2g}")

    try:
        n = data["n"] if args.steps is None else args.steps  # --steps 0 is a length too
        result = fit(scene, obs, n=n, wrt=wrt, u0=data["u0"],
                     controls=data["controls"], params=params, bounds=_bounds(args.bounds),
                     method=args.method, tikhonov=args.tikhonov, smoothness=args.smoothness,
                     checkpoint=args.checkpoint, maxiter=args.maxiter, tol=args.tol,
                     callback=tick)
    finally:
        if bar is not None:
            bar.close()
    summary: dict[str, Any] = {
        "scene": scene.name, "config": data["config"], "wrt": list(result.wrt),
        "method": args.method, "misfit": result.misfit,
        "start_misfit": result.history[0]["misfit"], "params": result.params,
        "iterations": result.iterations, "evaluations": result.evaluations,
        "seconds": result.seconds, "success": result.success, "message": result.message,
    }
    if data["truth_params"]:
        summary["param_rel_error"] = {
            k: abs(result.params[k] - v) / abs(v) if v else abs(result.params[k])
            for k, v in data["truth_params"].items() if k in result.wrt}
    if data["truth/u0"] is not None:
        summary["u0_mse"] = float(np.mean((result.state - data["truth/u0"]) ** 2))
    write_text(out / "history.csv", _history_csv(result.history))
    import h5py

    with atomic_path(out / "fitted.h5") as tmp, h5py.File(tmp, "w") as f:
        f.attrs["scene"] = scene.name
        f.attrs["config"] = json.dumps(data["config"])
        f.attrs["params"] = json.dumps(result.params)
        f["steps"] = np.array(list(result.predicted))
        f["states"] = np.stack(list(result.predicted.values()))
        f["u0"] = result.state
        if result.controls is not None:
            f["controls"] = result.controls
    if not args.no_plots:
        plot_fit(out / "fit.png", scene, obs, result, data["truth/u0"])
        plot_history(out / "history.png", result.history, f"{scene.name}: fit of "
                     f"{', '.join(result.wrt)}")
    write_json(out / "result.json", summary)
    return summary


def command(args: argparse.Namespace) -> int:
    """``adjointsim fit``: one fit (SCENE --observations FILE, or --demo), or --study params."""
    if args.study:
        return parameter_study(Path(args.out or "docs"), progress=not args.quiet)
    if args.demo is None and args.observations is None:
        raise ValueError("give SCENE --observations FILE.h5, or --demo "
                         f"{'|'.join(DEMOS)}, or --study params")
    if args.demo is not None and args.observations is not None:
        raise ValueError("--demo makes its own observations; drop --observations")
    name = args.demo or args.scene or "fit"
    out = Path(args.out or f"runs/fit-{name}")
    if (out / "result.json").exists() and not args.overwrite:
        raise ValueError(f"{out} holds a finished fit; pass --overwrite or another --out")
    if args.demo is not None:
        obs_file = out / "observations.h5"
        prob = demo_problem(args.demo, args.noise, args.seed)
        write_observations(obs_file, prob)
        if args.wrt is None:
            args.wrt = prob["wrt"]
        if not args.bounds and prob.get("bounds"):
            args.bounds = [f"{k}={'' if lo is None else lo}:{'' if hi is None else hi}"
                           for k, (lo, hi) in prob["bounds"].items()]
        scene_name = prob["scene"]
    else:
        obs_file, scene_name = Path(args.observations), args.scene
    summary = run_fit(obs_file, scene_name, out, args, progress=not args.quiet)
    extra = "".join(f", {k} = {v:.3g}" for k, v in summary.items()
                    if k == "u0_mse") + "".join(
        f", rel. error of {k} {v:.2g}" for k, v in summary.get("param_rel_error", {}).items())
    print(f"{summary['scene']}: misfit {summary['start_misfit']:.3g} -> {summary['misfit']:.3g} "
          f"in {summary['iterations']} iterations, {summary['seconds']:.2f} s{extra}; "
          f"{summary['message']}; wrote {out}/")
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = __doc__
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("scene", nargs="?", default=None,
                   help="registered solver name (default: the file's 'scene' attribute)")
    p.add_argument("--observations", default=None, help="HDF5 file: /steps, /states, "
                   "optional /u0, /controls; attrs scene, config (JSON), params (JSON), n")
    p.add_argument("--wrt", default=None, help="what to fit, comma-separated: state, controls, "
                   "params or parameter names (default state; a demo's own choice)")
    p.add_argument("--demo", choices=DEMOS, default=None, help="a built-in problem")
    p.add_argument("--study", choices=("params",), default=None,
                   help="params: the parameter-estimation table (writes OUT/fit-params.*)")
    p.add_argument("--noise", type=float, default=0.0,
                   help="--demo: relative noise on the observations (0.01 = 1%%)")
    p.add_argument("--seed", type=int, default=0, help="--demo: noise seed")
    p.add_argument("--steps", type=int, default=None, help="rollout length (default: the "
                   "file's n, else the last observed step)")
    p.add_argument("--method", default="L-BFGS-B", help="a gradient-based scipy.optimize "
                   "method (default L-BFGS-B)")
    p.add_argument("--maxiter", type=int, default=500)
    p.add_argument("--tol", type=float, default=1e-12, help="scipy minimize's tol (default "
                   "1e-12)")
    p.add_argument("--tikhonov", type=float, default=0.0, help="λ_T of mean((z - z0)^2)")
    p.add_argument("--smoothness", type=float, default=0.0,
                   help="λ_S of mean((D z)^2), D first differences in space (state) / time "
                   "(controls)")
    p.add_argument("--bounds", action="append", default=None, metavar="NAME=LO:HI",
                   help="bounds of a fitted parameter (repeat for several)")
    p.add_argument("--start", action="append", default=None, metavar="NAME=VALUE",
                   help="starting (or fixed) value of a parameter")
    p.add_argument("--checkpoint", type=int, default=None,
                   help="states held by the adjoint sweep (default all)")
    p.add_argument("--out", default=None, help="run directory (default runs/fit-SCENE|DEMO)")
    p.add_argument("--overwrite", action="store_true", help="replace a finished run")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=command)


# ----------------------------------------------------------------------------- the study
def parameter_study(out: Path, seeds: int = 5, progress: bool = True) -> int:
    """KS (α, β) and Burgers ν from solver trajectories, 0% and 1% noise (``seeds`` noise
    seeds), each from a perturbed start: ``OUT/fit-params.md`` and ``OUT/fit-params.json``."""
    from adjointsim.files import write_json, write_text

    from .fit import fit

    rows = []
    for demo in ("ks-params", "burgers-nu"):
        for noise in (0.0, 0.01):
            for seed in range(1 if noise == 0 else seeds):
                prob = demo_problem(demo, noise, seed)
                scene = make_scene(prob["scene"], prob["config"])
                obs = {int(k): s for k, s in zip(prob["steps"], prob["states"])}
                t = time.perf_counter()
                r = fit(scene, obs, wrt=prob["wrt"], u0=prob["u0"], params=prob["params"],
                        bounds=prob.get("bounds"), tol=1e-30, maxiter=500)
                seconds = time.perf_counter() - t
                for k in r.wrt:
                    true = prob["truth_params"][k]
                    rows.append({"problem": demo, "noise": noise, "seed": seed, "parameter": k,
                                 "true": true, "start": prob["params"][k], "fitted": r.params[k],
                                 "rel_error": abs(r.params[k] - true) / abs(true),
                                 "misfit": r.misfit, "iterations": r.iterations,
                                 "seconds": seconds})
                if progress:
                    print(f"{demo} noise {noise:g} seed {seed}: "
                          + ", ".join(f"{k} {r.params[k]:.10g}" for k in r.wrt)
                          + f" ({seconds:.2f} s)")
    lines = ["| problem | parameter | true | start | noise | rel. error (median over seeds) "
             "| spread (min – max) | iterations | seconds |", "|---" * 9 + "|"]
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["problem"], r["parameter"], r["noise"]), []).append(r)
    for (demo, k, noise), rs in groups.items():
        errs = np.array([r["rel_error"] for r in rs])
        spread = "–" if len(rs) == 1 else f"{errs.min():.2g} – {errs.max():.2g}"
        lines.append(f"| {demo} | {k} | {rs[0]['true']:.6g} | {rs[0]['start']:.6g} | "
                     f"{noise:.0%} ({len(rs)} seed{'s' * (len(rs) > 1)}) | "
                     f"{np.median(errs):.2g} | {spread} | "
                     f"{int(np.median([r['iterations'] for r in rs]))} | "
                     f"{np.median([r['seconds'] for r in rs]):.2f} |")
    text = "\n".join(lines)
    about = (
        "Parameter estimation with `adjointsim.fit` (L-BFGS-B, tol 1e-30, the initial state "
        "known), from `adjointsim fit --study params --out docs`.\n\n"
        "* ks-params: `ks1d-etdrk4`, N = 64, L = 22, Δt = 0.1, a smooth random initial state "
        "(seed 1234), observations every 5 steps up to step 100 (t = 10); α = anti_diffusion, "
        "β = hyper_diffusion (β bounded below by 0.05).\n"
        "* burgers-nu: the PBDL Burgers scene (N = 128 on [−1, 1], u0 = −sin(πx), Δt = 1/32 in 8 "
        "Rusanov sub-steps), every step up to 32; ν bounded to [0, 0.01].\n"
        "* Noise: Gaussian, σ = 1% of the trajectory's standard deviation, on every observed "
        "value; 5 noise seeds.\n\n")
    write_text(out / "fit-params.md", about + text + "\n")
    write_json(out / "fit-params.json", rows)
    print(text)
    return 0
