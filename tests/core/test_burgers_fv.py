"""Viscous Burgers, Rusanov finite volumes, 1D and 2D, periodic (and the PBDL preset)."""

from __future__ import annotations

import numpy as np
import pytest

from adjointsim.check import check_stepper
from adjointsim.fit_demos import pbdl_scene, pbdl_state
from adjointsim.solvers.burgers_fv import BurgersRusanov1D, BurgersRusanov2D
from tests.references import burgers_fv as numpy_reference


def _cole_hopf(s: np.ndarray, t: float, nu: float, a: float = 1.1) -> np.ndarray:
    """Exact periodic solution of u_t + u u_s = ν u_ss on [−1, 1): u = −2ν φ_s / φ with the heat
    solution φ = a + exp(−ν π² t) cos(π s)."""
    d = np.exp(-nu * np.pi**2 * t)
    return 2 * nu * np.pi * d * np.sin(np.pi * s) / (a + d * np.cos(np.pi * s))


def _exact(stepper, t: float) -> np.ndarray:
    """1D: Cole–Hopf. 2D: u(x, y) = w(x + y)/2 with w the Cole–Hopf solution for viscosity 2ν,
    since then u_t + u u_x + u u_y − ν Δu = (w_t + w w_s − 2ν w_ss)/2 = 0."""
    x, nu = stepper.nodes(), stepper.param_values[0]
    if stepper.ndim == 1:
        return _cole_hopf(x, t, nu)[None, None]
    return 0.5 * _cole_hopf(x[:, None] + x[None, :], t, 2 * nu)[None, None]


def _assert_passed(rows):
    for r in rows:
        assert r.passed, r


# ------------------------------------------------------------------ gradients
@pytest.mark.parametrize(
    "stepper",
    [
        BurgersRusanov1D(n=24, nu=0.1, amplitude=1.4, substeps=2, cfl=0.9),
        BurgersRusanov1D(n=40, nu=0.02, length=1.0, start=0.0, amplitude=0.7),
        BurgersRusanov1D(n=20, nu=0.05, dt=0.05, substeps=None),
        BurgersRusanov2D(n=12, nu=0.08, amplitude=1.2, substeps=3, cfl=0.8),
        BurgersRusanov2D(n=9, nu=0.15, length=1.0, amplitude=0.6, umax=1.0),
    ],
    ids=lambda s: f"{s.name}-n{s.grid_shape[0]}-sub{s.substeps}",
)
def test_gradients_non_default_scenes(stepper):
    _assert_passed(check_stepper(stepper, steps=25, batch=3, seed=2))


def test_gradients_pbdl_preset():
    st = pbdl_scene(umax=1.0)
    _assert_passed(check_stepper(st, steps=8, batch=2, seed=0))


def test_nu_gradient_through_the_pbdl_shock():
    """∂/∂ν of a loss on the shocked PBDL state at t = 1, against central differences.

    The PBDL initial state is odd about the face x = 0, where u_L = −u_R (a sonic point of the
    flux); perturbing ν keeps that symmetry, so the map stays differentiable along ν.
    """
    st = pbdl_scene(umax=1.0)
    u0 = pbdl_state(st)
    target = np.tanh(-st.nodes() / 0.05)[None, None]
    u = st.rollout(u0, 32)
    g = st.vjp(u0, 32, u - target, wrt_params=True).params["nu"]
    nu, e = st.param_values[0], 1e-4 * st.param_values[0]

    def loss(v):
        return 0.5 * np.sum((st.rollout(u0, 32, params={"nu": v}) - target) ** 2)

    assert g == pytest.approx((loss(nu + e) - loss(nu - e)) / (2 * e), rel=1e-6)


@pytest.mark.parametrize("cls", [BurgersRusanov1D, BurgersRusanov2D], ids=lambda c: c.name)
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_gradients_default_scene(cls, dtype):
    _assert_passed(check_stepper(cls.default(), steps=50, dtype=dtype))


