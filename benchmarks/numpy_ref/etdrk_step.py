"""One ETDRK1–4 step in NumPy on a spectral state, the update table of
:mod:`adjointsim.spectral.etdrk` written out order by order (the references check it)."""

from collections.abc import Callable

import numpy as np

ROLLOUTS: dict = {}


def etdrk_step(v: np.ndarray, c: dict, order: int, N: Callable) -> np.ndarray:  # noqa: N803
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
