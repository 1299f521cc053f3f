"""Fourier pseudo-spectral ETDRK1–4 on a periodic 1D grid: the kernel the 1D spectral solvers
share (viscous Burgers, linear advection–diffusion, Kuramoto–Sivashinsky: each in its module).

Continuous:  u_t = L u + N(u) + a g(x),  L diagonal in Fourier space, N(u) = −½ ∂_x(u²) (the
             conservative form, −½ i k · DFT(u²), optionally 2/3-dealiased), g a fixed forcing
             profile of amplitude a. Burgers: L = −ν k²; advection–diffusion: L = −i c k − ν k²,
             N ≡ 0 (every order is then exact: v' = E v, plus φ-weighted forcing).
Discrete:    v = rfft(u_k); one frame = ``substeps`` ETDRK steps of h = Δt/substeps (formulas
             in :mod:`adjointsim.spectral.etdrk`) as a tableau: stage y_s = d_s + Σ_q C_q ⊙ x_q
             over the step input, earlier stages and Y = rfft(z²) of their physical values
             z = irfft(y) (the multiplier −½ i k is folded into those C_q, the forcing into the
             constants d_s); u_{k+1} = irfft(v') + Δt c_k.
Adjoint:     the stages in reverse: x̄_q += conj(C_q) ⊙ ȳ_s, and through Y: ȳ += rfft(2 z ⊙
             irfft(Ȳ)); spectral cotangents use the weighted product of
             :mod:`adjointsim.spectral.fft1d`, under which rfft and irfft are each other's
             adjoints. c̄_k = Δt ū_{k+1}. Parameters: p̄ = Re Σ_k W_k Ĉ_q dC_q/dL ∂L/∂p with the
             coefficient cotangents Ĉ_q = Σ conj(ȳ_s) x_q (:func:`etdrk_coefficient_derivatives`),
             and the forcing amplitude from ⟨ȳ_s, ∂d_s/∂a⟩.

Cost: the forward keeps the spectral state between frames (an ETDRK4 step is 8 real FFTs);
under :meth:`Stepper.vjp` it records the stages' physical values on a tape, so the adjoint
step costs the same 8 FFTs without recomputation (it recomputes the step instead when the tape
would exceed ``TAPE_BYTES``, or when parameter cotangents need the spectral stages), and it
keeps the cotangent spectral between frames unless the physical one is needed (one FFT more
per frame). Where the packed layout is the states' own (one signal, or the library FFTs), the
stored states serve as the packed input and output of a step without copies. Forward +
gradient of a rollout costs about 2.1–2.4 forwards (``benchmarks/ks_speed.py``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

from .. import validate
from ..registry import register
from ..spectral import fft1d
from ..spectral.etdrk import etdrk_coefficient_derivatives, etdrk_coefficients
from ..stepper import Stepper

#: the largest stage tape kept between the forward and the adjoint sweep of a vjp
TAPE_BYTES = 1 << 30
#: tape buffers up to this size stay allocated between vjp calls (no page faults next time)
TAPE_KEEP_BYTES = 1 << 26

# Tableau rows: the step input, three stage values, their nonlinear terms, the step output.
V, A, B, C, NV, NA, NB, NC, OUT = range(9)
_TABLEAUX = {
    1: ((OUT, (("E", 1, V), ("phi1", 1, NV))),),
    2: (
        (A, (("E", 1, V), ("phi1", 1, NV))),
        (OUT, ((None, 1, A), ("phi2", 1, NA), ("phi2", -1, NV))),
    ),
    3: (
        (A, (("E2", 1, V), ("Q", 1, NV))),
        (B, (("E", 1, V), ("phi1", 2, NA), ("phi1", -1, NV))),
        (OUT, (("E", 1, V), ("f1", 1, NV), ("f2", 4, NA), ("f3", 1, NB))),
    ),
    4: (
        (A, (("E2", 1, V), ("Q", 1, NV))),
        (B, (("E2", 1, V), ("Q", 1, NA))),
        (C, (("E2", 1, A), ("Q", 2, NB), ("Q", -1, NV))),
        (OUT, (("E", 1, V), ("f1", 1, NV), ("f2", 2, NA), ("f2", 2, NB), ("f3", 1, NC))),
    ),
}
# N ≡ 0: every order reduces to the exact v' = E v.
_LINEAR_TABLEAU = ((OUT, (("E", 1, V),)),)


# ----------------------------------------------------------------- kernels
# A tableau term q adds coef[q] ⊙ st[src[q]] to its stage, times i where rot[q]; a stage s also
# adds the constant dconst[s] (the forcing's share) when dconst is not empty. Rows NV..NC hold
# Y = rfft(z²): the multiplier −½ i k (and the dealiasing mask) is folded into the coefficients.
@njit(cache=True, nogil=True)
def etdrk_forward(states, n, ctrl, dt, substeps, tgt, start, src, coef, rot, dconst, fplan,
                  nonlinear, tape):
    """Frames k < n: states[(k + 1) % S] from states[k % S]. A substep's physical stage values
    go to rows 1..3 of its ``ph`` block and its output's to row 0 (the next substep's input);
    with a tape (shape (n, substeps, rows, packed)) the blocks are the tape's, except for the
    last substep's output, which the adjoint re-packs from the stored state. ``states`` is
    C-contiguous (its rows are viewed as packed arrays where :func:`fft1d.direct`)."""
    ns, nb, npts = states.shape[0], states.shape[1], states.shape[3]
    m = npts // 2
    cdt = fplan[1].dtype
    consts = fplan[4]
    st = np.empty((2, 8, (m + 1) * nb), cdt)
    loc = np.empty((2, tgt.shape[0], m * nb), cdt)
    zin = np.empty(m * nb, cdt)
    t, w = np.empty(m * nb, cdt), np.empty((m + 1) * nb, cdt)
    empty = np.empty(0, cdt)
    has_tape = tape.shape[0] > 0
    cur = 0
    zv = zin
    # Where the packed layout is the states' own, an emitted output goes straight to its slot.
    direct = fft1d.direct(nb)
    for k in range(n):
        if k == 0 or ctrl.shape[0] > 0:
            # Otherwise the previous frame left v and its physical values in place.
            fft1d.pack(states[k % ns, :, 0, :], zin, consts)
            fft1d.rfft_packed(zin, zin, 0, st[cur, V], empty, empty, False, t, w, nb, fplan)
            zv = zin
        # Of a ping-pong buffer only the last state is read (both slots are checked for
        # non-finite values, so both get one); a controlled frame needs its own.
        emit = ns > 2 or k >= n - 2 or ctrl.shape[0] > 0
        for s in range(substeps):
            g = k * substeps + s
            last = s == substeps - 1
            ph = tape[k, s] if has_tape else loc[g % 2]
            out_z = loc[g % 2, 0] if last and has_tape else ph[0]
            if last and emit and direct:
                out_z = fft1d.packed_view(states[(k + 1) % ns], cdt)
            _substep(tgt, start, src, coef, rot, dconst, st[cur], zv, ph, st[1 - cur, V], out_z,
                     nonlinear or (last and emit), False, empty, t, w, nb, fplan, nonlinear)
            zv = out_z
            cur = 1 - cur
        if emit:
            out = states[(k + 1) % ns, :, 0, :]
            if not direct:
                fft1d.unpack(zv, out, consts)
            if ctrl.shape[0] > 0:
                out += dt * ctrl[k, :, 0, :]


@njit(cache=True, nogil=True)
def etdrk_adjoint(states, ctrl, cot, cmap, ubar, cbar, dt, substeps, tgt, start, src, coef, rot,
                  dconst, fplan, nonlinear, tape, want_p, chat, fsum):
    nb, npts = states.shape[1], states.shape[3]
    m = npts // 2
    cdt = fplan[1].dtype
    consts = fplan[4]
    has_tape = tape.shape[0] > 0
    nrec = 0 if has_tape else substeps
    st = np.empty((nrec + 1, 8, (m + 1) * nb), cdt)
    ph = np.empty((nrec, tgt.shape[0], m * nb), cdt)
    # Two sets of stage cotangents: one substep's input cotangent is the next one's ob.
    sbs = np.empty((2, 8, (m + 1) * nb), cdt)
    obuf = np.empty((m + 1) * nb, cdt)
    ob = obuf
    cur = 0
    zin, zt, zb = np.empty(m * nb, cdt), np.empty(m * nb, cdt), np.empty(m * nb, cdt)
    t, w = np.empty(m * nb, cdt), np.empty((m + 1) * nb, cdt)
    empty = np.empty(0, cdt)
    two, zero = consts[3], consts[0] - consts[0]
    direct = fft1d.direct(nb)
    carried = False  # ob already holds the spectral cotangent of the frame's output
    # The reverse sweep reads the stages' physical values, the parameter cotangents their
    # spectra; ETD1 with one substep needs neither (its input is the stored state).
    recompute = not has_tape and (want_p or (nonlinear and (tgt.shape[0] > 1 or substeps > 1)))
    for k in range(states.shape[0] - 1, -1, -1):
        ub = ubar[:, 0, :]
        if cbar.shape[0] > 0:
            cbar[k] = dt * ubar
        if (nonlinear or recompute) and direct:
            zin = fft1d.packed_view(states[k], cdt)
        elif nonlinear or recompute:
            fft1d.pack(states[k, :, 0, :], zin, consts)
        if recompute:
            fft1d.rfft_packed(zin, zin, 0, st[0, V], empty, empty, False, t, w, nb, fplan)
            for s in range(substeps):
                _substep(tgt, start, src, coef, rot, dconst, st[s], zin if s == 0 else ph[s - 1, 0],
                         ph[s], st[s + 1, V], ph[s, 0], nonlinear and s < substeps - 1,
                         s == substeps - 1 and not want_p, empty, t, w, nb, fplan, nonlinear)
        if not carried:
            fft1d.pack(ub, zb, consts)
            ob = obuf
            fft1d.rfft_packed(zb, zb, 0, ob, empty, empty, False, t, w, nb, fplan)
        for s in range(substeps - 1, -1, -1):
            sb = sbs[cur]
            ph_s = tape[k, s] if has_tape else ph[s]
            zv = zin if s == 0 else (tape[k, s - 1, 0] if has_tape else ph[s - 1, 0])
            _substep_adjoint(tgt, start, src, coef, rot, dconst, st[s] if want_p else sb, ph_s,
                             sb, ob, want_p, chat, fsum, nonlinear, empty, zt, t, w, nb, fplan)
            # The cotangent of this substep's input: spectral v and physical z_v = irfft(v).
            # Unless the frame's physical cotangent is needed (for the controls, an added
            # cotangent or the result), it stays spectral: rfft(irfft(x)) is x without the
            # imaginary parts of the zero and Nyquist modes.
            carried = s > 0 or (k > 0 and cbar.shape[0] == 0 and cmap[k] < 0)
            if carried:
                ob = sb[V]
                cur = 1 - cur
                if s == 0:
                    for b in range(nb):
                        for j in (0, m):
                            i = fft1d.at(j, b, m + 1, nb)
                            ob[i] = complex(ob[i].real, zero)
                if nonlinear:
                    _square_adjoint(sb[NV], zv, ob, True, empty, zt, t, w, nb, fplan)
            else:
                fft1d.irfft_packed(sb[V], empty, zb, w, nb, fplan)
                if nonlinear:
                    fft1d.irfft_packed(sb[NV], empty, zt, w, nb, fplan)
                    for i in range(zb.shape[0]):
                        a, b, c = zb[i], zt[i], zv[i]
                        zb[i] = complex(a.real + two * b.real * c.real,
                                        a.imag + two * b.imag * c.imag)
                fft1d.unpack(zb, ub, consts)
        if cmap[k] >= 0:
            ubar += cot[cmap[k]]


@njit(cache=True, nogil=True)
def _substep(tgt, start, src, coef, rot, dconst, st, zv, ph, out_v, out_z, need_z, stages_only,
             empty, t, w, nb, fplan, nonlinear):
    """One ETDRK step from st[V] and its physical values zv; every stage value and its Y land
    in st, the stages' physical values in ph[1..3], the result in out_v (and out_z). With
    ``stages_only`` it stops once the last stage's physical values are known (all that a
    reverse sweep reads): the last stage's Y feeds only the output."""
    if nonlinear:
        fft1d.rfft_packed(zv, zv, 1, st[NV], empty, empty, False, t, w, nb, fplan)
    for s in range(tgt.shape[0]):
        r = tgt[s]
        if r == OUT and stages_only:
            return
        y = out_v if r == OUT else st[r]
        _combine(y, coef, rot, dconst, s, start[s], start[s + 1], src, st, nb)
        if r != OUT and nonlinear:
            fft1d.irfft_packed(y, empty, ph[r], w, nb, fplan)
            if not (stages_only and tgt[s + 1] == OUT):
                fft1d.rfft_packed(ph[r], ph[r], 1, st[r + 4], empty, empty, False, t, w, nb,
                                  fplan)
    if need_z:
        fft1d.irfft_packed(out_v, empty, out_z, w, nb, fplan)