def test_controls_and_negative_states_are_differentiated():
    """Both flux branches (u > 0 and u < 0) and the control hook, against central differences."""
    st = BurgersRusanov1D(n=16, nu=0.05)
    rng = np.random.default_rng(0)
    u0 = st.random_state(rng, batch=2)  # batch element 1 is negative
    assert np.all(u0[0] > 0) and np.all(u0[1] < 0)
    c = st.random_controls(rng, 6, batch=2)
    w = rng.standard_normal(u0.shape)
    cb = st.vjp(u0, 6, w, controls=c).controls
    d = rng.standard_normal(c.shape)
    f = [np.sum(w * st.rollout(u0, 6, c + s * 1e-6 * d)) for s in (1, -1)]
    assert np.sum(cb * d) == pytest.approx((f[0] - f[1]) / 2e-6, rel=1e-6)


# ------------------------------------------------------------------ accuracy
@pytest.mark.parametrize(
    "cls, sizes", [(BurgersRusanov1D, (64, 128, 256)), (BurgersRusanov2D, (32, 64, 128))],
    ids=lambda v: getattr(v, "name", None),
)
def test_first_order_against_cole_hopf(cls, sizes):
    t_end, errors = 0.5, []
    for n in sizes:
        steps = int(np.ceil(t_end / cls(n=n, nu=0.05).dt))  # Δt at half the stability limit
        st = cls(n=n, nu=0.05, dt=t_end / steps)
        u = st.rollout(_exact(st, 0.0), steps)
        errors.append(np.sqrt(np.mean((u - _exact(st, t_end)) ** 2)))
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert abs(rates[-1] - 1.0) < 0.1, (errors, rates)
    assert errors[-1] < 5e-3


def test_pbdl_preset_reaches_t1_with_a_shock():
    st = pbdl_scene(umax=1.0)
    assert (st.grid_shape, st.dt, st.params["nu"]) == ((128,), 1 / 32, pytest.approx(0.01 / np.pi))
    # Δt = 1/32 alone has Courant number 1/32 · 1 / (2/128) = 2: the step is split.
    assert st.substeps == 3
    x = st.nodes()
    assert x[0] == pytest.approx(-1 + 1 / 128) and x[-1] == pytest.approx(1 - 1 / 128)
    u0 = pbdl_state(st, batch=2)
    np.testing.assert_allclose(u0[1, 0], -np.sin(np.pi * x))
    traj = st.rollout(u0, 32, keep="all")
    assert 32 * st.dt == 1.0 and np.all(np.isfinite(traj))
    u = traj[-1, 0, 0]
    jumps = np.diff(u)
    i = np.argmax(np.abs(jumps))
    # A steep negative jump across x = 0, a one-cell drop of ≥ 0.5 (gradient ≥ 30 vs π at t = 0).
    assert abs(x[i] + x[i + 1]) < 1e-12 and jumps[i] < -0.5
    assert 0.6 < u.max() < 0.75 and np.abs(u).max() <= 1.0
    np.testing.assert_allclose(u, -u[::-1], atol=1e-12)  # stays odd about x = 0


def test_a_dt_of_too_many_substeps_is_refused_unless_they_are_asked_for():
    """With substeps chosen from dt, dt = 1e9 (a slip of units) would take 3·10^10 substeps a
    step: refused, naming the largest stable substep; given, substeps are the caller's."""
    from adjointsim.solvers.burgers_fv import MAX_SUBSTEPS

    limit = 1 / (1.0 / (2 / 64))  # u_max / h at ν = 0
    with pytest.raises(ValueError, match=r"dt = 1e\+09 needs .* substeps to stay stable \(the "
                       r"largest stable substep is 0.03125\), more than the 100,000 chosen "
                       "unasked; choose a smaller dt, or pass substeps"):
        BurgersRusanov1D(n=64, nu=0.0, amplitude=1.0, dt=1e9, substeps=None)
    assert BurgersRusanov1D(n=64, nu=0.0, amplitude=1.0, dt=limit * MAX_SUBSTEPS,
                            substeps=None).substeps == MAX_SUBSTEPS
    assert BurgersRusanov1D(n=64, nu=0.0, amplitude=1.0, dt=1.0, substeps=64).substeps == 64


