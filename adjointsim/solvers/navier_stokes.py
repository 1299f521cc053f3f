"""2D incompressible Navier–Stokes in vorticity form, pseudo-spectral ETDRK1–4 (Kolmogorov flow).

Continuous, on [0, 2π)² doubly periodic, state ω = ∂_x v − ∂_y u (array axes −2: x, −1: y):
    ω_t + u·∇ω = ν Δω − μ ω + a F,   u = (ψ_y, −ψ_x),   −Δψ = ω  (mean of ψ zero),
ν = 1/Re, optional linear drag μ, Kolmogorov forcing F = −k_f cos(k_f y): the curl of the
x-momentum forcing (sin(k_f y), 0), amplitude a.
Split: ω̂' = L ω̂ + N(ω̂) with L = −ν|k|² − μ (diagonal, integrated exactly) and
    N(ω̂) = −m ⊙ (i k_x ℱ(u ω) + i k_y ℱ(v ω)) + a F̂,  (u, v, ω) = ℱ⁻¹(m ⊙ (i k_y ψ̂, −i k_x ψ̂, ω̂)),
the conservative form of u·∇ω (∇·u = 0), products in physical space. m is the 2/3 rule
(default on): modes with |k_x| or k_y above K = ⌊(n − 1)/3⌋ are cut from the inputs and from the
result, so the quadratic products alias only onto discarded modes; dealias=False sets m ≡ 1. The
constant forcing rides in N (every ETDRK order integrates a constant N exactly).
Discrete: ETDRK1–4 (:mod:`adjointsim.spectral.etdrk`) as an exponential Runge–Kutta tableau on
v = ℱ(ω_k): X_0 = v, X_i = A_i v + Σ_{j<i} B_ij N(X_j), ω_{k+1} = ℱ⁻¹(A_s v + Σ_j B_sj N(X_j))
+ Δt c_k (c_k the per-step control). Cost per stage: 3 inverse and 2 forward real FFTs; a call
whose batch is smaller than the solver thread count runs them on the threads (bitwise alike).
Adjoint (on Hermitian half spectra with the product ⟨·,·⟩_H of :mod:`adjointsim.spectral.fft2d`,
ℱ⁻¹ is an isometry and multipliers transpose to their conjugates): λ = ℱ(ω̄_{k+1});
N̄_j = B_sj λ, v̄ = A_s λ; for i = s−1..0: X̄_i = N'(X_i)* N̄_i, v̄ += A_i X̄_i, N̄_j += B_ij X̄_i,
where, with a = ℱ⁻¹(m i k_x N̄), b = ℱ⁻¹(m i k_y N̄),
    N'(X)* N̄ = m ⊙ (ℱ(a u + b v) + |k|⁻² (i k_x ℱ(b ω) − i k_y ℱ(a ω)))   (5 FFTs).
ν̄, μ̄ come from dA/dL, dB/dL (∂L/∂ν = −|k|², ∂L/∂μ = −1), ā from Σ_j ⟨N̄_j, F̂⟩_H. The adjoint
needs every stage's (u, v, ω): a vjp's forward sweep records them on a tape (≈ 40% less
adjoint work, 3·order fields per step, up to ``TAPE_BYTES``); otherwise, and for parameter
cotangents, they are recomputed from the stored step input.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from numba import njit

from .. import parallel, validate
from ..registry import register
from ..spectral.etdrk import etdrk_coefficient_derivatives, etdrk_coefficients
from ..spectral.fft2d import (
    dealias_cutoff,
    derivative_wavenumbers,
    hermitian_weights,
    irfft2,
    irfft2_lowpass,
    physical_with_control,
    random_smooth_field,
    rfft2,
    rfft2_lowpass,
    spectrum_zeros,
    wavenumbers,
)
from ..stepper import Choice, Range, Stepper

#: the largest stage tape a vjp keeps between its forward and adjoint sweeps
TAPE_BYTES = 1 << 30


# ------------------------------------------------------------------ kernels
# N and everything it reads live on the "kept region": rows with keep[p] and columns < ncols (the
# 2/3 mask; every mode without dealiasing). ``spec``, the input of the inverse transforms, is
# zero in the columns ≥ ncols, so the low-pass transforms skip them (and transform the others in
# place); ``pspec`` receives the forward transforms. kx, ky: derivative wavenumbers (Nyquist
# zeroed) in the state's real dtype. With a tape (n, B, s, 3, size, size) the forward kernel
# records every stage's (u, v, ω) for the adjoint.
@njit(cache=True, nogil=True)
def ns_forward(
    states, n, ctrl, dt, a, b, kx, ky, inv_k2, keep, ncols, reuse_omega, fmode, fval, tape,
    nthreads,
):
    nslot, nbatch, size = states.shape[0], states.shape[1], states.shape[-1]
    half = size // 2 + 1
    s = a.shape[0] - 1
    v = spectrum_zeros((size, half), states)
    nh = spectrum_zeros((s, size, half), states)
    spec = spectrum_zeros((3, size, half), states)
    pspec = np.zeros_like(spec)
    phys = np.empty((3, size, size), dtype=states.dtype)
    prod = np.empty((2, size, size), dtype=states.dtype)
    has_tape = tape.shape[0] > 0
    for bi in range(nbatch):
        rfft2(states[0, bi, 0], v, nthreads)
        for k in range(n):
            omega = states[k % nslot, bi, 0]
            for i in range(s):
                own = not (i == 0 and reuse_omega)
                f = tape[k, bi, i] if has_tape else phys
                _stage_fields(a[i], b[i], v, nh, i, spec, f, own, kx, ky, inv_k2, keep, ncols,
                              nthreads)
                if not own and has_tape:
                    f[2] = omega
                _nonlinear(f, f[2] if own else omega, prod, pspec, nh[i], kx, ky, keep, ncols,
                           fmode, fval, nthreads)
            # v ← A_s v + Σ_j B_sj N_j, in place: each entry reads v before writing it.
            for p in range(size):
                for q in range(half):
                    v[p, q] *= a[s, p, q]
            for j in range(s):
                _add_product(b[s, j], nh[j], v, keep, ncols)
            physical_with_control(v, states[(k + 1) % nslot, bi, 0], ctrl, k, bi, dt, nthreads)


@njit(cache=True, nogil=True)
def ns_adjoint(
    states, ctrl, cot, cmap, ubar, cbar, pbar, want_p, dt, a, b, da, db, kx, ky, inv_k2,
    keep, ncols, reuse_omega, fmode, fval, fbar, pidx, k2, weights, tape, nthreads,
):
    m, nbatch, size = states.shape[0], states.shape[1], states.shape[-1]
    half = size // 2 + 1
    s = a.shape[0] - 1
    v = spectrum_zeros((size, half), states)
    lam = np.zeros_like(v)
    nh = spectrum_zeros((s, size, half), states)
    nbar = np.zeros_like(nh)
    spec = spectrum_zeros((3, size, half), states)
    pspec = np.zeros_like(spec)
    has_tape = tape.shape[0] > 0
    stages = np.empty((0 if has_tape else s, 3, size, size), dtype=states.dtype)
    prod = np.empty((3, size, size), dtype=states.dtype)
    every_row = np.ones(size, dtype=np.bool_)
    # Per-mode accumulator of Re(conj(X̄_i) dX_i/dL): ν̄ and μ̄ are weighted sums of it.
    dldl = np.zeros((size, half)) if want_p else np.zeros((0, 0))
    inu, iforce, idrag = pidx[0], pidx[1], pidx[2]
    for bi in range(nbatch):
        rfft2(ubar[bi, 0], lam, nthreads)
        for k in range(m - 1, -1, -1):
            if cbar.shape[0] > 0:
                c = cbar[k, bi, 0]
                irfft2(lam, c, nthreads)
                c *= dt
            fields = tape[k, bi] if has_tape else stages
            if not has_tape:
                # Recompute the stages of step k; the last stage's N only matters for p̄.
                rfft2(states[k, bi, 0], v, nthreads)
                for i in range(s):
                    own = not (i == 0 and reuse_omega)
                    if not own:
                        fields[0, 2] = states[k, bi, 0]
                    _stage_fields(a[i], b[i], v, nh, i, spec, fields[i], own, kx, ky, inv_k2,
                                  keep, ncols, nthreads)
                    if i < s - 1 or want_p:
                        _nonlinear(fields[i], fields[i, 2], prod, pspec, nh[i], kx, ky, keep,
                                   ncols, fmode, fval, nthreads)
            # Reverse the output row, then the stages from the last to the first.
            for j in range(s):
                for p in range(size):
                    if keep[p]:
                        for q in range(ncols):
                            nbar[j, p, q] = b[s, j, p, q] * lam[p, q]
            if want_p:
                _accumulate_dl(dldl, lam, da[s], db[s], v, nh, s, every_row, half, keep, ncols)
            for p in range(size):
                for q in range(half):
                    lam[p, q] *= a[s, p, q]
            for i in range(s - 1, -1, -1):
                _nonlinear_adjoint(nbar[i], fields[i], spec, pspec, prod, kx, ky, inv_k2, keep,
                                   ncols, nthreads)
                if want_p and iforce >= 0:
                    pbar[iforce] += fbar * nbar[i, 0, fmode].real
                xbar = pspec[0]
                if want_p and i > 0:
                    _accumulate_dl(dldl, xbar, da[i], db[i], v, nh, i, keep, ncols, keep, ncols)
                _add_product(a[i], xbar, lam, keep, ncols)
                for j in range(i):
                    _add_product(b[i, j], xbar, nbar[j], keep, ncols)
            if cmap[k] >= 0:
                rfft2(cot[cmap[k], bi, 0], v, nthreads)
                lam += v
        irfft2(lam, ubar[bi, 0], nthreads)
    if want_p:
        # ⟨X̄, dX/dL ∂L/∂p⟩_H with ∂L/∂ν = −|k|², ∂L/∂μ = −1.
        for p in range(size):
            for q in range(half):
                g = weights[q] * dldl[p, q] / (size * size)
                if inu >= 0:
                    pbar[inu] -= k2[p, q] * g
                if idrag >= 0:
                    pbar[idrag] -= g


@njit(cache=True, nogil=True, inline="always")
def _i_times(k, z):
    """i k z for real k, without the two multiplications by zero of a complex product."""
    return complex(-k * z.imag, k * z.real)


@njit(cache=True, nogil=True)
def _transform_back(spec, phys, ncols, nthreads):
    """phys = irfft2(spec) for spec zero in the columns ≥ ncols; may destroy spec."""
    if ncols < spec.shape[-1]:
        irfft2_lowpass(spec, phys, ncols - 1, nthreads)
    else:
        irfft2(spec, phys, nthreads)


@njit(cache=True, nogil=True)
def _transform(phys, spec, ncols, nthreads):
    """spec = rfft2(phys) in the columns < ncols."""
    if ncols < spec.shape[-1]:
        rfft2_lowpass(phys, spec, ncols - 1, nthreads)
    else:
        rfft2(phys, spec, nthreads)


@njit(cache=True, nogil=True)
def _stage_fields(a, b, v, nh, i, spec, phys, own, kx, ky, inv_k2, keep, ncols, nthreads):
    """phys = (u, v, ω) of the masked stage value X_i = A_i v + Σ_{j<i} B_ij N_j (ω if own)."""
    size = v.shape[0]
    for p in range(size):
        if not keep[p]:
            spec[:, p, :ncols] = 0.0
            continue
        kx_p = kx[p]
        for q in range(ncols):
            x = v[p, q] if i == 0 else a[p, q] * v[p, q]
            for j in range(i):
                x += b[j, p, q] * nh[j, p, q]
            psi = inv_k2[p, q] * x
            spec[0, p, q] = _i_times(ky[q], psi)
            spec[1, p, q] = _i_times(-kx_p, psi)
            spec[2, p, q] = x
    nf = 3 if own else 2
    _transform_back(spec[:nf], phys[:nf], ncols, nthreads)


@njit(cache=True, nogil=True)
def _nonlinear(phys, omega, prod, pspec, out, kx, ky, keep, ncols, fmode, fval, nthreads):
    """out = −m ⊙ (i k_x ℱ(u ω) + i k_y ℱ(v ω)) + a F̂ on the kept region; (u, v) = phys[:2]."""
    size = omega.shape[0]
    for p in range(size):
        for q in range(size):
            prod[0, p, q] = phys[0, p, q] * omega[p, q]
            prod[1, p, q] = phys[1, p, q] * omega[p, q]
    _transform(prod[:2], pspec[:2], ncols, nthreads)
    for p in range(size):
        if keep[p]:
            kx_p = kx[p]
            for q in range(ncols):
                out[p, q] = -_i_times(kx_p, pspec[0, p, q]) - _i_times(ky[q], pspec[1, p, q])
    if fmode >= 0:
        out[0, fmode] += fval


@njit(cache=True, nogil=True)
def _nonlinear_adjoint(nbar, fields, spec, pspec, prod, kx, ky, inv_k2, keep, ncols, nthreads):
    """pspec[0] = N'(X)* nbar on the kept region, for the stage whose (u, v, ω) are ``fields``.

    With a = ℱ⁻¹(m i k_x N̄), b = ℱ⁻¹(m i k_y N̄): m (ℱ(a u + b v) + |k|⁻²(i k_x ℱ(b ω) −
    i k_y ℱ(a ω))), the input masks of u, v and ω transposed.
    """
    size = fields.shape[-1]
    for p in range(size):
        if not keep[p]:
            spec[:2, p, :ncols] = 0.0
            continue
        kx_p = kx[p]
        for q in range(ncols):
            spec[0, p, q] = _i_times(kx_p, nbar[p, q])
            spec[1, p, q] = _i_times(ky[q], nbar[p, q])
    _transform_back(spec[:2], prod[:2], ncols, nthreads)
    for p in range(size):
        for q in range(size):
            ga, gb = prod[0, p, q], prod[1, p, q]
            prod[0, p, q] = ga * fields[0, p, q] + gb * fields[1, p, q]
            prod[1, p, q] = ga * fields[2, p, q]
            prod[2, p, q] = gb * fields[2, p, q]
    _transform(prod, pspec, ncols, nthreads)
    for p in range(size):
        if keep[p]:
            kx_p = kx[p]
            for q in range(ncols):
                pspec[0, p, q] += inv_k2[p, q] * (
                    _i_times(kx_p, pspec[2, p, q]) - _i_times(ky[q], pspec[1, p, q])
                )


@njit(cache=True, nogil=True)
def _add_product(c, x, out, keep, ncols):
    """out += c x on the kept region."""
    for p in range(out.shape[0]):
        if keep[p]:
            for q in range(ncols):
                out[p, q] += c[p, q] * x[p, q]


@njit(cache=True, nogil=True)
def _accumulate_dl(dldl, xbar, da, db, v, nh, i, keep_a, ncols_a, keep, ncols):
    """dldl += Re(conj(X̄_i) (dA_i/dL v + Σ_j dB_ij/dL N_j)), the A-term over keep_a × ncols_a."""
    size = dldl.shape[0]
    for p in range(size):
        if keep_a[p]:
            for q in range(ncols_a):
                dldl[p, q] += (xbar[p, q].conjugate() * (da[p, q] * v[p, q])).real
    for j in range(i):
        for p in range(size):
            if keep[p]:
                for q in range(ncols):
                    dldl[p, q] += (xbar[p, q].conjugate() * (db[j, p, q] * nh[j, p, q])).real


# ------------------------------------------------------------------ tableau
def etdrk_tableau(
    order: int, c: dict[str, np.ndarray], dc: dict[str, np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(A of shape (s+1, *L.shape), B of shape (s+1, s, *L.shape)) of ETDRK ``order``.

    Stages X_i = A_i v + Σ_{j<i} B_ij N(X_j) for i = 0..s−1 (A_0 = 1), output row s. With
    ``dc`` (the coefficients' d/dL) the tableau's d/dL instead.
    """
    d = c if dc is None else dc
    if order == 1:
        rows_a, rows_b = [d["E"]], {(1, 0): d["phi1"]}
    elif order == 2:
        rows_a = [d["E"], d["E"]]
        rows_b = {(1, 0): d["phi1"], (2, 0): d["phi1"] - d["phi2"], (2, 1): d["phi2"]}
    elif order == 3:
        rows_a = [d["E2"], d["E"], d["E"]]
        rows_b = {(1, 0): d["Q"], (2, 0): -d["phi1"], (2, 1): 2 * d["phi1"],
                  (3, 0): d["f1"], (3, 1): 4 * d["f2"], (3, 2): d["f3"]}
    elif order == 4:
        # c = E2 a + Q (2 Nb − Nv) expands to E v + (E2 Q − Q) Nv + 2 Q Nb.
        e2q = c["E2"] * c["Q"] if dc is None else dc["E2"] * c["Q"] + c["E2"] * dc["Q"]
        rows_a = [d["E2"], d["E2"], d["E"], d["E"]]
        rows_b = {(1, 0): d["Q"], (2, 1): d["Q"], (3, 0): e2q - d["Q"], (3, 2): 2 * d["Q"],
                  (4, 0): d["f1"], (4, 1): 2 * d["f2"], (4, 2): 2 * d["f2"], (4, 3): d["f3"]}
    else:
        raise ValueError(f"ETDRK order must be 1, 2, 3 or 4, not {order!r}")
    s = order
    shape = np.shape(d["E"])
    a = np.zeros((s + 1, *shape))
    a[0] = 0.0 if dc is not None else 1.0
    a[1:] = rows_a
    b = np.zeros((s + 1, s, *shape))
    for (i, j), v in rows_b.items():
        b[i, j] = v
    return a, b


