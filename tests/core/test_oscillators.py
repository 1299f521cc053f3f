"""Coupled oscillators (RK4): the linear chain against the RK4 matrix polynomial, energy of the
free nonlinear chain, adjoint checks of both presets, bad input."""

import numpy as np
import pytest

from adjointsim.check import check_stepper
from adjointsim.solvers.oscillators import Oscillators


def rk4_matrix(m: np.ndarray, h: float) -> np.ndarray:
    """The RK4 step of the linear ODE y' = M y: I + hM + (hM)²/2 + (hM)³/6 + (hM)⁴/24."""
    a = h * m
    return np.eye(len(m)) + a + a @ a / 2 + a @ a @ a / 6 + a @ a @ a @ a / 24


def test_linear_chain_matches_the_rk4_matrix_polynomial_and_the_control_enters_linearly():
    s = Oscillators.linear_chain()
    # PBDL's system: ẋ = v, v̇ = −x + 0.2 L x + u e_last, L = [[−1, 1], [1, −1]]
    lap = np.array([[-1.0, 1.0], [1.0, -1.0]])
    m = np.block([[np.zeros((2, 2)), np.eye(2)], [-np.eye(2) + 0.2 * lap, np.zeros((2, 2))]])
    rng = np.random.default_rng(0)
    u0 = s.random_state(rng, 3)
    out = s.rollout(u0, 24)
    step = rk4_matrix(m, s.dt)
    expected = np.linalg.matrix_power(step, 24) @ u0.reshape(3, 4).T
    np.testing.assert_allclose(out.reshape(3, 4), expected.T, atol=1e-12)
    # a constant control c: forcing F = c e_{v_last}, one RK4 step adds (Σ_k h^k M^(k-1)/k!) F
    ctrl = np.full((1, 3, 1), 0.7)
    forcing = np.zeros(4)
    forcing[3] = 0.7
    a = s.dt * m
    phi = s.dt * (np.eye(4) + a / 2 + a @ a / 6 + a @ a @ a / 24)
    stepped = s.step(u0, ctrl[0]).reshape(3, 4)
    np.testing.assert_allclose(stepped, (step @ u0.reshape(3, 4).T).T + phi @ forcing, atol=1e-13)


def test_free_nonlinear_chain_conserves_energy_to_rk4_accuracy():
    s = Oscillators(n=3, dt=0.01, linear_coupling=0.3, cubic_coupling=1.0)
    k, lin, cub, _ = s.param_values

    def energy(u):
        x, v = u[:, 0], u[:, 1]
        d = np.diff(x, axis=1)
        return (0.5 * (v**2).sum(1) + 0.5 * k * (x**2).sum(1) + 0.5 * lin * (d**2).sum(1)
                + 0.25 * cub * (d**4).sum(1))

    u0 = s.random_state(np.random.default_rng(1), 4)
    traj = s.rollout(u0, 2000, keep="all")
    drift = np.abs(energy(traj[-1]) - energy(u0)) / energy(u0)
    assert drift.max() < 1e-8
    # and the motion is not trivial: the positions changed by O(1)
    assert np.abs(traj[-1, :, 0] - u0[:, 0]).max() > 0.1


@pytest.mark.parametrize("preset", ["default", "linear_chain"])
def test_adjoint_checks_pass_for_both_presets(preset):
    s = getattr(Oscillators, preset)()
    rows = check_stepper(s, steps=40, seed=3)
    assert {r.wrt for r in rows} == {"state", "controls", *s.param_names}
    failed = [r for r in rows if not r.passed]
    assert not failed, failed


def test_controls_gradient_reaches_only_the_last_oscillator_through_the_gain():
    s = Oscillators(n=3)
    rng = np.random.default_rng(2)
    u0 = s.random_state(rng, 2)
    ctrl = s.random_controls(rng, 5, 2)
    g = s.vjp(u0, 5, np.ones_like(u0), ctrl, wrt_params=True)
    half = Oscillators(n=3, gain=1.5).vjp(u0, 5, np.ones_like(u0), 2.0 * ctrl)
    # gain·u is what enters: doubling u and halving the gain moves nothing, and ū scales by g
    np.testing.assert_allclose(half.state, g.state, rtol=1e-12)
    np.testing.assert_allclose(2.0 * half.controls, g.controls, rtol=1e-12)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"dt": 3.0}, r"dt = 3 is beyond RK4's stability limit .* dt must be ≤ 2√2/ω = 2\.828"),
        ({"n": 0}, r"n must be an integer ≥ 1, got 0"),
        ({"dt": -0.1}, r"dt must be a finite number > 0, got -0\.1"),
        ({"stiffness": float("nan")}, "stiffness must be a finite number, got nan"),
    ],
)
def test_bad_scenes_are_refused_with_the_reason(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Oscillators(**kwargs)
