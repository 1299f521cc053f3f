"""Real FFTs inside numba (packed and library layouts) and their adjoints: dot-product tests."""

import numpy as np
import pytest

from adjointsim.spectral import fft1d

# Batches below and above LIBRARY_BATCH exercise both layouts; sizes cover radices 4, 2, 3
# and the generic prime branch (7, 11, 13).
BATCHES = (1, fft1d.LIBRARY_BATCH - 1, fft1d.LIBRARY_BATCH + 1)
SIZES = (2, 4, 6, 8, 10, 14, 22, 26, 48, 64, 96, 128)


def dot(a, b):
    return float(np.sum((np.conj(a) * b).real))


def dot_test(ax, y, x, aty):
    """|⟨A x, y⟩ − ⟨x, Aᵀ y⟩| relative to ‖A x‖ ‖y‖ (a random pair can nearly cancel)."""
    return abs(dot(ax, y) - dot(x, aty)) / (np.linalg.norm(ax) * np.linalg.norm(y))


@pytest.mark.parametrize("n", SIZES)
@pytest.mark.parametrize("batch", BATCHES)
def test_matches_numpy(n, batch):
    rng = np.random.default_rng(n + batch)
    u = rng.standard_normal((batch, n))
    x = rng.standard_normal((batch, n // 2 + 1)) + 1j * rng.standard_normal((batch, n // 2 + 1))
    np.testing.assert_allclose(fft1d.rfft(u), np.fft.rfft(u), rtol=0, atol=1e-13 * n)
    # irfft ignores the imaginary parts of the zero and Nyquist modes, like numpy's
    np.testing.assert_allclose(fft1d.irfft(x, n), np.fft.irfft(x, n), rtol=0, atol=1e-14 * n)


@pytest.mark.parametrize("batch", BATCHES)
def test_float32_stays_float32(batch):
    u = np.random.default_rng(0).standard_normal((batch, 48)).astype(np.float32)
    x = fft1d.rfft(u)
    assert x.dtype == np.complex64
    assert fft1d.irfft(x, 48).dtype == np.float32
    assert all(a.dtype in (np.float32, np.complex64) for a in fft1d.plan(48, np.float32)[1:])
    np.testing.assert_allclose(fft1d.irfft(x, 48), u, atol=1e-5)


@pytest.mark.parametrize("n", (6, 48, 128))
@pytest.mark.parametrize("batch", BATCHES)
def test_adjoints_dot_product(n, batch):
    rng = np.random.default_rng(7)
    u, ubar = rng.standard_normal((2, batch, n))
    x, xbar = rng.standard_normal((2, batch, n // 2 + 1)) + 1j * rng.standard_normal(
        (2, batch, n // 2 + 1)
    )
    assert dot_test(fft1d.rfft(u), xbar, u, fft1d.rfft_adjoint(xbar, n)) < 1e-13
    assert dot_test(fft1d.irfft(x, n), ubar, x, fft1d.irfft_adjoint(ubar)) < 1e-13


@pytest.mark.parametrize("order", (1, 2, 3, 4))
def test_derivative_and_mask_adjoints(order):
    n, length = 48, 5.0
    rng = np.random.default_rng(order)
    u, v = rng.standard_normal((2, 3, n))
    for mult in (fft1d.derivative_multiplier(n, length, order), fft1d.dealias_mask(n)):
        au, atv = fft1d.apply_multiplier(u, mult), fft1d.apply_multiplier(v, np.conj(mult))
        assert dot_test(au, v, u, atv) < 1e-13


def test_derivative_is_spectrally_exact():
    n, length = 32, 3.0
    x = length * np.arange(n) / n
    k = 2 * np.pi * 3 / length
    u = np.sin(k * x)[None]
    for order, exact in ((1, k * np.cos(k * x)), (2, -(k**2) * np.sin(k * x))):
        du = fft1d.apply_multiplier(u, fft1d.derivative_multiplier(n, length, order))
        np.testing.assert_allclose(du[0], exact, atol=1e-12 * k**order)


def test_dealias_mask_two_thirds():
    mask = fft1d.dealias_mask(128)
    assert mask[42] == 1 and mask[43] == 0 and mask.sum() == 43


@pytest.mark.parametrize("n1, n2", ((16, 48), (48, 16), (32, 32), (30, 64)))
def test_resample(n1, n2):
    rng = np.random.default_rng(n1 * n2)
    u, v = rng.standard_normal((2, 2, n1)), rng.standard_normal((2, 2, n2))
    assert dot_test(fft1d.resample(u, n2), v, u, fft1d.resample_adjoint(v, n1)) < 1e-13
    # band-limited signals are interpolated exactly
    x1, x2 = np.arange(n1) / n1, np.arange(n2) / n2
    k = min(n1, n2) // 2 - 1
    smooth = lambda x: np.cos(2 * np.pi * x) + 0.3 * np.sin(2 * np.pi * k * x)  # noqa: E731
    np.testing.assert_allclose(fft1d.resample(smooth(x1)[None], n2)[0], smooth(x2), atol=1e-12)


@pytest.mark.parametrize("batch", BATCHES)
def test_packed_kernels(batch):
    """rfft_packed's modes, multiplier, offset and accumulation; irfft_packed's multiplier."""
    n = 24
    m = n // 2
    fplan = fft1d.plan(n)
    rng = np.random.default_rng(batch)
    u, o = rng.standard_normal((2, batch, n))
    g = rng.standard_normal(m + 1) + 1j * rng.standard_normal(m + 1)
    f = rng.standard_normal(m + 1) + 1j * rng.standard_normal(m + 1)
    idx = np.array([[fft1d.at(k, b, m + 1, batch) for k in range(m + 1)] for b in range(batch)])
    z, zo = np.empty(m * batch, complex), np.empty(m * batch, complex)
    fft1d.pack(u, z, fplan[4])
    fft1d.pack(o, zo, fplan[4])
    t, w = np.empty(m * batch, complex), np.empty((m + 1) * batch, complex)
    empty = np.empty(0, complex)
    out = rng.standard_normal((m + 1) * batch) + 0j
    for mode, signal in ((0, u), (1, u**2), (2, 2 * u * o)):
        start = out.copy()
        fft1d.rfft_packed(z, zo, mode, out, g, f, True, t, w, batch, fplan)
        np.testing.assert_allclose(out[idx], start[idx] + g * np.fft.rfft(signal) + f, atol=1e-12)
        fft1d.rfft_packed(z, zo, mode, out, empty, empty, False, t, w, batch, fplan)
        np.testing.assert_allclose(out[idx], np.fft.rfft(signal), atol=1e-12)
    back = np.empty_like(u)
    fft1d.irfft_packed(out, g, z, w, batch, fplan)
    fft1d.unpack(z, back, fplan[4])
    np.testing.assert_allclose(back, np.fft.irfft(g * out[idx], n), atol=1e-12)


def test_odd_length_rejected():
    with pytest.raises(ValueError, match="even"):
        fft1d.plan(15)