@njit(cache=True, nogil=True)
def _combine(y, coef, rot, dconst, s, q0, q1, src, st, nb):
    """y = dconst[s] + Σ_{q0 ≤ q < q1} (i if rot[q]) coef[q] ⊙ st[src[q]]."""
    fresh = dconst.shape[0] == 0
    nk = coef.shape[1]
    if fft1d.at(1, 0, nk, nb) == 1:
        # Batch-major spectra: run along the modes of each signal.
        for b in range(nb):
            lo = b * nk
            if not fresh:
                y[lo : lo + nk] = dconst[s]
            for q in range(q0, q1):
                _axpy(y, lo, st, src[q], lo, coef, q, 0, nk, 1, rot[q], fresh and q == q0)
        return
    for k in range(nk):
        lo = k * nb
        if not fresh:
            y[lo : lo + nb] = dconst[s, k]
        for q in range(q0, q1):
            _axpy(y, lo, st, src[q], lo, coef, q, k, nb, 0, rot[q], fresh and q == q0)


@njit(cache=True, nogil=True, inline="always")
def _axpy(y, ylo, x, xrow, xlo, c, crow, ck, n, cstep, rot, first):
    """y[ylo + i] (+)= (i if rot) c[crow, ck + cstep·i] x[xrow, xlo + i] for i < n, assigning
    if ``first``. Rows are indexed in place: views cost a reference count each."""
    if rot:
        if first:
            for i in range(n):
                v = c[crow, ck + cstep * i] * x[xrow, xlo + i]
                y[ylo + i] = complex(-v.imag, v.real)
        else:
            for i in range(n):
                v = c[crow, ck + cstep * i] * x[xrow, xlo + i]
                y[ylo + i] += complex(-v.imag, v.real)
    elif first:
        for i in range(n):
            y[ylo + i] = c[crow, ck + cstep * i] * x[xrow, xlo + i]
    else:
        for i in range(n):
            y[ylo + i] += c[crow, ck + cstep * i] * x[xrow, xlo + i]


