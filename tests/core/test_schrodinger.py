"""Crank–Nicolson Schrödinger: unitarity, eigenstate phases, O(Δt²), adjoint checks, bad input."""

import numpy as np
import pytest

import adjointsim.solvers.schrodinger  # noqa: F401  (registers the solver)
from adjointsim.check import check_stepper
from adjointsim.solvers.schrodinger import SchrodingerCN
from tests.references.schrodinger import ROLLOUTS


def as_complex(u: np.ndarray) -> np.ndarray:
    return u[:, 0] + 1j * u[:, 1]


def as_channels(psi: np.ndarray) -> np.ndarray:
    return np.stack([psi.real, psi.imag], axis=1)


def cn_dense(s: SchrodingerCN, psi: np.ndarray, control: float) -> np.ndarray:
    """One step with dense matrices: (I + iΔt/2 H) ψ' = (I − iΔt/2 H) ψ, psi (B, N) complex."""
    a = np.eye(s.n) + 0.5j * s.dt * s.hamiltonian(control)
    return np.linalg.solve(a, (a.conj() @ psi.T)).T


def test_random_state_is_normalised():
    s = SchrodingerCN(n=20)
    psi = s.random_state(np.random.default_rng(0), 4)
    assert psi.shape == (4, 2, 20)
    np.testing.assert_allclose(s.h * np.sum(psi**2, axis=(1, 2)), 1.0, rtol=1e-14)


@pytest.mark.parametrize(
    "kw", [{}, {"n": 256}, {"potential": "harmonic", "potential_strength": 30.0}]
)
def test_norm_is_conserved_for_any_control(kw):
    s = SchrodingerCN(**kw)
    rng = np.random.default_rng(1)
    u0 = s.random_state(rng, 3)
    ctrl = 5.0 * s.random_controls(rng, 200, 3)
    traj = s.rollout(u0, 200, ctrl, keep="all")
    norms = s.h * np.sum(traj**2, axis=(2, 3))
    np.testing.assert_allclose(norms, 1.0, rtol=1e-12)


def test_controlled_step_matches_dense_crank_nicolson():
    s = SchrodingerCN(n=12, dt=0.1, mass=0.5, potential="harmonic", potential_strength=3.0)
    rng = np.random.default_rng(2)
    u0 = s.random_state(rng, 2)
    ctrl = s.random_controls(rng, 1, 2)
    psi = as_complex(u0)
    expected = np.stack([cn_dense(s, psi[b : b + 1], ctrl[0, b, 0])[0] for b in range(2)])
    np.testing.assert_allclose(as_complex(s.step(u0, ctrl[0])), expected, atol=1e-14)


@pytest.mark.parametrize("potential, control", [(None, 0.0), ("harmonic", 0.7)])
def test_eigenstates_pick_up_the_crank_nicolson_phase(potential, control):
    s = SchrodingerCN(potential=potential, potential_strength=5.0)
    energies, vectors = np.linalg.eigh(s.hamiltonian(control))
    if potential is None:  # the discrete box modes and their closed-form energies
        k = np.arange(1, s.n + 1)
        np.testing.assert_allclose(energies, 4 * s.kinetic * np.sin(k * np.pi * s.h / 4) ** 2)
    steps = 40
    for k in (0, 2, 9):
        psi0 = vectors[:, k][None] / np.sqrt(s.h)
        ctrl = np.full((steps, 1, 1), control)
        out = as_complex(s.rollout(as_channels(psi0), steps, ctrl))
        factor = (1 - 0.5j * s.dt * energies[k]) / (1 + 0.5j * s.dt * energies[k])
        np.testing.assert_allclose(out, factor**steps * psi0, atol=1e-12)


def test_second_order_in_time_against_exact_propagator():
    # Time-independent H (harmonic potential, constant control): exact exp(−iHT) by eigh, from
    # a mix of the three lowest eigenstates (resolved in time: Δt E ≲ 1).
    s0 = SchrodingerCN(potential="harmonic", potential_strength=4.0)
    energies, vectors = np.linalg.eigh(s0.hamiltonian(0.5))
    c0 = vectors[:, :3] @ np.array([0.6, 0.5j, -0.4 + 0.3j])
    psi0 = as_channels(c0[None])
    exact = vectors @ (np.exp(-1j * energies) * (vectors.T @ c0))
    errors, dts = [], [0.05, 0.025, 0.0125, 0.00625]
    for dt in dts:
        s = SchrodingerCN(dt=dt, potential="harmonic", potential_strength=4.0)
        steps = round(1.0 / dt)
        out = as_complex(s.rollout(psi0, steps, np.full((steps, 1, 1), 0.5)))[0]
        errors.append(np.sqrt(s.h) * np.linalg.norm(out - exact))
    orders = np.log2(np.array(errors[:-1]) / errors[1:])
    assert np.all(orders > 1.9) and abs(orders[-1] - 2) < 0.02, orders


