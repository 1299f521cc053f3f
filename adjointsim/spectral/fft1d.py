"""Real FFTs of even length N callable inside numba kernels, their adjoints, and spectral tools.

Kernels hold a batch of B real signals in a **packed** complex array of N·B/2 entries and their
half spectra (M + 1 = N/2 + 1 modes each) in flat complex arrays, in one of two layouts chosen
by the batch size (:func:`at` gives the index of mode k of signal b):

* B < ``LIBRARY_BATCH``: z[j·B + b] = u[b, 2j] + i u[b, 2j+1] and spectra mode-major
  (X[k·B + b]; with B = 1 both layouts agree), so every pointwise loop and butterfly runs over
  contiguous memory. A length-N real FFT is a length-M complex FFT of z plus one pass
  (X_k = E_k + e^{−2πik/N} O_k, E, O the spectra of the even and odd samples) that handles the
  modes k and M − k together; the inverse undoes it. The complex FFT is a self-sorting
  (Stockham) mixed-radix transform (radices 4, 2, 3 and a generic one for other primes): for
  small batches it beats a library call, whose fixed cost dominates there.
* B ≥ ``LIBRARY_BATCH``: the packed array, viewed as reals, holds the signals row by row and
  spectra are batch-major (X[b·(M + 1) + k]); DUCC0's r2c/c2r (through rocket-fft) transform
  all rows at once, vectorised across the batch.

Pointwise products of physical signals are componentwise on the packed arrays in both layouts.

Conventions (NumPy's): rfft is unnormalised, irfft carries 1/N and ignores the imaginary parts
of the zero and Nyquist modes. Adjoints under the real inner products ⟨x, y⟩ = Σ x y and
⟨X, Y⟩ = Re Σ_{k=0..M} conj(X_k) Y_k, with w_k = 1 for k ∈ {0, M} and 2 otherwise:

    irfftᵀ(ū) = (w/N) · rfft(ū),          rfftᵀ(X̄) = irfft(N X̄ / w).

Equivalently, with the weighted spectral product ⟨X, Y⟩_W = Re Σ (w_k/N) conj(X_k) Y_k (under
which irfft is an isometry), the adjoint of irfft is rfft and that of rfft is irfft; the
kernels carry spectral cotangents in this W-product, so a diagonal multiplier D (a derivative
(i k)^p, the 2/3 mask, an ETDRK coefficient) simply becomes conj(D): the adjoint of
u ↦ irfft(D ⊙ rfft(u)) is ū ↦ irfft(conj(D) ⊙ rfft(ū)). Spectral resampling N1 → N2 keeps the
modes k < min(N1, N2)/2 (the smaller grid's Nyquist mode is dropped) and scales them by
N2/N1; its adjoint is (N2/N1) times resampling back, N2 → N1.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
import rocket_fft  # noqa: F401  (registers the DUCC0 transforms for numba)
from numba import njit
from rocket_fft import c2r, r2c

#: batch size from which the real FFTs call DUCC0 instead of the Stockham loops. The crossover
#: of a whole ETDRK4 step, forward or adjoint, falls with N: near 2 signals for N = 128 to 256,
#: 4 to 8 for N = 48 to 64, above 32 for N = 32; 4 suits the grids of 48 points and more.
LIBRARY_BATCH = 4

Plan = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


# ----------------------------------------------------------------- plans and multipliers
@lru_cache(maxsize=64)
def _plan(n: int, dtype_str: str) -> Plan:
    if n < 2 or n % 2:
        raise ValueError(f"real FFT length must be even and at least 2, not {n}")
    m = n // 2
    cdtype = np.result_type(np.dtype(dtype_str), np.complex64)
    factors, rest = [], m
    for p in (4, 2, 3, 5):
        while rest % p == 0:
            factors.append(p)
            rest //= p
    q = 7
    while rest > 1:
        while rest % q == 0:
            factors.append(q)
            rest //= q
        q += 2
    tw_fwd, tw_inv, length = [], [], m
    for p in factors:
        sub = length // p
        angle = 2 * np.pi * np.outer(np.arange(sub), np.arange(p)).ravel() / length
        tw_fwd.append(np.exp(-1j * angle))
        tw_inv.append(np.exp(1j * angle))
        length = sub
    real_tw = np.exp(-2j * np.pi * np.arange(m + 1) / n)
    # Scalars in the working precision: a float64 literal would promote float32 arithmetic.
    consts = np.array([0.5, 1.0 / n, np.sin(np.pi / 3), 2.0], dtype=np.dtype(dtype_str))
    return (
        np.array(factors, dtype=np.int64),
        np.concatenate(tw_fwd or [np.ones(1)]).astype(cdtype),
        np.concatenate(tw_inv or [np.ones(1)]).astype(cdtype),
        real_tw.astype(cdtype),
        consts,
    )


def plan(n: int, dtype: Any = np.float64) -> Plan:
    """Kernel tables for real FFTs of even length ``n`` in precision ``dtype`` (cached).

    Returns (factors, forward twiddles, inverse twiddles, real-FFT twiddles e^{−2πik/n},
    constants [1/2, 1/n, sin(π/3), 2] in the real precision).
    """
    return _plan(int(n), np.dtype(dtype).str)


def wavenumbers(n: int, length: float) -> np.ndarray:
    """Angular wavenumbers k = 2π j / length, j = 0..n/2, of the half spectrum."""
    return 2 * np.pi * np.arange(n // 2 + 1) / length


def derivative_multiplier(n: int, length: float, order: int = 1) -> np.ndarray:
    """(i k)^order on the half spectrum; odd orders vanish at the Nyquist mode, as is usual,
    so the derivative of a real signal stays real."""
    k = wavenumbers(n, length)
    if order % 2:
        k[-1] = 0.0
    return (1j * k) ** order


def dealias_mask(n: int) -> np.ndarray:
    """The 2/3 rule: 1 for the modes k < n/3 that a quadratic product cannot alias, else 0."""
    return (np.arange(n // 2 + 1) < n / 3).astype(np.float64)


def hermitian_weights(n: int) -> np.ndarray:
    """w_k = 1 for the zero and Nyquist modes, 2 for the others (see the module docstring)."""
    w = np.full(n // 2 + 1, 2.0)
    w[0] = w[-1] = 1.0
    return w


# ----------------------------------------------------------------- complex FFT core
@njit(cache=True, nogil=True)
def cfft(x, y, nb, factors, tw, consts, forward):
    """Unnormalised complex FFT along the leading axis of the flat (M, nb) array ``x`` (sign −
    if ``forward``), using ``y`` as scratch. Returns the array that holds the result."""
    n, s, off = x.shape[0] // nb, nb, 0
    for f in range(factors.shape[0]):
        p = factors[f]
        sub = n // p
        if p == 4:
            _radix4(x, y, s, sub, tw, off, forward)
        elif p == 2:
            _radix2(x, y, s, sub, tw, off)
        elif p == 3:
            _radix3(x, y, s, sub, tw, off, -consts[0], -consts[2] if forward else consts[2])
        else:
            _radix_generic(x, y, s, sub, p, tw, off, forward)
        off += sub * p
        n, s = sub, s * p
        x, y = y, x
    return x


@njit(cache=True, nogil=True, inline="always")
def _rot(d, forward):
    # d times −i (forward) or +i (inverse), exactly
    return complex(d.imag, -d.real) if forward else complex(-d.imag, d.real)


@njit(cache=True, nogil=True)
def _radix4(x, y, s, sub, tw, off, forward):
    for j in range(sub):
        w1, w2, w3 = tw[off + 4 * j + 1], tw[off + 4 * j + 2], tw[off + 4 * j + 3]
        i0, i1, i2, i3 = s * j, s * (j + sub), s * (j + 2 * sub), s * (j + 3 * sub)
        o = 4 * s * j
        for t in range(s):
            a0, a1, a2, a3 = x[i0 + t], x[i1 + t], x[i2 + t], x[i3 + t]
            b0, b1, b2 = a0 + a2, a0 - a2, a1 + a3
            b3 = _rot(a1 - a3, forward)
            y[o + t] = b0 + b2
            y[o + s + t] = (b1 + b3) * w1
            y[o + 2 * s + t] = (b0 - b2) * w2
            y[o + 3 * s + t] = (b1 - b3) * w3


@njit(cache=True, nogil=True)
def _radix2(x, y, s, sub, tw, off):
    for j in range(sub):
        w1 = tw[off + 2 * j + 1]
        i0, i1, o = s * j, s * (j + sub), 2 * s * j
        for t in range(s):
            a0, a1 = x[i0 + t], x[i1 + t]
            y[o + t] = a0 + a1
            y[o + s + t] = (a0 - a1) * w1


@njit(cache=True, nogil=True)
def _radix3(x, y, s, sub, tw, off, c, sn):
    # c = cos(2π/3) = −1/2, sn = ∓ sin(2π/3) (forward: −)
    for j in range(sub):
        w1, w2 = tw[off + 3 * j + 1], tw[off + 3 * j + 2]
        i0, i1, i2, o = s * j, s * (j + sub), s * (j + 2 * sub), 3 * s * j
        for t in range(s):
            a0, a1, a2 = x[i0 + t], x[i1 + t], x[i2 + t]
            p, q = a1 + a2, a1 - a2
            r = a0 + c * p
            iq = complex(-sn * q.imag, sn * q.real)
            y[o + t] = a0 + p
            y[o + s + t] = (r + iq) * w1
            y[o + 2 * s + t] = (r - iq) * w2


@njit(cache=True, nogil=True)
def _radix_generic(x, y, s, sub, p, tw, off, forward):
    # Any other prime p, O(p²) per output; the p-th roots sit in the twiddles of index j = 1.
    root = np.exp((-2j if forward else 2j) * np.pi * np.arange(p) / p).astype(x.dtype)
    for j in range(sub):
        for k in range(p):
            w = tw[off + p * j + k]
            o = s * (p * j + k)
            for t in range(s):
                acc = x[s * j + t]
                for r in range(1, p):
                    acc += x[s * (j + r * sub) + t] * root[(r * k) % p]
                y[o + t] = acc * w


# ----------------------------------------------------------------- packed real FFTs
@njit(cache=True, nogil=True)
def library(nb):
    """True when batches of ``nb`` signals go through DUCC0's real transforms: then a packed
    array holds the real signals (nb, N) row by row, viewed as reals, instead of the
    even/odd pairs, and half spectra are batch-major too."""
    return nb >= LIBRARY_BATCH


@njit(cache=True, nogil=True)
def direct(nb):
    """True when a packed array of ``nb`` signals is their (nb, N) rows, viewed as complex:
    one signal, or the library path."""
    return nb == 1 or library(nb)


@njit(cache=True, nogil=True)
def packed_view(u, cdtype):
    """The C-contiguous signals ``u`` (any shape, the signal axis last) as a packed complex
    array without a copy: valid only where :func:`direct` holds."""
    return u.reshape(u.size).view(cdtype)


@njit(cache=True, nogil=True, inline="always")
def at(k, b, nk, nb):
    """Position of mode k of signal b in a half spectrum of nk modes: batch-major (b·nk + k)
    for one signal or the library path, else mode-major (k·nb + b)."""
    return b * nk + k if nb == 1 or nb >= LIBRARY_BATCH else k * nb + b


@njit(cache=True, nogil=True)
def pack(u, z, consts):
    """z ← u packed, for u of shape (B, N) (any strides)."""
    nb, n = u.shape
    if library(nb):
        zr = z.view(consts.dtype)
        for b in range(nb):
            zr[b * n : (b + 1) * n] = u[b]
    else:
        for j in range(n // 2):
            for b in range(nb):
                z[j * nb + b] = complex(u[b, 2 * j], u[b, 2 * j + 1])


@njit(cache=True, nogil=True)
def unpack(z, u, consts):
    """u ← the real signals packed in z, u of shape (B, N)."""
    nb, n = u.shape
    if library(nb):
        zr = z.view(consts.dtype)
        for b in range(nb):
            u[b] = zr[b * n : (b + 1) * n]
    else:
        for b in range(nb):
            for j in range(n // 2):
                v = z[j * nb + b]
                u[b, 2 * j] = v.real
                u[b, 2 * j + 1] = v.imag


@njit(cache=True, nogil=True)
def rfft_packed(src, other, mode, out, mult, add, acc, t, w, nb, fplan):
    """out (+)= mult ⊙ rfft(s) + add (accumulated if ``acc``), with s = src (mode 0), src²
    (mode 1) or 2 src ⊙ other (mode 2), all packed; ``mult``/``add`` of length M + 1, or empty
    for none. Scratch: ``t`` of the packed size, ``w`` of the spectral size (M + 1)·nb;
    ``src`` and ``other`` are kept."""
    factors, tw_fwd, _, real_tw, consts = fplan
    half, two = consts[0], consts[3]
    size = src.shape[0]
    if mode == 0:
        t[:] = src
    elif mode == 1:
        for i in range(size):
            v = src[i]
            t[i] = complex(v.real * v.real, v.imag * v.imag)
    else:
        for i in range(size):
            v, o = src[i], other[i]
            t[i] = complex(two * v.real * o.real, two * v.imag * o.imag)
    m = size // nb
    one = real_tw[0]
    zero = one - one
    have_mult, have_add = mult.shape[0] > 0, add.shape[0] > 0
    if library(nb):
        direct = not (acc or have_mult or have_add)
        r2c(t.view(consts.dtype).reshape(nb, 2 * m), (out if direct else w).reshape(nb, m + 1),
            np.ones(1, np.int64), True, 1.0, 1)
        if direct:
            return
        if acc and not (have_mult or have_add):
            # A loop of its own: with the branches below inside it, it would not vectorise.
            for i in range((m + 1) * nb):
                out[i] += w[i]
            return
        for b in range(nb):
            lo = b * (m + 1)
            for k in range(m + 1):
                v = w[lo + k]
                if have_mult:
                    v *= mult[k]
                if have_add:
                    v += add[k]
                out[lo + k] = out[lo + k] + v if acc else v
        return
    z = cfft(t, w[:size], nb, factors, tw_fwd, consts, True)
    # Mode 0 and Nyquist from z_0, then the pairs (k, M − k): X_k = e + r o and
    # X_{M−k} = conj(e − r o), e = (z_k + conj z_{M−k})/2, o = −i (z_k − conj z_{M−k})/2.
    for k in range(m // 2 + 1):
        rt = real_tw[k]
        lo, hi, dst = k * nb, ((m - k) % m) * nb, (m - k) * nb
        g1 = mult[k] if have_mult else one
        g2 = mult[m - k] if have_mult else one
        a1 = add[k] if have_add else zero
        a2 = add[m - k] if have_add else zero
        single = 2 * k == m
        for b in range(nb):
            zk = z[lo + b]
            if k == 0:
                x1 = complex(zk.real + zk.imag, zero.real)
                x2 = complex(zk.real - zk.imag, zero.real)
            else:
                zc = z[hi + b].conjugate()
                d = zk - zc
                e = half * (zk + zc)
                ro = rt * complex(half * d.imag, -half * d.real)
                x1 = e + ro
                x2 = (e - ro).conjugate()
            x1 = g1 * x1 + a1
            x2 = g2 * x2 + a2
            if acc:
                out[lo + b] += x1
                if not single:
                    out[dst + b] += x2
            else:
                out[lo + b] = x1
                if not single:
                    out[dst + b] = x2


@njit(cache=True, nogil=True)
def irfft_packed(x, mult, out, w, nb, fplan):
    """out (packed) = irfft(mult ⊙ x), x a half spectrum (M + 1, nb), ``mult`` of length
    M + 1 or empty for none. ``w`` is scratch of the spectral size (M + 1)·nb."""
    factors, _, tw_inv, real_tw, consts = fplan
    size = out.shape[0]
    m = size // nb
    inv_n = consts[1]
    have_mult = mult.shape[0] > 0
    if library(nb):
        src = x
        if have_mult:
            for b in range(nb):
                for k in range(m + 1):
                    w[b * (m + 1) + k] = mult[k] * x[b * (m + 1) + k]
            src = w
        c2r(src.reshape(nb, m + 1), out.view(consts.dtype).reshape(nb, 2 * m),
            np.ones(1, np.int64), False, inv_n, 1)
        return
    one = real_tw[0]
    a = w[:size] if factors.shape[0] % 2 else out
    g0 = mult[0] if have_mult else one
    gm = mult[m] if have_mult else one
    for b in range(nb):
        x0 = (g0 * x[b]).real
        xm = (gm * x[m * nb + b]).real
        a[b] = complex(inv_n * (x0 + xm), inv_n * (x0 - xm))
    # Pairs (k, M − k): Z_k = s + i c d, Z_{M−k} = conj(s − i c d), s = X_k + conj(X_{M−k}),
    # d = X_k − conj(X_{M−k}), c = e^{2πik/N}, all scaled by 1/N.
    for k in range(1, m // 2 + 1):
        lo, hi = k * nb, (m - k) * nb
        gk = (mult[k] if have_mult else one) * inv_n
        gc = (mult[m - k] if have_mult else one).conjugate() * inv_n
        c = real_tw[k].conjugate()
        for b in range(nb):
            xk, xc = gk * x[lo + b], gc * x[hi + b].conjugate()
            sm = xk + xc
            cd = c * (xk - xc)
            icd = complex(-cd.imag, cd.real)
            a[lo + b] = sm + icd
            a[hi + b] = (sm - icd).conjugate()
    cfft(a, out if factors.shape[0] % 2 else w[:size], nb, factors, tw_inv, consts, False)


# ----------------------------------------------------------------- array-level functions
@njit(cache=True, nogil=True)
def _rfft_rows(u, out, fplan):
    nb, n = u.shape
    z = np.empty(nb * (n // 2), dtype=out.dtype)
    t, w = np.empty_like(z), np.empty(out.size, dtype=out.dtype)
    flat = np.empty(out.size, dtype=out.dtype)
    empty = np.empty(0, dtype=out.dtype)
    pack(u, z, fplan[4])
    rfft_packed(z, z, 0, flat, empty, empty, False, t, w, nb, fplan)
    for k in range(out.shape[1]):
        for b in range(nb):
            out[b, k] = flat[at(k, b, out.shape[1], nb)]


@njit(cache=True, nogil=True)
def _irfft_rows(x, out, fplan):
    nb, n = out.shape
    flat = np.empty(x.size, dtype=x.dtype)
    for k in range(x.shape[1]):
        for b in range(nb):
            flat[at(k, b, x.shape[1], nb)] = x[b, k]
    z = np.empty(nb * (n // 2), dtype=x.dtype)
    irfft_packed(flat, np.empty(0, dtype=x.dtype), z, np.empty_like(flat), nb, fplan)
    unpack(z, out, fplan[4])


def _rows(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a.reshape(-1, a.shape[-1]))


def rfft(u: np.ndarray) -> np.ndarray:
    """Real FFT along the last axis (even length), as ``numpy.fft.rfft``; float32 → complex64."""
    u = np.asarray(u)
    n = u.shape[-1]
    out = np.empty((int(np.prod(u.shape[:-1])), n // 2 + 1), np.result_type(u, np.complex64))
    _rfft_rows(_rows(u), out, plan(n, u.dtype))
    return out.reshape(*u.shape[:-1], n // 2 + 1)


def irfft(x: np.ndarray, n: int) -> np.ndarray:
    """Inverse of :func:`rfft` to even length ``n`` (= 2 (x.shape[-1] − 1)), as
    ``numpy.fft.irfft``; complex64 → float32."""
    x = np.asarray(x)
    if x.shape[-1] != n // 2 + 1:
        raise ValueError(
            f"a length-{n} signal has {n // 2 + 1} half-spectrum modes, not {x.shape[-1]}"
        )
    real = np.empty(0, x.dtype).real.dtype
    out = np.empty((int(np.prod(x.shape[:-1])), n), real)
    _irfft_rows(_rows(x), out, plan(n, real))
    return out.reshape(*x.shape[:-1], n)


def rfft_adjoint(xbar: np.ndarray, n: int) -> np.ndarray:
    """rfftᵀ(X̄) = irfft(n X̄ / w): the cotangent of the signal given that of its spectrum."""
    return irfft(np.asarray(xbar) * (n / hermitian_weights(n)), n)


def irfft_adjoint(ubar: np.ndarray) -> np.ndarray:
    """irfftᵀ(ū) = (w / n) rfft(ū): the cotangent of the spectrum given that of the signal."""
    n = np.shape(ubar)[-1]
    return rfft(ubar) * (hermitian_weights(n) / n).astype(np.asarray(ubar).dtype)


def apply_multiplier(u: np.ndarray, mult: np.ndarray) -> np.ndarray:
    """irfft(mult ⊙ rfft(u)) along the last axis, e.g. a spectral derivative with
    :func:`derivative_multiplier`; its adjoint is ``apply_multiplier(ū, mult.conj())``."""
    u = np.asarray(u)
    return irfft(rfft(u) * np.asarray(mult).astype(np.result_type(u, np.complex64)), u.shape[-1])


def resample(u: np.ndarray, n2: int) -> np.ndarray:
    """Spectral interpolation of periodic signals (last axis) from n1 = u.shape[-1] to ``n2``
    points: modes k < min(n1, n2)/2 are kept, the rest (and the smaller Nyquist) dropped."""
    u = np.asarray(u)
    n1 = u.shape[-1]
    keep = min(n1, n2) // 2
    x = rfft(u)
    y = np.zeros((*x.shape[:-1], n2 // 2 + 1), dtype=x.dtype)
    y[..., :keep] = x[..., :keep] * np.asarray(n2 / n1, dtype=u.dtype)
    return irfft(y, n2)


def resample_adjoint(ubar: np.ndarray, n1: int) -> np.ndarray:
    """Adjoint of :func:`resample` from ``n1`` points: (n2/n1) · resample(ū, n1)."""
    ubar = np.asarray(ubar)
    return resample(ubar, n1) * np.asarray(ubar.shape[-1] / n1, dtype=ubar.dtype)
