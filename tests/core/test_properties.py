"""Registry-wide property tests: every registered solver, drawn scenes, all three checks; the
drawn ones on one solver thread and on two, every call split into chunks."""

from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

import adjointsim
from adjointsim import parallel
from adjointsim.check import TOLERANCES, check_stepper
from adjointsim.strategies import check_cases, scenes

NAMES = adjointsim.names()
SETTINGS = settings(
    max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow], database=None,
    derandomize=True,
)


@pytest.fixture(params=[1, 2], ids=["1-thread", "2-threads"])
def threads(request, monkeypatch) -> Iterator[int]:
    """The solver threads, with every call large enough to split (results must not change)."""
    monkeypatch.setattr(parallel, "MIN_CHUNK_WORK", 1)
    with parallel.using_threads(request.param):
        yield request.param


@pytest.mark.parametrize("name", NAMES)
def test_adjoint_checks_on_drawn_scenes(name, threads):
    @SETTINGS
    @given(check_cases(adjointsim.get(name)))
    def run(case):
        stepper, steps, batch, seed = case
        rows = check_stepper(stepper, steps=steps, seed=seed, batch=batch)
        failed = [r for r in rows if not r.passed]
        assert not failed, failed

    run()


@pytest.mark.parametrize("name", NAMES)
def test_default_scene_passes_in_float32(name):
    rows = check_stepper(adjointsim.get(name).default(), steps=20, dtype="float32")
    failed = [r for r in rows if not r.passed]
    assert not failed, (TOLERANCES["float32"], failed)


@pytest.mark.parametrize("name", NAMES)
def test_rollout_is_repeated_steps_and_float32_stays_float32(name, threads):
    @SETTINGS
    @given(scenes(adjointsim.get(name)))
    def run(stepper):
        rng = np.random.default_rng(1)
        u = stepper.random_state(rng, 2)
        whole = stepper.rollout(u, 3, keep="all")
        v = u
        for k in range(3):
            v = stepper.step(v)
            np.testing.assert_allclose(v, whole[k + 1], rtol=1e-12, atol=1e-12)
        u32 = u.astype(np.float32)
        assert stepper.rollout(u32, 2).dtype == np.float32
        g = stepper.vjp(u32, 2, np.ones_like(u32), wrt_params=True)
        assert g.state.dtype == np.float32

    run()


@pytest.mark.parametrize("name", NAMES)
def test_checkpointed_adjoint_equals_stored_adjoint(name):
    stepper = adjointsim.get(name).default()
    rng = np.random.default_rng(2)
    u = stepper.random_state(rng, 2)
    n = 13
    ctrl = None if stepper.control_shape is None else stepper.random_controls(rng, n, 2)
    cot = {k: stepper.random_state(rng, 2) for k in (0, 4, 9, n)}
    full = stepper.vjp(u, n, cot, ctrl, wrt_params=True)
    for budget in (4, 5, 8):
        part = stepper.vjp(u, n, cot, ctrl, wrt_params=True, checkpoint=budget)
        np.testing.assert_allclose(part.state, full.state, rtol=1e-12, atol=1e-14)
        if ctrl is not None:
            np.testing.assert_allclose(part.controls, full.controls, rtol=1e-12, atol=1e-14)
        for k, v in full.params.items():
            assert part.params[k] == pytest.approx(v, rel=1e-10, abs=1e-14)


@pytest.mark.parametrize("name", NAMES)
def test_parameter_cotangents_only_when_asked(name):
    stepper = adjointsim.get(name).default()
    u = stepper.random_state(np.random.default_rng(3), 1)
    assert stepper.vjp(u, 2, u).params is None
    assert set(stepper.vjp(u, 2, u, wrt_params=True).params) == set(stepper.param_names)