# ------------------------------------------------------------------ scene
class NavierStokes2D(Stepper):
    """Vorticity-form Navier–Stokes on [0, 2π)²; subclasses fix the ETDRK order."""

    order: ClassVar[int]
    complex_step = False
    _records_tape = True
    #: smallest (even) n the kernels and the default state support
    min_points: ClassVar[int] = 4
    # ν, μ and Δt large enough that even a one-step rollout depends measurably on them: the
    # checker's finite-difference tangent (no complex step through real FFTs) needs that.
    space = {
        "n": Choice((8, 12, 16, 24)),
        "nu": Range(0.1, 0.3),
        "dt": Range(0.03, 0.06),
        "forcing_wavenumber": Choice((None, 1, 2)),
        "drag": Choice((0.0, 1.0)),
        "dealias": Choice((True, False)),
    }

    def __init__(
        self,
        n: int = 32,
        nu: float = 0.01,
        dt: float = 0.01,
        forcing_wavenumber: int | None = 4,
        forcing_amplitude: float = 1.0,
        drag: float = 0.0,
        dealias: bool = True,
    ):
        name = self.name
        n = validate.integer(name, "n", n, ge=self.min_points, even=True, why="real FFT grid")
        kx, ky = wavenumbers(n)
        self.n = n
        self.grid_shape = (n, n)
        self.channels = 1
        self.control_shape = (1, n, n)
        # ETDRK integrates L exactly for any Δt > 0; Δt ≤ 0 would run backwards or stand still.
        self.dt = validate.number(name, "dt", dt, gt=0)
        self.dealias = validate.flag(name, "dealias", dealias)
        nu = validate.number(name, "nu", nu)
        drag = validate.number(name, "drag", drag)
        forcing_amplitude = validate.number(name, "forcing_amplitude", forcing_amplitude)
        cut = dealias_cutoff(n) if self.dealias else n // 2
        kf = forcing_wavenumber
        if kf is not None:
            kf = validate.integer(
                name, "forcing_wavenumber", kf, ge=1, le=min(cut, n // 2 - 1),
                why=f"or None, on a {n}² grid" + (" with 2/3 dealiasing" if self.dealias else ""),
            )
        self.forcing_wavenumber = kf
        self.k2 = kx**2 + ky**2
        names, values = ["nu"], [nu]
        if kf is not None:
            names.append("forcing")
            values.append(forcing_amplitude)
        if drag != 0:
            names.append("drag")
            values.append(drag)
        self.param_names, self.param_values = tuple(names), tuple(values)
        self._pidx = np.array([names.index(k) if k in names else -1
                               for k in ("nu", "forcing", "drag")], dtype=np.int64)
        # Rows and columns of the modes N can populate (all of them without dealiasing).
        self._keep = np.abs(kx[:, 0]) <= cut
        self._ncols = cut + 1 if dealias else n // 2 + 1
        dkx, dky = derivative_wavenumbers(n)
        self._dk = (dkx[:, 0], dky[0])
        self._inv_k2 = np.where(self.k2 > 0, 1.0 / np.where(self.k2 > 0, self.k2, 1.0), 0.0)
        self._tables: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        self.check_params(np.array(self.param_values))

    # -------------------------------------------------------------- presets
    @classmethod
    def default(cls) -> NavierStokes2D:
        return cls(n=16, nu=0.1, dt=0.05, forcing_wavenumber=2, forcing_amplitude=0.5, drag=0.5)

    @classmethod
    def kolmogorov_drag(cls, re: float = 1000.0, n: int = 64, dt: float = 0.01) -> NavierStokes2D:
        """Kolmogorov flow with forcing sin(4y) in x-momentum and linear drag μ = 0.1 (Kochkov
        et al.'s setup; ETDRK4 when called on the base class)."""
        re = validate.number("ns2d kolmogorov_drag", "re", re, gt=0, why="ν = 1/re")
        return cls._of_order(4)(
            n=n, nu=1.0 / re, dt=dt, forcing_wavenumber=4, forcing_amplitude=1.0, drag=0.1
        )

    @classmethod
    def _of_order(cls, order: int) -> type[NavierStokes2D]:
        """The class itself, or, called on the base class, the registered class of ``order``."""
        return cls if hasattr(cls, "order") else BY_ORDER[order]

    # -------------------------------------------------------------- contract
    @property
    def point_cost(self) -> float:  # type: ignore[override]
        # measured: about 3.6 + 6.8·order ns per point-step
        return 3.6 + 6.8 * self.order

    def check_params(self, p: np.ndarray) -> None:
        why = (
            "L = −ν|k|² − μ is integrated exactly, so the linear part sets no Δt limit; the "
            "explicit advection needs Courant number Δt max(|u|+|v|) n/2π ≲ 1, see courant_number"
        )
        values = dict(zip(self.param_names, p))
        validate.number(self.name, "nu", values["nu"], ge=0, why=why)
        validate.number(self.name, "drag", values.get("drag", 0.0), ge=0, why=why)

    def random_state(
        self, rng: np.random.Generator, batch: int = 1, dtype: Any = np.float64
    ) -> np.ndarray:
        """Smooth random vorticity (modes |k| ≤ min(4, n/4)), unit RMS per batch element."""
        return random_smooth_field(rng, self.state_shape(batch), min(4, self.n // 4), dtype)

    def courant_number(self, omega: np.ndarray) -> float:
        """Δt max(|u| + |v|) / h of a vorticity batch (B, 1, n, n): keep it below about 1."""
        u = self.velocity(np.asarray(omega, dtype=np.float64))
        return float(self.dt * np.max(np.abs(u).sum(axis=1)) * self.n / (2 * np.pi))

    def velocity(self, omega: np.ndarray) -> np.ndarray:
        """(u, v) = (ψ_y, −ψ_x) as an array (B, 2, n, n) for a vorticity batch (B, 1, n, n)."""
        psi = np.fft.rfft2(np.asarray(omega)[:, 0]) * self._inv_k2
        u = np.fft.irfft2(1j * self._dk[1][None, :] * psi, s=self.grid_shape)
        v = np.fft.irfft2(-1j * self._dk[0][:, None] * psi, s=self.grid_shape)
        return np.stack([u, v], axis=1).astype(np.asarray(omega).dtype)

    def velocity_adjoint(self, vel_bar: np.ndarray) -> np.ndarray:
        """The vorticity cotangent (B, 1, n, n) of a velocity cotangent (B, 2, n, n), e.g. for a
        velocity loss: ℱ⁻¹(|k|⁻² (−i k_y ℱ(ū) + i k_x ℱ(v̄)))."""
        spec = np.fft.rfft2(np.asarray(vel_bar))
        mixed = -1j * self._dk[1][None, :] * spec[:, 0] + 1j * self._dk[0][:, None] * spec[:, 1]
        out = np.fft.irfft2(mixed * self._inv_k2, s=self.grid_shape)
        return out[:, None].astype(np.asarray(vel_bar).dtype)

    def _coefficients(self, p: np.ndarray, dtype: np.dtype, deriv: bool):
        values = dict(zip(self.param_names, np.asarray(p, dtype=np.float64)))
        key = (values["nu"], values.get("drag", 0.0), np.dtype(dtype).str, deriv)
        hit = self._tables.get(key)
        if hit is None:
            lin = -values["nu"] * self.k2 - values.get("drag", 0.0)
            c = etdrk_coefficients(lin, self.dt, self.order)
            dc = etdrk_coefficient_derivatives(lin, self.dt, self.order) if deriv else None
            hit = tuple(t.astype(dtype) for t in etdrk_tableau(self.order, c, dc))
            if len(self._tables) >= 8:
                # None: another thread may have evicted the same entry first.
                self._tables.pop(next(iter(self._tables)), None)
            self._tables[key] = hit
        return hit

    def _args(self, p: np.ndarray, dtype: np.dtype):
        real = np.dtype(dtype)
        a, b = self._coefficients(p, real, False)
        kf = self.forcing_wavenumber
        iforce = self._pidx[1]
        # F̂ = a · rfft2(−k_f cos(k_f y)) has the single entry −a k_f n²/2 at (0, k_f).
        fval = -float(p[iforce]) * kf * self.n**2 / 2 if kf is not None else 0.0
        return (
            real.type(self.dt), a, b, self._dk[0].astype(real), self._dk[1].astype(real),
            self._inv_k2.astype(real), self._keep, self._ncols, not self.dealias,
            -1 if kf is None else kf, real.type(fval),
        )

    def _forward(self, states, n, ctrl, p, record=False):
        tape = self._new_tape(states, n, record)
        ns_forward(states, n, ctrl, *self._args(p, states.dtype), tape,
                   parallel.threads_inside(states.shape[1], self.n**2))
        return tape if tape.shape[0] else None

    def _new_tape(self, states: np.ndarray, n: int, record: bool) -> np.ndarray:
        """Room for every stage's (u, v, ω) when asked to record, within ``TAPE_BYTES``; else
        the empty tape, which the kernel takes for "record nothing"."""
        shape = (n, states.shape[1], self.order, 3, self.n, self.n)
        record = record and np.prod(shape) * states.dtype.itemsize <= TAPE_BYTES
        return np.empty(shape if record else (0, 1, 1, 1, 1, 1), dtype=states.dtype)

    def _adjoint(self, states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p, tape=None):
        dt, a, b, kx, ky, inv_k2, keep, ncols, reuse, fmode, fval = self._args(p, ubar.dtype)
        if want_p:
            da, db = self._coefficients(p, ubar.dtype, True)
        else:
            da, db = a[:0], b[:0]
        if tape is None:
            tape = np.empty((0, 1, 1, 1, 1, 1), dtype=ubar.dtype)
        else:
            tape = tape[: states.shape[0]]  # the steps from a prefix of the recorded states
        kf = self.forcing_wavenumber
        # p̄_a = Σ_i ⟨N̄_i, ∂N/∂a⟩_H = Σ_i (2/n²) Re N̄_i[0, k_f] · (−k_f n²/2).
        fbar = -float(kf) if kf is not None else 0.0
        ns_adjoint(
            states, ctrl, cot, cmap, ubar, cbar, pbar, want_p, dt, a, b, da, db, kx, ky,
            inv_k2, keep, ncols, reuse, fmode, fval, fbar, self._pidx, self.k2,
            hermitian_weights(self.n), tape, parallel.threads_inside(states.shape[1], self.n**2),
        )


@register
class NavierStokes2DETDRK1(NavierStokes2D):
    name = "ns2d-etdrk1"
    order = 1


@register
class NavierStokes2DETDRK2(NavierStokes2D):
    name = "ns2d-etdrk2"
    order = 2


@register
class NavierStokes2DETDRK3(NavierStokes2D):
    name = "ns2d-etdrk3"
    order = 3


@register
class NavierStokes2DETDRK4(NavierStokes2D):
    name = "ns2d-etdrk4"
    order = 4


BY_ORDER: dict[int, type[NavierStokes2D]] = {
    c.order: c for c in NavierStokes2D.__subclasses__()
}
