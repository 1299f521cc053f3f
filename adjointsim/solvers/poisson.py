"""Screened Poisson equation in 2D, 5-point stencil, solved directly by fast transforms.

Continuous:  (−Δ + κ) u = f on a square, homogeneous Dirichlet or periodic boundaries
             (see :mod:`adjointsim.grid`); κ = 0 (default) is the Poisson equation.
Discrete:    (−Δ_h + κ) u = f with the 5-point Laplacian Δ_h of :func:`adjointsim.grid.laplacian`.
             Dirichlet: a DST-I along y diagonalises −Δ_y; each sine mode j then leaves the
             tridiagonal system (−Δ_x + λ_j + κ) v = f̂_j along x, solved by the Thomas algorithm
             with factors computed once per call (half the transforms of a 2D DST; measured
             1.7x faster at 128²). Periodic: a 2D real FFT diagonalises −Δ_h; the mean of f is
             projected out and the zero-mean solution returned, for every κ, so the operator
             and its κ-derivative stay continuous at κ = 0 (where the mean mode is singular).
Stepping:    one "step" is one solve, u_{k+1} = (−Δ_h + κ)⁻¹ u_k (no time step, no control hook).
Adjoint:     −Δ_h + κ is symmetric (and the mean projection commutes with it), so the transposed
             solve is the same solve: ū_k = (−Δ_h + κ)⁻¹ ū_{k+1},  κ̄ −= ⟨ū_k, u_{k+1}⟩
             (from A u = f: Ā = −f̄ uᵀ, and ∂A/∂κ = I).
Transforms:  scipy.fft inside numba through rocket-fft (registered by its numba entry point, no
             import needed). Complex arrays (the complex-step check) transform their real and
             imaginary parts separately, so the FFT's round-off never mixes the two. A call
             whose batch is smaller than the thread count gives its transforms every solver
             thread (:func:`adjointsim.parallel.threads_inside`); the transforms split over
             their independent lines, each line's arithmetic unchanged, so the results are the
             same to the bit for every thread count.
"""

from __future__ import annotations

import numpy as np
import scipy.fft
from numba import njit, types
from numba.extending import overload

from .. import parallel, validate
from ..grid import DIRICHLET, boundary_code, spacing
from ..registry import register
from ..stepper import Choice, Range, Stepper


def _periodic_solve(f, out, symbol, workers):
    raise NotImplementedError  # numba-only; see the overload below


@overload(_periodic_solve)
def _periodic_solve_impl(f, out, symbol, workers):
    if not isinstance(f.dtype, types.Complex):
        return lambda f, out, symbol, workers: _filter(f, out, symbol, workers)
    # Complex step: the FFT's own imaginary unit must not mix the real and imaginary parts
    # (round-off of the real part would swamp a 1e-100 perturbation), so each part takes the
    # real transform and the (complexified) symbol is applied by hand.

    def complex_step(f, out, symbol, workers):
        nb, nc, nx, ny = f.shape
        re = scipy.fft.rfft2(np.ascontiguousarray(f.real), workers=workers)
        im = scipy.fft.rfft2(np.ascontiguousarray(f.imag), workers=workers)
        for b in range(nb):
            for c in range(nc):
                for i in range(nx):
                    for j in range(re.shape[3]):
                        s_re, s_im = symbol[i, j].real, symbol[i, j].imag
                        r, q = re[b, c, i, j], im[b, c, i, j]
                        re[b, c, i, j] = s_re * r - s_im * q
                        im[b, c, i, j] = s_re * q + s_im * r
        out[:] = (scipy.fft.irfft2(re, s=(nx, ny), workers=workers)
                  + 1j * scipy.fft.irfft2(im, s=(nx, ny), workers=workers))

    return complex_step


@njit(cache=True, nogil=True)
def _filter(f, out, symbol, workers):
    nb, nc, nx, ny = f.shape
    spec = scipy.fft.rfft2(f, workers=workers)
    for b in range(nb):
        for c in range(nc):
            for i in range(nx):
                for j in range(spec.shape[3]):
                    spec[b, c, i, j] *= symbol[i, j]
    out[:] = scipy.fft.irfft2(spec, s=(nx, ny), workers=workers)


