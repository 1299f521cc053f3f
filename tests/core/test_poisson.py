"""Poisson 2D direct solver: exact eigenmodes, O(h²) convergence, residuals, adjoint, bad input."""

import numpy as np
import pytest

import adjointsim.solvers.poisson  # noqa: F401  (registers the solver)
from adjointsim.check import check_stepper
from adjointsim.grid import nodes
from adjointsim.solvers.poisson import Poisson2D
from tests.references.poisson import ROLLOUTS


def grid(s: Poisson2D) -> tuple[np.ndarray, np.ndarray]:
    x = nodes(s.n, s.length, s.bc)
    return np.meshgrid(x, x, indexing="ij")


def residual(s: Poisson2D, u: np.ndarray, f: np.ndarray, kappa: float = 0.0) -> float:
    """‖(−Δ_h + κ) u − f‖ / ‖f‖ with the 5-point stencil written out in NumPy."""
    mode = "wrap" if s.bc == "periodic" else "constant"
    p = np.pad(u, [(0, 0), (0, 0), (1, 1), (1, 1)], mode=mode)
    neighbours = p[..., :-2, 1:-1] + p[..., 2:, 1:-1] + p[..., 1:-1, :-2] + p[..., 1:-1, 2:]
    lap = (neighbours - 4 * u) / s.h**2
    return float(np.linalg.norm(-lap + kappa * u - f) / np.linalg.norm(f))


@pytest.mark.parametrize("bc", ["dirichlet", "periodic"])
def test_discrete_eigenfunctions_are_solved_exactly(bc):
    length = np.pi if bc == "dirichlet" else 2 * np.pi
    s = Poisson2D(n=20, bc=bc, length=length, kappa=0.3)
    x, y = grid(s)
    for k, m in [(1, 1), (2, 5), (7, 3)]:
        mode = np.sin(k * x) * (np.sin(m * y) if bc == "dirichlet" else np.cos(m * y))
        lam = 4 / s.h**2 * (np.sin(k * s.h / 2) ** 2 + np.sin(m * s.h / 2) ** 2) + 0.3
        u = s.solve(mode[None, None])
        np.testing.assert_allclose(u[0, 0], mode / lam, atol=1e-14 * np.abs(mode / lam).max())


@pytest.mark.parametrize(
    "bc, kappa", [("dirichlet", 0.0), ("dirichlet", 0.5), ("periodic", 0.0)]
)
def test_second_order_convergence_to_analytic_solution(bc, kappa):
    errors, spacings = [], []
    for n in [16, 32, 64, 128]:
        s = Poisson2D(n=n, bc=bc, length=np.pi if bc == "dirichlet" else 2 * np.pi, kappa=kappa)
        x, y = grid(s)
        if bc == "dirichlet":
            exact = np.exp(x + y) * np.sin(x) * np.sin(y)
            f = -2 * np.exp(x + y) * np.sin(x + y) + kappa * exact
        else:
            exact = np.exp(np.sin(x) + np.cos(y))
            f = -(np.cos(x) ** 2 - np.sin(x) + np.sin(y) ** 2 - np.cos(y)) * exact
            exact = exact - exact.mean()  # the solver returns the zero-mean solution
        u = s.solve(f[None, None])[0, 0]
        errors.append(np.abs(u - exact).max())
        spacings.append(s.h)
    orders = np.diff(np.log(errors)) / np.diff(np.log(spacings))
    assert np.all(orders > 1.95), orders
    assert np.all(orders < 2.05), orders


@pytest.mark.parametrize("bc, kappa", [("dirichlet", 0.0), ("dirichlet", -0.5), ("periodic", 0.0),
                                       ("periodic", 1.7)])
def test_residual_of_the_solve_is_round_off(bc, kappa):
    s = Poisson2D(n=23, bc=bc, kappa=kappa)
    f = s.random_state(np.random.default_rng(0), 3)
    if bc == "periodic":
        f -= f.mean(axis=(2, 3), keepdims=True)  # solvable part; the mean is projected out
    u = s.solve(f)
    assert residual(s, u, f, kappa) < 1e-12
    if bc == "periodic":
        np.testing.assert_allclose(u.mean(axis=(2, 3)), 0, atol=1e-15)


