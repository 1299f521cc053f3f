"""The staggered-grid incompressible Navier–Stokes solver: its pressure solve, a divergence-free
result for every kind of side, exact discrete adjoints (complex-step dot products and the
gradient checker), the order of convergence on the Taylor–Green vortex, the lid-driven cavity
against Ghia, Ghia & Shin (1982), and one-line errors for scenes that cannot run."""

from __future__ import annotations

import numpy as np
import pytest

from adjointsim.check import check_stepper
from adjointsim.errors import UserError
from adjointsim.solvers.incompressible2d import Incompressible2D, cylinder
from adjointsim.stepper import NonFiniteInputError

SCENES = Incompressible2D.space["boundaries"].values
H = 1e-100  # complex step


def scene(boundaries: str, **kw) -> Incompressible2D:
    args = dict(nx=8, ny=6, dt=0.02, nu=0.02, profile="parabolic", lid_speed=0.7, buoyancy=0.3)
    return Incompressible2D(boundaries=boundaries, **{**args, **kw})


def dot_product_error(s: Incompressible2D, steps: int = 3, batch: int = 2, seed: int = 0) -> float:
    """|⟨J v, w⟩ − ⟨v, Jᵀ w⟩| / |⟨J v, w⟩| over the state, the controls and the parameters at
    once, J v by the complex step (exact to round-off), w on every state of the rollout."""
    rng = np.random.default_rng(seed)
    u = s.random_state(rng, batch)
    c = 0.5 * s.random_controls(rng, steps, batch)
    p = np.array(s.param_values)
    du, dc = rng.standard_normal(u.shape), rng.standard_normal(c.shape)
    dp = rng.standard_normal(p.shape)
    w = rng.standard_normal((steps + 1, *u.shape))
    run = s.rollout_prepared(u + 1j * H * du, steps, c + 1j * H * dc, p + 1j * H * dp,
                             keep="all", check_finite=False)
    tangent = np.sum(run.imag / H * w)
    g = s.vjp(u, steps, w, c, wrt_params=True)
    adjoint = (np.sum(du * g.state) + np.sum(dc * g.controls)
               + sum(d * g.params[k] for d, k in zip(dp, s.param_names)))
    return abs(tangent - adjoint) / abs(tangent)


# ------------------------------------------------------------------ the projection
def test_the_factors_solve_the_pressure_matrix():
    s = Incompressible2D.default()
    g = s.geometry
    rng = np.random.default_rng(0)
    b = rng.standard_normal(g.matrix.shape[0])
    np.testing.assert_allclose(g.matrix @ s.solve_pressure(b), b, atol=1e-12)
    assert g.matrix.shape[0] == g.fluid.sum() < s.nx * s.ny  # the box's cells are left out


@pytest.mark.parametrize("boundaries", SCENES)
@pytest.mark.parametrize("obstacle", [None, "box", "cylinder"])
def test_every_step_leaves_the_flow_divergence_free(boundaries, obstacle):
    s = scene(boundaries, obstacle=obstacle, density=True)
    rng = np.random.default_rng(1)
    u = s.random_state(rng, 2)
    out = s.rollout(u, 4, 0.5 * s.random_controls(rng, 4, 2), keep="all")[1:]
    for state in out:
        assert np.abs(s.divergence(state)).max() < 1e-11
    # the spare entries stay zero, and so does the density in solid cells
    assert not out[:, :, 0, :, s.ny].any() and not out[:, :, 1, s.nx, :].any()
    assert not out[:, :, 2, : s.nx, : s.ny][:, :, s.solid].any()


def test_walls_obstacles_and_inflow_hold_their_normal_velocity():
    s = scene("inflow outflow wall wall", obstacle="box", inflow_speed=1.3)
    out = s.rollout(s.random_state(np.random.default_rng(2), 1), 3)[0]
    u, v = out[0, :, : s.ny], out[1, : s.nx, :]
    y = (np.arange(s.ny) + 0.5) / s.ny
    prof = y * (1 - y) / np.mean(y * (1 - y))
    np.testing.assert_allclose(u[0], 1.3 * prof, rtol=1e-14)
    assert not v[:, 0].any() and not v[:, -1].any()  # the channel's walls
    solid = np.argwhere(s.solid)
    for i, j in solid:
        assert u[i, j] == u[i + 1, j] == v[i, j] == v[i, j + 1] == 0.0


