"""Guidance by repulsion: the note's forces against a NumPy reference, symmetries, adjoints."""

import numpy as np
import pytest

from adjointsim import get
from adjointsim.check import check_stepper

Guidance = get("guidance")


def reference_step(u, c, nd, dt=4 / 60, a=15.0, gd=1.0, ge=4.0, kd=0.2, ke=0.2):
    """One explicit Euler step written with NumPy broadcasting, u (4, A), c (D, 2)."""
    x, v = u[:2], u[2:]
    r = x[:, :, None] - x[:, None, :]  # r[:, i, j] = x_i − x_j
    d = 0.1 + np.sqrt((r**2).sum(axis=0))
    acc = np.zeros_like(x)
    dd = slice(0, nd)
    ee = slice(nd, None)
    off = ~np.eye(u.shape[1], dtype=bool)
    w_rep = np.where(off, 1 / d**2, 0)
    w_coh = np.where(off, (0.5 / d - 1) / d, 0)
    acc[:, dd] = -gd * v[:, dd] + kd * (r[:, dd, dd] * w_rep[dd, dd]).sum(axis=2)
    centre = x[:, ee].sum(axis=1, keepdims=True)
    w = x[:, dd] - centre
    rot = np.stack([-w[1], w[0]])
    acc[:, dd] += c[:, 0] * w + c[:, 1] * rot
    acc[:, ee] = (-ge * v[:, ee] + a * (r[:, ee, dd] * w_rep[ee, dd]).sum(axis=2)
                  + ke * (r[:, ee, ee] * w_coh[ee, ee]).sum(axis=2))
    return np.concatenate([x + dt * v, v + dt * acc])


@pytest.mark.parametrize("nd,ne", [(2, 4), (1, 3), (3, 1)])
def test_steps_follow_the_equations(nd, ne):
    s = Guidance(drivers=nd, evaders=ne)
    rng = np.random.default_rng(nd + ne)
    u = s.random_state(rng, 2)
    u[:, 2:] = rng.normal(size=u[:, 2:].shape)
    c = rng.normal(size=(10, 2, nd, 2))
    traj = s.rollout(u, 10, c, keep="all")
    for b in range(2):
        v = u[b]
        for k in range(10):
            v = reference_step(v, c[k, b], nd)
            np.testing.assert_allclose(traj[k + 1, b], v, rtol=1e-12, atol=1e-12)


def test_evaders_at_the_preferred_spacing_stay_at_rest():
    s = Guidance(drivers=1, evaders=2, repulsion=0.0)  # the driver does not act
    u = np.zeros((1, 4, 3))
    u[0, :2, 0] = [3.0, 0.0]
    u[0, 0, 1:] = [-0.2, 0.2]  # |r| = 0.4, d = 0.5: no evader-evader force
    out = s.step(u)
    np.testing.assert_allclose(out[0, :, 1:], u[0, :, 1:], atol=1e-11)


def test_the_second_coefficient_pushes_perpendicular_to_the_centre():
    s = Guidance(drivers=1, evaders=1, repulsion=0.0)
    u = np.zeros((1, 4, 2))
    u[0, :2, 0] = [3.0, 1.0]
    u[0, :2, 1] = [1.0, 1.0]
    out = s.step(u, np.array([[[0.0, 1.0]]]))
    dv = out[0, 2:, 0] / s.dt
    np.testing.assert_allclose(dv, [0.0, 2.0], atol=1e-12)  # rot90((2, 0)) = (0, 2)


def test_adjoint_checks():
    rows = check_stepper(Guidance(drivers=2, evaders=3), steps=30)
    assert len(rows) == 7 and all(r.passed for r in rows), rows


def test_bad_scenes():
    with pytest.raises(ValueError, match="drivers must be an integer ≥ 1, got 0"):
        Guidance(drivers=0)
    with pytest.raises(ValueError, match="repulsion must be a finite number ≥ 0"):
        Guidance(repulsion=-1.0)
    with pytest.raises(ValueError, match=r"expected \(1, 1, 2, 2\)"):
        Guidance().rollout(np.zeros((1, 4, 6)), 1, np.zeros((1, 1, 4)))
    with pytest.raises(ValueError, match="non-finite"):
        Guidance().rollout(np.full((1, 4, 6), np.nan), 1)
    # a per-call override names the parameter and its value in plain numbers
    with pytest.raises(ValueError, match=r"parameters must be ≥ 0, got repulsion = -1\.0$"):
        Guidance().rollout(Guidance().random_state(np.random.default_rng(0)), 1, None,
                           {"repulsion": -1.0})
