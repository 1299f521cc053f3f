"""Gradient verification: dot-product test, Taylor test and central finite differences.

For every registered solver and every differentiated input (the initial state, the controls,
each scene parameter) the checker draws a rollout and cotangents w_k on a random subset K of its
states (always including the last one) and compares the hand-written adjoint against:

* a **dot-product test**: ⟨J v, w⟩ against ⟨v, Jᵀ w⟩. ``J v`` is the complex-step derivative
  Im F(x + i h v) / h of the same compiled kernels (exact to round-off, no cancellation), or, for
  solvers that cannot run complex arrays, Ridders' extrapolation of central differences over
  two interleaved sequences of halving steps, whose error is estimated by the tableau and by
  how far the two sequences' extrapolations disagree;
* a **Taylor test** on the quadratic functional Φ = Σ_K ⟨w_k, u_k⟩ + ½‖u_k‖²: the remainder
  |Φ(x + εδ) − Φ(x) − ε⟨∇Φ, δ⟩| must be O(ε²) as ε → 0, down to the level where round-off
  (or the gradient's own precision) hides it. The reported rate is the median local order over
  the three smallest halvings above that floor (none is above it when Φ is linear along δ: no
  rate, no verdict); it passes at ``rate`` or more, or when remainder/ε² grows at most 2x over
  the last two halvings above the floor (a small quadratic term under a cubic one of the other
  sign converges to 2 from below; a gradient error e adds e·ε, which grows remainder/ε² 4x);
* a **central finite difference** of Φ along the same direction, extrapolated and estimated in
  the same way.

A reference with an error estimate cannot decide below that estimate, so a difference passes
when it is within max(tolerance, 10 × the reference's estimated error), and the row fails as
undecidable when the estimate itself exceeds a limit (``dot_ref``/``fd_ref``). ``dot_ref`` is
8e-8 in float64, so the dot-product bound never exceeds 8e-7: an adjoint error of relative size
1e-6 is always caught. The one exception: an undecidable central-FD reference does not fail a
row whose exact (complex-step) dot-product test and Taylor test passed; ``reason`` then notes
it. The step sequences start from a 10 % change of the trajectory (the stepper's
``check_perturbation``; 3 % for the semi-Lagrangian flows, whose interpolation switches cells)
(scaled by the
rollout's measured sensitivity: large steps keep the differences above round-off where the
state's influence decays, and the extrapolation skips steps outside the h² range) and halve
eleven times, so a long chaotic rollout is also probed where its Taylor expansion holds.

In float32 the adjoint runs in float32 while the references (tangent, Φ) run the float64
kernels from the same float32 inputs: the check then measures the float32 adjoint's own
error, not the round-off of a float32 finite difference. The dot-product bound also allows
the float32 adjoint's round-off: twice its measured distance to the same adjoint run in
float64, capped at 3 √(steps+1) ε₃₂ Σ|terms| (see ``_roundoff_allowance``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from . import registry, validate
from .stepper import Stepper

#: thresholds per dtype: dot-product rel. error and the largest reference error estimate that
#: still decides it, Taylor rate, central-FD rel. error and its largest reference estimate
TOLERANCES: dict[str, dict[str, float]] = {
    "float64": {"dot": 1e-10, "dot_ref": 8e-8, "rate": 1.9, "fd": 1e-6, "fd_ref": 1e-6},
    "float32": {"dot": 1e-4, "dot_ref": 1e-5, "rate": 1.8, "fd": 2e-2, "fd_ref": 2e-3},
}
#: a difference passes within this many estimated reference errors
REF_SAFETY = 10.0
_H_COMPLEX_STEP = 1e-100
#: halving steps of the Ridders tableau and the Taylor sequence (they share the rollouts)
_LEVELS = 11
#: the two step sequences h₀ c 2⁻ʲ (c = 1 and a ratio far from a power of two)
_OFFSETS = (1.0, 0.7)
_EPS = float(np.finfo(np.float64).eps)
_EPS32 = float(np.finfo(np.float32).eps)
#: the float32 adjoint's round-off allowance is at most this many √(steps+1) ε₃₂ Σ|terms|
_ROUNDOFF_SAFETY = 3.0
#: remainder/ε² may grow this much over the smallest-ε levels of an O(ε²) remainder
_TAYLOR_GROWTH = 2.0
_UNDECIDABLE = ": undecidable"


@dataclass(frozen=True)
class CheckResult:
    """One row of ``adjointsim gradcheck``.

    ``*_rel_err`` compares the adjoint with a reference, ``*_ref_err`` is that reference's
    estimated relative error (0 for the complex step) and ``*_bound`` what the comparison had to
    meet. A value that could not be measured is None, and ``reason`` says why a row failed (or,
    for a passing row, which reference could not decide and why that did not matter).
    """

    solver: str
    wrt: str
    dot_rel_err: float | None
    dot_ref_err: float | None
    dot_bound: float | None
    taylor_rate: float | None
    fd_rel_err: float | None
    fd_ref_err: float | None
    fd_bound: float | None
    passed: bool
    reason: str | None = None

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON values: non-finite numbers become None."""
        return {
            k: None if isinstance(v, float) and not math.isfinite(v) else v
            for k, v in asdict(self).items()
        }


