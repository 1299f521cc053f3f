"""2D real FFTs and spectral operators: dot-product tests of every adjoint, exactness on
band-limited fields, resampling round trips."""

import numpy as np
import pytest

from adjointsim.spectral import fft2d

SIZES = (8, 12, 32)


def dot(a, b):
    return float(np.sum((np.conj(a) * b).real))


def rel(a, b):
    return abs(a - b) / max(abs(a), abs(b))


@pytest.fixture
def rng():
    return np.random.default_rng(0)


def nodes(n):
    x = 2 * np.pi * np.arange(n) / n
    return np.meshgrid(x, x, indexing="ij")


@pytest.mark.parametrize("n", SIZES)
def test_transforms_match_numpy_and_their_adjoints_pass_the_dot_test(n, rng):
    m = n // 2 + 1
    x = rng.standard_normal((2, 3, n, n))
    # Arbitrary, non-Hermitian half spectra: the adjoints must hold on all of them.
    xh = rng.standard_normal((2, 3, n, m)) + 1j * rng.standard_normal((2, 3, n, m))
    fx, gx = np.empty_like(xh), np.empty_like(x)
    fft2d.rfft2(x, fx, 1)
    fft2d.irfft2(xh, gx, 1)
    np.testing.assert_allclose(fx, np.fft.rfft2(x), atol=1e-12)
    np.testing.assert_allclose(gx, np.fft.irfft2(xh, s=(n, n)), atol=1e-14)
    ft, gt = np.empty_like(x), np.empty_like(xh)
    fft2d.rfft2_adjoint(xh, ft)
    fft2d.irfft2_adjoint(x, gt)
    assert rel(dot(fx, xh), dot(x, ft)) <= 1e-13
    assert rel(dot(gx, x), dot(xh, gt)) <= 1e-13


@pytest.mark.parametrize("n", SIZES)
@pytest.mark.parametrize(
    "make", [
        lambda n: fft2d.derivative_multiplier(n, 0),
        lambda n: fft2d.derivative_multiplier(n, 1),
        fft2d.laplacian_multiplier,
        lambda n: fft2d.dealias_multiplier(n).astype(complex),
    ],
    ids=["d/dx", "d/dy", "laplacian", "dealias"],
)
def test_multiplier_adjoint_is_the_conjugate_multiplier(n, make, rng):
    mult = make(n)
    x, y = rng.standard_normal((2, 3, n, n))
    forward = fft2d.apply_multiplier(x, mult)
    adjoint = fft2d.apply_multiplier(y, mult.conj())
    assert rel(dot(forward, y), dot(x, adjoint)) <= 1e-13


@pytest.mark.parametrize(("n", "m"), [(8, 8), (12, 8), (8, 12), (32, 128), (128, 32), (16, 48)])
def test_resample_adjoint_dot_test(n, m, rng):
    x = rng.standard_normal((2, 1, n, n))
    y = rng.standard_normal((2, 1, m, m))
    assert rel(dot(fft2d.resample(x, m), y), dot(x, fft2d.resample_adjoint(y, n))) <= 1e-13


def test_spectral_derivatives_are_exact_on_trigonometric_polynomials():
    n = 16
    x, y = nodes(n)
    f = np.sin(3 * x) * np.cos(2 * y)
    dx = fft2d.apply_multiplier(f, fft2d.derivative_multiplier(n, 0))
    dy = fft2d.apply_multiplier(f, fft2d.derivative_multiplier(n, 1))
    lap = fft2d.apply_multiplier(f, fft2d.laplacian_multiplier(n))
    np.testing.assert_allclose(dx, 3 * np.cos(3 * x) * np.cos(2 * y), atol=1e-13)
    np.testing.assert_allclose(dy, -2 * np.sin(3 * x) * np.sin(2 * y), atol=1e-13)
    np.testing.assert_allclose(lap, -13 * f, atol=1e-12)
    # The Nyquist mode has no real derivative: d/dx zeroes it.
    nyquist = np.cos(n / 2 * x)
    np.testing.assert_allclose(
        fft2d.apply_multiplier(nyquist, fft2d.derivative_multiplier(n, 0)), 0.0, atol=1e-13
    )


