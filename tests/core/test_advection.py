"""Linear advection: upwind and Lax–Wendroff, 1D and 2D, periodic."""

from __future__ import annotations

import numpy as np
import pytest

from adjointsim.check import check_stepper
from adjointsim.solvers.lax_wendroff import LaxWendroffAdvection1D, LaxWendroffAdvection2D
from adjointsim.solvers.upwind import UpwindAdvection1D, UpwindAdvection2D
from tests.references import advection as numpy_reference

CLASSES = [UpwindAdvection1D, UpwindAdvection2D, LaxWendroffAdvection1D, LaxWendroffAdvection2D]


def _sine(stepper) -> np.ndarray:
    """sin(2π x) (1D) or sin(2π x) cos(2π y) (2D) on the unit box, shape (1, 1, *grid)."""
    x = stepper.nodes()
    if stepper.ndim == 1:
        return np.sin(2 * np.pi * x)[None, None]
    return (np.sin(2 * np.pi * x)[:, None] * np.cos(2 * np.pi * x)[None, :])[None, None]


def _assert_passed(rows):
    for r in rows:
        assert r.passed, r


# ------------------------------------------------------------------ gradients
@pytest.mark.parametrize(
    "stepper",
    [
        UpwindAdvection1D(n=20, velocity=-0.7, cfl=0.9),
        UpwindAdvection1D(n=13, velocity=2.0, length=3.0, dt=0.05),
        UpwindAdvection2D(n=10, velocity_x=-1.0, velocity_y=0.4, cfl=0.8),
        UpwindAdvection2D(n=9, velocity_x=0.3, velocity_y=-1.1, cfl=0.3),
        LaxWendroffAdvection1D(n=17, velocity=-1.3, cfl=0.95),
        LaxWendroffAdvection2D(n=11, velocity_x=-0.6, velocity_y=-0.9, cfl=0.7),
        LaxWendroffAdvection2D(n=8, velocity_x=1.0, velocity_y=-0.2, length=2.0, cfl=0.5),
    ],
    ids=lambda s: f"{s.name}-n{s.grid_shape[0]}-a{s.param_values}",
)
def test_gradients_non_default_scenes(stepper):
    _assert_passed(check_stepper(stepper, steps=30, batch=3, seed=1))


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.name)
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_gradients_default_scene(cls, dtype):
    _assert_passed(check_stepper(cls.default(), steps=50, dtype=dtype))


def test_velocity_gradient_is_one_sided_at_fixed_sign():
    """Upwind's stencil flips with the sign of a: the gradient is the one of the current branch."""
    st = UpwindAdvection1D(n=16, velocity=0.5, dt=0.02)
    u0 = _sine(st)
    w = np.cos(2 * np.pi * st.nodes())[None, None]
    for a in (0.5, -0.5):
        g = st.vjp(u0, 10, w, params={"velocity": a}, wrt_params=True).params["velocity"]
        f = [np.sum(w * st.rollout(u0, 10, params={"velocity": a + s * 1e-6})) for s in (1, -1)]
        assert g == pytest.approx((f[0] - f[1]) / 2e-6, rel=1e-6)


# ------------------------------------------------------------------ accuracy
def _advected_sine_error(cls, n: int, velocity: tuple[float, ...]) -> float:
    """RMS error after the sine has been carried once around the unit box (|a_d| = 1, T = 1)
    at the fixed Courant numbers |ν_d| = 1/4, stable for every scheme."""
    steps = 4 * n
    kwargs = {"velocity": velocity[0]} if cls.ndim == 1 else dict(
        zip(("velocity_x", "velocity_y"), velocity, strict=True)
    )
    st = cls(n=n, dt=1.0 / steps, **kwargs)
    u0 = _sine(st)
    return float(np.sqrt(np.mean((st.rollout(u0, steps) - u0) ** 2)))


@pytest.mark.parametrize(
    "cls, order, sizes, tol",
    [
        # Upwind's error is mostly the damping 1 − exp(−c h) of the mode: first order only once
        # c h ≪ 1, so its observed order approaches 1 from below on the finer grids.
        (UpwindAdvection1D, 1.0, (64, 128, 256, 512), 0.05),
        (UpwindAdvection2D, 1.0, (64, 128, 256), 0.12),
        (LaxWendroffAdvection1D, 2.0, (32, 64, 128), 0.02),
        (LaxWendroffAdvection2D, 2.0, (16, 32, 64), 0.02),
    ],
    ids=lambda v: getattr(v, "name", None),
)
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_observed_order_advected_sine(cls, order, sizes, tol, sign):
    errors = np.array([_advected_sine_error(cls, n, (sign, -sign)) for n in sizes])
    rates = np.log2(errors[:-1] / errors[1:])
    assert abs(rates[-1] - order) < tol, (errors, rates)
    assert np.all(np.diff(rates) > -1e-3), rates  # approaching the order, not drifting away


def test_upwind_at_courant_one_is_an_exact_shift():
    st = UpwindAdvection1D(n=24, velocity=-1.0, cfl=1.0)
    u0 = np.random.default_rng(0).standard_normal((2, 1, 24))
    np.testing.assert_allclose(st.rollout(u0, 5), np.roll(u0, -5, axis=-1), atol=1e-14)


