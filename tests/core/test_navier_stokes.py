"""2D Navier–Stokes (vorticity form, ETDRK1–4) and 2D advection–diffusion: gradient checks at
non-default scenes, accuracy against analytic solutions, convergence orders, invariants,
input validation, agreement with the NumPy reference."""


import numpy as np
import pytest

import adjointsim.solvers.advection_diffusion2d  # noqa: F401
import adjointsim.solvers.navier_stokes  # noqa: F401
from adjointsim import get
from adjointsim.check import check_stepper
from adjointsim.solvers.advection_diffusion2d import AdvectionDiffusion2D
from adjointsim.solvers.navier_stokes import NavierStokes2D
from adjointsim.spectral.fft2d import random_smooth_field
from tests.references.spectral2d import ROLLOUTS

ORDERS = (1, 2, 3, 4)


def ns(order: int, **kw) -> NavierStokes2D:
    return get(f"ns2d-etdrk{order}")(**kw)


def grid(n: int):
    x = 2 * np.pi * np.arange(n) / n
    return np.meshgrid(x, x, indexing="ij")


# ------------------------------------------------------------------ gradient checks
@pytest.mark.parametrize(
    ("order", "scene"),
    [
        (1, dict(n=12, nu=0.08, dt=0.04, forcing_wavenumber=None, dealias=False)),
        (2, dict(n=16, nu=0.05, dt=0.05, forcing_wavenumber=1, drag=0.2, dealias=False)),
        (3, dict(n=8, nu=0.2, dt=0.03, forcing_wavenumber=2, drag=0.3)),
        (4, dict(n=24, nu=0.03, dt=0.04, forcing_wavenumber=3, forcing_amplitude=0.3)),
    ],
)
def test_adjoint_checks_at_non_default_scenes(order, scene):
    rows = check_stepper(ns(order, **scene), steps=12, batch=2, seed=order)
    assert {r.wrt for r in rows} >= {"state", "controls", "nu"}
    assert all(r.passed for r in rows), rows


def test_advection_diffusion_adjoint_checks_at_a_non_default_scene():
    stepper = AdvectionDiffusion2D(n=12, velocity_x=-0.7, velocity_y=1.9, nu=0.05, dt=0.1)
    rows = check_stepper(stepper, steps=15, batch=3, seed=5)
    assert all(r.passed for r in rows), rows


def test_taped_adjoint_equals_the_recomputing_one():
    stepper = ns(4, n=16, nu=0.05, dt=0.05, forcing_wavenumber=2, drag=0.1)
    rng = np.random.default_rng(4)
    u = stepper.random_state(rng, 2)
    n = 9
    ctrl = stepper.random_controls(rng, n, 2)
    cot = {k: stepper.random_state(rng, 2) for k in (0, 3, n)}
    taped = stepper.vjp(u, n, cot, ctrl)
    traj = stepper.rollout(u, n, ctrl, keep="all")
    recomputed = stepper.vjp(u, n, cot, ctrl, trajectory=traj)
    np.testing.assert_allclose(taped.state, recomputed.state, rtol=1e-11, atol=1e-13)
    np.testing.assert_allclose(taped.controls, recomputed.controls, rtol=1e-11, atol=1e-13)
    for budget in (4, 5):
        nested = stepper.vjp(u, n, cot, ctrl, checkpoint=budget)
        np.testing.assert_allclose(nested.state, taped.state, rtol=1e-11, atol=1e-13)


