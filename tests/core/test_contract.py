"""The Stepper contract at its edges, for every registered solver.

Zero steps, empty batches, float32 and float64, cotangent keys that name the same step from both
ends, every checkpoint budget from the minimum up, and the cost and memory of binomial
checkpointing. The tests named ``test_defect*`` failed (or hung) before the fix they name.
"""

from __future__ import annotations

import contextlib
import signal
import tracemalloc
from math import comb

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import adjointsim
from adjointsim import registry
from adjointsim.stepper import MIN_CHECKPOINT, NonFiniteInputError
from adjointsim.strategies import scenes

NAMES = registry.names()
FTCS = adjointsim.get("diffusion1d-ftcs")


@contextlib.contextmanager
def returns_within(seconds: float):
    """Fail instead of hanging: the zero-step defects never returned."""

    def expire(signum, frame):
        raise TimeoutError(f"the call did not return within {seconds} s")

    old = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def count_kernel_calls(stepper) -> dict[str, int]:
    """Instrument one stepper: calls of each kernel and forward steps taken."""
    calls = {"forward": 0, "adjoint": 0, "steps": 0}
    forward, adjoint = stepper._forward, stepper._adjoint

    def counted_forward(states, n, ctrl, p):
        calls["forward"] += 1
        calls["steps"] += n
        forward(states, n, ctrl, p)

    def counted_adjoint(*args):
        calls["adjoint"] += 1
        adjoint(*args)

    stepper._forward, stepper._adjoint = counted_forward, counted_adjoint
    return calls


def close(actual, expected, dtype) -> None:
    tol = 2e-4 if np.dtype(dtype) == np.float32 else 1e-10
    actual, expected = np.asarray(actual, dtype=np.float64), np.asarray(expected, np.float64)
    scale = max(1.0, float(np.abs(expected).max(initial=0.0)))
    np.testing.assert_allclose(actual, expected, rtol=tol, atol=tol * scale)


def same_cotangents(a, b, dtype) -> None:
    close(a.state, b.state, dtype)
    assert (a.controls is None) == (b.controls is None)
    if a.controls is not None:
        close(a.controls, b.controls, dtype)
    assert a.params.keys() == b.params.keys()
    close(list(a.params.values()), list(b.params.values()), dtype)


# ---------------------------------------------------------------------- zero steps
@pytest.mark.parametrize("name", NAMES)
def test_defect1_zero_steps_return_the_input(name, monkeypatch):
    stepper = adjointsim.get(name).default()
    rng = np.random.default_rng(0)
    u = stepper.random_state(rng, 2)
    w = stepper.random_state(rng, 2)
    ctrl = None if stepper.control_shape is None else stepper.random_controls(rng, 0, 2)
    empty = np.empty

    def uninitialised_is_nan(*args, **kwargs):
        # Memory the code forgot to write now reads as NaN, deterministically.
        a = empty(*args, **kwargs)
        if a.dtype.kind in "fc":
            a.fill(np.nan)
        return a

    monkeypatch.setattr(np, "empty", uninitialised_is_nan)
    calls = count_kernel_calls(stepper)
    with returns_within(30):
        last = stepper.rollout(u, 0, ctrl)
        every = stepper.rollout(u, 0, ctrl, keep="all")
        g = stepper.vjp(u, 0, {0: w, -1: w}, ctrl, wrt_params=True)
    np.testing.assert_array_equal(last, u)
    assert not np.shares_memory(last, u)
    assert every.shape == (1, *u.shape)
    np.testing.assert_array_equal(every[0], u)
    np.testing.assert_array_equal(g.state, 2 * w)  # both keys name u_0 = u_n
    if ctrl is not None:
        assert g.controls.shape == (0, *ctrl.shape[1:])
    assert g.params == dict.fromkeys(stepper.param_names, 0.0)
    assert calls == {"forward": 0, "adjoint": 0, "steps": 0}


