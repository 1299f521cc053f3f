"""Multi-pole cart-pole: the note's equations step by step, equilibria, symmetry, adjoints."""

import numpy as np
import pytest

from adjointsim import get
from adjointsim.check import check_stepper

CartPole = get("cartpole")


def reference_step(u, force, dt=0.01, g=9.8, m=0.1, mt=1.1, ll=0.5):
    """One semi-implicit Euler step of the note's equations, NumPy, u (2, 1 + P)."""
    q, w = u[0].copy(), u[1].copy()
    th, om = q[1:], w[1:]
    a = (force + m * ll * np.sin(th) * om**2) / mt
    alpha = (g * np.sin(th) - np.cos(th) * a) / (ll * (4 / 3 - m * np.cos(th) ** 2 / mt))
    acc = (force + m * ll * np.sum(np.sin(th) * om**2 - alpha * np.cos(th))) / mt
    w = w + dt * np.concatenate([[acc], alpha])
    return np.stack([q + dt * w, w])


@pytest.mark.parametrize("poles", [1, 2, 4])
def test_steps_follow_the_equations(poles):
    s = CartPole(poles=poles)
    rng = np.random.default_rng(poles)
    u = s.random_state(rng, 3)
    f = rng.normal(0, 5, (20, 3, 1))
    traj = s.rollout(u, 20, f, keep="all")
    for b in range(3):
        v = u[b]
        for k in range(20):
            v = reference_step(v, f[k, b, 0])
            np.testing.assert_allclose(traj[k + 1, b], v, rtol=1e-12, atol=1e-12)


def test_single_pole_matches_the_classic_cartpole():
    """For one pole the cart's acceleration is gym's temp − m l θ̈ cosθ / M."""
    u = np.array([[[0.0, 0.3], [0.0, -0.7]]])
    out = CartPole(poles=1).step(u, np.array([[2.0]]))
    th, om, f, m, mt, ll, g, dt = 0.3, -0.7, 2.0, 0.1, 1.1, 0.5, 9.8, 0.01
    temp = (f + m * ll * om**2 * np.sin(th)) / mt
    thacc = (g * np.sin(th) - np.cos(th) * temp) / (ll * (4 / 3 - m * np.cos(th) ** 2 / mt))
    xacc = temp - m * ll * thacc * np.cos(th) / mt
    np.testing.assert_allclose(out[0, 1], [dt * xacc, om + dt * thacc], rtol=1e-13)


def test_upright_and_hanging_are_equilibria_and_identical_poles_stay_identical():
    s = CartPole(poles=3)
    for angle in (0.0, np.pi):
        u = np.zeros((1, 2, 4))
        u[0, 0, 1:] = angle
        np.testing.assert_allclose(s.rollout(u, 100), u, atol=1e-12)
    u = np.array([[[0.1, 2.5, 2.5, 2.5], [0.0, 0.3, 0.3, 0.3]]])
    out = s.rollout(u, 100, np.full((100, 1, 1), 1.5))
    np.testing.assert_allclose(out[0, :, 1:], out[0, :, 1:2].repeat(3, axis=1), rtol=1e-14)


def test_hanging_initial_states():
    u = CartPole(poles=4).random_state(np.random.default_rng(0), 500)
    assert np.all(np.abs(u[:, 0, 1:] - np.pi) <= np.pi / 6)
    assert np.all(np.abs(u[:, :, 0]) <= 1) and np.all(np.abs(u[:, 1, 1:]) <= 1)


@pytest.mark.parametrize("poles", [1, 4])
def test_adjoint_checks(poles):
    rows = check_stepper(CartPole(poles=poles), steps=30)
    assert {r.wrt for r in rows} == {"state", "controls", "gravity", "pole_mass",
                                     "total_mass", "length"}
    assert all(r.passed for r in rows), rows


def test_bad_scenes():
    with pytest.raises(ValueError, match="poles must be an integer ≥ 1 and ≤ 4, got 5"):
        CartPole(poles=5)
    with pytest.raises(ValueError, match="below 4/3"):
        CartPole().rollout(np.zeros((1, 2, 3)), 1, params={"pole_mass": 2.0})
    with pytest.raises(ValueError, match=r"controls have shape \(1, 1, 2\); expected \(1, 1, 1\)"):
        CartPole().rollout(np.zeros((1, 2, 3)), 1, np.zeros((1, 1, 2)))
