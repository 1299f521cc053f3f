"""Real 2D FFTs inside numba kernels, and their adjoints, on a doubly periodic n × n grid.

Layout: a physical array ``x[..., i, j]`` holds values at (x_i, y_j) = (i, j)·L/n; its half
spectrum ``X[..., p, q]`` (shape ``(..., n, n//2 + 1)``) holds the modes (k_x, k_y) with k_x in
FFT order along axis −2 and k_y = q ≥ 0 along axis −1 (numpy's ``rfft2`` convention: unnormalised
forward transform, 1/n² on the inverse). Only even n is supported.

The transforms are rocket-fft's DUCC kernels through ``rocket_fft.lowlevel``, which write into
caller-owned arrays, so the solvers' time loops allocate nothing. Each takes ``nthreads``: DUCC
splits a transform over its independent lines, each line's arithmetic unchanged, so the result
is the same to the bit on any number of threads; the 2D spectral steppers give a call's
transforms every solver thread when its batch is smaller than the thread count
(:func:`adjointsim.parallel.threads_inside`). Measured here (128², float64, one thread, CPU
time): r2c 28 µs and c2r 31 µs, against 31 and 36 µs for numpy.fft.rfft2 / irfft2 called inside
njit (rocket-fft's overloads allocate their result) and 63 µs for numpy.fft.rfft2 from Python; the
"lowpass" variants below, which skip the transforms of the k_y columns above a cutoff (2/3
rule: 43 of 65), take 23–25 µs.

Adjoints (Euclidean inner products; complex arrays as pairs of reals, ⟨A, B⟩ = Re Σ conj(A) B).
Let c_q = 1 for the k_y = 0 and Nyquist columns and 2 otherwise. For any complex X (Hermitian or
not) irfft2 computes (1/n²) Re Σ_half c_q X e^{+ik·x}: the half spectrum stands for the full one
and irfft2 drops the imaginary parts of the self-paired columns. Hence

    irfft2ᵀ(x̄) = (c / n²) · rfft2(x̄),        rfft2ᵀ(X̄) = n² · irfft2(X̄ / c).

A cleaner way to use this inside solvers: on the Hermitian half spectra H = rfft2(ℝ^{n×n}) take
the inner product ⟨X, Y⟩_H = (1/n²) Re Σ_half c_q conj(X) Y. Then irfft2: H → ℝ^{n×n} is an
isometry with inverse rfft2, so a spectral map S: H → H has the physical adjoint
irfft2 ∘ S* ∘ rfft2, and the H-adjoint of a diagonal multiplier m is conj(m) provided m maps H
to H (real even multipliers do; odd ones such as i k_x need their Nyquist entry zeroed, which
:func:`derivative_wavenumbers` does).

Spectral operators built on this (each with its adjoint, all dot-product tested):
``apply_multiplier`` (derivatives, Laplacian, 2/3 dealiasing: adjoint = the conjugate
multiplier) and ``resample`` (spectral interpolation between n × n and m × m grids, keeping the
modes |k_x|, k_y < min(n, m)/2; its adjoint is (m/n)² times resampling back, m → n).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import rocket_fft  # noqa: F401  (registers numpy.fft/scipy.fft for numba, loads the DUCC library)
from numba import njit
from rocket_fft import lowlevel

if TYPE_CHECKING:
    from numpy.typing import DTypeLike

__all__ = [
    "apply_multiplier",
    "dealias_cutoff",
    "dealias_multiplier",
    "derivative_multiplier",
    "derivative_wavenumbers",
    "hermitian_weights",
    "irfft2",
    "irfft2_adjoint",
    "irfft2_lowpass",
    "laplacian_multiplier",
    "random_smooth_field",
    "resample",
    "resample_adjoint",
    "rfft2",
    "rfft2_adjoint",
    "rfft2_lowpass",
    "spectrum_zeros",
    "wavenumbers",
]


# ------------------------------------------------------------------ wavenumbers and multipliers
def _check_even(n: int) -> int:
    if int(n) != n or n < 2 or n % 2:
        raise ValueError(f"2D spectral grids need an even number of points ≥ 2 per axis, not {n}")
    return int(n)


def wavenumbers(n: int, length: float = 2 * np.pi) -> tuple[np.ndarray, np.ndarray]:
    """(k_x of shape (n, 1), k_y of shape (1, n//2 + 1)) for a period ``length``, Nyquist kept."""
    n = _check_even(n)
    scale = 2 * np.pi / length
    kx = np.fft.fftfreq(n, 1.0 / n) * scale
    kx[n // 2] = abs(kx[n // 2])
    ky = np.arange(n // 2 + 1) * scale
    return kx[:, None], ky[None, :]


def derivative_wavenumbers(n: int, length: float = 2 * np.pi) -> tuple[np.ndarray, np.ndarray]:
    """Like :func:`wavenumbers`, Nyquist entries zeroed: i k then maps real fields to real fields
    (the Nyquist mode's derivative would be imaginary), and conj(i k) is its exact adjoint."""
    kx, ky = wavenumbers(n, length)
    kx, ky = kx.copy(), ky.copy()
    kx[n // 2] = 0.0
    ky[0, n // 2] = 0.0
    return kx, ky


def hermitian_weights(n: int) -> np.ndarray:
    """c_q, shape (n//2 + 1,): the number of full-spectrum columns each half column stands for."""
    n = _check_even(n)
    c = np.full(n // 2 + 1, 2.0)
    c[0] = c[-1] = 1.0
    return c


def dealias_cutoff(n: int) -> int:
    """The 2/3 rule: the largest K with 3K < n. Products of fields with |k_x|, |k_y| ≤ K alias
    only onto modes above K, which the mask then removes (n = 128 → K = 42, n = 32 → K = 10)."""
    return (_check_even(n) - 1) // 3


def dealias_multiplier(n: int) -> np.ndarray:
    """1 on the modes with |k_x| ≤ K and k_y ≤ K, 0 elsewhere (shape (n, n//2 + 1))."""
    kx, ky = wavenumbers(n)
    cut = dealias_cutoff(n)
    return ((np.abs(kx) <= cut) & (ky <= cut)).astype(np.float64)


def derivative_multiplier(n: int, axis: int, length: float = 2 * np.pi) -> np.ndarray:
    """i k along ``axis`` (−2 or 0: x, −1 or 1: y), shape (n, n//2 + 1), Nyquist zeroed."""
    kx, ky = derivative_wavenumbers(n, length)
    k = kx if axis in (0, -2) else ky
    return np.broadcast_to(1j * k, (n, n // 2 + 1)).copy()


def laplacian_multiplier(n: int, length: float = 2 * np.pi) -> np.ndarray:
    """−|k|² (shape (n, n//2 + 1), complex so that it can go straight to apply_multiplier)."""
    kx, ky = wavenumbers(n, length)
    return (-(kx**2) - ky**2).astype(np.complex128)


def random_smooth_field(
    rng: np.random.Generator,
    shape: tuple[int, ...],
    kmax: float = 4.0,
    dtype: DTypeLike = np.float64,
) -> np.ndarray:
    """Random real fields of shape (..., n, n) with modes |k| ≤ ``kmax`` only, unit RMS each."""
    n = _check_even(shape[-1])
    kx, ky = wavenumbers(n)
    keep = (kx**2 + ky**2 <= kmax**2) & ((kx != 0) | (ky != 0))
    spec = (rng.standard_normal((*shape[:-2], n, n // 2 + 1))
            + 1j * rng.standard_normal((*shape[:-2], n, n // 2 + 1))) * keep
    x = np.fft.irfft2(spec, s=(n, n))
    rms = np.sqrt(np.mean(x**2, axis=(-2, -1), keepdims=True))
    return (x / np.where(rms > 0, rms, 1.0)).astype(dtype)


# ------------------------------------------------------------------ transforms (numba kernels)
@njit(cache=True, nogil=True)
def _last_two(a):
    return np.array([a.ndim - 2, a.ndim - 1])


@njit(cache=True, nogil=True)
def rfft2(x, out, nthreads):
    """out = rfft2(x) over the last two axes; x (..., n, n) real, out (..., n, n//2+1) complex.
    ``nthreads``: DUCC's threads for this one call
    (see :func:`adjointsim.parallel.threads_inside`)."""
    lowlevel.r2c(x, out, _last_two(x), True, 1.0, nthreads)


@njit(cache=True, nogil=True)
def irfft2(xh, out, nthreads):
    """out = irfft2(xh) (with the 1/n² factor); out (..., n, n) real sets the length. Keeps xh."""
    n = out.shape[-1]
    lowlevel.c2r(xh, out, _last_two(xh), False, 1.0 / (n * n), nthreads)


@njit(cache=True, nogil=True)
def rfft2_lowpass(x, out, cutoff, nthreads):
    """rfft2 for the columns k_y ≤ ``cutoff`` only; used when a 2/3 mask follows the transform.

    The columns of ``out`` above the cutoff are left holding the transforms along y alone.
    """
    ax = np.array([x.ndim - 1])
    lowlevel.r2c(x, out, ax, True, 1.0, nthreads)
    lowlevel.c2c(out[..., : cutoff + 1], out[..., : cutoff + 1], ax - 1, True, 1.0, nthreads)


@njit(cache=True, nogil=True)
def irfft2_lowpass(xh, out, cutoff, nthreads):
    """irfft2 of a spectrum whose columns k_y > ``cutoff`` are zero, skipping their transforms.

    Transforms the columns k_y ≤ ``cutoff`` of ``xh`` in place, so it destroys them.
    """
    n = out.shape[-1]
    ax = np.array([xh.ndim - 1])
    lowlevel.c2c(xh[..., : cutoff + 1], xh[..., : cutoff + 1], ax - 1, False, 1.0, nthreads)
    lowlevel.c2r(xh, out, ax, False, 1.0 / (n * n), nthreads)


@njit(cache=True, nogil=True)
def spectrum_zeros(shape, like):
    """Zeroed complex array of ``shape`` in the precision of the real array ``like``."""
    z = np.zeros(1, dtype=like.dtype) * np.complex64(1.0)
    return np.zeros(shape, dtype=z.dtype)


@njit(cache=True, nogil=True)
def rfft2_adjoint(xh_bar, out):
    """out = rfft2ᵀ(xh_bar) = n² irfft2(xh_bar / c): the cotangent of x given that of rfft2(x)."""
    n = out.shape[-1]
    scaled = xh_bar.copy()
    scaled[..., 1 : n // 2] *= 0.5
    lowlevel.c2r(scaled, out, _last_two(scaled), False, 1.0, 1)


@njit(cache=True, nogil=True)
def irfft2_adjoint(x_bar, out):
    """out = irfft2ᵀ(x_bar) = (c / n²) rfft2(x_bar): the cotangent of xh given irfft2(xh)'s."""
    n = x_bar.shape[-1]
    lowlevel.r2c(x_bar, out, _last_two(x_bar), True, 2.0 / (n * n), 1)
    out[..., 0] *= 0.5
    out[..., n // 2] *= 0.5


def _spectrum_like(x: np.ndarray, n: int) -> np.ndarray:
    dtype = np.complex64 if x.dtype == np.float32 else np.complex128
    return np.empty((*x.shape[:-2], n, n // 2 + 1), dtype=dtype)


def apply_multiplier(x: np.ndarray, mult: np.ndarray) -> np.ndarray:
    """irfft2(mult · rfft2(x)) for a diagonal spectral multiplier ``mult`` of shape (n, n//2+1).

    Derivatives (:func:`derivative_multiplier`), the Laplacian and the 2/3 mask are such
    multipliers; the adjoint is ``apply_multiplier(x̄, mult.conj())`` when ``mult`` maps
    Hermitian spectra to Hermitian spectra (see the module docstring).
    """
    x = np.ascontiguousarray(x)
    n = x.shape[-1]
    spec = _spectrum_like(x, n)
    rfft2(x, spec, 1)
    spec *= mult.astype(spec.dtype)
    out = np.empty_like(x)
    irfft2(spec, out, 1)
    return out


def resample(x: np.ndarray, m: int) -> np.ndarray:
    """Spectral resampling of x (..., n, n) onto m × m points (n, m even), up or down.

    The modes |k_x|, k_y < min(n, m)/2 are copied (rescaled by m²/n² for the unnormalised
    transform) and all others of the target are zero, so a field band-limited below the coarser
    grid's Nyquist mode is reproduced exactly at the target points.
    """
    x = np.ascontiguousarray(x)
    n = x.shape[-1]
    _check_even(m)
    src = _spectrum_like(x, n)
    rfft2(x, src, 1)
    dst = np.zeros((*x.shape[:-2], m, m // 2 + 1), dtype=src.dtype)
    half = min(n, m) // 2
    dst[..., :half, :half] = src[..., :half, :half]
    dst[..., m - half + 1 :, :half] = src[..., n - half + 1 :, :half]
    out = np.empty((*x.shape[:-2], m, m), dtype=x.dtype)
    _irfft2_scaled(dst, out, 1.0 / (n * n))
    return out


def resample_adjoint(y_bar: np.ndarray, n: int) -> np.ndarray:
    """Adjoint of :func:`resample` to m points: the n × n cotangent (m/n)² · resample(ȳ, n)."""
    m = y_bar.shape[-1]
    return resample(y_bar, n) * np.asarray((m * m) / (n * n), dtype=y_bar.dtype)


@njit(cache=True, nogil=True)
def _irfft2_scaled(xh, out, fct):
    lowlevel.c2r(xh, out, _last_two(xh), False, fct, 1)


@njit(cache=True, nogil=True)
def physical_with_control(v, out, ctrl, k, b, dt, nthreads):
    """out = irfft2(v) + Δt ctrl[k, b, 0], and v = rfft2(out) again when a control was added:
    the end of a controlled spectral step, shared by the 2D spectral steppers."""
    irfft2(v, out, nthreads)
    if ctrl.shape[0] > 0:
        c = ctrl[k, b, 0]
        for p in range(out.shape[0]):
            for q in range(out.shape[1]):
                out[p, q] += dt * c[p, q]
        rfft2(out, v, nthreads)