@pytest.mark.parametrize("bc", ["dirichlet", "periodic"])
def test_periodic_mean_is_projected_and_float32_stays_float32(bc):
    s = Poisson2D(n=12, bc=bc)
    f = s.random_state(np.random.default_rng(1), 2)
    u32 = s.solve(f.astype(np.float32))
    assert u32.dtype == np.float32
    np.testing.assert_allclose(u32, s.solve(f), rtol=0, atol=1e-5 * np.abs(s.solve(f)).max())
    if bc == "periodic":
        np.testing.assert_allclose(s.solve(f + 3.0), s.solve(f), atol=1e-13)


@pytest.mark.parametrize("bc, kappa", [("dirichlet", 0.0), ("periodic", 0.4)])
def test_solve_adjoint_is_the_transpose_and_equals_the_solve(bc, kappa):
    s = Poisson2D(n=14, bc=bc, kappa=kappa)
    rng = np.random.default_rng(2)
    f, g = s.random_state(rng, 2), s.random_state(rng, 2)
    lhs = np.sum(s.solve(f) * g)
    rhs = np.sum(f * s.solve_adjoint(g))
    assert abs(lhs - rhs) <= 1e-13 * abs(lhs)
    np.testing.assert_allclose(s.solve_adjoint(g), s.solve(g), rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize(
    "kw",
    [
        {},
        {"bc": "dirichlet"},
        {"bc": "dirichlet", "n": 11, "kappa": 0.2},
        {"bc": "dirichlet", "n": 6, "kappa": -0.2},
        {"bc": "periodic", "n": 9, "kappa": 0.15},
        {"bc": "periodic", "n": 24, "kappa": -0.2},
    ],
)
def test_gradients_at_several_scenes(kw):
    rows = check_stepper(Poisson2D(**kw), steps=50, seed=1)
    assert all(r.passed for r in rows), rows
    assert all(r.dot_rel_err <= 1e-12 for r in rows), rows


def test_default_scene_float32_gradients():
    rows = check_stepper(Poisson2D.default(), steps=50, dtype="float32")
    assert all(r.passed for r in rows), rows


@pytest.mark.parametrize("bc, kappa", [("dirichlet", 0.0), ("dirichlet", 0.3), ("periodic", 0.0),
                                       ("periodic", 0.3)])
def test_forward_matches_numpy_reference(bc, kappa):
    s = Poisson2D(n=17, bc=bc, kappa=kappa)
    u0 = s.random_state(np.random.default_rng(3), 3)
    ref = ROLLOUTS["poisson2d"](s, u0, 5)
    np.testing.assert_allclose(s.rollout(u0, 5), ref, rtol=1e-12, atol=1e-13 * np.abs(ref).max())


def test_bad_input():
    s = Poisson2D(n=8)
    with pytest.raises(ValueError, match=r"expected \(B, 1, 8, 8\)"):
        s.solve(np.zeros((1, 8, 8)))
    with pytest.raises(ValueError, match=r"expected \(B, 1, 8, 8\)"):
        s.solve_adjoint(np.zeros((2, 1, 8, 9)))
    with pytest.raises(ValueError, match="κ must exceed −λ_min"):
        Poisson2D(n=8, kappa=-1.0)
    with pytest.raises(ValueError, match="κ must exceed −λ_min"):
        s.solve(np.zeros((1, 1, 8, 8)), params={"kappa": -2.0})
    with pytest.raises(ValueError, match="bc must be one of 'periodic', 'dirichlet'"):
        Poisson2D(bc="neumann")
    with pytest.raises(ValueError, match="no control hook"):
        s.rollout(np.zeros((1, 1, 8, 8)), 2, np.zeros((2, 1, 1)))


@pytest.mark.parametrize("bc", ["dirichlet", "periodic"])
def test_batch_one_is_bitwise_equal_on_one_and_two_threads(bc, monkeypatch):
    # Batch 1 on two threads gives the transforms both threads (no batch split to use them),
    # here from 128² on.
    from adjointsim import parallel

    monkeypatch.setattr(parallel, "MIN_POINTS_INSIDE", 128 * 128)
    s = Poisson2D(n=128, bc=bc, kappa=0.2)
    u0 = s.random_state(np.random.default_rng(3), 1)
    results = []
    for threads in (1, 2):
        with parallel.using_threads(threads):
            assert parallel.threads_inside(1, 128 * 128) == threads
            last = s.rollout(u0, 3)
            g = s.vjp(u0, 3, last, wrt_params=True)
        results.append((last, g.state, np.array([g.params["kappa"]])))
    for a, b in zip(*results):
        assert a.tobytes() == b.tobytes()
