"""A fit as a run: observation files, the built-in problems and the run directory of
``adjointsim fit`` (NumPy only).

Observation file layout (``--observations FILE.h5``)::

    /steps      int (K,)                      the observed step numbers k (0 = u_0)
    /states     float (K, B, C, *grid)        the observed states d_k
    /u0         float (B, C, *grid)           optional: the initial state (fixed), or the
                                              starting guess when it is fitted (default zero)
    /controls   float (n, B, *control_shape)  optional: the controls, fixed or starting guess
    /truth/u0, /truth/controls                optional: the true values, for error reports
    attrs: scene   the registry name of the solver (must match SOLVER)
           config  JSON of the scene's constructor keywords, e.g. {"n": 128, "nu": 0.003}
           params  optional JSON {parameter: value}: fixed values or starting guesses
           truth_params  optional JSON {parameter: value}: the true values, for error reports
           n       optional rollout length (default: the last observed step)

A run directory (``--out``, default ``runs/fit-DEMO`` or ``runs/fit-SOLVER``) receives
``config.json`` (the fit's configuration), ``history.csv`` (per iteration: misfit,
regularisation, objective, gradient norm, evaluations, seconds, CPU seconds), ``fitted.h5``
(fitted u0, controls and the predicted observed states, same layout), the plots ``fit.png``
(fitted against observed states) and ``history.png`` (misfit and gradient norm per iteration),
and last ``result.json`` (fitted parameters, misfit, errors against the truth when the file has
it, optimiser message, the parameters on a bound at the start and at the end). All files are
written atomically. A start outside its bounds is refused (give ``--start`` or wider
``--bounds``); a demo's own bounds apply to the parameters it fits.

Every input is checked before anything is written. The directory follows the run engine's rule
(:mod:`adjointsim.engine`). A fit takes seconds, so it keeps no checkpoint: ``--resume`` returns
a finished fit's result as it is and starts an unfinished (interrupted) one again from its
beginning; ``--overwrite`` discards the fit in ``--out`` and runs it again.

``--demo burgers`` (PBDL's Burgers reconstruction), ``--demo ks-params`` (KS α, β) and
``--demo burgers-nu`` (the Burgers viscosity) write their observation file into the run
directory and fit it; ``--scene KEY=VALUE`` (or a ``[scene]`` table) changes a demo's scene
(``nu``, ``n``, ``dt``, ...), the solver checks it, and config.json records it whole.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from . import engine, scenes
from .errors import UserError
from .files import atomic_path, pyplot, save_figure
from .fit import GRADIENT_METHODS, FitResult, StartOutsideBoundsError, fit, parse_wrt, problem
from .fit_demos import DEMOS, demo_problem, demo_scene
from .run import SEEDS, Config, Interval, check_memory, plot_history

if TYPE_CHECKING:
    from .stepper import Stepper

HISTORY_FIELDS = ("iteration", "misfit", "regularisation", "objective", "grad_norm",
                  "evaluations", "seconds", "cpu_seconds")


# ----------------------------------------------------------------------------- observation files
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


def read_observations(path: str | Path, solver: str | None) -> dict[str, Any]:
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
        name = f.attrs.get("scene", solver)
        if name is None:
            raise UserError(f"{path} names no solver (attribute 'scene'); give SOLVER")
        name = str(name)
        if solver is not None and solver != name:
            raise UserError(f"{path} holds observations of {name!r}, not {solver!r}")

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

        def attr_count(key: str) -> int | None:
            if key not in f.attrs:
                return None
            value = f.attrs[key]
            try:
                count = float(value) if np.ndim(value) == 0 else -1.0
            except (TypeError, ValueError):  # a string, say
                count = -1.0
            if not (count >= 0 and count.is_integer()):
                raise UserError(f"{path}: attribute {key!r} must be an integer ≥ 0, not "
                                f"{value!r}")
            return int(count)

        out = {"scene": name, "config": attr_json("config"), "params": attr_json("params"),
               "truth_params": attr_json("truth_params"),
               "steps": np.asarray(f["steps"][()]), "states": np.asarray(f["states"][()]),
               "n": attr_count("n")}
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


def make_scene(name: str, config: dict) -> Stepper:
    """The registered solver ``name`` built from its keywords ``config`` (an observation
    file's scene)."""
    try:
        return scenes.build(name, config)
    except ValueError as e:
        raise UserError(f"the scene config {config} does not fit {name}: {e}") from None


# ----------------------------------------------------------------------------- the config
ACCEPTED: dict[str, tuple | Interval | str] = {
    "solver": "a registered solver name",
    "observations": "a path to an HDF5 observation file",
    "demo": DEMOS,
    "scene": "a demo's solver keywords (nu, n, dt, ...)",
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
    solver: str | None = None
    observations: str | None = None
    demo: str | None = None
    #: a demo's solver keywords over its own (an observation file names its scene itself)
    scene: dict = field(default_factory=dict)
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
        """The observations' source, a demo's scene (checked by its solver and recorded whole,
        the demo's keywords included), the bounds and starts."""
        if self.demo is None and self.observations is None:
            raise UserError(f"give SOLVER --observations FILE.h5, or --demo {'|'.join(DEMOS)}"
                            f"{where}")
        if self.demo is not None and self.observations is not None:
            raise UserError(f"--demo makes its own observations; drop --observations{where}")
        if self.demo is not None and self.solver is not None:
            raise UserError(f"--demo {self.demo} names its own solver; drop SOLVER{where}")
        if self.demo is None and self.noise:
            raise UserError(f"--noise adds noise to a demo's observations; a file's are as "
                            f"they are{where}")
        if self.demo is None and self.scene:
            raise UserError(f"--scene sets a demo's scene; an observation file names its own "
                            f"(attribute config){where}")
        if self.demo is not None:
            try:
                self.scene = demo_scene(self.demo, self.scene)[1]
            except ValueError as e:
                raise UserError(f"config key 'scene'{where}: {e}") from None
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
def plot_fit(path: Path, scene: Stepper, obs: dict[int, np.ndarray], result: FitResult,
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


class FitRun(engine.Problem):
    """One ``adjointsim fit``: every input is checked when it is built (before anything is
    written); its one update is the optimiser's whole loop, each iteration a row of the
    history and a tick of the progress bar. It keeps no checkpoint: stopped, it is run again."""

    RESUMABLE = ()
    ADDED = ("solver",)
    HISTORIES: ClassVar = {"history.csv": HISTORY_FIELDS}
    RUN_FILES = ("observations.h5", "fitted.h5", "fit.png", "history.png")
    RESULT_KEYS: ClassVar = {"scene": str, "misfit": float, "start_misfit": float,
                             "params": dict, "iterations": int, "seconds": float,
                             "message": str}
    ATOMIC = False

    def __init__(self, config: FitConfig, out: str | Path, plots: bool = True):
        super().__init__(config, out)
        self.plots = plots

    def describe(self) -> str:
        return f"fit {self.scene.name}"

    def total(self) -> int:
        return self.config.maxiter

    def position(self) -> int:
        return self.iteration

    def done(self) -> bool:
        return self.result is not None

    def build(self) -> None:
        cfg = self.config
        self.prob = None if cfg.demo is None else demo_problem(cfg.demo, cfg.noise, cfg.seed,
                                                               cfg.scene)
        data = (read_observations(cfg.observations, cfg.solver) if self.prob is None
                else demo_observations(self.prob))
        scene = make_scene(data["scene"], data["config"])
        obs = {int(k): s for k, s in zip(data["steps"], data["states"])}
        wrt = cfg.wrt or ("state" if self.prob is None else self.prob["wrt"])
        bounds = cfg.bound_values()
        if not bounds and self.prob is not None:  # a demo's own bounds, on what is fitted
            fitted = parse_wrt(scene, wrt)[2]
            bounds = {k: b for k, b in self.prob.get("bounds", {}).items() if k in fitted}
        given = {
            "n": data["n"] if cfg.steps is None else cfg.steps,  # steps = 0 is a length too
            "wrt": wrt, "u0": data["u0"], "controls": data["controls"],
            "params": {**data["params"], **cfg.start_values()}, "bounds": bounds,
            "method": cfg.method, "tikhonov": cfg.tikhonov, "smoothness": cfg.smoothness,
            "checkpoint": cfg.checkpoint}
        u0 = data["u0"] if data["u0"] is not None else data["states"][0]
        states = (cfg.checkpoint or given["n"] + 1) if given["n"] is not None else 1
        check_memory(4 * states * np.asarray(u0).nbytes,
                     f"--steps {given['n']} ({states} stored states of "
                     f"{np.asarray(u0).nbytes:,} bytes, and the adjoint's as many)",
                     "choose fewer steps, or --checkpoint S to hold S states")
        try:
            problem(scene, obs, **given)  # every input checked before anything is written
        except StartOutsideBoundsError as e:
            lo, hi = ("" if b is None else b for b in e.bounds)
            whose = "" if cfg.bounds else " (the demo's)"
            raise UserError(f"the start of {e.name} ({e.start}) is outside its bounds "
                            f"{e.name}={lo}:{hi}{whose}; give a start inside them with --start "
                            f"{e.name}=VALUE, or wider --bounds {e.name}=LO:HI (a start moved "
                            "onto a bound would change the problem)") from None
        self.data, self.scene, self.obs, self.given = data, scene, obs, given
        self.result: FitResult | None = None
        self.iteration = 0

    def update(self) -> bool:
        """The optimiser's whole loop (the demo's observations written first)."""
        if self.prob is not None:
            write_observations(self.out / "observations.h5", self.prob)
        self.result = fit(self.scene, self.obs, maxiter=self.config.maxiter,
                          tol=self.config.tol, callback=self.tick, **self.given)
        return True

    def tick(self, row: dict) -> None:
        """One iteration of the optimiser, for the progress bar."""
        if row["iteration"]:
            self.iteration = row["iteration"]
            self.progress(self.iteration, misfit=f"{row['misfit']:.3g}",
                          grad=f"{row['grad_norm']:.2g}")

    def finish(self) -> dict:
        """The fitted values and their errors against the truth (where it is known);
        ``fitted.h5``."""
        result, data = self.result, self.data
        summary: dict[str, Any] = {
            "scene": self.scene.name, "config": data["config"], "wrt": list(result.wrt),
            "method": self.config.method, "misfit": result.misfit,
            "start_misfit": result.history[0]["misfit"], "params": result.params,
            "iterations": result.iterations, "evaluations": result.evaluations,
            "seconds": result.seconds, "success": result.success, "message": result.message,
            "start_active_bounds": result.start_active_bounds,
            "active_bounds": result.active_bounds,
        }
        if data["truth_params"]:
            summary["param_rel_error"] = {
                k: abs(result.params[k] - v) / abs(v) if v else abs(result.params[k])
                for k, v in data["truth_params"].items() if k in result.wrt}
        if data["truth/u0"] is not None:
            summary["u0_mse"] = float(np.mean((result.state - data["truth/u0"]) ** 2))
        _write_fitted(self.out / "fitted.h5", self.scene.name, data["config"], result)
        return summary

    def plot(self) -> None:
        """``fit.png`` and ``history.png`` (misfit and gradient norm per iteration)."""
        if not self.plots:
            return
        result = self.result
        plot_fit(self.out / "fit.png", self.scene, self.obs, result, self.data["truth/u0"])
        curves = {label: [{"iteration": h["iteration"], "value": max(h[key], 1e-300)}
                          for h in result.history]
                  for label, key in (("misfit", "misfit"), ("gradient norm", "grad_norm"))}
        plot_history(self.out / "history.png", curves, "iteration", "value", "iteration",
                     "misfit, gradient norm",
                     title=f"{self.scene.name}: fit of {', '.join(result.wrt)}")

    def histories(self) -> dict[str, list[dict]]:
        return {"history.csv": [] if self.result is None else self.result.history}


def run_fit(cfg: FitConfig, out: str | Path, resume: bool = False, overwrite: bool = False,
            progress: bool = True, plots: bool = True) -> dict[str, Any]:
    """Fit as configured in the run directory ``out`` (module doc); returns result.json's
    contents (the config and the fit's summary). A finished fit is returned as it is with
    ``resume``, refused without it; ``overwrite`` discards the fit in ``out``, once the new
    one's inputs are checked."""
    cfg.validate()
    return engine.run(FitRun(cfg, out, plots=plots), resume=resume, overwrite=overwrite,
                      progress=progress)


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
