"""Inverse problems with the hand-written adjoints: fit a rollout to observations (no torch).

Given a scene, observations d_k of the states u_k at chosen steps k ∈ K and a choice ``wrt`` of
unknowns z (any mix of the initial state u_0, the per-step controls c_0 .. c_{n-1} and the scene's
differentiable parameters p), :func:`fit` minimises

    J(z) = M(z) + R(z),   M = (1/N_obs) Σ_{k ∈ K} ‖u_k(z) − d_k‖²   (the misfit, an MSE),
    R = λ_T Σ_b mean((z_b − z_b⁰)²) + λ_S Σ_b mean((D z_b)²)

over the blocks b of z, with z⁰ the starting guess (Tikhonov) and D first differences along the
grid axes of the state and along time of the controls (smoothness; parameters take no D). The
gradient of M is one adjoint sweep, :meth:`Stepper.vjp` with the cotangents 2(u_k − d_k)/N_obs
at the observed steps (``wrt_params=True`` when parameters are fitted, ``checkpoint=`` for long
rollouts); R's is written out. Parameters are optimised in units of their starting magnitude
(p = |p⁰| ζ) so that they and the state are of similar scale for the optimiser; bounds are given
in the parameters' own units. A start outside its bounds is refused: scipy would move it onto
the bound, which changes the problem (and can end the fit there after 0 iterations).

The optimiser is :func:`scipy.optimize.minimize`, L-BFGS-B by default (bounds for parameters);
any of its gradient-based methods can be named. Everything runs in float64.
"""

from __future__ import annotations

import math
import numbers
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import minimize

from .files import short
from .stepper import NonFiniteStateError, Stepper

#: scipy methods that use the gradient (and so the adjoint)
GRADIENT_METHODS = ("L-BFGS-B", "BFGS", "CG", "TNC", "SLSQP", "trust-constr", "Newton-CG")
#: of these, the ones that take bounds
BOUNDED_METHODS = ("L-BFGS-B", "TNC", "SLSQP", "trust-constr")
BLOCKS = ("state", "controls", "params")
#: a parameter within this much of a bound, relative to the larger of the bound's and the start's
#: magnitude, sits on it (interior-point methods such as trust-constr stop ~1e-5 short of it)
ACTIVE_RTOL = 1e-4
ACCEPTED_BOUNDS = "accepted: (lo, hi), each a real number or None (no bound), lo ≤ hi"


class FitError(ValueError):
    """The fit cannot go on (a non-finite misfit, parameters beyond a stability limit)."""


class StartOutsideBoundsError(ValueError):
    """A fitted parameter's start lies outside its bounds (``name``, ``start``, ``bounds`` as
    given), so that a caller can say how to fix it in its own terms."""

    def __init__(self, name: str, start: float, bounds: tuple) -> None:
        self.name, self.start, self.bounds = name, start, bounds
        super().__init__(
            f"the start of {name} ({start}) is outside its bounds {_show_bounds(bounds)}; pass "
            f"a start inside them (params={{'{name}': ...}}) or wider bounds: a start moved "
            "onto a bound would change the problem")


@dataclass
class FitResult:
    """What :func:`fit` returns.

    ``state``, ``controls`` and ``params`` are the fitted (or, when not fitted, the given)
    initial state, controls and scene parameters; ``predicted`` maps each observed step to the
    fitted rollout's state there. ``history`` has one row per iteration (iteration 0 is the
    start): misfit, regularisation, objective, gradient norm (of the objective in the
    optimiser's variables), evaluations so far, seconds and CPU seconds of this process.
    ``start_active_bounds`` and ``active_bounds`` map the fitted parameters on one of their
    bounds (within :data:`ACTIVE_RTOL`) at the start and at the end to ``"lower"`` or
    ``"upper"``.
    """

    state: np.ndarray
    controls: np.ndarray | None
    params: dict[str, float]
    misfit: float
    predicted: dict[int, np.ndarray]
    history: list[dict[str, float]]
    success: bool
    message: str
    iterations: int
    evaluations: int
    seconds: float
    wrt: tuple[str, ...] = field(default=())
    start_active_bounds: dict[str, str] = field(default_factory=dict)
    active_bounds: dict[str, str] = field(default_factory=dict)