def test_lax_wendroff_2d_matches_its_amplification_factor():
    """One step on a Fourier mode multiplies it by the stated symbol (with the cross term)."""
    st = LaxWendroffAdvection2D(n=16, velocity_x=0.8, velocity_y=-0.6, cfl=0.9)
    nx, ny = st.courant(np.array(st.param_values))
    kx, ky = 2 * np.pi * 3 / 16, 2 * np.pi * 5 / 16
    i = np.arange(16)
    mode = np.exp(1j * (kx * i[:, None] + ky * i[None, :]))
    symbol = (
        1 - 1j * nx * np.sin(kx) - 1j * ny * np.sin(ky)
        - nx**2 * (1 - np.cos(kx)) - ny**2 * (1 - np.cos(ky)) - nx * ny * np.sin(kx) * np.sin(ky)
    )
    out = st.rollout(mode.real[None, None], 1) + 1j * st.rollout(mode.imag[None, None], 1)
    np.testing.assert_allclose(out[0, 0], symbol * mode, atol=1e-13)


# ------------------------------------------------------------------ invariants
@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.name)
def test_mass_is_conserved(cls):
    st = cls(n=20, cfl=0.9)
    u0 = st.random_state(np.random.default_rng(3), batch=2)
    traj = st.rollout(u0, 40, keep="all")
    mass = traj.sum(axis=tuple(range(2, traj.ndim)))
    np.testing.assert_allclose(mass, np.broadcast_to(mass[0], mass.shape), atol=1e-11)


@pytest.mark.parametrize(
    "stepper",
    [UpwindAdvection1D(n=40, velocity=-0.8, cfl=0.9), UpwindAdvection2D(n=20, cfl=1.0)],
    ids=lambda s: s.name,
)
def test_upwind_maximum_principle_and_tvd(stepper):
    rng = np.random.default_rng(4)
    u0 = np.sign(rng.standard_normal(stepper.state_shape(2)))  # rough, discontinuous data
    traj = stepper.rollout(u0, 30, keep="all")
    axes = tuple(range(2, traj.ndim))
    assert np.all(traj.max(axis=axes) <= traj.max(axis=axes)[0] + 1e-14)
    assert np.all(traj.min(axis=axes) >= traj.min(axis=axes)[0] - 1e-14)
    tv = sum(np.abs(traj - np.roll(traj, 1, axis=a)).sum(axis=axes) for a in axes[1:])
    assert np.all(np.diff(tv, axis=0) <= 1e-12)


def test_lax_wendroff_is_not_monotone_but_stays_bounded():
    """LW oscillates at a jump (it is linear and second order) but, L2-stable, never grows."""
    st = LaxWendroffAdvection1D(n=40, cfl=0.8)
    u0 = np.where(st.nodes() < 0.5, 1.0, 0.0)[None, None]
    traj = st.rollout(u0, 30, keep="all")
    assert traj.max() > 1.01
    norms = np.sqrt((traj**2).sum(axis=(1, 2, 3)))
    assert np.all(np.diff(norms) <= 1e-12)


# ------------------------------------------------------------------ forward vs NumPy
@pytest.mark.parametrize(
    "stepper",
    [
        UpwindAdvection1D(n=30, velocity=-0.6, cfl=0.7),
        UpwindAdvection2D(n=12, velocity_x=0.7, velocity_y=-1.2, cfl=0.9),
        LaxWendroffAdvection1D(n=25, velocity=1.4, cfl=0.9),
        LaxWendroffAdvection2D(n=14, velocity_x=-0.5, velocity_y=0.9, cfl=0.9),
    ],
    ids=lambda s: s.name,
)
def test_forward_matches_numpy_reference(stepper):
    u0 = stepper.random_state(np.random.default_rng(5), batch=3)
    np.testing.assert_allclose(
        stepper.rollout(u0, 25), numpy_reference.ROLLOUTS[stepper.name](stepper, u0, 25), atol=1e-12
    )


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize(
    "make, largest",
    [
        (lambda: UpwindAdvection1D(n=10, velocity=-2.0, dt=0.06), 0.05),
        (lambda: UpwindAdvection2D(n=10, velocity_x=1.0, velocity_y=-1.0, dt=0.06), 0.05),
        (lambda: LaxWendroffAdvection1D(n=10, velocity=1.0, dt=0.11), 0.1),
        # (|ν_x|^{2/3} + |ν_y|^{2/3}) ≤ 1 at ν_x = ν_y: Δt ≤ h / 2^{3/2}
        (
            lambda: LaxWendroffAdvection2D(n=10, velocity_x=1.0, velocity_y=1.0, dt=0.04),
            0.1 / 8**0.5,
        ),
    ],
)
def test_unstable_dt_names_the_largest_stable_dt(make, largest):
    with pytest.raises(ValueError, match="largest stable Δt is") as err:
        make()
    assert f"{largest:.6g}" in str(err.value)


def test_unstable_velocity_override_is_rejected():
    st = UpwindAdvection1D(n=10, velocity=1.0, cfl=0.9)
    with pytest.raises(ValueError, match="stability limit"):
        st.rollout(np.zeros((1, 1, 10)), 2, params={"velocity": -1.5})


def test_bad_scenes():
    with pytest.raises(ValueError, match="n must be an integer ≥ 2, got 1"):
        UpwindAdvection1D(n=1)
    with pytest.raises(ValueError, match="give dt"):
        LaxWendroffAdvection2D(velocity_x=0.0, velocity_y=0.0)


def test_every_space_draw_is_stable():
    for cls in CLASSES:
        for key, option in cls.space.items():
            values = getattr(option, "values", None) or (option.lo, option.hi)
            for v in values:
                st = cls(**{key: int(v) if getattr(option, "integer", False) else v})
                st.check_params(np.array(st.param_values))
