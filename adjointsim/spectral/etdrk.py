"""Exponential time-differencing Runge–Kutta (ETDRK1–4) coefficients for a diagonal linear part.

For u_t = L u + N(u) with L diagonal (one entry per Fourier mode) and step h, z = hL, E = e^z,
E2 = e^{z/2}. :func:`etdrk_coefficients` returns, per order, these arrays (same shape as L):

========  ======================================  ==============================================
order     keys                                    update (v = step input, Nx = N(x))
========  ======================================  ==============================================
1 (ETD1)  E, phi1                                 v' = E v + phi1 Nv
2 (CM)    E, phi1, phi2                           a = E v + phi1 Nv;  v' = a + phi2 (Na − Nv)
3 (CM)    E, E2, Q, phi1, f1, f2, f3              a = E2 v + Q Nv;  b = E v + phi1 (2 Na − Nv);
                                                  v' = E v + f1 Nv + 4 f2 Na + f3 Nb
4 (CM/KT) E, E2, Q, f1, f2, f3                    a = E2 v + Q Nv;  b = E2 v + Q Na;
                                                  c = E2 a + Q (2 Nb − Nv);
                                                  v' = E v + f1 Nv + 2 f2 (Na + Nb) + f3 Nc
========  ======================================  ==============================================

with (all but E, E2 carry one factor h)

    phi1 = (E − 1)/L = h φ1(z),       phi2 = (E − 1 − z)/(h L²) = h φ2(z),
    Q    = (E2 − 1)/L,
    f1 = h (−4 − z + E (4 − 3z + z²))/z³,  f2 = h (2 + z + E (z − 2))/z³,
    f3 = h (−4 − 3z − z² + E (4 − z))/z³.

E and E2 are exponentials evaluated directly (so a linear problem, N ≡ 0, is integrated exactly).
The others cancel catastrophically for small |z|; following Kassam & Trefethen (2005) each is
the mean of its formula G over ``points`` nodes r_j = exp(2πi (j + ½)/points) on the unit circle
around z, i.e. the trapezoidal rule for the Cauchy integral G(z) = (1/2πi)∮ G(ζ)/(ζ − z) dζ,
which converges geometrically because G is entire. For real L the mean is real (the nodes come
in conjugate pairs) and the real part is returned; complex L (e.g. advection, −i a k) gives
complex coefficients.

:func:`etdrk_coefficient_derivatives` returns d(coefficient)/dL for the same keys (complex
derivatives, as every coefficient is an analytic function of L). With C(L) = h G(hL):
dC/dL = h² G'(hL), and G'(z) = (1/2πi)∮ G(ζ)/(ζ − z)² dζ = mean_j G(z + r_j)/r_j on the same
circle (the differentiated Cauchy integrand), so no differentiated formula is needed;
dE/dL = h E, dE2/dL = (h/2) E2 directly. A parameter p entering L gets its cotangent from
p̄ = Re Σ_modes conj(C̄) dC/dL dL/dp, summed over the keys.

Both functions cache their results per (L, h, order, points) and return read-only arrays.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np

KEYS: dict[int, tuple[str, ...]] = {
    1: ("E", "phi1"),
    2: ("E", "phi1", "phi2"),
    3: ("E", "E2", "Q", "phi1", "f1", "f2", "f3"),
    4: ("E", "E2", "Q", "f1", "f2", "f3"),
}

# G(z) per contour-evaluated key, with C = h G(hL).
_FORMULAS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "phi1": lambda z: np.expm1(z) / z,
    "phi2": lambda z: (np.expm1(z) - z) / z**2,
    "Q": lambda z: np.expm1(z / 2) / z,
    "f1": lambda z: (-4 - z + np.exp(z) * (4 - 3 * z + z**2)) / z**3,
    "f2": lambda z: (2 + z + np.exp(z) * (z - 2)) / z**3,
    "f3": lambda z: (-4 - 3 * z - z**2 + np.exp(z) * (4 - z)) / z**3,
}

_CACHE: OrderedDict[tuple, dict[str, np.ndarray]] = OrderedDict()
_CACHE_SIZE = 256


def etdrk_coefficients(
    lin: np.ndarray, dt: float, order: int, points: int = 32
) -> dict[str, np.ndarray]:
    """The ETDRK coefficient arrays of ``order`` (1–4) for diagonal L = ``lin`` and step ``dt``.

    Keys and update formulas: see the module docstring. Arrays have ``lin``'s shape, float64
    for real ``lin``, complex128 for complex ``lin``.
    """
    return _cached("coef", lin, dt, order, points)


def etdrk_coefficient_derivatives(
    lin: np.ndarray, dt: float, order: int, points: int = 32
) -> dict[str, np.ndarray]:
    """d(coefficient)/dL, elementwise, for every key of :func:`etdrk_coefficients`."""
    return _cached("deriv", lin, dt, order, points)


def _cached(kind: str, lin: np.ndarray, dt: float, order: int, points: int) -> dict:
    if order not in KEYS:
        raise ValueError(f"ETDRK order must be 1, 2, 3 or 4, not {order!r}")
    if points < 2 or points % 2:
        raise ValueError(f"points must be an even number ≥ 2, not {points}")
    lin = np.asarray(lin)
    if lin.dtype.kind not in "fc":
        lin = lin.astype(np.float64)
    key = (kind, lin.dtype.str, lin.shape, lin.tobytes(), float(dt), int(order), int(points))
    hit = _CACHE.get(key)
    if hit is not None:
        _CACHE.move_to_end(key)
        return hit
    value = _compute(kind == "deriv", lin, float(dt), int(order), int(points))
    for a in value.values():
        a.setflags(write=False)
    _CACHE[key] = value
    if len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return value


def _compute(deriv: bool, lin: np.ndarray, h: float, order: int, points: int) -> dict:
    real = lin.dtype.kind == "f"
    lin = lin.astype(np.complex128)
    z = h * lin
    r = np.exp(2j * np.pi * (np.arange(points) + 0.5) / points)
    zr = z[..., None] + r
    out = {}
    for name in KEYS[order]:
        if name == "E":
            c = h * np.exp(z) if deriv else np.exp(z)
        elif name == "E2":
            c = 0.5 * h * np.exp(z / 2) if deriv else np.exp(z / 2)
        elif deriv:
            c = h * h * np.mean(_FORMULAS[name](zr) / r, axis=-1)
        else:
            c = h * np.mean(_FORMULAS[name](zr), axis=-1)
        out[name] = np.ascontiguousarray(c.real if real else c)
    return out


def reference_step(v: Any, c: dict, order: int, N: Callable[[Any], Any]) -> Any:  # noqa: N803
    """One ETDRK step on a spectral state, array-library agnostic (NumPy, torch, JAX): the
    update table above written out plainly, for reference implementations and benchmarks."""
    nv = N(v)
    if order == 1:
        return c["E"] * v + c["phi1"] * nv
    if order == 2:
        a = c["E"] * v + c["phi1"] * nv
        return a + c["phi2"] * (N(a) - nv)
    if order == 3:
        a = c["E2"] * v + c["Q"] * nv
        na = N(a)
        b = c["E"] * v + c["phi1"] * (2 * na - nv)
        return c["E"] * v + c["f1"] * nv + 4 * c["f2"] * na + c["f3"] * N(b)
    a = c["E2"] * v + c["Q"] * nv
    na = N(a)
    b = c["E2"] * v + c["Q"] * na
    nb = N(b)
    cc = c["E2"] * a + c["Q"] * (2 * nb - nv)
    return c["E"] * v + c["f1"] * nv + 2 * c["f2"] * (na + nb) + c["f3"] * N(cc)
