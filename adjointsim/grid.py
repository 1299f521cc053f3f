"""Grids and boundary conditions shared by the finite-difference solvers.

Conventions, on an interval of length L with N unknowns per axis:

* ``periodic``: nodes x_i = i h, h = L / N.
* ``dirichlet`` (homogeneous): interior nodes x_i = (i + 1) h, h = L / (N + 1); u = 0 outside.
* ``neumann`` (homogeneous, cell-centred): cell centres x_i = (i + 1/2) h, h = L / N; the ghost
  cell mirrors its neighbour, so the flux through the wall is zero.

With these choices the discrete Laplacian is symmetric for all three boundary conditions, so
it is its own adjoint.
"""

from __future__ import annotations

import numpy as np
from numba import njit

BOUNDARIES = {"periodic": 0, "dirichlet": 1, "neumann": 2}
PERIODIC, DIRICHLET, NEUMANN = 0, 1, 2


def boundary_code(bc: str) -> int:
    try:
        return BOUNDARIES[bc]
    except KeyError:
        raise ValueError(
            f"unknown boundary condition {bc!r}; choose one of {sorted(BOUNDARIES)}"
        ) from None


def spacing(n: int, length: float, bc: str) -> float:
    """Grid spacing h for ``n`` unknowns on an interval of ``length``."""
    return length / (n + 1) if boundary_code(bc) == DIRICHLET else length / n


def nodes(n: int, length: float, bc: str, start: float = 0.0) -> np.ndarray:
    """Positions of the ``n`` unknowns."""
    h = spacing(n, length, bc)
    offset = {PERIODIC: 0.0, DIRICHLET: h, NEUMANN: 0.5 * h}[boundary_code(bc)]
    return start + offset + h * np.arange(n)


@njit(cache=True, nogil=True)
def laplacian(u, out, inv_hx2, inv_hy2, bc):
    """out = Δ_h u for u of shape (B, C, Nx, Ny); a 1D grid is Ny = 1 with inv_hy2 = 0.

    Symmetric under every boundary condition, hence also its own adjoint. Interior points run
    in branch-free loops; only the edge points look up ghost values.
    """
    nb, nc, nx, ny = u.shape
    for b in range(nb):
        for c in range(nc):
            v = u[b, c]
            o = out[b, c]
            if ny == 1:
                for i in range(1, nx - 1):
                    o[i, 0] = inv_hx2 * (v[i - 1, 0] - 2.0 * v[i, 0] + v[i + 1, 0])
                for i in (0, nx - 1):
                    o[i, 0] = _edge_point(v, i, 0, nx, 1, inv_hx2, 0.0, bc)
                continue
            for i in range(1, nx - 1):
                for j in range(1, ny - 1):
                    o[i, j] = inv_hx2 * (v[i - 1, j] - 2.0 * v[i, j] + v[i + 1, j]) + inv_hy2 * (
                        v[i, j - 1] - 2.0 * v[i, j] + v[i, j + 1]
                    )
                for j in (0, ny - 1):
                    o[i, j] = _edge_point(v, i, j, nx, ny, inv_hx2, inv_hy2, bc)
            for i in (0, nx - 1):
                for j in range(ny):
                    o[i, j] = _edge_point(v, i, j, nx, ny, inv_hx2, inv_hy2, bc)


@njit(cache=True, nogil=True, inline="always")
def _edge_point(v, i, j, nx, ny, inv_hx2, inv_hy2, bc):
    left = v[i - 1, j] if i > 0 else ghost(v[0, j], v[nx - 1, j], bc)
    right = v[i + 1, j] if i < nx - 1 else ghost(v[nx - 1, j], v[0, j], bc)
    value = inv_hx2 * (left - 2.0 * v[i, j] + right)
    if ny > 1:
        down = v[i, j - 1] if j > 0 else ghost(v[i, 0], v[i, ny - 1], bc)
        up = v[i, j + 1] if j < ny - 1 else ghost(v[i, ny - 1], v[i, 0], bc)
        value += inv_hy2 * (down - 2.0 * v[i, j] + up)
    return value


@njit(cache=True, nogil=True, inline="always")
def ghost(u_edge, u_wrap, bc):
    """Value beyond an edge: the periodic image, zero (Dirichlet) or the mirror (Neumann)."""
    if bc == PERIODIC:
        return u_wrap
    if bc == DIRICHLET:
        return 0.0 * u_edge
    return u_edge

