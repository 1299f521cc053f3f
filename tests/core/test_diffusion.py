"""Diffusion, implicit (backward Euler, Crank–Nicolson / ADI) and explicit (FTCS): gradients,
accuracy, invariants."""


import numpy as np
import pytest

import adjointsim.solvers.implicit_diffusion as implicit
from adjointsim.check import check_stepper
from adjointsim.grid import nodes
from adjointsim.solvers.ftcs import FTCSDiffusion1D, FTCSDiffusion2D
from tests.references.ftcs import ROLLOUTS as FTCS_ROLLOUTS
from tests.references.implicit_diffusion import ROLLOUTS

CLASSES = [
    implicit.BackwardEulerDiffusion1D,
    implicit.CrankNicolsonDiffusion1D,
    implicit.BackwardEulerDiffusion2D,
    implicit.CrankNicolsonDiffusion2D,
]
BCS = ["periodic", "dirichlet", "neumann"]
ids = [c.name for c in CLASSES]


def forcing_profile(cls, n: int, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal((1,) + (n,) * cls.ndim)


def eigenmode(n: int, bc: str, k: int) -> tuple[np.ndarray, float, float]:
    """Eigenvector of δ²/h² on the unit interval, its discrete and its continuous eigenvalue."""
    x = nodes(n, 1.0, bc)
    h = x[1] - x[0]
    if bc == "periodic":
        wave, mode = 2 * np.pi * k, np.sin(2 * np.pi * k * x)
    else:
        wave = np.pi * k
        mode = np.sin(wave * x) if bc == "dirichlet" else np.cos(wave * x)
    return mode, -4 / h**2 * np.sin(wave * h / 2) ** 2, -(wave**2)


def product_mode(cls, n: int, bc: str, ks=(1, 2)):
    """(1, 1, *grid) mode with its discrete and continuous eigenvalues."""
    modes = [eigenmode(n, bc, k) for k in ks[: cls.ndim]]
    u = modes[0][0] if cls.ndim == 1 else np.multiply.outer(modes[0][0], modes[1][0])
    return u[None, None], sum(m[1] for m in modes), sum(m[2] for m in modes)


# ----------------------------------------------------------------------------- (a) gradients
@pytest.mark.parametrize("bc", BCS)
@pytest.mark.parametrize("cls", CLASSES, ids=ids)
def test_gradients_non_default_scenes(cls, bc):
    n = 7 if cls.ndim == 2 else 13
    stepper = cls(n=n, bc=bc, nu=0.35, dt=0.02, forcing=forcing_profile(cls, n),
                  forcing_amplitude=0.6)
    for row in check_stepper(stepper, steps=12, seed=3):
        assert row.passed, row


@pytest.mark.parametrize("cls", CLASSES, ids=ids)
def test_gradients_default_scene_float32(cls):
    for row in check_stepper(cls.default(), steps=50, dtype="float32"):
        assert row.passed, row


@pytest.mark.parametrize("cls", CLASSES, ids=ids)
def test_checkpointed_vjp_matches_full(cls):
    n = 8
    stepper = cls(n=n, bc="neumann", forcing=forcing_profile(cls, n))
    rng = np.random.default_rng(0)
    u0 = stepper.random_state(rng, 2)
    ctrl = stepper.random_controls(rng, 10, 2)
    cot = {4: stepper.random_state(rng, 2), 10: stepper.random_state(rng, 2)}
    full = stepper.vjp(u0, 10, cot, ctrl, wrt_params=True)
    seg = stepper.vjp(u0, 10, cot, ctrl, wrt_params=True, checkpoint=4)
    np.testing.assert_allclose(seg.state, full.state, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(seg.controls, full.controls, rtol=1e-12, atol=1e-14)
    for name in stepper.param_names:
        assert seg.params[name] == pytest.approx(full.params[name], rel=1e-12)


# ----------------------------------------------------------------------------- (b) accuracy
def observed_orders(errors: list[float]) -> np.ndarray:
    return np.log2(np.array(errors[:-1]) / np.array(errors[1:]))


@pytest.mark.parametrize("bc", BCS)
@pytest.mark.parametrize("cls", CLASSES, ids=ids)
def test_temporal_order(cls, bc):
    """A discrete eigenmode decays as exp(ν λ_h t) in the semi-discrete problem: the remaining
    error is the time stepping alone, first order (BE, LOD) or second order (CN, PR)."""
    nu, n = 0.5, 16
    u0, lam, _ = product_mode(cls, n, bc)
    T = 1.5 / (nu * -lam)
    exact = np.exp(nu * lam * T) * u0
    errors = []
    for steps in (10, 20, 40, 80):
        u = cls(n=n, bc=bc, nu=nu, dt=T / steps).rollout(u0, steps)
        errors.append(np.abs(u - exact).max() / np.abs(exact).max())
    expected = 1 if cls.theta == 1 else 2
    assert np.all(np.abs(observed_orders(errors) - expected) < 0.1), errors


@pytest.mark.parametrize("bc", BCS)
@pytest.mark.parametrize("cls", [implicit.CrankNicolsonDiffusion1D,
                                 implicit.CrankNicolsonDiffusion2D], ids=ids[1::2])
def test_space_time_order_against_the_pde(cls, bc):
    """Crank–Nicolson with Δt ∝ h against the continuous solution: second order in h."""
    nu, T = 0.2, 0.25
    errors = []
    for n in (16, 32, 64):
        grid_mode, _, kappa2 = product_mode(cls, n, bc)
        steps = n
        u = cls(n=n, bc=bc, nu=nu, dt=T / steps).rollout(grid_mode, steps)
        exact = np.exp(nu * kappa2 * T) * grid_mode
        errors.append(np.abs(u - exact).max() / np.abs(exact).max())
    assert np.all(observed_orders(errors) > 1.85), errors


@pytest.mark.parametrize("cls", [c for c in CLASSES if c.theta == 0.5 or c.ndim == 1],
                         ids=lambda c: c.name)
def test_forced_steady_state(cls):
    """The fixed point of BE, CN and Peaceman–Rachford solves ν Δ_h u + a g = 0 exactly."""
    n, nu, a = 10, 0.5, 0.8
    g = forcing_profile(cls, n)
    stepper = cls(n=n, bc="dirichlet", nu=nu, dt=0.05, forcing=g, forcing_amplitude=a)
    one = np.eye(n)
    d2 = (np.diag(np.ones(n - 1), -1) - 2 * one + np.diag(np.ones(n - 1), 1)) / stepper.h**2
    lap = d2 if cls.ndim == 1 else np.kron(d2, one) + np.kron(one, d2)
    steady = np.linalg.solve(nu * lap, -a * g.ravel()).reshape(g.shape)
    u = stepper.rollout(np.zeros((1, *g.shape)), 400)
    np.testing.assert_allclose(u[0], steady, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("cls", CLASSES, ids=ids)
def test_constant_control_equals_forcing(cls):
    n, steps = 9, 6
    g = forcing_profile(cls, n)
    forced = cls(n=n, bc="neumann", forcing=g, forcing_amplitude=0.7)
    free = cls(n=n, bc="neumann")
    u0 = free.random_state(np.random.default_rng(0), 2)
    ctrl = np.broadcast_to(0.7 * g, (steps, 2, *g.shape)).copy()
    np.testing.assert_allclose(free.rollout(u0, steps, ctrl), forced.rollout(u0, steps),
                               rtol=1e-13, atol=1e-14)


# ----------------------------------------------------------------------------- (c) invariants
@pytest.mark.parametrize("bc", ["periodic", "neumann"])
@pytest.mark.parametrize("cls", CLASSES, ids=ids)
def test_mass_is_conserved(cls, bc):
    stepper = cls(n=12, bc=bc, nu=0.7, dt=0.3)
    u0 = stepper.random_state(np.random.default_rng(0), 3)
    traj = stepper.rollout(u0, 40, keep="all")
    mass = traj.reshape(41, 3, -1).sum(axis=2)
    np.testing.assert_allclose(mass, np.broadcast_to(mass[0], mass.shape), rtol=0, atol=1e-11)


@pytest.mark.parametrize("bc", BCS)
@pytest.mark.parametrize("cls", CLASSES, ids=ids)
def test_energy_decays_at_any_time_step(cls, bc):
    """‖u‖₂ never grows, even 1000x beyond the explicit stability limit; backward Euler (and
    its LOD splitting: products of M-matrix inverses) also keeps the maximum principle."""
    stepper = cls(n=16, bc=bc, nu=1.0, dt=1000 * 0.5 / 16**2)
    traj = stepper.rollout(stepper.random_state(np.random.default_rng(1), 2), 30, keep="all")
    flat = traj.reshape(31, 2, -1)
    energy = np.sum(flat**2, axis=2)
    assert np.all(np.diff(energy, axis=0) <= 1e-12 * energy[:-1])
    if cls.theta == 1:
        peak = np.abs(flat).max(axis=2)
        assert np.all(np.diff(peak, axis=0) <= 1e-12)


# ----------------------------------------------------------------------------- (d) bad input
@pytest.mark.parametrize("cls", CLASSES, ids=ids)
def test_bad_input(cls):
    with pytest.raises(ValueError, match="largest stable Δt is unbounded"):
        cls(nu=-0.1, dt=0.01)
    stepper = cls(n=8)
    u0 = stepper.random_state(np.random.default_rng(0))
    with pytest.raises(ValueError, match="nu must be a finite number ≥ 0, got -1.0"):
        stepper.rollout(u0, 3, params={"nu": -1.0})
    for dt in (0.0, -0.1, np.inf, np.nan):
        with pytest.raises(ValueError, match="dt must be a finite number > 0"):
            cls(n=8, dt=dt)
    with pytest.raises(ValueError, match="n must be an integer ≥ 2, got 1"):
        cls(n=1, dt=0.1)


def test_default_time_step_is_not_the_explicit_limit():
    stepper = implicit.CrankNicolsonDiffusion2D(n=128, nu=0.1)
    assert stepper.dt == pytest.approx(1e-3 / 0.1)
    assert stepper.dt * 0.1 * sum(stepper.inv_h2) > 10 * 0.5
    assert implicit.BackwardEulerDiffusion1D(nu=0.0).dt == pytest.approx(1e-3)


# ----------------------------------------------------------------------------- (e) reference
@pytest.mark.parametrize("bc", BCS)
@pytest.mark.parametrize("cls", CLASSES, ids=ids)
def test_matches_numpy_reference(cls, bc):
    for n, forcing in ((3, False), (11, True)):
        g = forcing_profile(cls, n) if forcing else None
        stepper = cls(n=n, bc=bc, nu=0.4, forcing=g, forcing_amplitude=0.3, dt=0.07)
        u0 = stepper.random_state(np.random.default_rng(n), 3)
        np.testing.assert_allclose(stepper.rollout(u0, 9), ROLLOUTS[cls.name](stepper, u0, 9),
                                   rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("cls", CLASSES[2:], ids=ids[2:])
def test_batch_one_is_bitwise_equal_on_one_and_two_threads(cls):
    from adjointsim import parallel

    n, steps = 128, 3
    s = cls(n=n, bc="neumann", forcing=forcing_profile(cls, n))
    rng = np.random.default_rng(4)
    u0, ctrl = s.random_state(rng, 1), s.random_controls(rng, steps, 1)
    results = []
    for threads in (1, 2):
        with parallel.using_threads(threads):
            last = s.rollout(u0, steps, ctrl)
            g = s.vjp(u0, steps, last, ctrl, wrt_params=True)
        results.append((last, g.state, g.controls, np.array(list(g.params.values()))))
    for a, b in zip(*results):
        assert a.tobytes() == b.tobytes()


# ----------------------------------------------------------------------------- (f) FTCS
FTCS = [FTCSDiffusion1D, FTCSDiffusion2D]
ftcs_ids = [c.name for c in FTCS]


@pytest.mark.parametrize("bc", BCS)
@pytest.mark.parametrize("cls", FTCS, ids=ftcs_ids)
def test_ftcs_matches_numpy_reference(cls, bc):
    for n, forcing in ((3, False), (11, True)):
        g = forcing_profile(cls, n) if forcing else None
        stepper = cls(n=n, bc=bc, nu=0.4, forcing=g, forcing_amplitude=0.3)
        u0 = stepper.random_state(np.random.default_rng(n), 3)
        np.testing.assert_allclose(stepper.rollout(u0, 9), FTCS_ROLLOUTS[cls.name](stepper, u0, 9),
                                   rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("bc", BCS)
@pytest.mark.parametrize("cls", FTCS, ids=ftcs_ids)
def test_ftcs_eigenmode_grows_by_its_amplification_factor(cls, bc):
    """A discrete eigenmode of Δ_h is multiplied by 1 + ν Δt λ_h at every step, exactly."""
    nu, n, steps = 0.5, 16, 40
    u0, lam, _ = product_mode(cls, n, bc)
    stepper = cls(n=n, bc=bc, nu=nu)
    u = stepper.rollout(u0, steps)
    np.testing.assert_allclose(u, (1 + nu * stepper.dt * lam) ** steps * u0, rtol=0,
                               atol=1e-13 * np.abs(u0).max())


@pytest.mark.parametrize("bc", BCS)
@pytest.mark.parametrize("cls", FTCS, ids=ftcs_ids)
def test_ftcs_space_time_order_against_the_pde(cls, bc):
    """FTCS at a fixed diffusion number (Δt ∝ h²) against the continuous solution: the time
    error O(Δt) and the space error O(h²) make it second order in h."""
    nu, T = 0.2, 0.05
    errors = []
    for n in (16, 32, 64):
        grid_mode, _, kappa2 = product_mode(cls, n, bc)
        stepper = cls(n=n, bc=bc, nu=nu, dt=0.4 / (nu * sum(cls(n=n, bc=bc).inv_h2)))
        steps = round(T / stepper.dt)
        u = stepper.rollout(grid_mode, steps)
        exact = np.exp(nu * kappa2 * steps * stepper.dt) * grid_mode
        errors.append(np.abs(u - exact).max() / np.abs(exact).max())
    assert np.all(np.abs(observed_orders(errors) - 2) < 0.15), errors


@pytest.mark.parametrize("bc", BCS)
@pytest.mark.parametrize("cls", FTCS, ids=ftcs_ids)
def test_ftcs_keeps_the_maximum_principle_up_to_its_limit(cls, bc):
    """At the stability limit every update is a convex combination of neighbours: the peak
    never grows, and mass is conserved where the boundary lets none out."""
    stepper = cls(n=12, bc=bc, nu=0.7, dt=0.5 / (0.7 * sum(cls(n=12, bc=bc).inv_h2)))
    traj = stepper.rollout(stepper.random_state(np.random.default_rng(2), 3), 60, keep="all")
    flat = traj.reshape(61, 3, -1)
    assert np.all(np.diff(np.abs(flat).max(axis=2), axis=0) <= 1e-13)
    if bc != "dirichlet":
        mass = flat.sum(axis=2)
        np.testing.assert_allclose(mass, np.broadcast_to(mass[0], mass.shape), rtol=0,
                                   atol=1e-11)