def _positive(stepper: Stepper, name: str, value: Any) -> int:
    try:
        k = validate.count(stepper.name, name, value)
    except (TypeError, ValueError):
        k = 0
    if k < 1:
        raise ValueError(f"{stepper.name}: {name} must be a positive integer, not {value!r}")
    return k


def check_stepper(
    stepper: Stepper,
    steps: int = 50,
    dtype: str = "float64",
    seed: int = 0,
    batch: int = 2,
) -> list[CheckResult]:
    """Check the adjoint of ``stepper`` for its state, controls and every scene parameter."""
    if dtype not in TOLERANCES:
        raise ValueError(f"dtype must be one of {sorted(TOLERANCES)}, not {dtype!r}")
    # zero steps or an empty batch have no gradient to compare (the contract tests cover them)
    steps = _positive(stepper, "steps", steps)
    batch = _positive(stepper, "batch", batch)
    rng = np.random.default_rng(seed)
    real = np.dtype(dtype)
    u0 = stepper.random_state(rng, batch, real)
    ctrl = (
        stepper.random_controls(rng, steps, batch, real)
        if stepper.control_shape is not None
        else stepper.check_controls(None, steps, u0)
    )
    p = np.array(stepper.param_values, dtype=real)
    subset = sorted({steps, *rng.choice(steps + 1, size=min(3, steps + 1), replace=False).tolist()})
    w = {k: stepper.random_state(rng, batch, real) for k in subset}

    inputs: list[tuple[str, np.ndarray, np.ndarray]] = [
        ("state", u0, stepper.random_state(rng, batch, real))
    ]
    if stepper.control_shape is not None:
        # Controls enter as Δt c: scale the direction so the state moves by O(1) per unit ε.
        direction = stepper.random_controls(rng, steps, batch, real) / real.type(stepper.dt)
        inputs.append(("controls", ctrl, direction))
    for i, name in enumerate(stepper.param_names):
        direction = np.zeros_like(p)
        # Relative to the value, but never below an absolute 1e-3: a parameter at or near zero
        # (a buoyancy of 1e-226) moved relative to itself would move the trajectory by less
        # than its round-off, and no reference could see the slope.
        direction[i] = max(abs(p[i]), 1e-3)
        inputs.append((name, p, direction))

    def run(x: np.ndarray, which: str) -> np.ndarray:
        args = {"state": u0, "controls": ctrl, "params": p}
        args["params" if which not in ("state", "controls") else which] = x
        u, c, q = args["state"], args["controls"], args["params"]
        dt = np.result_type(u, c, q, np.float64)
        # Perturbed (complex-step) inputs on the fast path: rollout would reject complex
        # states, and a step too large for the scene must come back non-finite, not raise.
        return stepper.rollout_prepared(
            u.astype(dt), steps, c.astype(dt), q.astype(dt), keep="all", check_finite=False
        )

    def gradient(cot: dict[int, np.ndarray], which: str, dt: Any = real) -> np.ndarray:
        u = u0.astype(dt)
        g = stepper.vjp_prepared(
            u, steps, np.ascontiguousarray(ctrl, dtype=dt), p.astype(dt),
            *stepper.check_cotangents({k: v.astype(dt) for k, v in cot.items()}, steps, u),
            wrt_params=which not in ("state", "controls"),
        )
        if which == "state":
            return g.state
        if which == "controls":
            return g.controls
        return np.array([g.params[k] for k in stepper.param_names])

    base = run(u0, "state")
    quad_cot = {k: w[k] + base[k] for k in subset}
    scale = max(float(np.max(np.abs(base[subset]))), 1e-300)
    # Φ's round-off: 100 ε_mach Σ|terms| (the states' own round-off builds up over the steps),
    # amplified as the state direction's perturbations grow.
    phi0 = _linear(w, subset, base) + _half_square(subset, base)
    noise_phi = 100 * _EPS * (_magnitude(w, subset, base) + _half_square(subset, base))
    rows = []
    tol = TOLERANCES[dtype]
    for which, x, delta in inputs:
        x, delta = x.astype(np.float64), delta.astype(np.float64)
        grad_lin = gradient(w, which).astype(np.float64)
        grad_quad = gradient(quad_cot, which).astype(np.float64)
        adj = float(np.sum(grad_lin * delta))
        # float32: the same adjoint run in float64 on the same inputs measures the float32
        # adjoint's own round-off (see _compare's ``adjoint_err``).
        adj64 = adj if real == np.float64 else float(np.sum(gradient(w, which, np.float64) * delta))
        slope = float(np.sum(grad_quad * delta))

        # The tangent trajectory J δ: exact by complex step, else a one-sided difference that
        # only sets the perturbation size and the scale of the sums below.
        if stepper.complex_step:
            tangent_traj = np.imag(run(x + 1j * _H_COMPLEX_STEP * delta, which)) / _H_COMPLEX_STEP
        else:
            h = 1e-7 / max(float(np.max(np.abs(delta))), 1e-300)
            tangent_traj = (run(x + h * delta, which) - base) / h
        sensitivity = float(np.max(np.abs(tangent_traj[subset]))) / scale
        if which == "state":
            first = float(np.linalg.norm(tangent_traj[0]))
            growth = max(1.0, float(np.max(np.linalg.norm(
                tangent_traj.reshape(len(tangent_traj), -1), axis=1))) / max(first, 1e-300))
            noise_phi *= growth
        h0 = stepper.check_perturbation / max(sensitivity, 1.0)

        # Two interleaved sequences of halving steps: each gives Ridders' tableaus an
        # independent extrapolation, and how far the two disagree measures the round-off the
        # tableau's own estimate can miss. The first one also serves the Taylor test.
        lin_d: list[list[float]] = [[], []]
        quad_d: list[list[float]] = [[], []]
        remainders: list[float] = []
        hs: list[float] = []
        for j in range(_LEVELS):
            for seq, offset in enumerate(_OFFSETS):
                h = h0 * offset * 0.5**j
                plus, minus = run(x + h * delta, which), run(x - h * delta, which)
                if not (np.all(np.isfinite(plus[subset])) and np.all(np.isfinite(minus[subset]))):
                    continue  # too large a step for this scene: start lower
                lp, lm = _linear(w, subset, plus), _linear(w, subset, minus)
                qp = lp + _half_square(subset, plus)
                qm = lm + _half_square(subset, minus)
                lin_d[seq].append((lp - lm) / (2 * h))
                quad_d[seq].append((qp - qm) / (2 * h))
                if seq == 0:
                    remainders.append(abs(qp - phi0 - h * slope))
                    hs.append(h)

        reasons: list[str] = []
        # Σ|terms| of both sides: below 100 ε_mach of it a difference is cancellation.
        mag_lin = _magnitude(w, subset, tangent_traj) + float(np.sum(np.abs(grad_lin * delta)))
        if stepper.complex_step:
            tangent, tangent_err = _linear(w, subset, tangent_traj), 0.0
        else:
            tangent, tangent_err = _extrapolate(lin_d)
        dot_err, dot_ref, dot_bound, dot_reason = _compare(
            adj, tangent, tangent_err, mag_lin, tol["dot"], tol["dot_ref"], "dot-product",
            _roundoff_allowance(adj, adj64, steps, float(np.sum(np.abs(grad_lin * delta)))),
        )
        fd, fd_abs_err = _extrapolate(quad_d)
        mag_quad = (
            _magnitude(w, subset, tangent_traj) + _magnitude(base, subset, tangent_traj)
            + float(np.sum(np.abs(grad_quad * delta)))
        )
        fd_err, fd_ref, fd_bound, fd_reason = _compare(
            slope, fd, fd_abs_err, mag_quad, tol["fd"], tol["fd_ref"], "central-FD"
        )
        # The remainder is only read where it exceeds Φ's round-off and what the gradient's own
        # precision (the dot-product tolerance) can resolve.
        floors = [10 * (noise_phi + h * abs(slope) * tol["dot"]) for h in hs]
        rate = _taylor_rate(remainders, floors)
        # No remainder above its floor (rate None): Φ is linear along δ to round-off,
        # consistent with the slope at every ε; there is no second-order term to measure and
        # the dot-product and FD tests decide the first-order one.
        taylor_ok = rate is None or rate >= tol["rate"] or _quadratic(remainders, floors, hs)
        if dot_reason:
            reasons.append(dot_reason)
        if not taylor_ok:
            reasons.append(
                f"Taylor rate {rate:.3f} < {tol['rate']:g} and remainder/ε² grows more than "
                f"{_TAYLOR_GROWTH:g}x over the smallest ε"
            )
        notes: list[str] = []
        if fd_reason and fd_reason.endswith(_UNDECIDABLE) and not reasons and rate is not None \
                and stepper.complex_step:
            # An exact (complex-step) dot-product test at round-off and a quadratic Taylor
            # remainder already decided the gradient of Φ: a noisy FD reference cannot overrule
            # them, it only fails to add a third opinion.
            notes.append(f"{fd_reason}; not needed: exact dot-product and Taylor tests passed")
        elif fd_reason:
            reasons.append(fd_reason)
        rows.append(CheckResult(
            stepper.name, which, dot_err, dot_ref, dot_bound, rate, fd_err, fd_ref, fd_bound,
            passed=not reasons, reason="; ".join(reasons or notes) or None,
        ))
    return rows


