"""ETDRK coefficients (contour integrals and their L-derivatives) and the schemes' accuracy."""

import numpy as np
import pytest

import adjointsim.solvers.kuramoto_sivashinsky as ks
from adjointsim.solvers.advection_diffusion1d import ADVECTION_DIFFUSION
from adjointsim.solvers.burgers_spectral import BURGERS
from adjointsim.spectral.etdrk import KEYS, etdrk_coefficient_derivatives, etdrk_coefficients

mp = pytest.importorskip("mpmath")  # ships with torch (through sympy)

H = 0.25
# From stiff decay through the cancellation-prone |hL| ≪ 1 to growth, real and complex.
LIN = np.array([-1e4, -390.0, -20.0, -1.0, -1e-3, 1e-9, 0.3, 2.0])
LIN_C = LIN + 1j * np.array([0.0, 50.0, 3.0, 1.0, 0.0, 1e-3, -2.0, 0.5])
FORMULAS = {
    "E": lambda z: mp.exp(z),
    "E2": lambda z: mp.exp(z / 2),
    "phi1": lambda z: H * mp.expm1(z) / z,
    "phi2": lambda z: H * (mp.expm1(z) - z) / z**2,
    "Q": lambda z: H * mp.expm1(z / 2) / z,
    "f1": lambda z: H * (-4 - z + mp.exp(z) * (4 - 3 * z + z**2)) / z**3,
    "f2": lambda z: H * (2 + z + mp.exp(z) * (z - 2)) / z**3,
    "f3": lambda z: H * (-4 - 3 * z - z**2 + mp.exp(z) * (4 - z)) / z**3,
}


@pytest.mark.parametrize("lin", (LIN, LIN_C), ids=("real", "complex"))
def test_coefficients_and_derivatives_match_extended_precision(lin):
    mp.mp.dps = 60
    coef, deriv = {}, {}
    for order in (2, 3):  # between them, every key of every order (phi2 is ETDRK2's alone)
        coef.update(etdrk_coefficients(lin, H, order))
        deriv.update(etdrk_coefficient_derivatives(lin, H, order))
    assert set(coef) == set(deriv) == set(FORMULAS)
    assert coef["f1"].dtype == (np.float64 if lin.dtype.kind == "f" else np.complex128)
    for key, f in FORMULAS.items():
        for i, lam in enumerate(lin):
            z = mp.mpc(H * complex(lam))
            exact, slope = complex(f(z)), complex(H * mp.diff(f, z))
            assert abs(coef[key][i] - exact) <= 2e-15 * abs(exact) + 1e-300
            # the Cauchy-integral derivative loses about eps·|hL| relative accuracy
            assert abs(deriv[key][i] - slope) <= 1e-13 * max(abs(slope), abs(exact))


def test_keys_cache_and_read_only():
    for order, keys in KEYS.items():
        c = etdrk_coefficients(LIN, H, order)
        assert tuple(c) == keys
        assert c is etdrk_coefficients(LIN.copy(), H, order)
        assert not c["E"].flags.writeable
    with pytest.raises(ValueError, match="order"):
        etdrk_coefficients(LIN, H, 5)


def burgers_errors(order: int) -> np.ndarray:
    n, T = 64, 1.0
    x = 2 * np.pi * np.arange(n) / n
    u0 = (0.5 * np.sin(x) + 0.2 * np.cos(2 * x))[None, None]
    ref = BURGERS[4](n=n, nu=0.1, dt=T / 1024).rollout(u0, 1024)
    return np.array([
        np.abs(BURGERS[order](n=n, nu=0.1, dt=T / m).rollout(u0, m) - ref).max()
        for m in (8, 16, 32)
    ])


@pytest.mark.parametrize("order", (1, 2, 3, 4))
def test_temporal_convergence_order(order):
    errors = burgers_errors(order)
    rates = np.log2(errors[:-1] / errors[1:])
    # two-sided: a scheme of another order (a wrong tableau) must not pass (measured within 0.12)
    assert np.all(np.abs(rates - order) < 0.2), rates


@pytest.mark.parametrize("order", (1, 2, 3, 4))
@pytest.mark.parametrize("substeps", (1, 3))
def test_linear_problem_exact(order, substeps):
    """u_t = −c u_x + ν u_xx + a g with g constant in time: every order is exact."""
    n, length, c, nu, a = 32, 2 * np.pi, 0.7, 0.05, 0.3
    x = length * np.arange(n) / n
    g = np.cos(2 * x)[None]
    stepper = ADVECTION_DIFFUSION[order](
        n=n, velocity=c, nu=nu, dt=0.4, substeps=substeps, forcing=g, forcing_amplitude=a
    )
    u0 = (np.sin(x) + 0.5 * np.cos(3 * x))[None, None]
    t = 0.4 * 25
    u = stepper.rollout(u0, 25)
    lam2 = -2j * c - 4 * nu  # the forced mode k = 2: û' = λ û + a ĝ
    exact = (
        np.exp(-nu * t) * np.sin(x - c * t)
        + 0.5 * np.exp(-9 * nu * t) * np.cos(3 * (x - c * t))
        + np.real(a * (np.exp(lam2 * t) - 1) / lam2 * np.exp(2j * x))
    )
    np.testing.assert_allclose(u[0, 0], exact, atol=1e-13)


def test_kassam_trefethen_accuracy():
    stepper = ks.KuramotoSivashinskyETDRK.kassam_trefethen()
    u0 = stepper.kassam_trefethen_state()
    u = stepper.rollout(u0, 40)  # t = 10
    fine = ks.KS[4](n=128, length=32 * np.pi, dt=0.25, substeps=64).rollout(u0, 40)
    err = np.abs(u - fine).max() / np.abs(fine).max()
    assert err <= 1e-5, err
