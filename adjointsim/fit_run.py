"""A fit as a run: observation files, the built-in problems and the run directory of
``adjointsim fit`` (NumPy only).

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

A run directory (``--out``, default ``runs/fit-DEMO`` or ``runs/fit-SCENE``) receives
``config.json`` (the fit's configuration), ``history.csv`` (per iteration: misfit,
regularisation, objective, gradient norm, evaluations, seconds, CPU seconds), ``fitted.h5``
(fitted u0, controls and the predicted observed states, same layout), the plots ``fit.png``
(fitted against observed states) and ``history.png`` (misfit and gradient norm per iteration),
and last ``result.json`` (fitted parameters, misfit, errors against the truth when the file has
it, optimiser message, the parameters on a bound at the start and at the end). All files are
written atomically. A start outside its bounds is refused (give ``--start`` or wider
``--bounds``); a demo's own bounds apply to the parameters it fits.

Every input is checked before anything is written. A fit takes seconds, so it keeps no
checkpoint: ``--resume`` returns a finished fit's result as it is and starts an unfinished
(interrupted) one again from its beginning; ``--overwrite`` discards the fit in ``--out`` and
runs it again.

``--demo burgers`` (PBDL's Burgers reconstruction), ``--demo ks-params`` (KS α, β) and
``--demo burgers-nu`` (the Burgers viscosity) write their observation file into the run
directory and fit it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from . import registry
from .errors import UserError
from .files import atomic_path, pyplot, save_figure, write_json
from .fit import GRADIENT_METHODS, FitResult, StartOutsideBoundsError, fit, parse_wrt, problem
from .run import (
    SEEDS,
    Config,
    Interval,
    check_memory,
    discard,
    finished_result,
    holds_run,
    plot_history,
    refuse_foreign,
    require_checkpoint,
    write_history,
)

DEMOS = ("burgers", "ks-params", "burgers-nu")
PBDL_T_OBS_STEP = 16
#: what a fit's directory holds besides config.json and result.json: replaced by ``overwrite``
RUN_FILES = ("observations.h5", "history.csv", "fitted.h5", "fit.png", "history.png")
HISTORY_FIELDS = ("iteration", "misfit", "regularisation", "objective", "grad_norm",
                  "evaluations", "seconds", "cpu_seconds")
RESULT_KEYS = ("scene", "misfit", "params", "iterations")


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
        raise UserError(f"unknown demo {name!r}; choose from {', '.join(DEMOS)}")
    states = traj[steps].copy()
    if noise:
        rng = np.random.default_rng(seed)
        states += noise * float(np.std(traj[1:])) * rng.standard_normal(states.shape)
    return {"scene": scene.name, "config": config, "steps": np.array(steps), "states": states,
            "truth_params": dict(scene.params), **out}


def write_observations(path: str | Path, prob: dict[str, Any]) -> None:
    """An observation file (module doc) for ``prob`` as made by :func:`demo_problem`."""
    import h5py

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
        raise UserError(f"observation file {path} does not exist")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise UserError(f"{path} is not a readable HDF5 file ({e})") from None
    with f:
        for key in ("steps", "states"):
            if key not in f:
                raise UserError(f"{path} has no dataset /{key} (see `adjointsim fit --help` "
                                "for the layout)")
        name = f.attrs.get("scene", scene_name)
        if name is None:
            raise UserError(f"{path} names no scene (attribute 'scene'); give SCENE")
        name = str(name)
        if scene_name is not None and scene_name != name:
            raise UserError(f"{path} holds observations of {name!r}, not {scene_name!r}")

        def attr_json(key: str) -> dict:
            if key not in f.attrs:
                return {}
            try:
                value = json.loads(f.attrs[key])
            except (TypeError, json.JSONDecodeError):
                raise UserError(f"{path}: attribute {key!r} is not JSON") from None
            if not isinstance(value, dict):
                raise UserError(f"{path}: attribute {key!r} must be a JSON object")
            return value

        out = {"scene": name, "config": attr_json("config"), "params": attr_json("params"),
               "truth_params": attr_json("truth_params"),
               "steps": np.asarray(f["steps"][()]), "states": np.asarray(f["states"][()]),
               "n": int(f.attrs["n"]) if "n" in f.attrs else None}
        for key in ("u0", "controls", "truth/u0", "truth/controls"):
            out[key] = np.asarray(f[key][()]) if key in f else None
    steps, states = out["steps"], out["states"]
    if steps.ndim != 1 or steps.dtype.kind not in "iu":
        raise UserError(f"{path}: /steps must be a 1D integer array, not {steps.dtype} "
                        f"of shape {steps.shape}")
    if states.shape[:1] != steps.shape:
        raise UserError(f"{path}: /states has {states.shape[0] if states.ndim else 0} "
                        f"states for {len(steps)} steps")
    if len(set(steps.tolist())) != len(steps):
        raise UserError(f"{path}: /steps names a step twice")
    for key in ("params", "truth_params"):
        for name, value in out[key].items():
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise UserError(f"{path}: attribute {key!r}: {name} must be a number, "
                                f"not {value!r}")
    for key in ("states", "u0", "controls", "truth/u0", "truth/controls"):
        if out[key] is not None:
            if out[key].dtype.kind not in "iuf":
                raise UserError(f"{path}: /{key} has dtype {out[key].dtype}; expected real "
                                "numbers")
            out[key] = out[key].astype(np.float64)
    return out


def make_scene(name: str, config: dict):
    """The registered scene ``name`` built from its constructor keywords ``config``."""
    cls = registry.get(name)
    try:
        return cls(**config)
    except TypeError as e:
        raise UserError(f"the scene config {config} does not fit {name}: {e}") from None


# ----------------------------------------------------------------------------- the config
ACCEPTED: dict[str, tuple | Interval | str] = {
    "scene": "a registered solver name",
    "observations": "a path to an HDF5 observation file",
    "demo": DEMOS,
    "wrt": "state, controls, params or parameter names, comma-separated",
    "noise": Interval(0),
    "seed": SEEDS,
    "steps": Interval(0),
    "method": GRADIENT_METHODS,
    "maxiter": Interval(0),
    "tol": Interval(0),
    "tikhonov": Interval(0),
    "smoothness": Interval(0),
    "bounds": "a list of NAME=LO:HI (either side may be empty)",
    "start": "a list of NAME=VALUE",
    "checkpoint": Interval(1),
}


@dataclass
class FitConfig(Config):
    """One fit: the observations (a file, or a built-in problem), what is fitted and how."""

    #: the registered solver (default: the observation file's ``scene`` attribute)
    scene: str | None = None
    observations: str | None = None
    demo: str | None = None
    #: default: state, or the demo's own choice
    wrt: str | None = None
    #: a demo's relative observation noise (0.01 = 1 %) and its seed
    noise: float = 0.0
    seed: int = 0
    #: rollout length (default: the file's n, else the last observed step)
    steps: int | None = None
    method: str = "L-BFGS-B"
    maxiter: int = 500
    tol: float = 1e-12
    tikhonov: float = 0.0
    smoothness: float = 0.0
    #: ["NAME=LO:HI", ...] bounds of fitted parameters (default: a demo's own)
    bounds: list = field(default_factory=list)
    #: ["NAME=VALUE", ...] starting (or fixed) parameter values
    start: list = field(default_factory=list)
    #: states held by the adjoint sweep (default all)
    checkpoint: int | None = None

    ACCEPTED: ClassVar[dict[str, tuple | Interval | str]] = ACCEPTED

    def check(self, where: str) -> None:
        if self.demo is None and self.observations is None:
            raise UserError(f"give SCENE --observations FILE.h5, or --demo {'|'.join(DEMOS)}"
                            f"{where}")
        if self.demo is not None and self.observations is not None:
            raise UserError(f"--demo makes its own observations; drop --observations{where}")
        if self.demo is not None and self.scene is not None:
            raise UserError(f"--demo {self.demo} names its own scene; drop SCENE{where}")
        if self.demo is None and self.noise:
            raise UserError(f"--noise adds noise to a demo's observations; a file's are as "
                            f"they are{where}")
        self.bound_values(where)
        self.start_values(where)

    def bound_values(self, where: str = "") -> dict[str, tuple[float | None, float | None]]:
        """``bounds`` as {parameter: (lo, hi)}, either side None."""
        out = {}
        for key, value in _pairs(self.bounds, "bounds", "NAME=LO:HI", where).items():
            lo, sep, hi = value.partition(":")
            if not sep:
                raise UserError(f"config key 'bounds'{where}: takes NAME=LO:HI (either side "
                                f"may be empty), not {key}={value}")
            takes = "takes NAME=LO:HI, LO ≤ HI finite numbers (either may be empty)"
            lo, hi = (None if not v else _number(v, f"bounds {key}", where, takes)
                      for v in (lo, hi))
            if lo is not None and hi is not None and lo > hi:
                raise UserError(f"config key 'bounds'{where}: bounds {key}={value} are reversed "
                                f"({lo} > {hi}); {takes}")
            out[key] = (lo, hi)
        return out

    def start_values(self, where: str = "") -> dict[str, float]:
        """``start`` as {parameter: value}."""
        return {k: _number(v, f"start {k}", where, "takes NAME=VALUE, VALUE a finite number")
                for k, v in _pairs(self.start, "start", "NAME=VALUE", where).items()}


def _pairs(items: list, key: str, form: str, where: str) -> dict[str, str]:
    out = {}
    for item in items:
        name, sep, value = str(item).partition("=")
        if not isinstance(item, str) or not sep or not name.strip():
            raise UserError(f"config key {key!r}{where}: takes {form}, not {item!r}")
        out[name.strip()] = value.strip()
    return out


def _number(text: str, what: str, where: str, takes: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise UserError(f"config key {what}{where}: {text!r} is not a number; {takes}") from None
    if not math.isfinite(v):
        raise UserError(f"config key {what}{where}: {text!r} is not a finite number; {takes}")
    return v


# ----------------------------------------------------------------------------- the run
def plot_fit(path: Path, scene, obs: dict[int, np.ndarray], result: FitResult,
             truth_u0: np.ndarray | None) -> None:
    """Fitted against observed states (first batch element and channel) at up to four observed
    steps, and the fitted initial state against the truth when it is known."""
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


def demo_observations(prob: dict[str, Any]) -> dict[str, Any]:
    """A problem of :func:`demo_problem` as :func:`read_observations` returns its file."""
    return {"scene": prob["scene"], "config": prob["config"], "params": prob["params"],
            "truth_params": prob["truth_params"], "steps": prob["steps"],
            "states": prob["states"], "n": None, "u0": prob["u0"], "controls": None,
            "truth/u0": prob.get("truth_u0"), "truth/controls": None}


def run_fit(cfg: FitConfig, out: str | Path, resume: bool = False, overwrite: bool = False,
            progress: bool = True, plots: bool = True) -> dict[str, Any]:
    """Fit as configured in the run directory ``out`` (module doc); returns result.json's
    contents. A finished fit is returned as it is with ``resume``, refused without it;
    ``overwrite`` discards the fit in ``out``, once the new one's inputs are checked."""
    cfg.validate()
    if resume and overwrite:
        raise UserError("--resume keeps a fit and --overwrite discards it: pass one")
    out = Path(out)
    config = cfg.as_dict()
    if resume and not (out / "config.json").exists():
        require_checkpoint(out)  # a finished fit there, or no fit to resume at all
    if not overwrite:
        refuse_foreign(out, config)
        finished = finished_result(out, resume, keys=RESULT_KEYS)
        if finished is not None:
            return finished
    prob = None if cfg.demo is None else demo_problem(cfg.demo, cfg.noise, cfg.seed)
    data = (read_observations(cfg.observations, cfg.scene) if prob is None
            else demo_observations(prob))
    scene = make_scene(data["scene"], data["config"])
    obs = {int(k): s for k, s in zip(data["steps"], data["states"])}
    wrt = cfg.wrt or ("state" if prob is None else prob["wrt"])
    bounds = cfg.bound_values()
    if not bounds and prob is not None:  # a demo's own bounds, on what is fitted
        fitted = parse_wrt(scene, wrt)[2]
        bounds = {k: b for k, b in prob.get("bounds", {}).items() if k in fitted}
    given = {
        "n": data["n"] if cfg.steps is None else cfg.steps,  # steps = 0 is a length too
        "wrt": wrt, "u0": data["u0"], "controls": data["controls"],
        "params": {**data["params"], **cfg.start_values()}, "bounds": bounds,
        "method": cfg.method, "tikhonov": cfg.tikhonov, "smoothness": cfg.smoothness,
        "checkpoint": cfg.checkpoint}
    u0 = data["u0"] if data["u0"] is not None else data["states"][0]
    states = (cfg.checkpoint or given["n"] + 1) if given["n"] is not None else 1
    check_memory(4 * states * np.asarray(u0).nbytes,
                 f"--steps {given['n']} ({states} stored states of {np.asarray(u0).nbytes:,} "
                 "bytes, and the adjoint's as many)", "choose fewer steps, or --checkpoint S to "
                 "hold S states")
    try:
        problem(scene, obs, **given)  # every input checked before anything is written
    except StartOutsideBoundsError as e:
        lo, hi = ("" if b is None else b for b in e.bounds)
        whose = "" if cfg.bounds else " (the demo's)"
        raise UserError(f"the start of {e.name} ({e.start}) is outside its bounds "
                        f"{e.name}={lo}:{hi}{whose}; give a start inside them with --start "
                        f"{e.name}=VALUE, or wider --bounds {e.name}=LO:HI (a start moved onto "
                        "a bound would change the problem)") from None
    if overwrite:
        if not holds_run(out, config):  # somebody else's files are never discarded
            refuse_foreign(out, config)
        discard(out, RUN_FILES)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "config.json", config)
    if prob is not None:
        write_observations(out / "observations.h5", prob)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=cfg.maxiter, desc=f"fit {scene.name}", unit="it")

    def tick(row: dict) -> None:
        if bar is not None and row["iteration"]:
            bar.update(1)
            bar.set_postfix(misfit=f"{row['misfit']:.3g}", grad=f"{row['grad_norm']:.2g}")

    try:
        result = fit(scene, obs, maxiter=cfg.maxiter, tol=cfg.tol, callback=tick, **given)
    finally:
        if bar is not None:
            bar.close()
    summary: dict[str, Any] = {
        "scene": scene.name, "config": data["config"], "wrt": list(result.wrt),
        "method": cfg.method, "misfit": result.misfit,
        "start_misfit": result.history[0]["misfit"], "params": result.params,
        "iterations": result.iterations, "evaluations": result.evaluations,
        "seconds": result.seconds, "success": result.success, "message": result.message,
        "start_active_bounds": result.start_active_bounds, "active_bounds": result.active_bounds,
    }
    if data["truth_params"]:
        summary["param_rel_error"] = {
            k: abs(result.params[k] - v) / abs(v) if v else abs(result.params[k])
            for k, v in data["truth_params"].items() if k in result.wrt}
    if data["truth/u0"] is not None:
        summary["u0_mse"] = float(np.mean((result.state - data["truth/u0"]) ** 2))
    write_history(out / "history.csv", result.history, HISTORY_FIELDS)
    _write_fitted(out / "fitted.h5", scene.name, data["config"], result)
    if plots:
        plot_fit(out / "fit.png", scene, obs, result, data["truth/u0"])
        curves = {label: [{"iteration": h["iteration"], "value": max(h[key], 1e-300)}
                          for h in result.history]
                  for label, key in (("misfit", "misfit"), ("gradient norm", "grad_norm"))}
        plot_history(out / "history.png", curves, "iteration", "value", "iteration",
                     "misfit, gradient norm",
                     title=f"{scene.name}: fit of {', '.join(result.wrt)}")
    write_json(out / "result.json", summary)
    return summary


def _write_fitted(path: Path, scene_name: str, config: dict, result: FitResult) -> None:
    """The fitted u0, controls and predicted observed states, in the observation layout."""
    import h5py

    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["scene"] = scene_name
        f.attrs["config"] = json.dumps(config)
        f.attrs["params"] = json.dumps(result.params)
        f["steps"] = np.array(list(result.predicted))
        f["states"] = np.stack(list(result.predicted.values()))
        f["u0"] = result.state
        if result.controls is not None:
            f["controls"] = result.controls