@pytest.mark.parametrize("name", ("ns2d-etdrk2", "advdiff2d-etdrk4"))
def test_batch_one_on_two_threads_is_bitwise_the_one_thread_result(name, monkeypatch):
    """At batch 1 the transforms run on the solver threads (here from 128² on): nothing may
    change a bit."""
    from adjointsim import parallel

    monkeypatch.setattr(parallel, "MIN_POINTS_INSIDE", 128 * 128)
    kw = dict(nu=1e-3, dt=0.005, forcing_wavenumber=6) if name.startswith("ns2d") else {}
    stepper = get(name)(n=128, **kw)
    rng = np.random.default_rng(3)
    u0 = stepper.random_state(rng, 1)
    cot = rng.standard_normal(u0.shape)
    ctrl = 0.1 * rng.standard_normal((3, 1, *stepper.control_shape))
    runs = []
    for threads in (1, 2):
        with parallel.using_threads(threads):
            traj = stepper.rollout(u0, 3, ctrl, keep="all")
            taped = stepper.vjp(u0, 3, cot)
            full = stepper.vjp(u0, 3, cot, ctrl, wrt_params=True, trajectory=traj)
            params = np.array(list(full.params.values()))
            runs.append((traj, taped.state, full.state, full.controls, params))
    for a, b in zip(*runs):
        np.testing.assert_array_equal(a, b)


def test_velocity_adjoint_dot_test():
    stepper = ns(2, n=16)
    rng = np.random.default_rng(8)
    omega = rng.standard_normal((2, 1, 16, 16))
    vel_bar = rng.standard_normal((2, 2, 16, 16))
    lhs = np.sum(stepper.velocity(omega) * vel_bar)
    rhs = np.sum(omega * stepper.velocity_adjoint(vel_bar))
    assert abs(lhs - rhs) <= 1e-13 * abs(lhs)


# ------------------------------------------------------------------ accuracy
@pytest.mark.parametrize("order", ORDERS)
@pytest.mark.parametrize("drag", (0.0, 0.3))
def test_taylor_green_vortex_decays_exactly(order, drag):
    # ω = 2 cos x cos y has ψ = ω/2 and u·∇ω = 0: a steady nonlinear solution up to the decay
    # exp(−(2ν + μ) t), which every ETDRK order integrates exactly.
    nu, dt, steps = 0.07, 0.1, 30
    stepper = ns(order, n=16, nu=nu, dt=dt, forcing_wavenumber=None, drag=drag)
    x, y = grid(16)
    omega = 2 * np.cos(x) * np.cos(y)
    out = stepper.rollout(omega[None, None], steps)
    exact = omega * np.exp(-(2 * nu + drag) * dt * steps)
    np.testing.assert_allclose(out[0, 0], exact, atol=1e-13)
    vel = stepper.velocity(omega[None, None])
    np.testing.assert_allclose(vel[0, 0], -np.cos(x) * np.sin(y), atol=1e-14)
    np.testing.assert_allclose(vel[0, 1], np.sin(x) * np.cos(y), atol=1e-14)


@pytest.mark.parametrize("order", ORDERS)
def test_laminar_kolmogorov_flow_is_integrated_exactly(order):
    # From rest the forced shear flow stays a shear flow (u·∇ω = 0), so
    # ω(t) = −a k cos(k y) (1 − e^{−λt}) / λ with λ = ν k² + μ, at any Δt.
    nu, drag, k, a, dt, steps = 0.05, 0.1, 3, 0.7, 0.25, 12
    stepper = ns(order, n=16, nu=nu, dt=dt, forcing_wavenumber=k, forcing_amplitude=a, drag=drag)
    out = stepper.rollout(np.zeros((1, 1, 16, 16)), steps)
    lam = nu * k**2 + drag
    _, y = grid(16)
    exact = -a * k * np.cos(k * y) * (1 - np.exp(-lam * dt * steps)) / lam
    np.testing.assert_allclose(out[0, 0], exact, atol=1e-12)


def test_advection_diffusion_is_exact_for_any_step():
    nu, ax, ay = 0.03, 0.8, -1.3
    x, y = grid(16)
    u0 = np.cos(2 * x + 3 * y) + 0.5 * np.sin(x - 4 * y)

    def exact(t):
        xs, ys = x - ax * t, y - ay * t
        return (np.exp(-13 * nu * t) * np.cos(2 * xs + 3 * ys)
                + 0.5 * np.exp(-17 * nu * t) * np.sin(xs - 4 * ys))

    for dt, steps in ((0.7, 5), (0.01, 350)):
        stepper = AdvectionDiffusion2D(n=16, velocity_x=ax, velocity_y=ay, nu=nu, dt=dt)
        out = stepper.rollout(u0[None, None], steps)
        np.testing.assert_allclose(out[0, 0], exact(dt * steps), atol=1e-12)