@pytest.mark.parametrize("offset, order", [(0.5, 2.0), (0.0, 1.0)])
def test_time_dependent_control_order_depends_on_where_it_is_sampled(offset, order):
    # u_k is held over step k: sampled at the midpoint t_k + Δt/2 the scheme stays second
    # order, at the left end t_k it drops to first order.
    s0 = SchrodingerCN()
    modes = np.sin(np.pi * np.outer([1, 2], s0.x) / s0.length)
    psi0 = as_channels(np.array([[1.0, 0.5j], [0.3, -1.0]]) @ modes)

    def run(dt: float, offset: float) -> np.ndarray:
        s = SchrodingerCN(dt=dt)
        steps = round(1.0 / dt)
        t = (np.arange(steps) + offset) * dt
        ctrl = np.broadcast_to(3 * np.sin(4 * t)[:, None, None], (steps, 2, 1)).copy()
        return s.rollout(psi0, steps, ctrl)

    reference = run(1 / 2048, 0.5)
    errors = [np.abs(run(dt, offset) - reference).max() for dt in 0.05 / 2 ** np.arange(5)]
    orders = np.log2(np.array(errors[:-1]) / errors[1:])
    assert np.all(orders > order - 0.1) and abs(orders[-1] - order) < 0.1, orders


def test_adjoint_is_the_inverse_step():
    # The step is unitary, so its transpose (conjugate transpose) undoes it: the cotangent
    # ψ_n pulled back through n steps is ψ_0.
    s = SchrodingerCN(n=20, potential="harmonic")
    rng = np.random.default_rng(5)
    u0 = s.random_state(rng, 2)
    ctrl = s.random_controls(rng, 30, 2)
    un = s.rollout(u0, 30, ctrl)
    np.testing.assert_allclose(s.vjp(u0, 30, un, ctrl).state, u0, atol=1e-12)


@pytest.mark.parametrize(
    "kw",
    [
        {"potential": "harmonic"},
        {"n": 14, "dt": 0.05, "mass": 0.5, "potential": "harmonic", "potential_strength": -1.5},
        {"n": 7, "dt": 0.1, "mass": 0.5},
        {"n": 9, "potential": np.linspace(-1.0, 2.0, 9) ** 2, "potential_strength": 0.8},
        {"n": 256},
    ],
)
def test_gradients_at_several_scenes(kw):
    rows = check_stepper(SchrodingerCN(**kw), steps=50, seed=2)
    assert all(r.passed for r in rows), rows
    assert all(r.dot_rel_err <= 1e-12 for r in rows), rows


def test_default_scene_float32_gradients_and_dtype():
    s = SchrodingerCN.default()
    rows = check_stepper(s, steps=50, dtype="float32")
    assert all(r.passed for r in rows), rows
    rng = np.random.default_rng(6)
    u0 = s.random_state(rng, 2, np.float32)
    ctrl = s.random_controls(rng, 5, 2, np.float32)
    assert s.rollout(u0, 5, ctrl).dtype == np.float32
    assert s.vjp(u0, 5, u0, ctrl).controls.dtype == np.float32


@pytest.mark.parametrize("kw", [{}, {"n": 64, "potential": "harmonic", "potential_strength": 2.0}])
def test_forward_matches_numpy_reference(kw):
    s = SchrodingerCN(**kw)
    u0 = s.random_state(np.random.default_rng(7), 3)
    ref = ROLLOUTS["schrodinger1d-cn"](s, u0, 20)
    np.testing.assert_allclose(s.rollout(u0, 20), ref, rtol=0, atol=1e-12)


def test_bad_input():
    s = SchrodingerCN(n=8)
    u = s.random_state(np.random.default_rng(8), 2)
    with pytest.raises(ValueError, match=r"expected \(B, 2, 8\)"):
        s.rollout(u[:, :1], 3)
    with pytest.raises(ValueError, match=r"expected \(3, 2, 1\)"):
        s.rollout(u, 3, np.zeros((3, 2)))
    with pytest.raises(ValueError, match="mass must be a finite number > 0, got 0.0"):
        SchrodingerCN(mass=0.0)
    with pytest.raises(ValueError, match="potential must be one of 'harmonic', got 'well'"):
        SchrodingerCN(potential="well")
    with pytest.raises(ValueError, match=r"potential must have shape \(8,\)"):
        SchrodingerCN(n=8, potential=np.zeros(9))
    with pytest.raises(ValueError, match="no parameter"):
        s.rollout(u, 3, params={"potential": 1.0})