def test_defect1_nonfinite_replay_terminates():
    """A blow-up the replay cannot reproduce gets an error, not an endless replay."""
    stepper = FTCS(n=12)
    u = stepper.random_state(np.random.default_rng(1), 1)
    stepper.rollout(u, 2)  # compiled (or loaded from the cache) before the clock starts
    forward = stepper._forward
    first = [True]

    def flaky(states, n, ctrl, p):
        forward(states, n, ctrl, p)
        if first[0]:
            first[0] = False
            states[n % states.shape[0]] = np.nan

    stepper._forward = flaky
    with returns_within(30), pytest.raises(FloatingPointError, match="replay stayed finite"):
        stepper.rollout(u, 700)


# ------------------------------------------------------------- keys naming one step
def test_defect5_cotangent_keys_naming_one_step_are_summed():
    stepper = FTCS(n=12)
    rng = np.random.default_rng(2)
    u = stepper.random_state(rng, 2)
    a, b, c = (stepper.random_state(rng, 2) for _ in range(3))
    n = 3
    summed = stepper.vjp(u, n, {3: a + b, 0: c}, wrt_params=True)
    both = stepper.vjp(u, n, {3: a, -1: b, -4: c}, wrt_params=True)
    np.testing.assert_allclose(both.state, summed.state, rtol=1e-14)
    assert both.params["nu"] == pytest.approx(summed.params["nu"], rel=1e-14)
    with pytest.raises(ValueError, match=r"outside the rollout: steps run from 0 \(u_0\) to 3"):
        stepper.vjp(u, n, {-5: a})
    with pytest.raises(TypeError, match="integer step numbers"):
        stepper.vjp(u, n, {1.0: a})
    bad = a.copy()
    bad[0, 0, 1] = np.inf
    with pytest.raises(ValueError, match="cotangent of step 2 has non-finite values"):
        stepper.vjp(u, n, {2: bad})


# ------------------------------------------------------------------ empty batch
@pytest.mark.parametrize("name", NAMES)
def test_defect8_empty_batch_runs_no_kernel(name):
    stepper = adjointsim.get(name).default()
    rng = np.random.default_rng(3)
    n = 2
    u = stepper.random_state(rng, 0)
    assert u.shape[0] == 0
    ctrl = None if stepper.control_shape is None else stepper.random_controls(rng, n, 0)
    calls = count_kernel_calls(stepper)
    assert stepper.rollout(u, n, ctrl).shape == u.shape
    assert stepper.rollout(u, n, ctrl, keep="all").shape == (n + 1, *u.shape)
    one = None if ctrl is None else ctrl[0]
    assert stepper.step(u, one).shape == u.shape
    for checkpoint in (None, MIN_CHECKPOINT):
        g = stepper.vjp(u, n, {1: u, -1: u}, ctrl, wrt_params=True, checkpoint=checkpoint)
        assert g.state.shape == u.shape
        if ctrl is not None:
            assert g.controls.shape == ctrl.shape
        assert g.params == dict.fromkeys(stepper.param_names, 0.0)
    traj = np.zeros((n + 1, *u.shape))
    assert stepper.vjp(u, n, u, ctrl, trajectory=traj).state.shape == u.shape
    assert calls == {"forward": 0, "adjoint": 0, "steps": 0}


# ------------------------------------------------------------ checkpointing cost
def binomial_optimum(n: int, s: int) -> int:
    """Fewest forward steps to reverse n steps with a budget of s states (Revolve with s - 2
    stored states, the budget also counting the two-state buffer the kernels advance in)."""
    snaps = s - 2
    if n <= 1:
        return 0
    t = 1
    while comb(snaps + t, t) < n:
        t += 1
    return t * n - comb(snaps + t, t - 1)