def parse_wrt(stepper: Stepper, wrt: str | Sequence[str]) -> tuple[bool, bool, tuple[str, ...]]:
    """(fit the state, fit the controls, the parameter names fitted) from ``wrt``: entries
    ``state``, ``controls``, ``params`` (every parameter) or single parameter names."""
    items = [w.strip() for w in (wrt.split(",") if isinstance(wrt, str) else wrt)]
    items = [w for w in items if w]
    if not items:
        raise ValueError("wrt is empty; name what to fit: state, controls, params or "
                         f"parameter names {list(stepper.param_names)}")
    names: list[str] = []
    for w in items:
        if w == "params":
            names += [p for p in stepper.param_names if p not in names]
        elif w in stepper.param_names:
            if w not in names:
                names.append(w)
        elif w not in ("state", "controls"):
            raise ValueError(
                f"unknown wrt entry {w!r}; choose from state, controls, params or the "
                f"parameters of {stepper.name}: {', '.join(stepper.param_names) or '(none)'}"
            )
    if "params" in items and not stepper.param_names:
        raise ValueError(f"{stepper.name} has no differentiable parameters to fit")
    if "controls" in items and stepper.control_shape is None:
        raise ValueError(f"{stepper.name} has no control hook; drop 'controls' from wrt")
    return "state" in items, "controls" in items, tuple(names)


def check_observations(
    stepper: Stepper, observations: Mapping[int, Any], n: int | None, batch: int
) -> tuple[int, dict[int, np.ndarray]]:
    """(rollout length, {step: observed state}) checked against the scene: steps in 0..n,
    states of shape (batch, C, *grid), finite."""
    if not isinstance(observations, Mapping) or not observations:
        raise ValueError("observations must be a non-empty mapping {step: state}")
    if batch == 0:
        raise ValueError("the observations (or u0) have an empty batch (B = 0): nothing to fit")
    obs: dict[int, np.ndarray] = {}
    for key, value in observations.items():
        if isinstance(key, bool) or not isinstance(key, int | np.integer):
            raise TypeError(f"observation steps are integers, not {key!r}")
        k = int(key)
        if k < 0 or (n is not None and k > n):
            top = "n" if n is None else str(n)
            raise ValueError(f"observation step {k} is outside the rollout: steps run from 0 "
                             f"(u_0) to {top}")
        a = np.asarray(value)
        expected = stepper.state_shape(batch)
        if a.shape != expected:
            raise ValueError(f"{stepper.name}: the observation at step {k} has shape {a.shape}; "
                             f"expected {expected} = (batch, channels, *grid)")
        if a.dtype.kind not in "iuf":
            raise TypeError(f"the observation at step {k} has dtype {a.dtype}; expected real")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"the observation at step {k} has non-finite values")
        obs[k] = a.astype(np.float64)
    n = max(obs) if n is None else int(n)
    return n, dict(sorted(obs.items()))


def _show_bounds(bounds: tuple) -> str:
    return "(" + ", ".join("None" if b is None else str(b) for b in bounds) + ")"