@njit(cache=True, nogil=True)
def _factor(kappa, bc, lam, inv_h2, like):
    """Factors (fa, fb) of −Δ_h + κ, once per call: Dirichlet, the Thomas 1/pivot and c' of the
    x-system of each sine mode j (column j); periodic, the inverse symbol (mean mode 0) and none.
    """
    n = lam.shape[0]
    if bc == DIRICHLET:
        inv_pivot = np.empty((n, n), like.dtype)
        upper = np.empty((n, n), like.dtype)
        for j in range(n):
            diag = 2.0 * inv_h2 + lam[j] + kappa
            c = 0.0 * diag
            for i in range(n):
                inv_pivot[i, j] = 1.0 / (diag + inv_h2 * c)
                c = -inv_h2 * inv_pivot[i, j]
                upper[i, j] = c
        return inv_pivot, upper
    symbol = np.empty((n, n // 2 + 1), like.dtype)
    for i in range(n):
        for j in range(n // 2 + 1):
            symbol[i, j] = 1.0 / (lam[i] + lam[j] + kappa) if i + j > 0 else 0.0
    return symbol, np.empty((0, 0), like.dtype)


@njit(cache=True, nogil=True)
def _solve(f, out, fa, fb, bc, inv_h2, workers):
    """out = (−Δ_h + κ)⁻¹ f for f of shape (B, C, Nx, Ny); ``out`` may be ``f``. ``workers``:
    the transforms' threads."""
    nb, nc, nx, ny = f.shape
    if bc == DIRICHLET:
        g = scipy.fft.dst(f, type=1, axis=3, workers=workers)
        for b in range(nb):
            for c in range(nc):
                for j in range(ny):
                    g[b, c, 0, j] *= fa[0, j]
                for i in range(1, nx):
                    for j in range(ny):
                        g[b, c, i, j] = (g[b, c, i, j] + inv_h2 * g[b, c, i - 1, j]) * fa[i, j]
                for i in range(nx - 2, -1, -1):
                    for j in range(ny):
                        g[b, c, i, j] -= fb[i, j] * g[b, c, i + 1, j]
        out[:] = scipy.fft.idst(g, type=1, axis=3, workers=workers)
    else:
        _periodic_solve(f, out, fa, workers)


@njit(cache=True, nogil=True)
def poisson_forward(states, n, p, bc, lam, inv_h2, workers):
    fa, fb = _factor(p[0], bc, lam, inv_h2, states)
    s = states.shape[0]
    for k in range(n):
        _solve(states[k % s], states[(k + 1) % s], fa, fb, bc, inv_h2, workers)


@njit(cache=True, nogil=True)
def poisson_adjoint(states, p, cot, cmap, ubar, pbar, want_p, bc, lam, inv_h2, workers):
    fa, fb = _factor(p[0], bc, lam, inv_h2, ubar)
    m = states.shape[0]
    last = np.empty_like(ubar)
    if want_p:
        # u_m is not among the stored step inputs: one extra solve per adjoint call.
        last[:] = states[m - 1]
        _solve(last, last, fa, fb, bc, inv_h2, workers)
    for k in range(m - 1, -1, -1):
        _solve(ubar, ubar, fa, fb, bc, inv_h2, workers)
        if want_p:
            nxt = last if k == m - 1 else states[k + 1]
            pbar[0] -= np.sum(ubar * nxt)
        if cmap[k] >= 0:
            ubar += cot[cmap[k]]


@register
class Poisson2D(Stepper):
    """Direct solver of (−Δ_h + κ) u = f on an n × n grid; one step is one solve.

    Default lengths, periodic [0, 2π)² and Dirichlet [0, √2 π]², put the smallest eigenvalue of
    −Δ_h (periodic: of the non-constant modes) at ≈ 1: repeated solves neither blow up nor decay
    (on [0, π]² they would lose a factor 2 per solve, burying the gradient signal of a 50-solve
    rollout under round-off). ``dt`` is 1 and unused: the "step" has no time scale.
    """

    name = "poisson2d"
    point_cost = 3.0
    space = {
        "n": Range(6, 24, integer=True),
        "bc": Choice(("periodic", "dirichlet")),
        "kappa": Range(0.1, 0.4),
    }
    control_shape = None
    param_names = ("kappa",)
    #: smallest n per boundary condition: a 1-point periodic grid holds only the mean, which
    #: the periodic solve drops
    min_points = {"periodic": 2, "dirichlet": 1}

    def __init__(
        self, n: int = 16, bc: str = "periodic", length: float | None = None, kappa: float = 0.0
    ):
        bc = validate.choice(self.name, "bc", bc, tuple(self.min_points))
        self.bc_code = boundary_code(bc)
        self.bc = bc
        self.n = validate.integer(
            self.name, "n", n, ge=self.min_points[bc],
            why=f"the smallest grid with {bc} boundaries",
        )
        self.grid_shape = (self.n, self.n)
        self.channels = 1
        self.dt = 1.0
        if length is None:
            length = np.pi * (np.sqrt(2.0) if self.bc_code == DIRICHLET else 2.0)
        self.length = validate.number(self.name, "length", length, gt=0)
        self.h = spacing(self.n, self.length, bc)
        self.inv_h2 = 1.0 / self.h**2
        # Eigenvalues of the 1D −Δ_h: sine modes 1..n (Dirichlet), FFT order (periodic).
        k = np.arange(1, self.n + 1) if self.bc_code == DIRICHLET else np.arange(self.n)
        denominator = 2 * (self.n + 1) if self.bc_code == DIRICHLET else self.n
        self.eigenvalues = 4.0 * self.inv_h2 * np.sin(np.pi * k / denominator) ** 2
        self.param_values = (validate.number(self.name, "kappa", kappa),)
        self.check_params(np.array(self.param_values))

    @property
    def smallest_eigenvalue(self) -> float:
        """Smallest eigenvalue of −Δ_h (periodic: on zero-mean fields)."""
        lam = self.eigenvalues
        return float(2.0 * lam[0] if self.bc_code == DIRICHLET else lam[1])

    def check_params(self, p: np.ndarray) -> None:
        if not p[0] > -self.smallest_eigenvalue:
            raise ValueError(
                f"{self.name}: kappa = κ = {p[0]:.6g} makes −Δ_h + κ singular or indefinite; "
                f"κ must exceed −λ_min = {-self.smallest_eigenvalue:.6g}"
            )

    def _args(self) -> tuple:
        return self.bc_code, self.eigenvalues, self.inv_h2

    def _forward(self, states, n, ctrl, p):
        inside = parallel.threads_inside(states.shape[1], self.n**2)
        poisson_forward(states, n, p, *self._args(), inside)

    def _adjoint(self, states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p):
        poisson_adjoint(states, p, cot, cmap, ubar, pbar, want_p, *self._args(),
                        parallel.threads_inside(ubar.shape[0], self.n**2))

    # ----------------------------------------------------------------- operator API
    def solve(self, f: np.ndarray, params: dict[str, float] | None = None) -> np.ndarray:
        """u = (−Δ_h + κ)⁻¹ f for a batch f of shape (B, 1, n, n) (periodic: mean of f dropped)."""
        return self.rollout(f, 1, params=params)

    def solve_adjoint(self, ubar: np.ndarray, params: dict[str, float] | None = None) -> np.ndarray:
        """f̄ = (−Δ_h + κ)⁻ᵀ ū, the transposed solve (equal to :meth:`solve`: A is symmetric)."""
        ubar = self.check_state(ubar, "ubar")
        p = self.param_array(params, ubar.dtype)
        fbar = np.array(ubar, dtype=np.result_type(ubar, p))
        no_cot = np.zeros((0, *fbar.shape), fbar.dtype)
        self._adjoint(
            fbar[None], no_cot[:, 0], p, no_cot, np.full(1, -1), fbar, no_cot[:, 0],
            np.zeros(1), False,
        )
        return fbar