def test_binomial_optimum_formula():
    # Hand-checked: recompute every input from u_0 (S = 1), and store everything (t = 1).
    assert binomial_optimum(10, 3) == 45
    assert binomial_optimum(10, 12) == 9
    assert binomial_optimum(1000, 4) == 44 * 1000 - comb(46, 3)


@pytest.mark.parametrize("n", [10, 100, 1000, 4000])
def test_defect4_checkpointing_stays_within_the_binomial_bound(n):
    stepper = FTCS(n=8)
    rng = np.random.default_rng(4)
    u = stepper.random_state(rng, 1)
    w = stepper.random_state(rng, 1)
    stored = stepper.vjp(u, n, w, wrt_params=True)
    calls = count_kernel_calls(stepper)
    for s in (MIN_CHECKPOINT, 4, 5, 8, 16):
        if s == MIN_CHECKPOINT and n > 1000:
            continue  # quadratic by nature (n²/2 steps); n = 1000 covers it
        calls["steps"] = 0
        g = stepper.vjp(u, n, w, wrt_params=True, checkpoint=s)
        assert calls["steps"] <= binomial_optimum(n, s) + 2, (n, s)
        np.testing.assert_allclose(g.state, stored.state, rtol=1e-13, atol=1e-300)
        assert g.params["nu"] == pytest.approx(stored.params["nu"], rel=1e-12)


def test_checkpointing_is_optimal_for_short_rollouts():
    stepper = FTCS(n=6)
    rng = np.random.default_rng(8)
    u = stepper.random_state(rng, 1)
    calls = count_kernel_calls(stepper)
    for n in range(1, 41):
        w = stepper.random_state(rng, 1)
        for s in range(MIN_CHECKPOINT, 13):
            calls["steps"] = 0
            stepper.vjp(u, n, w, checkpoint=s)
            assert calls["steps"] == binomial_optimum(n, s), (n, s)


@pytest.mark.parametrize("s", [MIN_CHECKPOINT, 4, 5, 8, 16])
def test_defect4_checkpointing_holds_at_most_s_states(s):
    """Measured with tracemalloc: u_0 and at most s - 1 more states, besides ū and the FTCS
    kernels' one work array (the Laplacian); the cotangent is passed without a copy."""
    stepper = FTCS(n=20000)  # large states: everything else is small beside them
    rng = np.random.default_rng(5)
    u = stepper.random_state(rng, 1)
    w = stepper.random_state(rng, 1)
    n = 60
    stored = stepper.vjp(u, n, w)
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        g = stepper.vjp(u, n, w, checkpoint=s)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    states = peak / u.nbytes
    assert states <= (s - 1) + 2 + 0.1, f"checkpoint={s} held {states:.2f} states beside u_0"
    assert states >= s - 1, "the budget was not used: the measurement is broken"
    np.testing.assert_allclose(g.state, stored.state, rtol=1e-13, atol=1e-300)