@njit(cache=True, nogil=True)
def _substep_adjoint(tgt, start, src, coef, rot, dconst, st, ph, sb, ob, want_p, chat, fsum,
                     nonlinear, empty, zt, t, w, nb, fplan):
    """Reverse the stages of one step: ob is the cotangent of its output; sb receives those of
    the input v and of every stage value and Y (a row is assigned on first touch instead of
    being zeroed; rows V and NV are always touched). ``st`` is read only if ``want_p``."""
    touched = np.zeros(8, np.bool_)
    for s in range(tgt.shape[0] - 1, -1, -1):
        r = tgt[s]
        ybar = ob if r == OUT else sb[r]
        if r != OUT:
            if nonlinear and touched[r + 4]:
                _square_adjoint(sb[r + 4], ph[r], ybar, touched[r], empty, zt, t, w, nb, fplan)
                touched[r] = True
            if not touched[r]:
                continue  # nothing depends on this stage
        if want_p and dconst.shape[0] > 0:
            for k in range(fsum.shape[1]):
                for b in range(nb):
                    fsum[s, k] += ybar[fft1d.at(k, b, fsum.shape[1], nb)]
        q0, q1 = start[s], start[s + 1]
        first = np.zeros(q1 - q0, np.bool_)
        for q in range(q0, q1):
            first[q - q0] = not touched[src[q]]
            touched[src[q]] = True
        _combine_adjoint(sb, ybar, coef, rot, q0, q1, src, first, nb)
        if want_p:
            for q in range(q0, q1):
                x = src[q]
                for k in range(coef.shape[1]):
                    acc = 0j
                    for b in range(nb):
                        i = fft1d.at(k, b, coef.shape[1], nb)
                        acc += ybar[i].conjugate() * st[x, i]
                    chat[q, k] += acc