def _linear(w: dict[int, np.ndarray], subset: list[int], traj: np.ndarray) -> Any:
    return sum(np.sum(w[k] * traj[k]) for k in subset)


def _half_square(subset: list[int], traj: np.ndarray) -> float:
    return float(sum(0.5 * np.sum(traj[k] ** 2) for k in subset))


def _magnitude(w: dict[int, np.ndarray] | np.ndarray, subset: list[int], traj: np.ndarray) -> float:
    """Σ|terms| of ⟨w, traj⟩ over the subset: the scale below which a sum is cancellation."""
    return float(sum(np.sum(np.abs(w[k] * traj[k])) for k in subset))


def _compare(
    adjoint: float,
    reference: float,
    reference_err: float,
    magnitude: float,
    tol: float,
    ref_limit: float,
    what: str,
    adjoint_err: float = 0.0,
) -> tuple[float, float, float, str | None]:
    """Relative mismatch, the reference's relative error estimate, the bound the mismatch must
    meet and why it failed (None when it passed). ``adjoint_err`` is the absolute round-off
    the adjoint's own value may carry (float32)."""
    denom = max(abs(adjoint), abs(reference), 100 * _EPS * magnitude, 1e-300)
    err = abs(adjoint - reference) / denom
    ref = reference_err / denom
    bound = max(tol, REF_SAFETY * ref, adjoint_err / denom)
    if not math.isfinite(err) or not math.isfinite(ref):
        return err, ref, bound, f"{what} reference is non-finite"
    if ref > ref_limit:
        return err, ref, bound, f"{what} reference error estimate {ref:.2e} > {ref_limit:g}" \
            + _UNDECIDABLE
    if err > bound:
        return err, ref, bound, f"{what} rel. error {err:.2e} > {bound:.2e}"
    return err, ref, bound, None