def test_a_channel_at_rest_with_a_uniform_inflow_is_plug_flow():
    """Uniform inflow between free-slip walls: the exact solution is u = U everywhere."""
    s = Incompressible2D(nx=6, ny=4, dt=0.05, nu=0.01, boundaries="inflow outflow slip slip",
                         inflow_speed=0.8)
    out = s.rollout(np.zeros(s.state_shape(1)), 10)
    np.testing.assert_allclose(out[0, 0, :, :4], 0.8, rtol=1e-12)
    np.testing.assert_allclose(out[0, 1, :6, :], 0.0, atol=1e-12)


# ------------------------------------------------------------------ the adjoint
@pytest.mark.parametrize("boundaries", SCENES)
@pytest.mark.parametrize("density", [False, True])
def test_the_adjoint_is_the_transposed_tangent(boundaries, density):
    for obstacle in (None, "box"):
        err = dot_product_error(scene(boundaries, density=density, obstacle=obstacle))
        assert err < 1e-12, (obstacle, err)


@pytest.mark.parametrize("buoyancy", [0.0, 1e-226, -1e-8])
def test_the_checker_passes_a_buoyancy_at_or_near_zero(buoyancy):
    # The buoyancy's range holds zero; a parameter moved only relative to its own value would
    # not move the flow at all there, and the checker would report a wrong gradient.
    s = Incompressible2D(nx=3, ny=3, boundaries="inflow outflow wall wall", profile="uniform",
                         density=True, nu=0.03125, buoyancy=buoyancy, dt=0.03125)
    rows = check_stepper(s, steps=1, seed=0, batch=1)
    assert all(r.passed for r in rows), [r for r in rows if not r.passed]


@pytest.mark.parametrize("boundaries", SCENES)
def test_the_maccormack_adjoint_is_the_transposed_tangent(boundaries):
    for obstacle in (None, "box"):
        s = scene(boundaries, density=True, obstacle=obstacle, advection="maccormack")
        assert dot_product_error(s, steps=4) < 1e-12, obstacle
        out = s.rollout(s.random_state(np.random.default_rng(6), 2), 3)
        assert np.abs(s.divergence(out)).max() < 1e-11


def test_maccormack_is_sharper_than_semi_lagrangian():
    """A smoke step carried across a periodic box keeps more of its contrast (measured: 0.76
    against 0.41); semi-Lagrangian keeps its mass exactly in a uniform flow, MacCormack's
    clamp does not."""
    peaks = {}
    for advection in ("semi-lagrangian", "maccormack"):
        s = Incompressible2D(nx=16, ny=8, dt=0.03, nu=0.0, density=True, advection=advection,
                             boundaries="periodic periodic periodic periodic")
        u = np.zeros(s.state_shape(1))
        u[0, 0] = 1.0
        u[0, 2, 4:8, :8] = 1.0
        out = s.rollout(u, 40)[0, 2, :16, :8]
        if advection == "semi-lagrangian":
            assert abs(out.mean() - 0.25) < 1e-12
        peaks[advection] = out.max() - out.min()
    assert peaks["maccormack"] > peaks["semi-lagrangian"] + 0.3, peaks


@pytest.mark.parametrize("boundaries", SCENES)
def test_the_smallest_grid_runs_and_reverses(boundaries):
    s = scene(boundaries, nx=1, ny=1, density=True)
    assert dot_product_error(s) < 1e-12
    u = s.random_state(np.random.default_rng(3), 2)
    assert np.abs(s.divergence(s.rollout(u, 2))).max() < 1e-12


def test_the_obstacle_of_the_wake_scene():
    s = Incompressible2D(nx=16, ny=8, length=2.0, dt=0.02, nu=0.005,
                         boundaries="inflow outflow slip slip", obstacle="cylinder",
                         density=True, buoyancy=0.1)
    assert s.solid.sum() == cylinder(16, 8, (4, 4), 1).sum() > 0
    assert dot_product_error(s) < 1e-12


@pytest.mark.parametrize("which", ["default", "cavity", "periodic"])
def test_gradcheck_passes_for_state_controls_and_parameters(which):
    s = {
        "default": Incompressible2D.default(),
        "cavity": Incompressible2D(nx=6, ny=6, dt=0.02, nu=0.02),
        "periodic": scene("periodic periodic periodic periodic", nx=5, ny=4, density=True),
    }[which]
    rows = check_stepper(s, steps=12, seed=4)
    assert {r.wrt for r in rows} >= {"state", "controls", *s.param_names}
    failed = [r for r in rows if not r.passed]
    assert not failed, failed