@njit(cache=True, nogil=True)
def _combine_adjoint(sb, ybar, coef, rot, q0, q1, src, first, nb):
    """sb[src[q]] (+)= conj((i if rot[q]) coef[q]) ⊙ ybar for q0 ≤ q < q1, assigning where
    ``first[q − q0]``: the transpose of :func:`_combine`. A function of its own, as
    :func:`_combine` is: inlined into the stage loop, these loops ran several times slower."""
    nk = coef.shape[1]
    if fft1d.at(1, 0, nk, nb) == 1:
        for b in range(nb):
            for q in range(q0, q1):
                _axpy_adjoint(sb, src[q], b * nk, ybar, coef, q, 0, nk, 1, rot[q], first[q - q0])
        return
    for k in range(nk):
        for q in range(q0, q1):
            _axpy_adjoint(sb, src[q], k * nb, ybar, coef, q, k, nb, 0, rot[q], first[q - q0])


@njit(cache=True, nogil=True, inline="always")
def _axpy_adjoint(xb, xrow, lo, ybar, c, crow, ck, n, cstep, rot, first):
    """xb[xrow, lo + i] (+)= conj((i if rot) c[crow, ck + cstep·i]) ybar[lo + i], i < n:
    the transpose of :func:`_axpy` (assigning if ``first``)."""
    if rot:
        if first:
            for i in range(n):
                v = c[crow, ck + cstep * i].conjugate() * ybar[lo + i]
                xb[xrow, lo + i] = complex(v.imag, -v.real)
        else:
            for i in range(n):
                v = c[crow, ck + cstep * i].conjugate() * ybar[lo + i]
                xb[xrow, lo + i] += complex(v.imag, -v.real)
    elif first:
        for i in range(n):
            xb[xrow, lo + i] = c[crow, ck + cstep * i].conjugate() * ybar[lo + i]
    else:
        for i in range(n):
            xb[xrow, lo + i] += c[crow, ck + cstep * i].conjugate() * ybar[lo + i]