def _roundoff_allowance(adj32: float, adj64: float, steps: int, magnitude: float) -> float:
    """The absolute round-off a float32 adjoint's ⟨v, Jᵀw⟩ may carry (0 in float64).

    It is its measured distance to the same adjoint run in float64 on the same inputs, times
    two, but never more than what float32 arithmetic can explain: three standard deviations
    of a random walk of ε₃₂-sized errors over the sweep, 3 √(steps+1) ε₃₂ Σ|terms| of the sum
    (advection2d-upwind's state, seed 2, measures 0.6 of one). A bug only in the float32 path
    cannot hide behind that cap, and a wrong adjoint (in both precisions) does not widen it.
    """
    if adj32 == adj64:
        return 0.0
    cap = _ROUNDOFF_SAFETY * math.sqrt(steps + 1) * _EPS32 * magnitude
    return min(2 * abs(adj32 - adj64), cap)


def _extrapolate(sequences: list[list[float]]) -> tuple[float, float]:
    """The better of the sequences' Ridders extrapolations and an error estimate: the larger
    of its own tableau estimate and its distance to the other extrapolation."""
    results = [_ridders(d) for d in sequences]
    best = min(results, key=lambda r: r[1])
    spread = max(abs(best[0] - r[0]) for r in results)
    return best[0], max(best[1], spread)


