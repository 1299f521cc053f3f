"""Every input of a reverse sweep is checked: a NaN or an infinity in the stored trajectory, the
controls, a parameter, a cotangent or the initial state is refused by ``vjp`` with an error that
names the input (and the step), for every registered solver.

The checks run before any kernel, so the sweep below compiles nothing: the trajectories are
stacks of random states, not rollouts (a check that let one through would reverse garbage).
"""

from __future__ import annotations

import functools
import math
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import adjointsim
from adjointsim import NonFiniteInputError

NAMES = adjointsim.names()
INPUTS = ("trajectory", "controls", "params", "cotangents", "u0")
SETTINGS = settings(
    max_examples=4, deadline=None, database=None, derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
BAD = st.sampled_from([math.nan, math.inf, -math.inf])


@functools.cache
def scene(name: str) -> adjointsim.Stepper:
    return adjointsim.get(name).default()


def put(a: np.ndarray, index: int, value: float) -> np.ndarray:
    """A copy of ``a`` with ``value`` at flat ``index`` (taken modulo its size)."""
    a = a.copy()
    a.flat[index % a.size] = value
    return a


@st.composite
def sweeps(draw, stepper: adjointsim.Stepper, which: str):
    """Valid vjp arguments with one non-finite value put into input ``which``.

    Returns (kwargs of vjp, a pattern the error must match)."""
    n, batch = draw(st.integers(1, 4)), draw(st.integers(1, 3))
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    bad, index = draw(BAD), draw(st.integers(0, 10**6))
    u0 = stepper.random_state(rng, batch)
    args = {
        "u0": u0, "n": n,
        "cotangents": {k: stepper.random_state(rng, batch) for k in (0, n // 2, n)},
        "controls": None if stepper.control_shape is None
        else stepper.random_controls(rng, n, batch),
        "params": None, "wrt_params": draw(st.booleans()), "trajectory": None,
    }
    if which == "trajectory" or draw(st.booleans()):
        args["trajectory"] = np.stack([u0, *(stepper.random_state(rng, batch) for _ in range(n))])
    if which == "trajectory":
        k = draw(st.integers(0, n))
        args["trajectory"][k] = put(args["trajectory"][k], index, bad)
        return args, rf"\btrajectory\b.*\bstep {k}\b"
    if which == "controls":
        k = draw(st.integers(0, n - 1))
        args["controls"][k] = put(args["controls"][k], index, bad)
        return args, rf"\bcontrols\b.*\bstep {k}\b"
    if which == "params":
        i = draw(st.integers(0, len(stepper.param_names) - 1))
        name = stepper.param_names[i]
        if draw(st.booleans()):
            args["params"] = {name: bad}
        else:
            args["params"] = put(np.array(stepper.param_values), i, bad)
        return args, rf"\bparameters?\b.*\b{name}\b"
    if which == "cotangents":
        k = draw(st.sampled_from((0, n // 2, n)))
        form = draw(st.sampled_from(("key", "key from the end", "stacked", "last")))
        if form == "last":  # one array: the cotangent of u_n
            k, args["cotangents"] = n, stepper.random_state(rng, batch)
            args["cotangents"] = put(args["cotangents"], index, bad)
        elif form == "stacked":  # one per state, u_0 .. u_n
            stacked = np.stack([stepper.random_state(rng, batch) for _ in range(n + 1)])
            stacked[k] = put(stacked[k], index, bad)
            args["cotangents"] = stacked
        else:
            key = k - (n + 1) if form == "key from the end" else k
            del args["cotangents"][k]
            args["cotangents"][key] = put(stepper.random_state(rng, batch), index, bad)
        return args, rf"\bcotangent of step {k}\b"
    args["u0"] = put(u0, index, bad)
    if args["trajectory"] is not None:
        args["trajectory"][0] = args["u0"]
    return args, r"\bu0\b"


@pytest.mark.parametrize("which", INPUTS)
@pytest.mark.parametrize("name", NAMES)
def test_a_non_finite_input_of_a_reverse_sweep_is_named(name, which):
    stepper = scene(name)
    if which == "controls" and stepper.control_shape is None:
        pytest.skip(f"{name} has no controls")
    if which == "params" and not stepper.param_names:
        pytest.skip(f"{name} has no parameters")

    @SETTINGS
    @given(sweeps(stepper, which))
    def run(case):
        args, pattern = case
        with pytest.raises(NonFiniteInputError) as err:
            stepper.vjp(**args)
        message = str(err.value)
        assert message.startswith(f"{name}: ") and re.search(pattern, message), message

    run()