@njit(cache=True, nogil=True)
def _square_adjoint(ybar_sq, z, ybar, acc, empty, zt, t, w, nb, fplan):
    """ybar (+)= rfft(2 z ⊙ irfft(ybar_sq)): through Y = rfft(z²) and z = irfft(y)."""
    fft1d.irfft_packed(ybar_sq, empty, zt, w, nb, fplan)
    fft1d.rfft_packed(zt, z, 2, ybar, empty, empty, acc, t, w, nb, fplan)


# ----------------------------------------------------------------- scenes
class ETDRKScene1D(Stepper):
    """Periodic grid of ``n`` points on [0, length), an ETDRK order, sub-steps per frame,
    optional 2/3 dealiasing of the nonlinear term and an optional forcing profile.

    Subclasses set ``order``, ``nonlinear`` and ``linear_params`` (names of the parameters
    entering L) and implement :meth:`linear_basis`, with L = Σ_j p_j · basis_j.
    """

    order: int
    nonlinear: bool = True
    linear_params: tuple[str, ...]
    complex_step = False  # real FFTs cannot run complex arrays
    _records_tape = True
    # The real FFTs change algorithm at this batch size: chunks stay on the batch's side of it.
    _min_chunk_rows = fft1d.LIBRARY_BATCH
    #: amplitude of :meth:`random_state`
    amplitude: float = 1.0

    @property
    def point_cost(self) -> float:  # type: ignore[override]
        # measured: a step with the quadratic term costs about 1.8 + 1.85·order ns per point
        return self.substeps * (1.8 + 1.85 * self.order if self.nonlinear else 2.7)
    #: smallest (even) n: below 4 only the mean and the Nyquist mode are left
    min_points: int = 4

    def __init__(
        self,
        n: int,
        length: float,
        dt: float,
        params: tuple[float, ...],
        substeps: int = 1,
        dealias: bool = False,
        forcing: np.ndarray | None = None,
        forcing_amplitude: float = 1.0,
    ):
        name = self.name
        n = validate.integer(name, "n", n, ge=self.min_points, even=True, why="real FFT grid")
        self.grid_shape = (n,)
        self.channels = 1
        self.control_shape = (1, n)
        self.length = validate.number(name, "length", length, gt=0)
        # ETDRK integrates L exactly for any Δt > 0; Δt ≤ 0 would run backwards or stand still.
        self.dt = validate.number(name, "dt", dt, gt=0)
        self.substeps = validate.integer(name, "substeps", substeps, ge=1)
        self.dealias = validate.flag(name, "dealias", dealias)
        params = tuple(validate.number(name, k, p) for k, p in zip(self.linear_params, params))
        amplitude = validate.number(name, "forcing_amplitude", forcing_amplitude)
        self.k = fft1d.wavenumbers(n, self.length)
        self.basis = [np.asarray(b) for b in self.linear_basis()]
        # N(u) = i·gi ⊙ rfft(u²), gi = −k/2 (zero at Nyquist), times the 2/3 mask if dealiased
        self.nonlinear_multiplier = -0.5 * fft1d.derivative_multiplier(n, self.length, 1).imag * (
            fft1d.dealias_mask(n) if self.dealias else 1.0
        )
        if forcing is None:
            self.forcing_hat = np.zeros(0, dtype=np.complex128)
            self.param_names, self.param_values = self.linear_params, params
        else:
            g = validate.array(name, "forcing", forcing, (1, n))
            self.forcing_hat = np.fft.rfft(g[0])
            self.param_names = (*self.linear_params, "forcing")
            self.param_values = (*params, amplitude)
        self.check_params(np.array(self.param_values))
        self._tableau = self._build_tableau()
        self._args_cache: dict[tuple, tuple] = {}
        # A tape buffer kept between vjp calls (see _new_tape) lives in "_tape_buffer".

    # ------------------------------------------------------------ to override
    def linear_basis(self) -> list[np.ndarray]:
        """One half-spectrum array per entry of ``linear_params``: L = Σ p_j basis_j."""
        raise NotImplementedError

    # ------------------------------------------------------------ public helpers
    def nodes(self) -> np.ndarray:
        """Grid points x_i = i · length / n."""
        return self.length * np.arange(self.grid_shape[0]) / self.grid_shape[0]

    def linear_operator(self, p: np.ndarray | None = None) -> np.ndarray:
        """The diagonal L on the half spectrum for parameters ``p`` (kernel order)."""
        p = np.asarray(self.param_values if p is None else p, dtype=np.float64)
        lin = sum(pj * b for pj, b in zip(p, self.basis))
        return np.asarray(lin) + np.zeros(len(self.k))

    def random_state(
        self, rng: np.random.Generator, batch: int = 1, dtype: Any = np.float64
    ) -> np.ndarray:
        """Smooth random fields: modes up to |k| ≤ 6·2π/length with decaying amplitudes, zero
        mean, scaled to max |u| = ``amplitude``."""
        return self._smooth(rng, batch, self.amplitude)[:, None, :].astype(dtype)

    def _smooth(self, rng: np.random.Generator, count: int, amplitude: float) -> np.ndarray:
        n = self.grid_shape[0]
        spec = np.zeros((count, n // 2 + 1), dtype=np.complex128)
        kmax = min(6, n // 2 - 1)
        spec[:, 1 : kmax + 1] = (
            rng.standard_normal((count, kmax)) + 1j * rng.standard_normal((count, kmax))
        ) / np.arange(1, kmax + 1)
        u = np.fft.irfft(spec, n)
        return u * (amplitude / np.abs(u).max(axis=1, keepdims=True))

    # ------------------------------------------------------------ kernels
    def _build_tableau(self) -> tuple:
        """Kernel tableau arrays (tgt, start, src, rot) and the terms behind them: every term
        as (stage, key, scale, source), and the kept ones (those that read a nonzero row)."""
        has_n = self.nonlinear or self.forcing_hat.size > 0
        stages = _TABLEAUX[self.order] if has_n else _LINEAR_TABLEAU
        terms = [(s, key, scale, source) for s, (_, row) in enumerate(stages)
                 for key, scale, source in row]
        kept = [term for term in terms if term[3] < NV or self.nonlinear]
        start = np.searchsorted([term[0] for term in kept], np.arange(len(stages) + 1))
        as_int = lambda a: np.array(a, dtype=np.int64)  # noqa: E731
        return (
            as_int([target for target, _ in stages]), as_int(start),
            as_int([term[3] for term in kept]), as_int([term[3] >= NV for term in kept]),
            terms, kept,
        )

    def _coefficient_table(self, p: np.ndarray, deriv: bool) -> dict[str, np.ndarray]:
        lin = self.linear_operator(np.asarray(p).real)
        get = etdrk_coefficient_derivatives if deriv else etdrk_coefficients
        table = dict(get(lin, self.dt / self.substeps, self.order))
        table[None] = np.full(lin.shape, 0.0 if deriv else 1.0)
        return table

    def _kernel_args(self, p: np.ndarray, dtype: np.dtype) -> tuple:
        key = (np.asarray(p).tobytes(), np.dtype(dtype).str)
        # One lookup: another thread may clear the cache between a test and a read.
        hit = self._args_cache.get(key)
        if hit is None:
            if len(self._args_cache) >= 8:
                self._args_cache.clear()
            hit = self._args_cache[key] = self._make_kernel_args(p, dtype)
        return hit

    def _make_kernel_args(self, p: np.ndarray, dtype: np.dtype) -> tuple:
        cdt = np.result_type(dtype, np.complex64)
        tgt, start, src, rot, terms, kept = self._tableau
        table = self._coefficient_table(p, deriv=False)
        coef = np.array([
            scale * table[key] * (self.nonlinear_multiplier if source >= NV else 1.0)
            for _, key, scale, source in kept
        ])
        coef = coef.astype(cdt if coef.dtype.kind == "c" else dtype)
        dconst = np.zeros((0, len(self.k)), dtype=cdt)
        if self.forcing_hat.size:
            dconst = np.zeros((len(tgt), len(self.k)), dtype=np.complex128)
            for s, key, scale, source in terms:
                if source >= NV:
                    dconst[s] += scale * table[key] * self.forcing_hat * p[-1].real
            dconst = dconst.astype(cdt)
        return (
            np.asarray(self.dt, dtype=dtype)[()], self.substeps, tgt, start, src, coef, rot,
            dconst, fft1d.plan(self.grid_shape[0], dtype), self.nonlinear,
        )

    def _forward(self, states, n, ctrl, p, record=False):
        args = self._kernel_args(p, states.dtype)
        tape = self._new_tape(states, n, record)
        etdrk_forward(states, n, ctrl, *args, tape)
        return tape if tape.shape[0] else None

    def _new_tape(self, states: np.ndarray, n: int, record: bool) -> np.ndarray:
        """Room for the stages when asked to record and the tape is worth it, within
        ``TAPE_BYTES``; else the empty tape, which the kernel takes for "record nothing"."""
        nb, npts = states.shape[1], states.shape[3]
        shape = (n, self.substeps, len(self._tableau[0]), npts // 2 * nb)
        cdt = np.result_type(states.dtype, np.complex64)
        size = int(np.prod(shape))
        useful = self.order > 1 or self.substeps > 1  # else the stored states suffice
        if not (record and self.nonlinear and useful and size * cdt.itemsize <= TAPE_BYTES):
            return np.empty((0, 1, 1, 1), dtype=cdt)
        # The kept buffer leaves the stepper while a tape uses it (_adjoint gives it back): a
        # nested or concurrent vjp on this stepper records into a buffer of its own.
        buffer = self.__dict__.pop("_tape_buffer", None)
        if buffer is None or buffer.dtype != cdt or buffer.size < size:
            if buffer is not None:
                self._tape_buffer = buffer
            buffer = np.empty(size, dtype=cdt)
        return buffer[:size].reshape(shape)

    def _adjoint(self, states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p, tape=None):
        dtype = ubar.dtype
        args = self._kernel_args(p, dtype)
        recorded = tape
        if tape is None:
            tape = np.empty((0, 1, 1, 1), dtype=np.result_type(dtype, np.complex64))
        else:
            tape = tape[: states.shape[0]]  # the steps from a prefix of the recorded states
        tgt, _, src, _, terms, kept = self._tableau
        chat = np.zeros((len(src), len(self.k)), dtype=np.complex128)
        fsum = np.zeros((len(tgt), len(self.k)), dtype=np.complex128)
        states = np.ascontiguousarray(states, dtype=dtype)
        etdrk_adjoint(states, ctrl, cot, cmap, ubar, cbar, *args, tape, want_p, chat, fsum)
        if recorded is not None and recorded.base.nbytes <= TAPE_KEEP_BYTES:
            self._tape_buffer = recorded.base  # no page faults for the next vjp's tape
        if want_p:
            self._parameter_cotangents(p, chat, fsum, pbar)

    def _parameter_cotangents(self, p, chat, fsum, pbar) -> None:
        """p̄ from the coefficient cotangents Ĉ_q = Σ conj(ȳ_s) x_q and the summed stage
        cotangents (for the forcing): p̄_j += Re Σ_k W_k Ĉ_q dC_q/dL ∂L/∂p_j, etc."""
        _, _, _, _, terms, kept = self._tableau
        weight = fft1d.hermitian_weights(self.grid_shape[0]) / self.grid_shape[0]
        dtable = self._coefficient_table(p, deriv=True)
        sens = np.zeros(len(self.k), dtype=np.complex128)
        for q, (_, key, scale, source) in enumerate(kept):
            factor = 1j * self.nonlinear_multiplier if source >= NV else 1.0
            sens += weight * chat[q] * scale * dtable[key] * factor
        if self.forcing_hat.size:
            table = self._coefficient_table(p, deriv=False)
            for s, key, scale, source in terms:
                if source >= NV:
                    fbar = weight * np.conj(fsum[s]) * self.forcing_hat
                    sens += fbar * p[-1].real * scale * dtable[key]
                    pbar[-1] += np.sum(fbar * scale * table[key]).real
        for j, b in enumerate(self.basis):
            pbar[j] += np.sum(sens * b).real


def register_orders(base: type, prefix: str, namespace: dict) -> dict[int, type]:
    """Register ``{prefix}-etdrk1`` .. ``-etdrk4``, one subclass of ``base`` per order, as
    module attributes ``{base name}1`` .. ``4`` of ``namespace`` (so they pickle)."""
    classes = {}
    for order in (1, 2, 3, 4):
        name = f"{base.__name__}{order}"
        cls = type(name, (base,), {
            "name": f"{prefix}-etdrk{order}", "order": order, "__module__": namespace["__name__"],
            "__qualname__": name,
            "__doc__": f"{base.__doc__.splitlines()[0]} ETDRK{order} (ETD1 = exponential Euler).",
        })
        namespace[name] = classes[order] = register(cls)
    return classes