def _ridders(d: list[float]) -> tuple[float, float]:
    """Ridders' extrapolation of central differences ``d[j]`` at steps h₀/2ʲ (Press et al.,
    Numerical Recipes §5.7) and its error estimate, the larger difference of the chosen
    tableau entry to its two lower-order neighbours.

    The largest steps may lie outside the range where the expansion in h² holds, so the
    tableau is started at each level and the start with the smallest estimate is kept.
    """
    result = (math.nan, math.inf)
    for start in range(len(d)):
        best, err = d[start], math.inf
        prev = [d[start]]
        for i in range(start + 1, len(d)):
            cur = [d[i]]
            fac = 4.0  # central differences expand in even powers of h
            for j in range(1, i - start + 1):
                cur.append((cur[j - 1] * fac - prev[j - 1]) / (fac - 1))
                fac *= 4.0
                e = max(abs(cur[j] - cur[j - 1]), abs(cur[j] - prev[j - 1]))
                if e <= err:
                    best, err = cur[j], e
            if abs(cur[-1] - prev[-1]) >= 2 * err:  # higher order stopped helping: round-off
                break
            prev = cur
        if err < result[1]:
            result = (best, err)
    return result


def _quadratic(remainders: list[float], floors: list[float], hs: list[float]) -> bool:
    """Whether the remainder is O(ε²) at the smallest ε: over the last three levels above
    their floors (two halvings), remainder/ε² grows by at most ``_TAYLOR_GROWTH`` as ε shrinks.

    A correct gradient whose quadratic term is small along δ (a cubic term dominating the
    larger steps, possibly of the other sign) gives local rates below 2 that converge to it,
    with remainder/ε² settling at the quadratic coefficient. A gradient error e adds e·ε: where
    it dominates, remainder/ε² doubles at every halving, 4x over the two.
    """
    above = [i for i in range(len(remainders)) if remainders[i] > floors[i]][-3:]
    if len(above) < 3:
        return False
    q = [remainders[i] / hs[i] ** 2 for i in above]
    growth = max(q[k] / q[j] for j in range(len(q)) for k in range(j + 1, len(q)))
    return growth <= _TAYLOR_GROWTH


def _taylor_rate(remainders: list[float], floors: list[float]) -> float | None:
    """Median order of the Taylor remainder over the last (smallest-ε) three halvings whose
    remainders both stand above their floors; None when fewer than two halvings do (a single
    one may lie before the range where the remainder is quadratic, and a gradient error
    large enough to matter keeps the remainder above the floor at every ε)."""
    rates = [
        math.log2(remainders[i] / remainders[i + 1])
        for i in range(len(remainders) - 1)
        if remainders[i] > floors[i] and remainders[i + 1] > floors[i + 1]
    ]
    return float(np.median(rates[-3:])) if len(rates) >= 2 else None


def check(
    names: Iterable[str] | None = None,
    steps: int = 50,
    dtype: str = "float64",
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> list[CheckResult]:
    """Check the default scene of each named registered solver (all of them by default)."""
    rows: list[CheckResult] = []
    for name in names if names is not None else registry.names():
        if progress:
            progress(name)
        rows.extend(check_stepper(registry.get(name).default(), steps, dtype, seed))
    return rows