# ------------------------------------------------------------------ implicit viscosity
def test_the_implicit_viscous_matrix_is_symmetric_for_every_kind_of_side():
    for boundaries in SCENES:
        s = scene(boundaries, obstacle="box", viscosity="implicit")
        a = s.geometry.velocity_laplacian()
        assert a.shape[0] == s.geometry.ufree.sum() + s.geometry.vfree.sum()
        assert abs(a - a.T).max() == 0.0, boundaries


@pytest.mark.parametrize("boundaries", SCENES)
def test_implicit_and_explicit_steps_differ_at_second_order_in_the_viscosity(boundaries):
    """One step from the same state: backward and forward Euler differ by kd² Δ_h² u, so
    halving ν quarters the difference, for every kind of side: the implicit step's matrix is
    the explicit step's Laplacian, ghost layers, copies, mirrors, lids and inflow included."""
    u = scene(boundaries, obstacle="box", density=True).random_state(np.random.default_rng(8), 2)

    def gap(nu: float) -> float:
        out = [scene(boundaries, obstacle="box", density=True, nu=nu, viscosity=v).rollout(u, 1)
               for v in ("explicit", "implicit")]
        return float(np.abs(out[0] - out[1]).max())

    ratio = gap(0.02) / gap(0.01)
    assert 3.5 < ratio < 4.5, ratio


@pytest.mark.parametrize("boundaries", SCENES)
def test_the_implicit_adjoint_is_the_transposed_tangent(boundaries):
    for obstacle in (None, "box"):
        s = scene(boundaries, density=True, obstacle=obstacle, viscosity="implicit", nu=0.5)
        assert dot_product_error(s) < 1e-12, obstacle
        out = s.rollout(s.random_state(np.random.default_rng(9), 2), 3)
        assert np.abs(s.divergence(out)).max() < 1e-11
    s = scene(boundaries, density=True, viscosity="implicit", advection="maccormack")
    assert dot_product_error(s, steps=4) < 1e-12


@pytest.mark.parametrize("which", ["inflow", "cavity"])
def test_gradcheck_passes_with_implicit_viscosity(which):
    """ν Δt/h² = 2.56 and 1.44, far beyond the explicit step's limit of ¼."""
    s = {
        "inflow": Incompressible2D(nx=8, ny=6, dt=0.02, nu=2.0, boundaries="inflow outflow wall "
                                   "wall", profile="parabolic", obstacle="box", density=True,
                                   buoyancy=0.5, viscosity="implicit"),
        "cavity": Incompressible2D(nx=6, ny=6, dt=0.04, nu=1.0, viscosity="implicit"),
    }[which]
    rows = check_stepper(s, steps=12, seed=4)
    assert {r.wrt for r in rows} >= {"state", "controls", *s.param_names}
    failed = [r for r in rows if not r.passed]
    assert not failed, failed


def shear_mode(n: int, nu: float, dt: float, steps: int, viscosity: str) -> tuple[float, float]:
    """A channel (periodic in x, no-slip walls at y = 0 and 1) holding u = sin(π y): advection
    carries it along itself unchanged, the pressure stays zero, and the viscous step scales it
    by its discrete eigenvalue. The amplitude after ``steps`` and that eigenvalue's power."""
    s = Incompressible2D(nx=4, ny=n, length=4.0 / n, dt=dt, nu=nu,
                         boundaries="periodic periodic wall wall", viscosity=viscosity)
    u = np.zeros(s.state_shape(1))
    u[0, 0, :, :n] = 0.5 * np.sin(np.pi * (np.arange(n) + 0.5) / n)
    out = s.rollout(u, steps)[0, 0, :, :n] / u[0, 0, :, :n]
    assert np.ptp(out) < 1e-12  # still the same mode
    kd, lam = nu * dt * n**2, 4.0 * np.sin(np.pi / (2 * n)) ** 2
    factor = 1.0 / (1.0 + kd * lam) if viscosity == "implicit" else 1.0 - kd * lam
    return float(out.mean()), factor**steps


