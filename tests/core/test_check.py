"""The gradient checker itself: it never flags a correct adjoint where its finite-difference
references are noisy, and it still catches small adjoint errors (its command, adjointsim
gradcheck, is tested in tests/commands/test_gradcheck.py)."""

import json
import math
from dataclasses import replace

import numpy as np
import pytest

import adjointsim
from adjointsim.check import (
    REF_SAFETY,
    TOLERANCES,
    CheckResult,
    _extrapolate,
    _quadratic,
    _ridders,
    _roundoff_allowance,
    _taylor_rate,
    check,
    check_stepper,
)


def _small(name: str):
    cls = adjointsim.get(name)
    if name.startswith("ks1d"):
        return cls(n=16, length=3 * np.pi, dt=0.1)
    return cls.default()


def _perturbed(stepper, rel: float, only_float32: bool = False):
    """The same scene whose adjoint returns every cotangent scaled by 1 + rel (or only when
    it runs in float32: a bug of the float32 path alone)."""
    vjp = stepper.vjp_prepared

    def wrong(*args, **kwargs):
        g = vjp(*args, **kwargs)
        if only_float32 and args[0].dtype != np.float32:
            return g
        return replace(
            g,
            state=g.state * (1 + rel),
            controls=None if g.controls is None else g.controls * (1 + rel),
            params=None if g.params is None else {k: v * (1 + rel) for k, v in g.params.items()},
        )

    stepper.vjp_prepared = wrong
    return stepper


# One complex-step solver and two FFT solvers (Ridders-extrapolated finite differences).
@pytest.mark.parametrize("name", ["diffusion1d-ftcs", "ks1d-etdrk4", "ns2d-etdrk2"])
@pytest.mark.parametrize("steps", [1, 40])
def test_a_relative_adjoint_error_of_1e_6_is_caught(name, steps):
    rows = check_stepper(_perturbed(_small(name), 1e-6), steps=steps, seed=1)
    assert rows and not any(r.passed for r in rows), rows
    for r in rows:
        assert "dot-product rel. error" in r.reason, r
        assert r.dot_ref_err <= TOLERANCES["float64"]["dot_ref"], r
    # ... and the unperturbed adjoint of the same scene passes.
    assert all(r.passed for r in check_stepper(_small(name), steps=steps, seed=1))


@pytest.mark.parametrize("name", ["diffusion1d-ftcs", "ks1d-etdrk4"])
def test_a_dropped_intermediate_cotangent_is_caught(name):
    """A classic adjoint bug: the cotangents of intermediate states are ignored (only the last
    state's, which the sweep starts from, is kept)."""
    stepper = _small(name)
    adjoint = stepper._adjoint

    def dropping(states, ctrl, p, cot, cmap, *rest):
        return adjoint(states, ctrl, p, cot, np.full_like(cmap, -1), *rest)

    stepper._adjoint = dropping
    rows = check_stepper(stepper, steps=30, seed=0)
    assert not any(r.passed for r in rows), rows


@pytest.mark.parametrize(
    "name, steps, seed",
    [
        ("ns2d-etdrk1", 1, 0),  # forcing: a linear map, round-off-dominated differences
        ("ns2d-etdrk2", 1, 3),
        ("ks1d-etdrk4", 500, 2),  # a long rollout: perturbations scaled by its sensitivity
        ("burgers1d-etdrk2", 200, 5),
    ],
)
def test_correct_fft_adjoints_pass_at_settings_that_used_to_fail(name, steps, seed):
    rows = check_stepper(adjointsim.get(name).default(), steps=steps, seed=seed)
    failed = [r for r in rows if not r.passed]
    assert not failed, failed
    for r in rows:
        assert r.dot_ref_err <= TOLERANCES["float64"]["dot_ref"]
        assert r.dot_rel_err <= r.dot_bound == max(TOLERANCES["float64"]["dot"],
                                                   REF_SAFETY * r.dot_ref_err)


def test_ridders_estimate_bounds_its_error():
    x, h0 = 0.7, 0.5
    d = [(math.exp(x + h) - math.exp(x - h)) / (2 * h) for h in h0 * 0.5 ** np.arange(12)]
    # The estimate may undershoot at round-off level: the checker allows REF_SAFETY of them.
    best, err = _ridders(d)
    assert abs(best - math.exp(x)) <= REF_SAFETY * err < 1e-12
    # A first level far outside the asymptotic range is skipped, not trusted.
    best2, err2 = _ridders([100.0, *d[1:]])
    assert abs(best2 - math.exp(x)) <= REF_SAFETY * err2 < 1e-12


def test_two_disagreeing_extrapolations_widen_the_estimate():
    # Round-off the tableau cannot see shows as disagreement between the two step sequences.
    value, err = _extrapolate([[2.0, 2.0, 2.0, 2.0], [2.0 + 1e-9] * 4])
    assert value in (2.0, 2.0 + 1e-9) and err == pytest.approx(1e-9)


def test_taylor_rate_sees_a_first_order_remainder():
    eps = 1e-2 * 0.5 ** np.arange(10)
    floors = [1e-14] * 10
    assert _taylor_rate(list(3 * eps**2), floors) == pytest.approx(2.0)
    # a gradient error of 1e-3 (relative to a slope of order one) dominates at small ε
    assert _taylor_rate(list(3 * eps**2 + 1e-3 * eps), floors) < 1.3
    assert not _quadratic(list(3 * eps**2 + 1e-3 * eps), floors, list(eps))
    assert _taylor_rate(list(1e-16 * np.ones(10)), floors) is None