@pytest.mark.parametrize("order", ORDERS)
def test_temporal_convergence_order(order):
    # A smooth, forced, non-chaotic flow up to T = 1; reference: ETDRK4 at Δt = T/1024.
    u0 = 2 * random_smooth_field(np.random.default_rng(1), (1, 1, 16, 16), 3)
    scene = dict(n=16, nu=0.05, forcing_wavenumber=2, forcing_amplitude=1.0, drag=0.1)

    def run(o, m):
        return ns(o, dt=1.0 / m, **scene).rollout(u0, m)

    ref = run(4, 1024)
    errors = np.array([np.abs(run(order, m) - ref).max() for m in (16, 32, 64)])
    rates = np.log2(errors[:-1] / errors[1:])
    # two-sided: a scheme of another order (a wrong tableau) must not pass (measured within 0.07)
    assert np.all(np.abs(rates - order) < 0.2), (errors, rates)


# ------------------------------------------------------------------ invariants
@pytest.mark.parametrize("order", (1, 4))
def test_mean_vorticity_is_conserved_and_decays_with_drag(order):
    rng = np.random.default_rng(2)
    u0 = random_smooth_field(rng, (2, 1, 16, 16), 4) + np.array([0.3, -1.2])[:, None, None, None]
    free = ns(order, n=16, nu=0.05, dt=0.05, forcing_wavenumber=2)
    out = free.rollout(u0, 40)
    np.testing.assert_allclose(out.mean(axis=(-2, -1)), u0.mean(axis=(-2, -1)), atol=1e-13)
    ctrl = free.random_controls(rng, 40, 2)
    out = free.rollout(u0, 40, ctrl)
    shift = free.dt * ctrl.sum(axis=0).mean(axis=(-2, -1))
    np.testing.assert_allclose(out.mean(axis=(-2, -1)), u0.mean(axis=(-2, -1)) + shift, atol=1e-12)
    damped = ns(order, n=16, nu=0.05, dt=0.05, forcing_wavenumber=2, drag=0.4)
    out = damped.rollout(u0, 40)
    np.testing.assert_allclose(
        out.mean(axis=(-2, -1)), u0.mean(axis=(-2, -1)) * np.exp(-0.4 * 2.0), atol=1e-13
    )


def _energy_enstrophy(stepper, traj):
    """Energy ½⟨|u|²⟩ and enstrophy ½⟨ω²⟩ of batch element 0 along a trajectory."""
    vel = np.stack([stepper.velocity(u[:1]) for u in traj])
    return 0.5 * np.mean(vel**2, axis=(1, 2, 3, 4)), 0.5 * np.mean(traj[:, 0] ** 2, axis=(1, 2, 3))


def test_unforced_energy_and_enstrophy_decay():
    stepper = ns(2, n=32, nu=0.01, dt=0.02, forcing_wavenumber=None)
    u0 = 3 * random_smooth_field(np.random.default_rng(3), (1, 1, 32, 32), 6)
    traj = stepper.rollout(u0, 300, keep="all")
    energy, enstrophy = _energy_enstrophy(stepper, traj)
    assert np.all(np.diff(energy) <= 1e-12 * energy[0])
    assert np.all(np.diff(enstrophy) <= 1e-12 * enstrophy[0])
    assert energy[-1] < 0.95 * energy[0]


def test_forced_flow_stays_within_the_energy_bound():
    # ‖ω‖ ≤ max(‖ω_0‖, ‖F‖/ν) (Poincaré) bounds every forced run with ν > 0.
    stepper = _kolmogorov(300, "coarse", get("ns2d-etdrk3"))
    u0 = random_smooth_field(np.random.default_rng(5), (1, 1, 32, 32), 4)
    traj = stepper.rollout(u0, 3000, keep="all")
    rms = np.sqrt(np.mean(traj**2, axis=(-3, -2, -1)))[:, 0]
    bound = max(rms[0], 6 / np.sqrt(2) / stepper.params["nu"])
    assert np.all(np.isfinite(rms)) and rms.max() <= bound