def test_the_shear_mode_of_a_channel_decays_by_the_discrete_factor_and_converges():
    """Each step multiplies the mode by 1/(1 + kd λ) (implicit) or 1 − kd λ (explicit), λ the
    discrete Laplacian's eigenvalue 4 sin²(π/2n); backward Euler converges at first order in
    Δt to the space-discrete decay e^{−ν λ n² t} (measured from ν Δt/h² = 1.28, five times the
    explicit limit: errors 7.2e-3, 3.7e-3, 1.8e-3), which is 9.7e-4 from e^{−ν π² t}."""
    nu, t, n = 0.1, 0.5, 16
    semi_discrete = np.exp(-nu * 4 * n**2 * np.sin(np.pi / (2 * n)) ** 2 * t)
    errors = []
    for steps in (10, 20, 40):
        amp, exact = shear_mode(n, nu, t / steps, steps, "implicit")
        assert abs(amp - exact) < 1e-13 * exact
        errors.append(abs(amp - semi_discrete))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all((orders > 0.9) & (orders < 1.1)), (errors, orders)
    assert abs(semi_discrete - np.exp(-nu * np.pi**2 * t)) < 1.2e-3
    amp, exact = shear_mode(n, nu, 0.0025, 200, "explicit")
    assert abs(amp - exact) < 1e-13 * exact


def test_explicit_and_implicit_viscosity_agree_to_first_order_in_the_time_step():
    """The Taylor–Green vortex at 16² (ν = 0.05, t = 0.5): the two schemes' results differ by
    O(Δt), and halving Δt halves the difference."""
    gaps = []
    for steps in (8, 16, 32):
        out = []
        for viscosity in ("explicit", "implicit"):
            s = Incompressible2D(nx=16, ny=16, length=2 * np.pi, dt=0.5 / steps, nu=0.05,
                                 boundaries="periodic periodic periodic periodic",
                                 viscosity=viscosity)
            out.append(s.rollout(taylor_green(16, 0.0, 0.05), steps))
        gaps.append(float(np.abs(out[0] - out[1]).max()))
    ratios = np.array(gaps[:-1]) / np.array(gaps[1:])
    assert np.all((ratios > 1.7) & (ratios < 2.3)), (gaps, ratios)


def test_implicit_viscosity_lifts_the_viscous_limit_but_not_the_advective_one():
    s = scene("wall wall wall lid", nu=1.0, viscosity="implicit")  # ν Δt/h² = 1.28
    u = s.random_state(np.random.default_rng(10), 1)
    assert np.abs(s.divergence(s.rollout(u, 3, params={"nu": 5.0}))).max() < 1e-11
    with pytest.raises(ValueError, match="advective limit for the lid"):
        scene("wall wall wall lid", nu=1.0, viscosity="implicit", dt=0.2)


# ------------------------------------------------------------------ accuracy
def taylor_green(n: int, t: float, nu: float) -> np.ndarray:
    """The decaying Taylor–Green vortex u = sin x cos y, v = −cos x sin y (times e^{−2νt}) on
    the faces of an n × n grid of [0, 2π)²."""
    h = 2 * np.pi / n
    s = np.zeros((1, 2, n + 1, n + 1))
    faces, centres = np.arange(n + 1) * h, (np.arange(n) + 0.5) * h
    s[0, 0, :, :n] = np.sin(faces)[:, None] * np.cos(centres)[None, :]
    s[0, 1, :n, :] = -np.cos(centres)[:, None] * np.sin(faces)[None, :]
    return s * np.exp(-2 * nu * t)


def taylor_green_error(n: int, nu: float = 0.01, t: float = 1.0) -> float:
    steps = int(round(t / (np.pi / n)))  # Courant number 1/2 at the peak speed 1
    s = Incompressible2D(nx=n, ny=n, length=2 * np.pi, dt=t / steps, nu=nu,
                         boundaries="periodic periodic periodic periodic")
    return float(np.abs(s.rollout(taylor_green(n, 0.0, nu), steps) - taylor_green(n, t, nu)).max())


def test_order_of_convergence_on_the_taylor_green_vortex():
    """Semi-Lagrangian with bilinear samples at a fixed Courant number: first order (measured
    0.90, 0.95, and 0.97 from 64 to 128)."""
    errors = [taylor_green_error(n) for n in (16, 32, 64)]
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(orders > 0.85) and orders[-1] > orders[0], (errors, orders)