def test_a_small_quadratic_term_under_a_cubic_one_is_second_order():
    """ks1d-etdrk3 controls at 500 steps (seed 4): the cubic term dominates the larger ε and has
    the other sign, the local rates climb to 2 from below (median 1.8) and remainder/ε²
    settles. A relative gradient error of 1e-6 on the same remainder is not O(ε²)."""
    eps = 1e-2 * 0.5 ** np.arange(12)
    right = np.abs(3e-4 * eps**2 - 1.0 * eps**3)  # changes sign at ε = 3e-4
    floors = [0.9 * right[9]] * 12  # round-off hides the remainder below the tenth level
    assert _taylor_rate(list(right), floors) < TOLERANCES["float64"]["rate"]
    assert _quadratic(list(right), floors, list(eps))
    wrong = np.abs(1e-6 * eps + 3e-4 * eps**2 - 1.0 * eps**3)  # slope 1, error 1e-6
    assert _taylor_rate(list(wrong), floors) < 1.1
    assert not _quadratic(list(wrong), floors, list(eps))
    # fewer than two halvings above the floor decide nothing
    assert not _quadratic(list(right), [1.0] * 10 + floors[10:], list(eps))


def test_an_undecidable_fd_reference_does_not_overrule_the_exact_tests():
    """guidance controls at 500 steps (seed 4): the complex-step dot-product test is exact to
    1.4e-15 and the Taylor remainder is second order, but the central-FD reference's estimate
    (8.7e-6) is above its limit; the row passes and says so. The same row with a 1e-6 adjoint
    error fails on the dot-product test."""
    rows = {r.wrt: r for r in check_stepper(adjointsim.get("guidance").default(), 500, seed=4)}
    row = rows["controls"]
    assert row.passed and row.fd_ref_err > TOLERANCES["float64"]["fd_ref"], row
    assert "undecidable; not needed" in row.reason and row.dot_ref_err == 0
    wrong = check_stepper(_perturbed(adjointsim.get("guidance").default(), 1e-6), 500, seed=4)
    assert not any(r.passed for r in wrong)
    assert all("dot-product rel. error" in r.reason for r in wrong), wrong


@pytest.mark.parametrize("only_float32", [False, True])
@pytest.mark.parametrize("name", ["diffusion1d-ftcs", "advection2d-upwind"])
def test_a_float32_adjoint_error_of_1e_3_is_caught(name, only_float32):
    """advection2d-upwind state (seed 2) carries 1.2e-4 of float32 round-off; the allowance for
    it still catches 1e-3, also when only the float32 path is wrong (the allowance is capped
    by what float32 arithmetic can explain)."""
    rows = check_stepper(_perturbed(adjointsim.get(name).default(), 1e-3, only_float32),
                         dtype="float32", seed=2)
    assert rows and not any(r.passed for r in rows), rows
    assert all("dot-product rel. error" in r.reason for r in rows), rows
    assert all(r.passed for r in check_stepper(adjointsim.get(name).default(), dtype="float32",
                                                seed=2))


def test_float32_roundoff_allowance_is_capped():
    assert _roundoff_allowance(1.0, 1.0, 50, 1.0) == 0.0
    assert _roundoff_allowance(1.0 + 1e-6, 1.0, 50, 1.0) == pytest.approx(2e-6)
    cap = 3 * math.sqrt(51) * float(np.finfo(np.float32).eps)
    assert _roundoff_allowance(1.1, 1.0, 50, 1.0) == pytest.approx(cap)


def test_rows_without_a_measurement_are_json_null():
    row = CheckResult("s", "state", math.nan, math.inf, 1e-10, None, 1e-9, 1e-10, 1e-6, False,
                      "dot-product reference is non-finite")
    d = row.as_dict()
    assert d["dot_rel_err"] is None and d["dot_ref_err"] is None and d["taylor_rate"] is None
    json.dumps(d, allow_nan=False)


@pytest.mark.slow
def test_a_1e_6_adjoint_error_is_caught_on_ns2d_state_at_500_steps():
    """The state's influence decays e^-12 over the rollout: the Ridders reference's estimate is
    2.5e-8..6.8e-8 here, inside the 8e-8 limit that keeps the bound at most 8e-7."""
    def state(stepper):
        return next(r for r in check_stepper(stepper, 500, seed=0) if r.wrt == "state")

    right = state(adjointsim.get("ns2d-etdrk4").default())
    assert right.passed and right.dot_bound <= 8e-7, right
    wrong = state(_perturbed(adjointsim.get("ns2d-etdrk4").default(), 1e-6))
    assert not wrong.passed and "dot-product rel. error" in wrong.reason, wrong


@pytest.mark.slow
@pytest.mark.parametrize("steps", [1, 50, 200, 500])
@pytest.mark.parametrize("seed", range(6))
def test_every_solver_passes_gradcheck(steps, seed):
    """`adjointsim gradcheck --all --steps S --seed K` for the issue's grid (about 5 min)."""
    failed = [r for r in check(steps=steps, seed=seed) if not r.passed]
    assert not failed, failed


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(3))
def test_every_solver_passes_gradcheck_in_float32(seed):
    failed = [r for r in check(dtype="float32", seed=seed) if not r.passed]
    assert not failed, failed


@pytest.mark.parametrize("key", ["steps", "batch"])
@pytest.mark.parametrize("value", [0, -1, 2.5, "2", True])
def test_steps_or_a_batch_that_is_not_a_positive_integer_is_named(key, value):
    """batch=0 failed in numpy's reduction ('zero-size array to reduction operation')."""
    sizes = {"steps": 2, "batch": 2, key: value}
    with pytest.raises(ValueError, match=f"diffusion1d-ftcs: {key} must be a positive integer, "
                                         f"not {value!r}$"):
        check_stepper(adjointsim.get("diffusion1d-ftcs").default(), **sizes)