@pytest.mark.slow
@pytest.mark.parametrize("re", (300, 1000))
@pytest.mark.parametrize(("resolution", "steps"), [("reference", 4000), ("coarse", 10000)])
def test_kolmogorov_long_runs_stay_bounded(re, resolution, steps):
    stepper = _kolmogorov(re, resolution)
    u = random_smooth_field(np.random.default_rng(6), (1, 1, stepper.n, stepper.n), 4)
    snapshots = [u]
    for _ in range(steps // 100):
        snapshots.append(stepper.rollout(snapshots[-1], 100))
    traj = np.stack(snapshots)
    energy, enstrophy = _energy_enstrophy(stepper, traj)
    assert np.all(np.isfinite(traj))
    assert enstrophy.max() <= max(enstrophy[0], 0.5 * (6 / np.sqrt(2) * re) ** 2)
    assert energy.max() <= max(energy[0], 0.5 * (re / np.sqrt(2)) ** 2)
    assert max(stepper.courant_number(w) for w in traj) < 1.0


# ------------------------------------------------------------------ presets, input, dtypes
def _kolmogorov(re: float, resolution: str, cls=None):
    """List et al.'s Kolmogorov scenes (those of the ``kolmogorov`` neural-stepper problem):
    forcing sin(6y), ν = 1/Re; 128² at Δt = 0.005, or coarse 32² at Δt = 0.02; ETDRK4."""
    n, dt = {"reference": (128, 0.005), "coarse": (32, 0.02)}[resolution]
    return (cls or get("ns2d-etdrk4"))(n=n, nu=1.0 / re, dt=dt, forcing_wavenumber=6,
                                        forcing_amplitude=1.0)


def test_presets():
    drag = get("ns2d-etdrk2").kolmogorov_drag()
    assert drag.forcing_wavenumber == 4 and drag.params["drag"] == 0.1
    assert NavierStokes2D.kolmogorov_drag().name == "ns2d-etdrk4"


def test_scenes_without_forcing_or_drag_have_no_such_parameters():
    assert ns(2, forcing_wavenumber=None).param_names == ("nu",)
    assert ns(2, drag=0.2).param_names == ("nu", "forcing", "drag")


def test_bad_input_is_rejected_with_the_reason():
    with pytest.raises(ValueError, match="nu must be a finite number ≥ 0.*no Δt limit.*Courant"):
        ns(2, nu=-0.1)
    with pytest.raises(ValueError, match="drag must be a finite number ≥ 0, got -0.1"):
        ns(2, drag=-0.1)
    with pytest.raises(ValueError, match="forcing_wavenumber must be an integer ≥ 1 and ≤ 10"):
        ns(2, n=32, forcing_wavenumber=11)
    with pytest.raises(ValueError, match="even"):
        ns(2, n=15)
    with pytest.raises(ValueError, match="nu must be a finite number ≥ 0, got -0.5"):
        AdvectionDiffusion2D(nu=-0.5)
    stepper = ns(2, n=16)
    with pytest.raises(ValueError, match="nu must be a finite number ≥ 0, got -1.0"):
        stepper.rollout(stepper.random_state(np.random.default_rng(0)), 2, params={"nu": -1.0})


REFERENCE_SCENES = [("advdiff2d-etdrk4", {})] + [
    (f"ns2d-etdrk{order}", dict(dealias=dealias, drag=0.2, forcing_amplitude=0.5))
    for order in ORDERS
    for dealias in (True, False)
]


@pytest.mark.parametrize(("name", "kw"), REFERENCE_SCENES)
def test_forward_matches_the_numpy_reference(name, kw):
    stepper = get(name)(n=24, **kw)
    u = stepper.random_state(np.random.default_rng(7), 3)
    np.testing.assert_allclose(
        stepper.rollout(u, 25), ROLLOUTS[name](stepper, u, 25), rtol=0, atol=1e-13
    )