def check_bounds(
    bounds: Mapping[str, Any], fit_names: Sequence[str], start: Mapping[str, float]
) -> dict[str, tuple[float | None, float | None]]:
    """``bounds`` ({parameter: (lo, hi)}) checked: fitted parameters only, real numbers or None,
    no NaN, lo ≤ hi, each start inside (else :class:`StartOutsideBoundsError`); returned as
    floats, an infinite side as None."""
    out: dict[str, tuple[float | None, float | None]] = {}
    for name, given in bounds.items():
        if name not in start:
            raise ValueError(f"bounds name {name}, which is not a parameter (the parameters: "
                             f"{', '.join(start) or '(none)'}); drop its bounds")
        if name not in fit_names:
            raise ValueError(f"bounds name {name}, which is not fitted: bounds are accepted for "
                             f"the fitted parameters {', '.join(fit_names) or '(none)'}; fit "
                             f"{name} (wrt) or drop its bounds")
        numbers = isinstance(given, tuple | list) and len(given) == 2 and all(
            b is None or (isinstance(b, int | float | np.integer | np.floating)
                          and not isinstance(b, bool)) for b in given)
        if not numbers:
            raise ValueError(f"bounds of {name} {given!r} are not a pair of numbers or None; "
                             f"{ACCEPTED_BOUNDS}")
        lo, hi = (None if b is None else float(b) for b in given)
        shown = _show_bounds(tuple(given))
        if any(b is not None and math.isnan(b) for b in (lo, hi)):
            raise ValueError(f"bounds of {name} {shown} have a NaN; {ACCEPTED_BOUNDS}")
        if lo == math.inf or hi == -math.inf:
            raise ValueError(f"bounds of {name} {shown} exclude every value; {ACCEPTED_BOUNDS}")
        if lo is not None and hi is not None and lo > hi:
            raise ValueError(f"bounds of {name} {shown} are reversed: lo {given[0]} > hi "
                             f"{given[1]}; {ACCEPTED_BOUNDS}")
        lo = None if lo == -math.inf else lo
        hi = None if hi == math.inf else hi
        p = start[name]
        if (lo is not None and p < lo) or (hi is not None and p > hi):
            raise StartOutsideBoundsError(name, p, tuple(given))
        out[name] = (lo, hi)
    return out


def _smooth_grad(a: np.ndarray, axes: Sequence[int]) -> tuple[float, np.ndarray]:
    """Σ_axes mean((D a)²) and its gradient (D the forward difference along each axis)."""
    value, grad = 0.0, np.zeros_like(a)
    for ax in axes:
        if a.shape[ax] < 2:
            continue
        d = np.diff(a, axis=ax)
        value += float(np.mean(d * d))
        w = 2.0 * d / d.size
        pad = [(0, 0)] * a.ndim
        pad[ax] = (1, 0)
        lo = np.pad(w, pad)  # +w at i+1
        pad[ax] = (0, 1)
        hi = np.pad(w, pad)  # −w at i
        grad += lo - hi
    return value, grad


@dataclass
class FitProblem:
    """The objective of a fit in the optimiser's variables z (see :func:`problem`).

    ``z0``: the starting point; ``objective(z)`` returns (J, ∇J) (J = 1e3 (1 + J(z0)) with a
    zero gradient for a trial point whose rollout is not finite or whose parameters break the
    scene's limits, once the start has been evaluated); ``unpack(z)`` gives (state, controls,
    params); ``last`` holds the misfit, regularisation and gradient norm of the last admissible
    call and the evaluation count; ``bounds`` the scipy bounds; ``predict(z)`` the states at the
    observed steps; ``active_bounds(params)`` the fitted parameters on a bound (see
    :class:`FitResult`).
    """

    z0: np.ndarray
    objective: Callable[[np.ndarray], tuple[float, np.ndarray]]
    unpack: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray | None, dict[str, float]]]
    predict: Callable[[np.ndarray], dict[int, np.ndarray]]
    last: dict[str, Any]
    bounds: list | None
    observations: dict[int, np.ndarray]
    n: int
    wrt: tuple[str, ...]
    active_bounds: Callable[[Mapping[str, float]], dict[str, str]]