@pytest.mark.parametrize(("n", "cut"), [(8, 2), (16, 5), (32, 10), (48, 15), (128, 42)])
def test_dealias_cutoff_is_the_two_thirds_rule(n, cut):
    assert fft2d.dealias_cutoff(n) == cut
    assert 3 * cut < n <= 3 * (cut + 1)
    mask = fft2d.dealias_multiplier(n)
    assert mask.shape == (n, n // 2 + 1)
    assert mask.sum() == (2 * cut + 1) * (cut + 1)


def test_dealiasing_removes_exactly_the_modes_above_the_cutoff():
    n = 12
    x, y = nodes(n)
    low = np.cos(3 * x + 2 * y)
    high = np.cos(4 * x) + np.sin(5 * y)
    np.testing.assert_allclose(
        fft2d.apply_multiplier(low + high, fft2d.dealias_multiplier(n).astype(complex)), low,
        atol=1e-13,
    )


@pytest.mark.parametrize("n", (8, 32))
def test_lowpass_transforms_equal_the_full_ones_on_their_columns(n, rng):
    cut = fft2d.dealias_cutoff(n)
    x = rng.standard_normal((3, n, n))
    out = np.empty((3, n, n // 2 + 1), dtype=complex)
    fft2d.rfft2_lowpass(x, out, cut, 1)
    np.testing.assert_allclose(out[..., : cut + 1], np.fft.rfft2(x)[..., : cut + 1], atol=1e-12)
    xh = np.fft.rfft2(x)
    xh[..., cut + 1 :] = 0.0
    expected = np.fft.irfft2(xh, s=(n, n))
    back = np.empty_like(x)
    fft2d.irfft2_lowpass(xh, back, cut, 1)
    np.testing.assert_allclose(back, expected, atol=1e-14)


def test_resampling_reproduces_band_limited_fields_at_the_target_points():
    coarse, fine = 32, 128
    xc, yc = nodes(coarse)
    xf, yf = nodes(fine)

    def field(x, y):
        return 1.5 + np.cos(3 * x - 5 * y) + np.sin(15 * y) * np.cos(2 * x)

    np.testing.assert_allclose(fft2d.resample(field(xf, yf), coarse), field(xc, yc), atol=1e-12)
    np.testing.assert_allclose(fft2d.resample(field(xc, yc), fine), field(xf, yf), atol=1e-12)


def test_resampling_round_trips(rng):
    coarse, fine = 32, 128
    u = rng.standard_normal((2, 1, coarse, coarse))
    up_down = fft2d.resample(fft2d.resample(u, fine), coarse)
    # Coarse → fine → coarse loses only the coarse grid's Nyquist modes.
    kx, ky = fft2d.wavenumbers(coarse)
    keep = ((np.abs(kx) < coarse // 2) & (ky < coarse // 2)).astype(complex)
    np.testing.assert_allclose(up_down, fft2d.apply_multiplier(u, keep), atol=1e-13)
    # Fine → coarse → fine is a projection: idempotent, mean-preserving.
    v = rng.standard_normal((2, 1, fine, fine))
    once = fft2d.resample(fft2d.resample(v, coarse), fine)
    twice = fft2d.resample(fft2d.resample(once, coarse), fine)
    np.testing.assert_allclose(twice, once, atol=1e-13)
    np.testing.assert_allclose(once.mean(axis=(-2, -1)), v.mean(axis=(-2, -1)), atol=1e-14)


def test_float32_stays_float32(rng):
    x = rng.standard_normal((2, 16, 16)).astype(np.float32)
    assert fft2d.resample(x, 8).dtype == np.float32
    assert fft2d.apply_multiplier(x, fft2d.laplacian_multiplier(16)).dtype == np.float32
    out = fft2d.spectrum_zeros((2, 16, 9), x)
    assert out.dtype == np.complex64
    fft2d.rfft2(x, out, 1)
    np.testing.assert_allclose(out, np.fft.rfft2(x), rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("n", (12, 128))
def test_transforms_on_several_threads_are_bitwise_those_on_one(n, rng):
    x = rng.standard_normal((n, n))
    cut = fft2d.dealias_cutoff(n)
    results = []
    for nthreads in (1, 2, 3):
        full = fft2d.spectrum_zeros((n, n // 2 + 1), x)
        low = np.zeros_like(full)
        back, back_low = np.empty_like(x), np.empty_like(x)
        fft2d.rfft2(x, full, nthreads)
        fft2d.rfft2_lowpass(x, low, cut, nthreads)
        fft2d.irfft2(full, back, nthreads)
        masked = full.copy()
        masked[:, cut + 1 :] = 0.0
        fft2d.irfft2_lowpass(masked, back_low, cut, nthreads)
        results.append((full, low, back, back_low))
    for other in results[1:]:
        for a, b in zip(results[0], other):
            np.testing.assert_array_equal(a, b)


def test_threads_inside_go_to_large_grids_in_calls_smaller_than_the_thread_count():
    from adjointsim import parallel

    big = parallel.MIN_POINTS_INSIDE
    with parallel.using_threads(1):
        assert parallel.threads_inside(1, big) == 1
    with parallel.using_threads(4):
        assert [parallel.threads_inside(b, big) for b in (1, 3, 4, 16)] == [4, 4, 1, 1]
        assert parallel.threads_inside(1, big - 1) == 1
        # Inside one chunk of a split call the split already uses the threads.
        inner = parallel.map_chunks(lambda b: parallel.threads_inside(b, big), [1, 1])
        assert inner == [1, 1]


def test_odd_grids_are_rejected():
    with pytest.raises(ValueError, match="even"):
        fft2d.wavenumbers(15)
    with pytest.raises(ValueError, match="even"):
        fft2d.resample(np.zeros((8, 8)), 7)
