"""Thomas solves (plain and cyclic) against dense solves, their adjoint and complex step."""

import numpy as np
import pytest

from adjointsim.tridiagonal import TILE, factor, solve, solve_rows, transpose


def dense(coef: np.ndarray, n: int, cyclic: bool) -> np.ndarray:
    lower, diag, upper, first, last = coef
    a = (
        np.diag(np.full(n, diag, dtype=coef.dtype))
        + np.diag(np.full(n - 1, lower, dtype=coef.dtype), -1)
        + np.diag(np.full(n - 1, upper, dtype=coef.dtype), 1)
    )
    a[0, 0], a[-1, -1] = first, last
    if cyclic:
        a[0, -1] += lower
        a[-1, 0] += upper
    return a


# Non-symmetric, diagonally dominant: Dirichlet-like ends, Neumann-like ends.
COEFS = [np.array([-0.7, 3.0, -1.3, 3.0, 3.0]), np.array([-0.7, 2.1, -1.3, 1.4, 0.8])]


@pytest.mark.parametrize("n", [2, 3, 17])
@pytest.mark.parametrize("cyclic", [False, True])
@pytest.mark.parametrize("coef", COEFS)
def test_solves_match_dense(n, cyclic, coef):
    rng = np.random.default_rng(n)
    a = dense(coef, n, cyclic)
    f = factor(coef, n, cyclic)
    d = rng.standard_normal((3, n, 5))
    x = d.copy()
    solve(f, x)
    np.testing.assert_allclose(x, np.linalg.solve(a, d), rtol=1e-13, atol=1e-14)
    # More lines than one tile, and a partial last tile.
    rows = rng.standard_normal((2, 2 * TILE + 3, n))
    y = rows.copy()
    solve_rows(f, y)
    np.testing.assert_allclose(y, np.linalg.solve(a, rows.transpose(0, 2, 1)).transpose(0, 2, 1),
                               rtol=1e-13, atol=1e-14)


@pytest.mark.parametrize("cyclic", [False, True])
@pytest.mark.parametrize("coef", COEFS)
def test_transposed_solve_is_the_adjoint(cyclic, coef):
    n = 11
    rng = np.random.default_rng(1)
    d, w = rng.standard_normal((2, 1, n, 4))
    x, dbar = d.copy(), w.copy()
    solve(factor(coef, n, cyclic), x)
    solve(factor(transpose(coef), n, cyclic), dbar)
    np.testing.assert_allclose(dbar[0], np.linalg.solve(dense(coef, n, cyclic).T, w[0]), rtol=1e-13)
    lhs, rhs = np.sum(x * w), np.sum(d * dbar)
    assert abs(lhs - rhs) <= 1e-14 * abs(lhs)


@pytest.mark.parametrize("cyclic", [False, True])
def test_complex_step_gives_the_matrix_cotangent(cyclic):
    """d⟨w, x⟩/d coef from complex step equals Σ Ā ∂A/∂coef with Ā = −d̄ xᵀ."""
    n, h = 9, 1e-30
    coef = COEFS[1]
    rng = np.random.default_rng(2)
    d, w = rng.standard_normal((2, 1, n, 3))
    x = d.copy()
    solve(factor(coef, n, cyclic), x)
    dbar = w.copy()
    solve(factor(transpose(coef), n, cyclic), dbar)
    abar = -np.einsum("im,jm->ij", dbar[0], x[0])
    for k in range(5):
        dc = np.zeros(5)
        dc[k] = 1.0
        xc = d.astype(complex)
        solve(factor(coef + 1j * h * dc, n, cyclic), xc)
        tangent = np.sum(w * xc.imag) / h
        da = dense(coef + dc, n, cyclic) - dense(coef, n, cyclic)
        assert tangent == pytest.approx(np.sum(abar * da), rel=1e-12)


def test_float32_right_hand_sides_stay_float32():
    n = 16
    coef = COEFS[0]
    d = np.random.default_rng(3).standard_normal((2, 5, n)).astype(np.float32)
    x = d.copy()
    solve_rows(factor(coef, n, True), x)
    assert x.dtype == np.float32
    exact = np.linalg.solve(dense(coef, n, True), d.astype(np.float64).transpose(0, 2, 1))
    np.testing.assert_allclose(x, exact.transpose(0, 2, 1), rtol=1e-5, atol=1e-6)


def test_too_small_system_is_rejected():
    with pytest.raises(ValueError, match="n >= 2"):
        factor(COEFS[0], 1, False)