def problem(
    stepper: Stepper,
    observations: Mapping[int, Any],
    *,
    n: int | None = None,
    wrt: str | Sequence[str] = "state",
    u0: np.ndarray | None = None,
    controls: np.ndarray | None = None,
    params: Mapping[str, float] | None = None,
    bounds: Mapping[str, tuple[float | None, float | None]] | None = None,
    method: str = "L-BFGS-B",
    tikhonov: float = 0.0,
    smoothness: float = 0.0,
    checkpoint: int | None = None,
) -> FitProblem:
    """The checked objective of :func:`fit` (same arguments), for an optimiser of one's own."""
    if method not in GRADIENT_METHODS:
        raise ValueError(f"method {method!r} is not a gradient-based scipy method; choose from "
                         f"{', '.join(GRADIENT_METHODS)}")
    fit_state, fit_controls, fit_names = parse_wrt(stepper, wrt)
    for what, lam in (("tikhonov", tikhonov), ("smoothness", smoothness)):
        if isinstance(lam, np.ndarray) and lam.ndim == 0:
            lam = lam[()]
        if isinstance(lam, bool) or not isinstance(lam, numbers.Real):
            raise TypeError(f"{what} must be a finite number ≥ 0, not {short(lam)}")
        if not (math.isfinite(lam) and lam >= 0):
            raise ValueError(f"{what} must be a finite number ≥ 0, not {lam}")

    # ------------------------------------------------------------ the fixed and starting values
    batch = 1
    if u0 is not None:
        u0 = stepper.check_state(u0, "u0").astype(np.float64)
        batch = u0.shape[0]
    elif observations and isinstance(observations, Mapping):
        first = np.asarray(next(iter(observations.values())))
        batch = first.shape[0] if first.ndim == len(stepper.state_shape()) else 1
    n, obs = check_observations(stepper, observations, n, batch)
    if u0 is None:
        if not fit_state:
            raise ValueError("u0 is needed when the initial state is not fitted (wrt has no "
                             "'state')")
        u0 = np.zeros(stepper.state_shape(batch))
    if controls is not None:
        controls = stepper.check_controls(np.asarray(controls, dtype=np.float64), n, u0)
    elif fit_controls:
        controls = np.zeros((n, batch, *stepper.control_shape))
    p0 = dict(stepper.params)
    if params is not None:
        unknown = sorted(set(params) - set(p0))
        if unknown:
            raise ValueError(f"{stepper.name} has no parameter(s) {unknown}; its parameters "
                             f"are {list(stepper.param_names)}")
        p0.update({k: float(v) for k, v in params.items()})
    stepper.param_array(p0, np.float64)  # finite and within the scheme's limits
    bounds = check_bounds(bounds or {}, fit_names, p0)
    if bounds and method not in BOUNDED_METHODS:
        raise ValueError(f"method {method} takes no bounds; use one of "
                         f"{', '.join(BOUNDED_METHODS)} or drop the bounds")
    if fit_controls and n == 0:
        raise ValueError("controls cannot be fitted over a rollout of 0 steps")

    # ------------------------------------------------------------ the packing of z
    scale = np.array([abs(p0[k]) if p0[k] != 0 else 1.0 for k in fit_names])
    sizes = {"state": u0.size if fit_state else 0,
             "controls": controls.size if fit_controls else 0,
             "params": len(fit_names)}
    start = {"state": u0.ravel(), "controls": controls.ravel() if fit_controls else None,
             "params": np.array([p0[k] for k in fit_names]) / scale}
    blocks = [b for b in BLOCKS if sizes[b]]
    z0 = np.concatenate([start[b] for b in blocks])

    def unpack(z: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, dict[str, float]]:
        i, u, c, p = 0, u0, controls, dict(p0)
        for b in blocks:
            part = z[i:i + sizes[b]]
            i += sizes[b]
            if b == "state":
                u = part.reshape(u0.shape)
            elif b == "controls":
                c = part.reshape(controls.shape)
            else:
                p.update({k: float(v * s) for k, v, s in zip(fit_names, part, scale)})
        return u, c, p

    grid_axes = tuple(range(2, u0.ndim))
    count = sum(a.size for a in obs.values())
    last: dict[str, Any] = {"evaluations": 0}

    def rollout_at_observations(u, c, p) -> dict[int, np.ndarray]:
        if checkpoint is None:
            traj = stepper.rollout(u, n, c, p, keep="all")
            last["trajectory"] = traj
            return {k: traj[k] for k in obs}
        # Long rollouts: advance from one observed step to the next, keeping only those states.
        out, cur, at = {}, u, 0
        for k in obs:
            if k > at:
                cur = stepper.rollout(cur, k - at, None if c is None else c[at:k], p)
                at = k
            out[k] = cur
        return out

    def predict(z: np.ndarray) -> dict[int, np.ndarray]:
        out = rollout_at_observations(*unpack(z))
        last.pop("trajectory", None)
        return out

    def objective(z: np.ndarray) -> tuple[float, np.ndarray]:
        last["evaluations"] += 1
        evaluations = last["evaluations"]
        u, c, p = unpack(z)
        try:
            pred = rollout_at_observations(u, c, p)
        except (NonFiniteStateError, ValueError) as e:
            if "z" in last:
                # A line-search trial beyond the stable range. Infinity would end scipy's line
                # search; a large finite value with no slope makes it back off instead.
                last.pop("trajectory", None)
                return 1e3 * (1.0 + last["start"]), np.zeros_like(z)
            if isinstance(e, NonFiniteStateError):
                raise FitError(f"the misfit is non-finite at the starting guess: {e}") from None
            raise FitError(f"the starting guess is not admissible: {e}") from None
        res = {k: pred[k] - obs[k] for k in obs}
        misfit = sum(float(np.sum(r * r)) for r in res.values()) / count
        if not math.isfinite(misfit):
            raise FitError(f"the misfit is non-finite ({misfit}) at evaluation {evaluations}")
        cot = {k: 2.0 * r / count for k, r in res.items()}
        g = stepper.vjp(u, n, cot, c, p, wrt_params=bool(fit_names), checkpoint=checkpoint,
                        trajectory=last.pop("trajectory", None))
        reg, parts = 0.0, []
        for b in blocks:
            if b == "state":
                x, x0, gx, axes = u, start["state"].reshape(u0.shape), g.state, grid_axes
            elif b == "controls":
                x, x0, gx = c, start["controls"].reshape(controls.shape), g.controls
                axes = (0,)
            else:
                x, x0, axes = z[-len(fit_names):], start["params"], ()
                gx = np.array([g.params[k] for k in fit_names]) * scale
            gx = np.array(gx, dtype=np.float64)
            if tikhonov:
                d = x - x0
                reg += tikhonov * float(np.mean(d * d))
                gx = gx + tikhonov * 2.0 * d / d.size
            if smoothness and axes:
                v, gs = _smooth_grad(x, axes)
                reg += smoothness * v
                gx = gx + smoothness * gs
            parts.append(gx.ravel())
        grad = np.concatenate(parts)
        last.setdefault("start", misfit + reg)
        last.update(z=z.copy(), misfit=misfit, reg=reg, grad_norm=float(np.linalg.norm(grad)))
        return misfit + reg, grad

    scipy_bounds = None
    if method in BOUNDED_METHODS and bounds:
        scipy_bounds = [(None, None)] * (len(z0) - len(fit_names))
        for k, s in zip(fit_names, scale):
            lo, hi = bounds.get(k, (None, None))
            scipy_bounds.append((None if lo is None else lo / s, None if hi is None else hi / s))
    wrt_names = (*(("state",) if fit_state else ()), *(("controls",) if fit_controls else ()),
                 *fit_names)

    def active_bounds(values: Mapping[str, float]) -> dict[str, str]:
        out = {}
        for k, (lo, hi) in bounds.items():
            p = values[k]
            near = [(abs(p - b), side) for side, b in (("lower", lo), ("upper", hi))
                    if b is not None and abs(p - b) <= ACTIVE_RTOL * max(abs(b), abs(p0[k]))]
            if near:
                out[k] = min(near)[1]
        return out

    return FitProblem(z0=z0, objective=objective, unpack=unpack, predict=predict, last=last,
                      bounds=scipy_bounds, observations=obs, n=n, wrt=wrt_names,
                      active_bounds=active_bounds)


