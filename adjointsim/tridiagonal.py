"""Constant-coefficient tridiagonal solves (Thomas algorithm), plain and cyclic, batched.

The n × n matrix A (n ≥ 2) is described by ``coef = [lower, diag, upper, first, last]``::

    A[i, i-1] = lower,  A[i, i] = diag,  A[i, i+1] = upper,  except A[0, 0] = first and
    A[n-1, n-1] = last;  a *cyclic* matrix also has the corners A[0, n-1] = lower and
    A[n-1, 0] = upper (the periodic wrap of the same stencil).

Homogeneous Dirichlet rows are ``first = last = diag``; a mirrored (Neumann) ghost gives
``first = diag + lower``, ``last = diag + upper``.

:func:`factor` does the O(n) work that depends on the matrix only, once; :func:`solve` then
solves any number of right-hand sides in place. The cyclic case uses Sherman–Morrison:
A = A' + u vᵀ with γ = −first, u = (γ, 0, …, 0, upper)ᵀ, v = (1, 0, …, 0, lower/γ)ᵀ, and A' the
plain tridiagonal matrix with A'[0, 0] = first − γ and A'[n-1, n-1] = last − lower·upper/γ;
then x = y − (vᵀy) z / (1 + vᵀz) with A'y = d, A'z = u. :func:`solve` works along the middle
axis of (L, n, M) arrays, :func:`solve_rows` along the last axis of (L, M, n) ones.

Adjoint: x = A⁻¹d gives d̄ = A⁻ᵀ x̄, a solve with ``factor(transpose(coef), n, cyclic)``, and
Ā = −d̄ xᵀ. There is no pivoting: the pivots must not vanish (true for diagonally dominant A).
Real arithmetic throughout (no conjugates), so complex inputs give complex-step derivatives.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def transpose(coef):
    """Coefficients of Aᵀ: the lower and upper diagonals (and the corners) swap."""
    out = coef.copy()
    out[0] = coef[2]
    out[2] = coef[0]
    return out


@njit(cache=True, nogil=True)
def factor(coef, n, cyclic):
    """Factorisation F of shape (5, n), of ``coef``'s dtype, for :func:`solve`.

    Rows: 1/w_i (Thomas pivots w_i of A'), lower/w_i, upper/w_i, the Sherman–Morrison column
    z/(1 + vᵀz) and the row v (both zero for a non-cyclic matrix).
    """
    if n < 2:
        raise ValueError("tridiagonal systems need n >= 2 unknowns")
    lower, diag, upper, first, last = coef[0], coef[1], coef[2], coef[3], coef[4]
    f = np.zeros((5, n), dtype=coef.dtype)
    gamma = -first
    d0 = first - gamma if cyclic else first
    dn = last - lower * upper / gamma if cyclic else last
    w = d0
    f[0, 0] = 1.0 / w
    f[2, 0] = upper / w
    for i in range(1, n):
        w = (dn if i == n - 1 else diag) - lower * f[2, i - 1]
        f[0, i] = 1.0 / w
        f[1, i] = lower / w
        f[2, i] = upper / w
    f[2, n - 1] = 0.0
    if cyclic:
        z = np.zeros((1, n, 1), dtype=coef.dtype)
        z[0, 0, 0] = gamma
        z[0, n - 1, 0] = upper
        _thomas(f, z)
        scale = 1.0 / (1.0 + z[0, 0, 0] + (lower / gamma) * z[0, n - 1, 0])
        for i in range(n):
            f[3, i] = scale * z[0, i, 0]
        f[4, 0] = 1.0
        f[4, n - 1] = lower / gamma
    return f


@njit(cache=True, nogil=True)
def solve(f, x):
    """Solve A x = d in place along axis 1 of ``x`` (L, n, M), for all L·M right-hand sides.

    ``f`` comes from :func:`factor`. The M lines of each block are swept side by side (SIMD).
    """
    _thomas(f, x)
    if f[4, 0].real != 0:
        nl, n, nm = x.shape
        v = f[4, n - 1]
        t = np.empty(nm, dtype=x.dtype)
        for lo in range(nl):
            for m in range(nm):
                t[m] = x[lo, 0, m] + v * x[lo, n - 1, m]
            for i in range(n):
                z = f[3, i]
                for m in range(nm):
                    x[lo, i, m] -= z * t[m]


#: lines solved side by side by :func:`solve_rows`
TILE = 16


@njit(cache=True, nogil=True)
def solve_rows(f, x):
    """Solve A x = d in place along the last axis of a C-ordered ``x`` (L, M, n).

    One contiguous line at a time would be latency-bound and a strided sweep across lines
    thrashes the cache at power-of-two n, so tiles of :data:`TILE` lines are transposed into a
    buffer and solved there with :func:`solve`.
    """
    nl, nm, n = x.shape
    width = max(1, min(TILE, nm))
    # A partial last tile is solved at full width: its spare lanes hold stale, finite values.
    buf = np.zeros((1, n, width), dtype=x.dtype)
    for lo in range(nl):
        for m0 in range(0, nm, width):
            w = min(width, nm - m0)
            for t in range(w):
                for i in range(n):
                    buf[0, i, t] = x[lo, m0 + t, i]
            solve(f, buf)
            for t in range(w):
                for i in range(n):
                    x[lo, m0 + t, i] = buf[0, i, t]


@njit(cache=True, nogil=True)
def _thomas(f, x):
    # Forward elimination y_i = d_i / w_i − (lower / w_i) y_{i−1}, then back substitution
    # x_i = y_i − (upper / w_i) x_{i+1}: one multiply-add on each dependency chain.
    nl, n, nm = x.shape
    for lo in range(nl):
        p = f[0, 0]
        for m in range(nm):
            x[lo, 0, m] *= p
        for i in range(1, n):
            p = f[0, i]
            q = f[1, i]
            for m in range(nm):
                x[lo, i, m] = p * x[lo, i, m] - q * x[lo, i - 1, m]
        for i in range(n - 2, -1, -1):
            q = f[2, i]
            for m in range(nm):
                x[lo, i, m] -= q * x[lo, i + 1, m]