#: Ghia, Ghia & Shin (1982), Re = 100: u on the vertical centreline, v on the horizontal one
GHIA_Y = np.array([1.0, 0.9766, 0.9688, 0.9609, 0.9531, 0.8516, 0.7344, 0.6172, 0.5, 0.4531,
                   0.2813, 0.1719, 0.1016, 0.0703, 0.0625, 0.0547, 0.0])
GHIA_U = np.array([1.0, 0.84123, 0.78871, 0.73722, 0.68717, 0.23151, 0.00332, -0.13641,
                   -0.20581, -0.21090, -0.15662, -0.10150, -0.06434, -0.04775, -0.04192,
                   -0.03717, 0.0])
GHIA_X = np.array([1.0, 0.9688, 0.9609, 0.9531, 0.9453, 0.9063, 0.8594, 0.8047, 0.5, 0.2344,
                   0.2266, 0.1563, 0.0938, 0.0781, 0.0703, 0.0625, 0.0])
GHIA_V = np.array([0.0, -0.05906, -0.07391, -0.08864, -0.10313, -0.16914, -0.22445, -0.24533,
                   0.05454, 0.17527, 0.17507, 0.16077, 0.12317, 0.10890, 0.10091, 0.09233, 0.0])


def cavity_deviation(n: int, t: float = 20.0) -> tuple[float, float]:
    """Largest |u − u_Ghia| and |v − v_Ghia| on the centrelines (lid speed 1) after the cavity
    at Re = 100 has run from rest to time t, at 0.8 × the largest stable Δt."""
    h, nu = 1.0 / n, 0.01
    dt = 0.8 * min(h, h * h / (4 * nu))
    steps = int(np.ceil(t / dt))
    s = Incompressible2D(nx=n, ny=n, dt=dt, nu=nu, boundaries="wall wall wall lid")
    out = s.rollout(np.zeros(s.state_shape(1)), steps)[0]
    centres = np.concatenate([[0.0], (np.arange(n) + 0.5) * h, [1.0]])
    u = np.concatenate([[0.0], out[0, n // 2, :n], [1.0]])
    v = np.concatenate([[0.0], out[1, :n, n // 2], [0.0]])
    return (float(np.abs(np.interp(GHIA_Y, centres, u) - GHIA_U).max()),
            float(np.abs(np.interp(GHIA_X, centres, v) - GHIA_V).max()))


#: the largest deviations measured (0.044, 0.023, 0.013; see docs/howto/walls-and-obstacles.md),
#: with a little room
CAVITY_BOUND = {16: 0.05, 32: 0.026, 64: 0.015}


def test_lid_driven_cavity_at_re_100_against_ghia_coarse():
    deviations = {n: max(cavity_deviation(n)) for n in (16, 32)}
    assert all(d < CAVITY_BOUND[n] for n, d in deviations.items()), deviations


@pytest.mark.slow
def test_lid_driven_cavity_at_re_100_against_ghia_converges():
    deviations = {n: max(cavity_deviation(n)) for n in (16, 32, 64)}
    assert all(d < CAVITY_BOUND[n] for n, d in deviations.items()), deviations
    assert deviations[64] < deviations[32] < deviations[16], deviations


# ------------------------------------------------------------------ bad scenes, bad input
@pytest.mark.parametrize("kw, match", [
    ({"boundaries": "inflow outflow wall wall", "obstacle": np.eye(8, 6, dtype=bool)},
     "an obstacle covers the left inflow; move the obstacle"),
    ({"obstacle": np.ones((8, 6), dtype=bool)}, "the obstacle covers every cell"),
    ({"boundaries": "inflow wall wall wall"},
     r"net flux of 6 \(per unit inflow_speed, in cell widths\) into a region of fluid with no "
     "outflow"),
])
def test_scenes_that_cannot_be_projected_are_named_in_one_line(kw, match):
    with pytest.raises(UserError, match=match) as err:
        scene(**{"boundaries": "wall wall wall lid", **kw})
    assert "\n" not in str(err.value)


def test_a_pocket_of_fluid_walled_in_by_an_obstacle_is_projected_on_its_own():
    """A pocket of 2 × 2 cells has no outflow: its pressure is pinned at one cell, and its flow
    stays divergence-free beside the channel's."""
    ring = np.zeros((8, 6), dtype=bool)
    ring[3:7, 1:5] = True
    ring[4:6, 2:4] = False
    s = scene("inflow outflow wall wall", obstacle=ring, density=True)
    assert s.geometry.ufree[5, 2:4].all() and s.geometry.vfree[4:6, 3].all()
    assert dot_product_error(s) < 1e-12
    out = s.rollout(s.random_state(np.random.default_rng(7), 1), 3)
    assert np.abs(s.divergence(out)).max() < 1e-11
    assert np.abs(out[0, 0, 5, 2:4]).max() > 0  # the pocket's fluid moves


def test_an_obstacle_beside_the_inflow_but_off_it_is_accepted():
    s = scene("inflow outflow wall wall", obstacle=cylinder(8, 6, (2, 3), 1.2))
    assert s.solid[1].any() and not s.solid[0].any()
    assert dot_product_error(s) < 1e-12


@pytest.mark.parametrize("kw, match", [
    ({"dt": 0.2, "lid_speed": 1.0}, r"dt = 0.2 is beyond the advective limit for the lid: "
                                     r"dt ≤ h/\|lid_speed\| = 0.125"),
    ({"dt": 0.1, "boundaries": "inflow outflow wall wall", "profile": "parabolic"},
     r"advective limit for the inflow: dt ≤ h/\(peak inflow speed\) = 0.0\d+"),
    ({"nu": 1.0}, r"dt = 0.02 with nu = 1 is beyond the explicit viscosity's stability "
                  r"limit: dt ≤ h²/\(4 nu\) = 0.00390625"),
    ({"boundaries": "periodic wall wall wall"}, "periodic sides come in pairs"),
    ({"boundaries": "wall wall wall"}, "must name four sides"),
    ({"boundaries": "wall wall wall roof"}, "each one of wall, slip, lid"),
    ({"obstacle": "sphere"}, "obstacle must be one of 'cylinder', 'box'"),
    ({"advection": "upwind"}, "advection must be one of 'semi-lagrangian', 'maccormack'"),
    ({"viscosity": "crank"}, "viscosity must be one of 'explicit', 'implicit'"),
    ({"obstacle": np.zeros((6, 8), dtype=bool)}, r"boolean mask of shape \(8, 6\)"),
    ({"nu": float("nan")}, "nu must be a finite number"),
    ({"inflow_speed": float("inf")}, "inflow_speed must be a finite number"),
])
def test_bad_scenes_get_one_line_naming_the_limit(kw, match):
    with pytest.raises(ValueError, match=match) as err:
        scene(**{"boundaries": "wall wall wall lid", "lid_speed": 1.0, **kw})
    assert "\n" not in str(err.value)


def test_a_state_the_solver_made_beyond_courant_1_steps_on_as_in_one_rollout():
    """The scene hypothesis drew: the inflow from the right at 1.5 squeezes past the box, and
    within three steps from a start at Courant number 0.375 the flow outruns h/dt. Stepping
    on from each state gives the n-step rollout bit for bit (the solver used to refuse the
    state it had made as the next call's input)."""
    s = Incompressible2D(nx=8, ny=3, boundaries="outflow inflow slip lid", profile="uniform",
                         obstacle="box", density=False, viscosity="explicit", nu=0.03125,
                         buoyancy=0.0, inflow_speed=1.5, dt=0.046875)
    u = s.random_state(np.random.default_rng(1), 2)
    whole = s.rollout(u, 3, keep="all")
    assert s.courant_number(u) <= 0.5
    assert max(s.courant_number(w) for w in whole) > 1.0
    v = u
    for k in range(3):
        v = s.step(v)
        np.testing.assert_array_equal(v, whole[k + 1])


def test_bad_states_and_parameters_get_one_line():
    s = scene("inflow outflow wall wall")
    u = s.random_state(np.random.default_rng(5), 2)
    fast = u.copy()
    fast[1, 0, 3, 2] = 9.0
    assert s.courant_number(fast) == pytest.approx(9 * 0.02 * 8)  # reported, not refused
    assert np.isfinite(s.rollout(fast, 1)).all()
    bad = u.copy()
    bad[0, 1, 2, 2] = np.nan
    with pytest.raises(NonFiniteInputError, match=r"u0 has non-finite values in batch "
                                                  r"element\(s\) \[0\]"):
        s.rollout(bad, 1)
    with pytest.raises(ValueError, match="advective limit for the inflow"):
        s.rollout(u, 1, params={"inflow_speed": 100.0})
    with pytest.raises(ValueError, match="explicit viscosity's stability limit"):
        s.vjp(u, 1, u, params={"nu": 10.0})
