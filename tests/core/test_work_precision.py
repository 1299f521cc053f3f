"""The spectral benchmarks: the work-precision command (CSV, PNG, convergence in Δt), the NumPy
ETDRK4 baseline, the PyTorch KS baseline (forward and autograd gradient against ours) and, when
exponax is installed, its twins of our scenes."""

import csv

import numpy as np
import pytest
import torch

import adjointsim.solvers.kuramoto_sivashinsky  # noqa: F401
import adjointsim.solvers.navier_stokes  # noqa: F401
from adjointsim import get
from adjointsim.bench.work_precision import (
    ORDERS,
    NumpyETDRK4,
    exponax_rollout,
    exponax_twin,
    load_exponax,
    median_times,
    relative_error,
)
from adjointsim.cli import main


@pytest.fixture(scope="module")
def ks_quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("wp")
    code = main(["bench", "work-precision", "ks", "--quick", "--out", str(out), "--no-exponax",
                 "--no-progress", "--repeats", "1"])
    assert code == 0
    return out


def test_work_precision_quick_writes_csv_and_png(ks_quick):
    png = ks_quick / "work_precision_ks.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with open(ks_quick / "work_precision_ks.csv") as f:
        rows = list(csv.DictReader(f))
    schemes = {r["scheme"] for r in rows}
    assert schemes == {f"ks1d-etdrk{o}" for o in ORDERS} | {"numpy-etdrk4"}
    assert all(float(r["time_s"]) > 0 and float(r["error"]) > 0 for r in rows)


def test_work_precision_error_decreases_with_dt(ks_quick):
    with open(ks_quick / "work_precision_ks.csv") as f:
        rows = list(csv.DictReader(f))
    for scheme in {r["scheme"] for r in rows}:
        pts = sorted((float(r["dt"]), float(r["error"])) for r in rows if r["scheme"] == scheme)
        errors = [e for _, e in pts]
        assert all(a < b for a, b in zip(errors, errors[1:])), (scheme, pts)
        # The coarsest step is at least 10x less accurate than the finest (16x smaller) one.
        assert errors[-1] > 10 * errors[0], (scheme, pts)


def test_numpy_baseline_is_the_same_scheme(ks_quick):
    with open(ks_quick / "work_precision_ks.csv") as f:
        rows = list(csv.DictReader(f))
    ours = {r["dt"]: float(r["error"]) for r in rows if r["scheme"] == "ks1d-etdrk4"}
    numpy = {r["dt"]: float(r["error"]) for r in rows if r["scheme"] == "numpy-etdrk4"}
    for dt, e in ours.items():
        assert numpy[dt] == pytest.approx(e, rel=1e-6)


def test_numpy_etdrk4_matches_navier_stokes():
    stepper = get("ns2d-etdrk4")(n=16, nu=0.05, dt=0.02, forcing_wavenumber=2, drag=0.1)
    u0 = stepper.random_state(np.random.default_rng(0), 2)
    ref = stepper.rollout(u0, 10)
    assert relative_error(NumpyETDRK4(stepper).rollout(u0, 10), ref) < 1e-12


def test_cli_rejects_unknown_scene(capsys):
    assert main(["bench", "work-precision", "heat"]) == 2
    err = capsys.readouterr().err.strip()
    assert "invalid choice" in err and len(err.splitlines()) == 1


def test_median_times_loops_short_calls_in_turn():
    calls = []
    times = median_times({"a": lambda: calls.append("a"), "b": lambda: calls.append("b")},
                         repeats=3, min_time=1e-4)
    assert set(times) == {"a", "b"} and min(times.values()) >= 0
    assert calls.count("a") > 4 and calls.count("b") > 4
    # Sampled in turn: a sample of b comes before the last sample of a.
    first_b, last_a = calls.index("b", 2), len(calls) - 1 - calls[::-1].index("a")
    assert first_b < last_a


# ----------------------------------------------------------------- PyTorch baseline
@pytest.mark.parametrize("dealias", [False, True])
def test_torch_ks_matches_ours_forward_and_gradient(dealias):
    from torch_spectral import TorchKS, forward_and_gradient

    stepper = get("ks1d-etdrk4")(n=128, length=64.0, dt=0.25, dealias=dealias)
    u0 = stepper.random_state(np.random.default_rng(1), 3)
    model = TorchKS(128, 64.0, 0.25, dealias=dealias)
    last, grad = forward_and_gradient(model, u0, 100)
    ours = stepper.rollout(u0, 100)
    assert relative_error(last, ours) < 1e-10
    ours_grad = stepper.vjp(u0, 100, ours).state
    assert relative_error(grad, ours_grad) < 1e-8


def test_torch_ks_step_is_one_rollout_step():
    from torch_spectral import TorchKS

    model = TorchKS(32, 22.0, 0.1, anti_diffusion=0.8, hyper_diffusion=1.2)
    stepper = get("ks1d-etdrk4")(n=32, length=22.0, dt=0.1, anti_diffusion=0.8,
                                 hyper_diffusion=1.2)
    u0 = stepper.random_state(np.random.default_rng(2), 2)
    u1 = model.step(torch.from_numpy(u0)).numpy()
    assert relative_error(u1, stepper.step(u0)) < 1e-12


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