@pytest.mark.parametrize("name", NAMES)
def test_every_checkpoint_budget_gives_the_stored_gradient(name):
    stepper = adjointsim.get(name).default()
    rng = np.random.default_rng(6)
    n = 6
    u = stepper.random_state(rng, 2)
    ctrl = None if stepper.control_shape is None else stepper.random_controls(rng, n, 2)
    cot = {k: stepper.random_state(rng, 2) for k in (0, 2, -1)}
    stored = stepper.vjp(u, n, cot, ctrl, wrt_params=True)
    for s in range(MIN_CHECKPOINT, n + 3):
        same_cotangents(stepper.vjp(u, n, cot, ctrl, wrt_params=True, checkpoint=s), stored,
                        np.float64)


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
def test_every_checkpoint_budget_long_rollouts(name):
    stepper = adjointsim.get(name).default()
    rng = np.random.default_rng(7)
    for n in (17, 40):
        u = stepper.random_state(rng, 2)
        ctrl = None if stepper.control_shape is None else stepper.random_controls(rng, n, 2)
        cot = {k: stepper.random_state(rng, 2) for k in (0, 5, n // 2, -2, -1)}
        stored = stepper.vjp(u, n, cot, ctrl, wrt_params=True)
        for s in range(MIN_CHECKPOINT, n + 3):
            part = stepper.vjp(u, n, cot, ctrl, wrt_params=True, checkpoint=s)
            same_cotangents(part, stored, np.float64)


# ------------------------------------------------------------------ the property sweep
@st.composite
def edge_cases(draw, name: str):
    stepper = draw(scenes(registry.get(name)), label="scene")
    n = draw(st.sampled_from((0, 1, 2)), label="n")
    batch = draw(st.sampled_from((0, 1, 3)), label="batch")
    dtype = draw(st.sampled_from((np.float32, np.float64)), label="dtype")
    keys = draw(st.lists(st.integers(-(n + 1), n), min_size=1, max_size=4, unique=True),
                label="cotangent keys")
    seed = draw(st.integers(0, 2**32 - 1), label="seed")
    return stepper, n, batch, np.dtype(dtype), keys, seed


def check_edge_case(stepper, n, batch, dtype, keys, seed) -> None:
    rng = np.random.default_rng(seed)
    u = stepper.random_state(rng, batch, dtype)
    ctrl = None if stepper.control_shape is None else stepper.random_controls(rng, n, batch, dtype)
    cot = {k: stepper.random_state(rng, batch, dtype) for k in keys}
    inputs = [u.copy(), None if ctrl is None else ctrl.copy()]
    cot_copies = {k: v.copy() for k, v in cot.items()}
    calls = count_kernel_calls(stepper)

    traj = stepper.rollout(u, n, ctrl, keep="all")
    assert traj.shape == (n + 1, *u.shape) and traj.dtype == dtype
    np.testing.assert_array_equal(traj[0], u)
    close(stepper.rollout(u, n, ctrl), traj[n], dtype)
    for k in range(n):
        close(stepper.step(traj[k], None if ctrl is None else ctrl[k]), traj[k + 1], dtype)

    dense = np.zeros((n + 1, *u.shape), dtype=dtype)
    for k, v in cot.items():
        dense[k] += v  # a negative key counts from the end, as numpy indexes
    ref = stepper.vjp(u, n, dense, ctrl, wrt_params=True)
    assert ref.state.dtype == dtype
    same_cotangents(stepper.vjp(u, n, cot, ctrl, wrt_params=True), ref, dtype)
    same_cotangents(stepper.vjp(u, n, cot, ctrl, wrt_params=True, trajectory=traj), ref, dtype)
    for s in range(MIN_CHECKPOINT, max(MIN_CHECKPOINT, n + 2) + 1):
        part = stepper.vjp(u, n, cot, ctrl, wrt_params=True, checkpoint=s)
        same_cotangents(part, ref, dtype)
    if n >= 1:
        # Chain rule across u_1: reverse steps 1 .. n-1, then step 0.
        c0, c1 = (None, None) if ctrl is None else (ctrl[:1], ctrl[1:])
        tail = stepper.vjp(traj[1], n - 1, dense[1:], c1, wrt_params=True)
        head = stepper.vjp(u, 1, {0: dense[0], 1: tail.state}, c0, wrt_params=True)
        close(head.state, ref.state, dtype)
        if ctrl is not None:
            close(np.concatenate([head.controls, tail.controls]), ref.controls, dtype)
        close([head.params[k] + tail.params[k] for k in ref.params], list(ref.params.values()),
              dtype)
    if n == 0 or batch == 0:
        assert calls == {"forward": 0, "adjoint": 0, "steps": 0}
        if n == 0:
            close(ref.state, dense.sum(axis=0), dtype)
        assert ref.state.shape == u.shape
        assert all(v == 0.0 for v in ref.params.values())
    np.testing.assert_array_equal(u, inputs[0])  # inputs are never modified
    if ctrl is not None:
        np.testing.assert_array_equal(ctrl, inputs[1])
    for k, v in cot.items():
        np.testing.assert_array_equal(v, cot_copies[k])


@pytest.mark.parametrize("name", NAMES)
def test_contract_at_the_edges(name):
    @settings(max_examples=10, deadline=None, suppress_health_check=list(HealthCheck))
    @given(case=edge_cases(name))
    def run(case):
        check_edge_case(*case)

    run()


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
def test_contract_at_the_edges_many(name):
    @settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
    @given(case=edge_cases(name))
    def run(case):
        check_edge_case(*case)

    run()


@pytest.mark.parametrize("name", NAMES)
def test_float32_stays_float32_and_agrees_with_float64(name):
    """Every solver, once: float32 inputs give float32 states and cotangents (state, controls,
    parameters as numbers), within float32 round-off of the float64 run."""
    stepper = adjointsim.get(name).default()
    rng = np.random.default_rng(3)
    n = 5
    u0 = stepper.random_state(rng, 2)
    c = None if stepper.control_shape is None else 0.1 * stepper.random_controls(rng, n, 2)
    cot = rng.standard_normal((n + 1, *u0.shape))
    out64 = stepper.rollout(u0, n, c)
    g64 = stepper.vjp(u0, n, cot, c, wrt_params=True)
    u32, cot32 = u0.astype(np.float32), cot.astype(np.float32)
    c32 = None if c is None else c.astype(np.float32)
    out32 = stepper.rollout(u32, n, c32)
    g32 = stepper.vjp(u32, n, cot32, c32, wrt_params=True)
    assert out32.dtype == g32.state.dtype == np.float32
    pairs = [(out32, out64), (g32.state, g64.state)]
    if c is not None:
        assert g32.controls.dtype == np.float32
        pairs.append((g32.controls, g64.controls))
    # float32 round-off over 5 steps measured at most 3.4e-6 of the scale (ns2d, advdiff2d):
    # room for it, not for a float32 path that loses precision beyond round-off
    tol = 5e-5
    for a, b in pairs:
        assert np.abs(a - b).max() <= tol * max(np.abs(b).max(), 1.0), name
    for k, v in g64.params.items():
        assert abs(g32.params[k] - v) <= tol * max(abs(v), 1.0), (name, k)


# ------------------------------------------------------------ a non-finite stored trajectory
@pytest.mark.parametrize("name", NAMES)
def test_defect_a_non_finite_trajectory_is_named_not_reversed(name):
    """A NaN in a stored trajectory gave NaN parameter cotangents without an error (the linear
    schemes' state cotangent never reads the states) or an error blaming the cotangents."""
    stepper = adjointsim.get(name).default()
    rng = np.random.default_rng(9)
    n = 5
    u = stepper.random_state(rng, 2)
    ctrl = None if stepper.control_shape is None else stepper.random_controls(rng, n, 2)
    traj = stepper.rollout(u, n, ctrl, keep="all")
    traj[3, 1].flat[0] = np.nan
    w = stepper.random_state(rng, 2)
    with pytest.raises(NonFiniteInputError, match=r"trajectory holds a non-finite value at "
                                                  r"step 3 \(of 0\.\.5\), in batch element\(s\) "
                                                  r"\[1\]"):
        stepper.vjp(u, n, w, ctrl, wrt_params=True, trajectory=traj)
    # The fast path checks no input, but never returns a non-finite gradient either.
    u0, n, c, p = stepper.prepare(u, n, ctrl)
    try:
        g = stepper.vjp_prepared(u0, n, c, p, *stepper.check_cotangents(w, n, u0),
                                 wrt_params=True, trajectory=traj)
    except NonFiniteInputError as e:
        assert "trajectory handed to vjp_prepared holds a non-finite value at step 3" in str(e)
    else:
        assert np.isfinite(g.state).all() and np.isfinite(list(g.params.values())).all()
