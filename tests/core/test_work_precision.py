"""The spectral benchmarks' pieces: the NumPy ETDRK4 baseline, the timing of short calls and,
when exponax is installed, its twins of our scenes. The work-precision command is tested in
tests/commands/test_bench_work_precision.py, the PyTorch KS baseline in
tests/training/test_torch_spectral.py."""

import numpy as np
import pytest

import adjointsim.solvers.kuramoto_sivashinsky  # noqa: F401
import adjointsim.solvers.navier_stokes  # noqa: F401
from adjointsim import get
from adjointsim.bench.work_precision import (
    NumpyETDRK4,
    exponax_rollout,
    exponax_twin,
    load_exponax,
    median_times,
    relative_error,
)


def test_numpy_etdrk4_matches_navier_stokes():
    stepper = get("ns2d-etdrk4")(n=16, nu=0.05, dt=0.02, forcing_wavenumber=2, drag=0.1)
    u0 = stepper.random_state(np.random.default_rng(0), 2)
    ref = stepper.rollout(u0, 10)
    assert relative_error(NumpyETDRK4(stepper).rollout(u0, 10), ref) < 1e-12


def test_median_times_loops_short_calls_in_turn():
    calls = []
    times = median_times({"a": lambda: calls.append("a"), "b": lambda: calls.append("b")},
                         repeats=3, min_time=1e-4)
    assert set(times) == {"a", "b"} and min(times.values()) >= 0
    assert calls.count("a") > 4 and calls.count("b") > 4
    # Sampled in turn: a sample of b comes before the last sample of a.
    first_b, last_a = calls.index("b", 2), len(calls) - 1 - calls[::-1].index("a")
    assert first_b < last_a


# ----------------------------------------------------------------- exponax (optional)
@pytest.mark.parametrize(
    ("name", "scene"),
    [
        ("ks1d-etdrk4", dict(n=64, length=22.0, dt=0.2)),
        # JAX compiles each twin for seconds: the 2D ones run with the slow tests.
        pytest.param("ns2d-etdrk2", dict(n=32, nu=0.02, dt=0.01, forcing_wavenumber=3),
                     marks=pytest.mark.slow),
        pytest.param("ns2d-etdrk4", dict(n=16, nu=0.05, dt=0.02, forcing_wavenumber=None,
                                          drag=0.2), marks=pytest.mark.slow),
    ],
)
def test_exponax_twin_matches_ours(name, scene):
    loaded = load_exponax()
    if loaded is None:
        pytest.skip("exponax not installed")
    jax, _ = loaded
    stepper = get(name)(**scene)
    u0 = stepper.random_state(np.random.default_rng(3), 2)
    twin, sign = exponax_twin(stepper)
    last = sign * np.asarray(jax.jit(exponax_rollout(twin, 20))(sign * u0))
    assert relative_error(last, stepper.rollout(u0, 20)) < 1e-11


def test_exponax_twin_refuses_dealiased_ks():
    if load_exponax() is None:
        pytest.skip("exponax not installed")
    with pytest.raises(ValueError, match="no exact twin"):
        exponax_twin(get("ks1d-etdrk4")(dealias=True))