# ------------------------------------------------------------------ invariants
@pytest.mark.parametrize(
    "stepper",
    [BurgersRusanov1D(n=48, nu=0.02, cfl=0.9, substeps=2), BurgersRusanov2D(n=20, cfl=0.9)],
    ids=lambda s: s.name,
)
def test_mean_conserved_energy_decays_maximum_principle(stepper):
    rng = np.random.default_rng(1)
    axes = tuple(range(2, 2 + stepper.ndim))
    u0 = np.clip(rng.standard_normal(stepper.state_shape(3)), -1, 1)  # rough, both signs
    traj = stepper.rollout(u0, 40, keep="all")
    axes = tuple(range(2, traj.ndim))
    mean = traj.mean(axis=axes)
    np.testing.assert_allclose(mean, np.broadcast_to(mean[0], mean.shape), atol=1e-14)
    energy = (traj**2).sum(axis=axes)
    assert np.all(np.diff(energy, axis=0) <= 1e-12)
    peak = np.abs(traj).max(axis=axes)
    assert np.all(np.diff(peak, axis=0) <= 1e-14)
    if stepper.ndim == 1:
        tv = np.abs(traj - np.roll(traj, 1, axis=-1)).sum(axis=axes)
        assert np.all(np.diff(tv, axis=0) <= 1e-12)


def test_pbdl_total_variation_does_not_grow():
    st = pbdl_scene(umax=1.0)
    traj = st.rollout(pbdl_state(st), 32, keep="all")[:, 0, 0]
    tv = np.abs(traj - np.roll(traj, 1, axis=-1)).sum(axis=-1)
    assert np.all(np.diff(tv) <= 1e-12)


# ------------------------------------------------------------------ forward vs NumPy
@pytest.mark.parametrize(
    "stepper",
    [
        BurgersRusanov1D(n=30, nu=0.03, substeps=2, cfl=0.8),
        BurgersRusanov2D(n=14, nu=0.1, amplitude=1.3, cfl=0.9),
        pbdl_scene(umax=1.0),
    ],
    ids=lambda s: f"{s.name}-n{s.grid_shape[0]}",
)
def test_forward_matches_numpy_reference(stepper):
    rng = np.random.default_rng(7)
    u0 = stepper.amplitude * np.clip(rng.standard_normal(stepper.state_shape(3)), -1, 1)
    np.testing.assert_allclose(
        stepper.rollout(u0, 12), numpy_reference.ROLLOUTS[stepper.name](stepper, u0, 12), atol=1e-12
    )


# ------------------------------------------------------------------ bad input
def test_unstable_dt_names_the_limit_and_the_largest_stable_dt():
    with pytest.raises(ValueError, match="largest stable Δt is 0.0111") as err:
        # 1 / (u_max/h + 2ν/h²) = 1 / (64 + 26.08) with h = 1/64
        BurgersRusanov1D(n=128, nu=0.01 / np.pi, dt=1 / 32, substeps=1)
    assert "stability limit 1" in str(err.value) and "substeps ≥ 3" in str(err.value)
    with pytest.raises(ValueError, match="largest stable Δt"):
        BurgersRusanov2D(n=16, dt=0.1)
    with pytest.raises(ValueError, match="nu must be a finite number ≥ 0, got -0.1"):
        BurgersRusanov1D(nu=-0.1)
    with pytest.raises(ValueError, match="umax must be a finite number > 0, got -1.0"):
        BurgersRusanov1D(umax=-1.0)
    with pytest.raises(ValueError, match="n must be an integer ≥ 2, got 1"):
        BurgersRusanov2D(n=1)


def test_unstable_nu_override_is_rejected():
    st = BurgersRusanov1D(n=32, nu=0.05, cfl=0.9)
    with pytest.raises(ValueError, match="largest stable Δt"):
        st.rollout(st.random_state(np.random.default_rng(0)), 2, params={"nu": 0.5})


def test_umax_sets_the_stability_bound():
    assert BurgersRusanov1D(amplitude=0.5).umax == 0.5
    loose, tight = BurgersRusanov1D(umax=1.0), BurgersRusanov1D(umax=4.0)
    assert tight.dt < loose.dt
    with pytest.raises(ValueError, match="largest stable Δt"):
        BurgersRusanov1D(umax=4.0, dt=loose.dt)


def test_every_space_draw_is_stable():
    for cls in (BurgersRusanov1D, BurgersRusanov2D):
        for key, option in cls.space.items():
            values = getattr(option, "values", None) or (option.lo, option.hi)
            for v in values:
                st = cls(**{key: int(v) if getattr(option, "integer", False) else v})
                st.check_params(np.array(st.param_values))