def fit(
    stepper: Stepper,
    observations: Mapping[int, Any],
    *,
    maxiter: int = 500,
    method: str = "L-BFGS-B",
    tol: float | None = 1e-12,
    options: Mapping[str, Any] | None = None,
    callback: Callable[[dict[str, float]], None] | None = None,
    **kwargs: Any,
) -> FitResult:
    """Fit the rollout of ``stepper`` to ``observations`` ({step: state (B, C, *grid)}).

    Keywords of :func:`problem`: ``n`` (rollout length, default the last observed step),
    ``wrt`` (what to fit, see :func:`parse_wrt`), ``u0``, ``controls``, ``params`` (the starting
    guesses of the fitted blocks and the fixed values of the others; defaults: a zero state,
    zero controls when fitted, none otherwise, the scene's parameters), ``bounds``
    ({parameter: (lo, hi)}, either side None; a start outside them is refused with
    :class:`StartOutsideBoundsError`), ``tikhonov`` and ``smoothness`` (λ_T, λ_S, module
    doc), ``checkpoint`` (for the vjp). ``method``, ``tol`` and ``options`` go to
    :func:`scipy.optimize.minimize` (``maxiter`` is put in ``options``; for TNC, which has no
    iteration limit, as ``maxfun``, a limit on evaluations). ``callback`` gets each
    iteration's history row. A fit that stops after 0 iterations says why in its message.
    """
    if isinstance(maxiter, bool) or int(maxiter) != maxiter or maxiter < 0:
        raise ValueError(f"maxiter must be an integer ≥ 0, not {maxiter!r}")
    t_start, cpu_start = time.perf_counter(), time.process_time()
    prob = problem(stepper, observations, method=method, **kwargs)
    last, history = prob.last, []

    def record(z: np.ndarray) -> None:
        if "z" not in last or not np.array_equal(last["z"], z):
            prob.objective(z)
        row = {"iteration": len(history), "misfit": last["misfit"], "regularisation": last["reg"],
               "objective": last["misfit"] + last["reg"], "grad_norm": last["grad_norm"],
               "evaluations": last["evaluations"], "seconds": time.perf_counter() - t_start,
               "cpu_seconds": time.process_time() - cpu_start}
        history.append(row)
        if callback is not None:
            callback(row)

    z0 = prob.z0
    record(z0)
    # TNC has no iteration limit, only one on evaluations (scipy ignores its maxiter)
    opts = {"maxfun" if method == "TNC" else "maxiter": int(maxiter), **dict(options or {})}
    if maxiter == 0:
        z, success, message, nit = z0, True, "maxiter = 0: the starting guess", 0
    else:
        res = minimize(prob.objective, z0, jac=True, method=method, bounds=prob.bounds, tol=tol,
                       options=opts, callback=lambda zk, *rest: record(np.asarray(zk)))
        z, success, message = res.x, bool(res.success), str(res.message)
        nit = int(getattr(res, "nit", len(history) - 1))
    start_active = prob.active_bounds(prob.unpack(z0)[2])
    if nit == 0 and maxiter > 0:
        why = ("the stopping test already holds at the start" if success
               else "no step improved on the start")
        on = "; on a bound at the start: " + ", ".join(
            f"{k} ({side})" for k, side in start_active.items()) if start_active else ""
        message += f"; 0 iterations: {why} (gradient norm {history[0]['grad_norm']:.3g}{on})"
    u, c, p = prob.unpack(z)
    pred = prob.predict(z)
    obs = prob.observations
    misfit = sum(float(np.sum((pred[k] - obs[k]) ** 2)) for k in obs) / sum(
        a.size for a in obs.values())
    return FitResult(
        state=u.copy(), controls=None if c is None else c.copy(), params=p, misfit=misfit,
        predicted={k: v.copy() for k, v in pred.items()}, history=history, success=success,
        message=message, iterations=nit, evaluations=last["evaluations"],
        seconds=time.perf_counter() - t_start, wrt=prob.wrt, start_active_bounds=start_active,
        active_bounds=prob.active_bounds(p),
    )
