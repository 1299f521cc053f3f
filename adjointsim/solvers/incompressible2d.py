"""2D incompressible Navier–Stokes on a staggered (MAC) grid with walls, inflow, outflow and
obstacles; semi-Lagrangian (or MacCormack) advection and an exact pressure projection.

Continuous, on a box of nx × ny square cells of side h:
    u_t + (u·∇)u = ν Δu + b ρ e_y + f,   ∇·u = 0,   ρ_t + u·∇ρ = s,
with an optional advected density ρ (smoke) lifting the flow through the Boussinesq term b ρ,
body forces f and density sources s as per-step controls. Each side of the box is a no-slip
wall, a free-slip wall, a moving lid (tangential speed ``lid_speed``), an inflow (normal speed
``inflow_speed`` times a uniform or parabolic profile), an outflow (pressure zero, zero normal
gradient of the tangential velocity) or periodic (in pairs). Obstacles are a mask of solid
cells (staircase walls): every face touching a solid cell carries zero velocity.

Discrete (Chorin's splitting, one step from u_k to u_{k+1}; c = Δt/h):
 0. boundary values: the normal velocity of wall, obstacle and inflow faces is set (zero, or
    inflow_speed · profile); a periodic side's last face copies its first;
 1. advection, the book's semi-Lagrangian scheme: every free face (and density cell) at x
    takes the value at x − Δt u(x), sampled bilinearly from the padded fields, where one
    ghost layer holds each side's tangential condition (−u inside a no-slip wall, +u at a
    free-slip wall or an outflow, 2U − u at a lid, the opposite side when periodic) and the
    sample points are clamped into that layer (or wrapped, when periodic). With
    ``advection="maccormack"`` (the book's ``advect.mac_cormack``) the result φ̂ is
    corrected to φ̂ + ½ (φ − φ̂(x + Δt u(x))) and clamped to the four values of φ around the
    backtraced point;
 2. viscosity, explicit (the default): u += ν Δt Δ_h u on the free faces (5-point Laplacian,
    same ghost layer; an outflow face mirrors itself across its side); or, with
    ``viscosity="implicit"``, backward Euler: u ← x, the solution of x − ν Δt Δ_h x = u on the
    free faces, the same Laplacian with the same boundary values; I − kd A (kd = ν Δt/h², A
    the Laplacian's matrix on the free faces, symmetric) is factorised once per geometry and ν;
 3. forces: u += Δt f, v += Δt (f_y + b ρ̄) (ρ̄ the advected density averaged onto the face),
    ρ += Δt s;
 4. projection: M φ = −(D u) on the fluid cells, u −= G φ on the free faces, where D is the
    undivided divergence, G the undivided gradient (φ = 0 in an outflow's ghost cell: a
    Dirichlet condition) and M = −D G the graph Laplacian of the fluid cells (Neumann at walls
    and obstacles). M is factorised once per geometry (scipy's SuperLU); a connected region of
    fluid without an outflow gets M + e_c e_cᵀ at one of its cells c, which leaves the solution
    of a compatible right-hand side unchanged (its equations sum to φ_c = 0) and makes M
    invertible. After the step the discrete divergence D u is zero to the solve's round-off.

State (B, C, nx + 1, ny + 1), x along axis −2: channel 0 holds u at the faces (i h, (j + ½) h),
i ≤ nx, j < ny; channel 1 holds v at ((i + ½) h, j h), i < nx, j ≤ ny; channel 2 (with
``density``) holds ρ at the cell centres, i < nx, j < ny. The entries outside these ranges are
spare: the step writes zero into them and ignores them. Controls have the state's shape per
step and act on the free faces and fluid cells only.

Adjoint: every stage above is reversed in the opposite order; the projection's adjoint is the
transposed solve with the same factors (M is symmetric), and so is the implicit viscous step's.
Its solution x has the derivative (I − kd A)⁻¹ (Δt/h²) h² Δ_h x in ν (h² Δ_h x = A x + b, b the
boundary values' part), which gives ν the cotangent (Δt/h²) ⟨λ, h² Δ_h x⟩, λ = (I − kd A)⁻¹ x̄
the adjoint solution. The bilinear sample's derivative in its sample point is that of the cell
it falls in (one-sided on a cell edge, zero where clamped), so the discrete adjoint matches the
tangent of the code everywhere the sample points stay off cell edges (the gradients are those
of a piecewise-smooth map). MacCormack's clamp adds switches wherever a corrected value meets a
bound: its adjoint is exact too (the dot-product test holds to round-off), but finite
differences and the Taylor test see those switches at any step size a long rollout allows, so
the gradient checker, which runs the semi-Lagrangian default, cannot confirm it. The
semi-Lagrangian adjoint needs nothing of the forward step but its padded input: the velocity's
samples are fixed stencils and each backtrace is recomputed where its cotangent is scattered,
which also gives back the advected fields that the parameters' cotangents need. MacCormack's
adjoint recomputes the step's advection first (its clamp reads it); an implicit viscous step
with parameter cotangents solves its forward system once more.

Limits, checked when the scene is made and when a call overrides the parameters: ν Δt/h² ≤ ¼
(explicit viscosity only) and a Courant number (speed · Δt/h) of at most 1 for the speeds the
sides impose, the lid's and the peak inflow's. The state's own speed is not limited, neither the
state a call is given nor the ones it makes: the semi-Lagrangian step is stable at any Courant
number (a backtrace is clamped at the box's sides), and flows made from slow starts outrun h/Δt
(a buoyant plume, or the flow through a channel narrowed by an obstacle, faster than its
inflow). A bound on the given state would refuse the next step of a stepwise rollout that one
n-step call makes without complaint; the results of the two are the same bit for bit. Where the
Courant number exceeds 1 a backtrace may jump a solid one cell thick, which is a loss of
accuracy, not of stability: :meth:`Incompressible2D.courant_number` reports it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu

from .. import validate
from ..errors import UserError
from ..registry import register
from ..stepper import Choice, Range, Stepper

SIDES = ("wall", "slip", "lid", "inflow", "outflow", "periodic")
WALL, SLIP, LID, INFLOW, OUTFLOW, PERIODIC = range(6)
#: face kinds: advected, diffused and projected; set by the boundary; a periodic side's copy
FREE, FIXED, COPY = 0, 1, 2
PROFILES = ("uniform", "parabolic")
OBSTACLES = ("cylinder", "box")
ADVECTIONS = ("semi-lagrangian", "maccormack")
VISCOSITIES = ("explicit", "implicit")
#: largest Courant number (speed · Δt / h) accepted
MAX_COURANT = 1.0
#: largest ν Δt / h² of the explicit viscosity (the 5-point Laplacian's limit)
MAX_DIFFUSION = 0.25


# ------------------------------------------------------------------ bilinear samples
@njit(cache=True, nogil=True)
def _coord(q, size, off, period, periodic):
    """The cell (i0) and fraction of coordinate ``q`` on an axis of ``size`` samples, and
    dq'/dq (1, or 0 where clamped). Periodic axes wrap q − off into [0, period)."""
    d = 1.0
    if periodic:
        q = q - period * np.floor((q.real - off) / period)
    elif q.real < 0.0:
        q = q - q
        d = 0.0
    elif q.real > size - 1:
        q = q - q + (size - 1)
        d = 0.0
    i0 = int(np.floor(q.real))
    if i0 > size - 2:
        i0 = size - 2
    return i0, q - i0, d


@njit(cache=True, nogil=True)
def _sample(q, a, b, geo):
    """Bilinear sample of the padded field ``q`` at index coordinates (a, b); ``geo`` holds
    (offset, period, periodic) of both axes."""
    i, fa, _ = _coord(a, q.shape[0], geo[0], geo[1], geo[2])
    j, fb, _ = _coord(b, q.shape[1], geo[3], geo[4], geo[5])
    return ((1 - fa) * ((1 - fb) * q[i, j] + fb * q[i, j + 1])
            + fa * ((1 - fb) * q[i + 1, j] + fb * q[i + 1, j + 1]))


@njit(cache=True, nogil=True)
def _sample_adjoint(q, qbar, a, b, geo, g):
    """Scatter the cotangent ``g`` of a sample into ``qbar``; return the sample (as
    :func:`_sample` computes it) and the cotangents of a, b."""
    i, fa, da = _coord(a, q.shape[0], geo[0], geo[1], geo[2])
    j, fb, db = _coord(b, q.shape[1], geo[3], geo[4], geo[5])
    value = ((1 - fa) * ((1 - fb) * q[i, j] + fb * q[i, j + 1])
             + fa * ((1 - fb) * q[i + 1, j] + fb * q[i + 1, j + 1]))
    qbar[i, j] += (1 - fa) * (1 - fb) * g
    qbar[i, j + 1] += (1 - fa) * fb * g
    qbar[i + 1, j] += fa * (1 - fb) * g
    qbar[i + 1, j + 1] += fa * fb * g
    abar = da * g * ((1 - fb) * (q[i + 1, j] - q[i, j]) + fb * (q[i + 1, j + 1] - q[i, j + 1]))
    bbar = db * g * ((1 - fa) * (q[i, j + 1] - q[i, j]) + fa * (q[i + 1, j + 1] - q[i + 1, j]))
    return value, abar, bbar


# ------------------------------------------------------------------ ghost layers
@njit(cache=True, nogil=True)
def _ghost_sign(side):
    """A tangential ghost value is sign · (the inner value) (+ 2 · lid speed at a lid)."""
    return 1.0 if side == SLIP or side == OUTFLOW or side == PERIODIC else -1.0


@njit(cache=True, nogil=True)
def _pad_u(u, big, sides, lid):
    """big (nx + 1, ny + 2): u with a ghost row below and above (the bottom/top conditions)."""
    nx1, ny = u.shape
    for i in range(nx1):
        for j in range(ny):
            big[i, j + 1] = u[i, j]
        lo, hi = (ny - 1, 0) if sides[2] == PERIODIC else (0, ny - 1)
        big[i, 0] = _ghost_sign(sides[2]) * u[i, lo] + 2.0 * lid[2]
        big[i, ny + 1] = _ghost_sign(sides[3]) * u[i, hi] + 2.0 * lid[3]


@njit(cache=True, nogil=True)
def _unpad_u(big, ubar, sides):
    nx1, ny = ubar.shape
    for i in range(nx1):
        for j in range(ny):
            ubar[i, j] += big[i, j + 1]
        lo, hi = (ny - 1, 0) if sides[2] == PERIODIC else (0, ny - 1)
        ubar[i, lo] += _ghost_sign(sides[2]) * big[i, 0]
        ubar[i, hi] += _ghost_sign(sides[3]) * big[i, ny + 1]


@njit(cache=True, nogil=True)
def _pad_v(v, big, sides, lid):
    """big (nx + 2, ny + 1): v with a ghost column left and right (the left/right conditions)."""
    nx, ny1 = v.shape
    lo, hi = (nx - 1, 0) if sides[0] == PERIODIC else (0, nx - 1)
    for j in range(ny1):
        for i in range(nx):
            big[i + 1, j] = v[i, j]
        big[0, j] = _ghost_sign(sides[0]) * v[lo, j] + 2.0 * lid[0]
        big[nx + 1, j] = _ghost_sign(sides[1]) * v[hi, j] + 2.0 * lid[1]


@njit(cache=True, nogil=True)
def _unpad_v(big, vbar, sides):
    nx, ny1 = vbar.shape
    lo, hi = (nx - 1, 0) if sides[0] == PERIODIC else (0, nx - 1)
    for j in range(ny1):
        for i in range(nx):
            vbar[i, j] += big[i + 1, j]
        vbar[lo, j] += _ghost_sign(sides[0]) * big[0, j]
        vbar[hi, j] += _ghost_sign(sides[1]) * big[nx + 1, j]


@njit(cache=True, nogil=True)
def _pad_d(d, big, px, py):
    """big (nx + 2, ny + 2): the density with a ghost ring, zero-gradient or periodic."""
    nx, ny = d.shape
    for i in range(nx):
        for j in range(ny):
            big[i + 1, j + 1] = d[i, j]
    for j in range(1, ny + 1):
        big[0, j] = big[nx, j] if px else big[1, j]
        big[nx + 1, j] = big[1, j] if px else big[nx, j]
    for i in range(nx + 2):
        big[i, 0] = big[i, ny] if py else big[i, 1]
        big[i, ny + 1] = big[i, 1] if py else big[i, ny]


@njit(cache=True, nogil=True)
def _unpad_d(big, dbar, px, py):
    """Adds the transpose of :func:`_pad_d` of ``big`` to ``dbar``; destroys ``big``."""
    nx, ny = dbar.shape
    for i in range(nx + 2):
        big[i, ny if py else 1] += big[i, 0]
        big[i, 1 if py else ny] += big[i, ny + 1]
    for j in range(1, ny + 1):
        big[nx if px else 1, j] += big[0, j]
        big[1 if px else nx, j] += big[nx + 1, j]
    for i in range(nx):
        for j in range(ny):
            dbar[i, j] += big[i + 1, j + 1]


@njit(cache=True, nogil=True)
def _refresh(u, v, ukind, vkind):
    """A periodic side's last face copies its first."""
    nx1, ny = u.shape
    for j in range(ny):
        if ukind[nx1 - 1, j] == COPY:
            u[nx1 - 1, j] = u[0, j]
    nx, ny1 = v.shape
    for i in range(nx):
        if vkind[i, ny1 - 1] == COPY:
            v[i, ny1 - 1] = v[i, 0]


@njit(cache=True, nogil=True)
def _fold(ub, vb, ukind, vkind):
    """Transpose of :func:`_refresh`, in place on the cotangents."""
    nx1, ny = ub.shape
    for j in range(ny):
        if ukind[nx1 - 1, j] == COPY:
            ub[0, j] += ub[nx1 - 1, j]
            ub[nx1 - 1, j] = 0.0
    nx, ny1 = vb.shape
    for i in range(nx):
        if vkind[i, ny1 - 1] == COPY:
            vb[i, 0] += vb[i, ny1 - 1]
            vb[i, ny1 - 1] = 0.0


# ------------------------------------------------------------------ the pressure solve
@njit(cache=True, nogil=True)
def _solve(b, x, w, lp, li, lx, up, ui, ux, udiag, perm_r, perm_c):
    """x = M⁻¹ b from SuperLU's factors Pr M Pc = L U (L unit lower, its diagonal left out; U
    strictly upper with its diagonal ``udiag``), both CSC. ``w`` is scratch."""
    n = b.shape[0]
    for i in range(n):
        w[perm_r[i]] = b[i]
    for j in range(n):
        wj = w[j]
        for k in range(lp[j], lp[j + 1]):
            w[li[k]] -= lx[k] * wj
    for j in range(n - 1, -1, -1):
        w[j] /= udiag[j]
        wj = w[j]
        for k in range(up[j], up[j + 1]):
            w[ui[k]] -= ux[k] * wj
    for i in range(n):
        x[i] = w[perm_c[i]]


# ------------------------------------------------------------------ one step
@njit(cache=True, nogil=True)
def _face_cells(i, n, periodic):
    """The cells (lo, hi) on both sides of face i of an axis of n cells; −1 outside."""
    lo = i - 1
    hi = i
    if lo < 0:
        lo = n - 1 if periodic else -1
    if hi >= n:
        hi = -1
    return lo, hi


@njit(cache=True, nogil=True)
def _begin(src, u, v, d, ukind, vkind, uprof, vprof, fluid, speed, has_d):
    """Step 0: the boundary values. u, v, d: the state's fields (spare entries cut off)."""
    nx1, ny = u.shape
    nx = nx1 - 1
    for i in range(nx1):
        for j in range(ny):
            k = ukind[i, j]
            u[i, j] = src[0, i, j] if k == FREE else speed * uprof[i, j]
    for i in range(nx):
        for j in range(ny + 1):
            k = vkind[i, j]
            v[i, j] = src[1, i, j] if k == FREE else speed * vprof[i, j]
    _refresh(u, v, ukind, vkind)
    if has_d:
        for i in range(nx):
            for j in range(ny):
                d[i, j] = src[2, i, j] if fluid[i, j] else 0.0


# A field's samples sit at (i + ox, j + oy) in cell widths (u: (0, ½), v: (½, 0), the density:
# (½, ½)), and its padded array holds sample (i, j) at index coordinates (i + ox, j + oy) + the
# ghost layer's offset, which for all three fields is (ox, oy) again. The velocity's own sample
# points are faces, so its bilinear samples at these points are a face value or the mean of two
# or four face values: fixed stencils, which the kernels below apply directly.
#: sample points: u faces, v faces, cell centres (the density)
AT_U, AT_V, AT_CELL = 0, 1, 2


@njit(cache=True, nogil=True)
def _velocity(big_u, big_v, i, j, at):
    """The velocity at sample (i, j) of the points ``at``, from the padded components."""
    if at == AT_U:
        return (1.0 * big_u[i, j + 1],
                0.25 * (big_v[i, j] + big_v[i, j + 1] + big_v[i + 1, j] + big_v[i + 1, j + 1]))
    if at == AT_V:
        return (0.25 * (big_u[i, j] + big_u[i + 1, j] + big_u[i, j + 1] + big_u[i + 1, j + 1]),
                1.0 * big_v[i + 1, j])
    return (0.5 * (big_u[i, j + 1] + big_u[i + 1, j + 1]),
            0.5 * (big_v[i + 1, j] + big_v[i + 1, j + 1]))


@njit(cache=True, nogil=True)
def _velocity_adjoint(bu, bv, i, j, at, gx, gy):
    """Transpose of :func:`_velocity`: adds the cotangents (gx, gy) of the velocity at sample
    (i, j) into the padded components' cotangents."""
    if at == AT_U:
        bu[i, j + 1] += gx
        gy = 0.25 * gy
        bv[i, j] += gy
        bv[i, j + 1] += gy
        bv[i + 1, j] += gy
        bv[i + 1, j + 1] += gy
    elif at == AT_V:
        gx = 0.25 * gx
        bu[i, j] += gx
        bu[i + 1, j] += gx
        bu[i, j + 1] += gx
        bu[i + 1, j + 1] += gx
        bv[i + 1, j] += gy
    else:
        gx, gy = 0.5 * gx, 0.5 * gy
        bu[i, j + 1] += gx
        bu[i + 1, j + 1] += gx
        bv[i + 1, j] += gy
        bv[i + 1, j + 1] += gy


@njit(cache=True, nogil=True)
def _advect_field(out, free, big, big_u, big_v, at, ox, oy, c, geo):
    """Semi-Lagrangian: out = the padded field ``big`` at x − c u(x), on the ``free`` samples."""
    for i in range(free.shape[0]):
        for j in range(free.shape[1]):
            if free[i, j]:
                vx, vy = _velocity(big_u, big_v, i, j, at)
                out[i, j] = _sample(big, i + 2 * ox - c * vx, j + 2 * oy - c * vy, geo)


@njit(cache=True, nogil=True)
def _advect_field_adjoint(gout, free, big, bbig, big_u, big_v, bu, bv, at, ox, oy, c, geo, out,
                          keep):
    """Transpose of :func:`_advect_field`: the cotangents ``gout`` of the free samples move
    into ``bbig`` (the field's) and ``bu``, ``bv`` (the velocity's); they become zero. With
    ``keep``, ``out`` receives the advected samples too (what the forward step wrote), which
    the parameters' cotangents need: the same bilinear weights give them at no extra pass."""
    for i in range(free.shape[0]):
        for j in range(free.shape[1]):
            if free[i, j]:
                g = gout[i, j]
                gout[i, j] = 0.0
                vx, vy = _velocity(big_u, big_v, i, j, at)
                value, ax, ay = _sample_adjoint(big, bbig, i + 2 * ox - c * vx,
                                                j + 2 * oy - c * vy, geo, g)
                if keep:
                    out[i, j] = value
                _velocity_adjoint(bu, bv, i, j, at, -c * ax, -c * ay)


@njit(cache=True, nogil=True)
def _bounds(q, a, b, geo):
    """The smallest and largest of the four values around (a, b) and their indices."""
    i, _, _ = _coord(a, q.shape[0], geo[0], geo[1], geo[2])
    j, _, _ = _coord(b, q.shape[1], geo[3], geo[4], geo[5])
    lo, hi = (i, j), (i, j)
    for di in range(2):
        for dj in range(2):
            if q[i + di, j + dj].real < q[lo].real:
                lo = (i + di, j + dj)
            if q[i + di, j + dj].real > q[hi].real:
                hi = (i + di, j + dj)
    return lo, hi


@njit(cache=True, nogil=True)
def _correct_field(out, free, big, big_hat, big_u, big_v, at, ox, oy, c, geo):
    """MacCormack: out = φ̂ + ½ (φ − φ̂(x + c u(x))) on the free samples, clamped to the values
    of φ around the backtraced point x − c u(x). φ, φ̂: the field before and after the
    semi-Lagrangian step, padded (``big``, ``big_hat``)."""
    pi, pj = int(2 * ox), int(2 * oy)
    for i in range(free.shape[0]):
        for j in range(free.shape[1]):
            if free[i, j]:
                vx, vy = _velocity(big_u, big_v, i, j, at)
                back = _sample(big_hat, i + 2 * ox + c * vx, j + 2 * oy + c * vy, geo)
                value = big_hat[i + pi, j + pj] + 0.5 * (big[i + pi, j + pj] - back)
                lo, hi = _bounds(big, i + 2 * ox - c * vx, j + 2 * oy - c * vy, geo)
                if value.real < big[lo].real:
                    value = big[lo]
                elif value.real > big[hi].real:
                    value = big[hi]
                out[i, j] = value


@njit(cache=True, nogil=True)
def _correct_field_adjoint(gout, free, big, big_hat, bbig, bhat, big_u, big_v, bu, bv, at, ox,
                           oy, c, geo):
    """Transpose of :func:`_correct_field`: ``gout`` becomes the cotangent of φ̂ at the free
    samples (zero where the value was clamped); the rest moves into ``bbig`` (φ), ``bhat``
    (φ̂, padded) and ``bu``, ``bv`` (the velocity)."""
    pi, pj = int(2 * ox), int(2 * oy)
    for i in range(free.shape[0]):
        for j in range(free.shape[1]):
            if free[i, j]:
                g = gout[i, j]
                vx, vy = _velocity(big_u, big_v, i, j, at)
                fx, fy = i + 2 * ox + c * vx, j + 2 * oy + c * vy
                value = big_hat[i + pi, j + pj] + 0.5 * (big[i + pi, j + pj]
                                                         - _sample(big_hat, fx, fy, geo))
                lo, hi = _bounds(big, i + 2 * ox - c * vx, j + 2 * oy - c * vy, geo)
                if value.real < big[lo].real:
                    bbig[lo] += g
                    gout[i, j] = 0.0
                elif value.real > big[hi].real:
                    bbig[hi] += g
                    gout[i, j] = 0.0
                else:
                    bbig[i + pi, j + pj] += 0.5 * g
                    _, ax, ay = _sample_adjoint(big_hat, bhat, fx, fy, geo, -0.5 * g)
                    _velocity_adjoint(bu, bv, i, j, at, c * ax, c * ay)


@njit(cache=True, nogil=True)
def _neighbours(i, n, periodic):
    """The faces before and after face i of the n + 1 faces along an axis, as the Laplacian
    reads them: a side's face (i = 0 or n, not periodic) mirrors itself across the side."""
    im = i - 1 if i > 0 else (n - 1 if periodic else i)
    ip = i + 1 if i < n else i
    return im, ip


@njit(cache=True, nogil=True)
def _laplacian_u(big, i, j, px):
    """The 5-point Laplacian (times h²) of u at free face (i, j), from the padded field.
    An outflow face (i = 0 or nx, not periodic) mirrors itself across the side."""
    im, ip = _neighbours(i, big.shape[0] - 1, px)
    return big[im, j + 1] + big[ip, j + 1] + big[i, j] + big[i, j + 2] - 4.0 * big[i, j + 1]


@njit(cache=True, nogil=True)
def _laplacian_u_adjoint(bbig, i, j, px, g):
    """Transpose of :func:`_laplacian_u` times ``g``, added into the padded ``bbig``."""
    im, ip = _neighbours(i, bbig.shape[0] - 1, px)
    bbig[im, j + 1] += g
    bbig[ip, j + 1] += g
    bbig[i, j] += g
    bbig[i, j + 2] += g
    bbig[i, j + 1] -= 4.0 * g


@njit(cache=True, nogil=True)
def _laplacian_v(big, i, j, py):
    """As :func:`_laplacian_u`, for v at free face (i, j)."""
    jm, jp = _neighbours(j, big.shape[1] - 1, py)
    return big[i, j] + big[i + 2, j] + big[i + 1, jm] + big[i + 1, jp] - 4.0 * big[i + 1, j]


@njit(cache=True, nogil=True)
def _laplacian_v_adjoint(bbig, i, j, py, g):
    """Transpose of :func:`_laplacian_v` times ``g``, added into the padded ``bbig``."""
    jm, jp = _neighbours(j, bbig.shape[1] - 1, py)
    bbig[i, j] += g
    bbig[i + 2, j] += g
    bbig[i + 1, jm] += g
    bbig[i + 1, jp] += g
    bbig[i + 1, j] -= 4.0 * g


@njit(cache=True, nogil=True)
def _buoyancy_cells(j, ny, py):
    """The cells below and above v face j (a side's face uses its one cell, or wraps)."""
    lo = j - 1 if j > 0 else (ny - 1 if py else 0)
    hi = j if j < ny else (0 if py else ny - 1)
    return lo, hi


@njit(cache=True, nogil=True)
def _viscous_solve(b, x, w, t, kd, vfac):
    """x = (I − kd A)⁻¹ b, A the Laplacian of the free faces (:func:`velocity_laplacian`), from
    the factors of I − Re(kd) A. An imaginary part of kd (a complex-step perturbation of ν)
    enters by one more solve, x ← (I − Re(kd) A)⁻¹ (b + i Im(kd) A x), whose error is of second
    order in it: exact for the complex step. I − kd A is symmetric, so this is also the
    transposed solve. ``w``, ``t``: scratch."""
    lp, li, lx, up, ui, ux, udiag, perm_r, perm_c, ap, ai, av = vfac
    _solve(b, x, w, lp, li, lx, up, ui, ux, udiag, perm_r, perm_c)
    delta = kd - kd.real
    if delta != 0:
        for r in range(b.shape[0]):
            s = 0.0 * x[r]
            for q in range(ap[r], ap[r + 1]):
                s += av[q] * x[ai[q]]
            t[r] = b[r] + delta * s
        _solve(t, x, w, lp, li, lx, up, ui, ux, udiag, perm_r, perm_c)


@njit(cache=True, nogil=True)
def _inputs(src, u, v, d, big_u, big_v, big_d, ukind, vkind, uprof, vprof, fluid, speed, sides,
            lid, has_d):
    """Step 0 and the padded step inputs (big_u, big_v, big_d)."""
    _begin(src, u, v, d, ukind, vkind, uprof, vprof, fluid, speed, has_d)
    _pad_u(u, big_u, sides, lid)
    _pad_v(v, big_v, sides, lid)
    if has_d:
        _pad_d(d, big_d, sides[0] == PERIODIC, sides[2] == PERIODIC)


@njit(cache=True, nogil=True)
def _advect(u, v, d1, big_u, big_v, big_d, big_uh, big_vh, big_dh, ufree, vfree, fluid, ukind,
            vkind, sides, lid, c, gu, gv, gd, mc, has_d):
    """Step 1: the advected velocity into u, v (whose fixed faces hold the boundary values) and
    the advected density into d1, from the padded inputs; with ``mc``, corrected (MacCormack),
    the semi-Lagrangian results kept padded in big_uh, big_vh, big_dh."""
    _advect_field(u, ufree, big_u, big_u, big_v, AT_U, 0.0, 0.5, c, gu)
    _advect_field(v, vfree, big_v, big_u, big_v, AT_V, 0.5, 0.0, c, gv)
    if has_d:
        _advect_field(d1, fluid, big_d, big_u, big_v, AT_CELL, 0.5, 0.5, c, gd)
    _refresh(u, v, ukind, vkind)
    if mc:
        _pad_u(u, big_uh, sides, lid)
        _pad_v(v, big_vh, sides, lid)
        _correct_field(u, ufree, big_u, big_uh, big_u, big_v, AT_U, 0.0, 0.5, c, gu)
        _correct_field(v, vfree, big_v, big_vh, big_u, big_v, AT_V, 0.5, 0.0, c, gv)
        if has_d:
            _pad_d(d1, big_dh, sides[0] == PERIODIC, sides[2] == PERIODIC)
            _correct_field(d1, fluid, big_d, big_dh, big_u, big_v, AT_CELL, 0.5, 0.5, c, gd)
        _refresh(u, v, ukind, vkind)


@njit(cache=True, nogil=True)
def _viscosity(u, v, big_u1, big_v1, kd, sides, lid, ukind, vkind, implicit, uidx, vidx, vfac,
               big_zu, big_zv, vrhs, vsol, vscratch, vtmp):
    """Step 2 on the free faces of the advected u, v (padded in big_u1, big_v1), Δ_h here the
    Laplacian times h²: explicit, u += kd Δ_h u; implicit (backward Euler), u ← the solution x
    of x − kd Δ_h x = u, whose Laplacian reads the boundary values and lids as the explicit
    one does. ``uidx``, ``vidx``
    number the free faces; big_zu, big_zv, vrhs, vsol, vscratch, vtmp: scratch."""
    nx1, ny = u.shape
    nx = nx1 - 1
    px, py = sides[0] == PERIODIC, sides[2] == PERIODIC
    if not implicit:
        for i in range(nx1):
            for j in range(ny):
                if ukind[i, j] == FREE:
                    u[i, j] += kd * _laplacian_u(big_u1, i, j, px)
        for i in range(nx):
            for j in range(ny + 1):
                if vkind[i, j] == FREE:
                    v[i, j] += kd * _laplacian_v(big_v1, i, j, py)
        return
    # the right-hand side: u plus kd times the Laplacian of the boundary values alone
    for i in range(nx1):
        for j in range(ny):
            if ukind[i, j] == FREE:
                vrhs[uidx[i, j]] = u[i, j]
                u[i, j] = 0.0
    for i in range(nx):
        for j in range(ny + 1):
            if vkind[i, j] == FREE:
                vrhs[vidx[i, j]] = v[i, j]
                v[i, j] = 0.0
    _refresh(u, v, ukind, vkind)
    _pad_u(u, big_zu, sides, lid)
    _pad_v(v, big_zv, sides, lid)
    for i in range(nx1):
        for j in range(ny):
            if ukind[i, j] == FREE:
                vrhs[uidx[i, j]] += kd * _laplacian_u(big_zu, i, j, px)
    for i in range(nx):
        for j in range(ny + 1):
            if vkind[i, j] == FREE:
                vrhs[vidx[i, j]] += kd * _laplacian_v(big_zv, i, j, py)
    _viscous_solve(vrhs, vsol, vscratch, vtmp, kd, vfac)
    for i in range(nx1):
        for j in range(ny):
            if ukind[i, j] == FREE:
                u[i, j] = vsol[uidx[i, j]]
    for i in range(nx):
        for j in range(ny + 1):
            if vkind[i, j] == FREE:
                v[i, j] = vsol[vidx[i, j]]
    _refresh(u, v, ukind, vkind)


@njit(cache=True, nogil=True)
def _forward_step(src, dst, ctrl, k, bi, p, dt, c, kdiff, sides, lid, ukind, vkind, uprof,
                  vprof, fluid, ufree, vfree, cell_index, gu, gv, gd, fac, mc, implicit, uidx,
                  vidx, vfac, work):
    """One step from ``src`` (C, nx + 1, ny + 1) into ``dst`` (see
    :meth:`Incompressible2D._work` for ``work``); ``mc``: MacCormack advection; ``implicit``:
    backward-Euler viscosity with the factors ``vfac``."""
    (u, v, d, big_u, big_v, big_d, big_u1, big_v1, d1, rhs, phi, scratch, big_uh, big_vh,
     big_dh, vrhs, vsol, vscratch, vtmp) = work
    nx1, ny = u.shape
    nx = nx1 - 1
    nu, buoy, speed = p[0], p[1], p[2]
    has_d = src.shape[0] > 2
    px, py = sides[0] == PERIODIC, sides[2] == PERIODIC
    _inputs(src, u, v, d, big_u, big_v, big_d, ukind, vkind, uprof, vprof, fluid, speed, sides,
            lid, has_d)
    _advect(u, v, d1, big_u, big_v, big_d, big_uh, big_vh, big_dh, ufree, vfree, fluid, ukind,
            vkind, sides, lid, c, gu, gv, gd, mc, has_d)
    _pad_u(u, big_u1, sides, lid)
    _pad_v(v, big_v1, sides, lid)
    # the MacCormack scratch (big_uh, big_vh) is free again: the implicit solve's scratch
    _viscosity(u, v, big_u1, big_v1, kdiff * nu, sides, lid, ukind, vkind, implicit, uidx, vidx,
               vfac, big_uh, big_vh, vrhs, vsol, vscratch, vtmp)
    controlled = ctrl.shape[0] > 0
    if controlled or has_d:
        for i in range(nx1):
            for j in range(ny):
                if ukind[i, j] == FREE and controlled:
                    u[i, j] += dt * ctrl[k, bi, 0, i, j]
        for i in range(nx):
            for j in range(ny + 1):
                if vkind[i, j] == FREE:
                    if controlled:
                        v[i, j] += dt * ctrl[k, bi, 1, i, j]
                    if has_d:
                        lo, hi = _buoyancy_cells(j, ny, py)
                        v[i, j] += dt * buoy * 0.5 * (d1[i, lo] + d1[i, hi])
    _refresh(u, v, ukind, vkind)
    # the projection
    for i in range(nx):
        for j in range(ny):
            q = cell_index[i, j]
            if q >= 0:
                rhs[q] = -(u[i + 1, j] - u[i, j] + v[i, j + 1] - v[i, j])
    _solve(rhs, phi, scratch, *fac)
    for i in range(nx1):
        lo, hi = _face_cells(i, nx, px)
        for j in range(ny):
            if ukind[i, j] == FREE:
                a = phi[cell_index[lo, j]] if lo >= 0 else 0.0
                b = phi[cell_index[hi, j]] if hi >= 0 else 0.0
                u[i, j] -= b - a
    for j in range(ny + 1):
        lo, hi = _face_cells(j, ny, py)
        for i in range(nx):
            if vkind[i, j] == FREE:
                a = phi[cell_index[i, lo]] if lo >= 0 else 0.0
                b = phi[cell_index[i, hi]] if hi >= 0 else 0.0
                v[i, j] -= b - a
    _refresh(u, v, ukind, vkind)
    dst[:] = 0.0
    dst[0, :, :ny] = u
    dst[1, :nx, :] = v
    if has_d:
        for i in range(nx):
            for j in range(ny):
                if fluid[i, j]:
                    dst[2, i, j] = d1[i, j] + (dt * ctrl[k, bi, 2, i, j] if controlled else 0.0)


@njit(cache=True, nogil=True)
def ins_forward(states, n, ctrl, p, dt, c, kdiff, sides, lid, ukind, vkind, uprof, vprof, fluid,
                ufree, vfree, cell_index, gu, gv, gd, fac, mc, implicit, uidx, vidx, vfac, work):
    nslot, nbatch = states.shape[0], states.shape[1]
    for bi in range(nbatch):
        for k in range(n):
            _forward_step(states[k % nslot, bi], states[(k + 1) % nslot, bi], ctrl, k, bi, p, dt,
                          c, kdiff, sides, lid, ukind, vkind, uprof, vprof, fluid, ufree, vfree,
                          cell_index, gu, gv, gd, fac, mc, implicit, uidx, vidx, vfac, work)


@njit(cache=True, nogil=True)
def ins_adjoint(states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p, dt, c, kdiff, sides, lid,
                ukind, vkind, uprof, vprof, fluid, ufree, vfree, cell_index, gu, gv, gd, fac, mc,
                implicit, uidx, vidx, vfac, work, bwork):
    m, nbatch = states.shape[0], states.shape[1]
    (u, v, d, big_u, big_v, big_d, big_u1, big_v1, d1, rhs, phi, scratch, big_uh, big_vh,
     big_dh, vrhs, vsol, vscratch, vtmp) = work
    ub, vb, db, bu, bv, bd, phib, buh, bvh, bdh, wu, wv, gvb = bwork
    nx1, ny = u.shape
    nx = nx1 - 1
    nu, buoy, speed = p[0], p[1], p[2]
    has_d = states.shape[2] > 2
    px, py = sides[0] == PERIODIC, sides[2] == PERIODIC
    kd = kdiff * nu
    controlled = cbar.shape[0] > 0
    # Semi-Lagrangian advection is reversed from the step's padded input alone; the advected
    # fields the parameters' cotangents need come out of that reverse pass. MacCormack's
    # correction needs them before it: its step is recomputed.
    keep = want_p and not mc
    for bi in range(nbatch):
        out = ubar[bi]
        for k in range(m - 1, -1, -1):
            _inputs(states[k, bi], u, v, d, big_u, big_v, big_d, ukind, vkind, uprof, vprof,
                    fluid, speed, sides, lid, has_d)
            if mc:
                _advect(u, v, d1, big_u, big_v, big_d, big_uh, big_vh, big_dh, ufree, vfree,
                        fluid, ukind, vkind, sides, lid, c, gu, gv, gd, mc, has_d)
            ub[:] = out[0, :, :ny]
            vb[:] = out[1, :nx, :]
            if has_d:
                for i in range(nx):
                    for j in range(ny):
                        db[i, j] = out[2, i, j] if fluid[i, j] else 0.0
            # the projection: u −= G φ, φ = M⁻¹ (−D u), then the copies
            _fold(ub, vb, ukind, vkind)
            rhs[:] = 0.0
            for i in range(nx1):
                lo, hi = _face_cells(i, nx, px)
                for j in range(ny):
                    if ukind[i, j] == FREE:
                        if lo >= 0:
                            rhs[cell_index[lo, j]] += ub[i, j]
                        if hi >= 0:
                            rhs[cell_index[hi, j]] -= ub[i, j]
            for j in range(ny + 1):
                lo, hi = _face_cells(j, ny, py)
                for i in range(nx):
                    if vkind[i, j] == FREE:
                        if lo >= 0:
                            rhs[cell_index[i, lo]] += vb[i, j]
                        if hi >= 0:
                            rhs[cell_index[i, hi]] -= vb[i, j]
            _solve(rhs, phib, scratch, *fac)
            for i in range(nx):
                for j in range(ny):
                    q = cell_index[i, j]
                    if q >= 0:
                        y = phib[q]
                        ub[i + 1, j] -= y
                        ub[i, j] += y
                        vb[i, j + 1] -= y
                        vb[i, j] += y
            # the forces and the buoyancy
            _fold(ub, vb, ukind, vkind)
            if controlled and has_d:
                for i in range(nx):
                    for j in range(ny):
                        if fluid[i, j]:
                            cbar[k, bi, 2, i, j] = dt * db[i, j]
            if controlled:
                for i in range(nx1):
                    for j in range(ny):
                        if ukind[i, j] == FREE:
                            cbar[k, bi, 0, i, j] = dt * ub[i, j]
            for i in range(nx):
                for j in range(ny + 1):
                    if vkind[i, j] == FREE:
                        g = vb[i, j]
                        if controlled:
                            cbar[k, bi, 1, i, j] = dt * g
                        if has_d:
                            gvb[i, j] = g
                            lo, hi = _buoyancy_cells(j, ny, py)
                            db[i, lo] += dt * buoy * 0.5 * g
                            db[i, hi] += dt * buoy * 0.5 * g
            # the viscosity: ū += kd Δ_hᵀ w, w = ū (explicit) or (I − kd A)⁻¹ ū (implicit)
            for i in range(nx1):
                for j in range(ny):
                    if ukind[i, j] == FREE:
                        wu[i, j] = ub[i, j]
            for i in range(nx):
                for j in range(ny + 1):
                    if vkind[i, j] == FREE:
                        wv[i, j] = vb[i, j]
            if implicit:
                for i in range(nx1):
                    for j in range(ny):
                        if ukind[i, j] == FREE:
                            vrhs[uidx[i, j]] = wu[i, j]
                for i in range(nx):
                    for j in range(ny + 1):
                        if vkind[i, j] == FREE:
                            vrhs[vidx[i, j]] = wv[i, j]
                _viscous_solve(vrhs, vsol, vscratch, vtmp, kd, vfac)
                for i in range(nx1):
                    for j in range(ny):
                        if ukind[i, j] == FREE:
                            wu[i, j] = vsol[uidx[i, j]]
                for i in range(nx):
                    for j in range(ny + 1):
                        if vkind[i, j] == FREE:
                            wv[i, j] = vsol[vidx[i, j]]
            bu[:] = 0.0
            bv[:] = 0.0
            for i in range(nx1):
                for j in range(ny):
                    if ukind[i, j] == FREE:
                        _laplacian_u_adjoint(bu, i, j, px, kd * wu[i, j])
            for i in range(nx):
                for j in range(ny + 1):
                    if vkind[i, j] == FREE:
                        _laplacian_v_adjoint(bv, i, j, py, kd * wv[i, j])
            _unpad_u(bu, ub, sides)
            _unpad_v(bv, vb, sides)
            # the advection
            _fold(ub, vb, ukind, vkind)
            bu[:] = 0.0
            bv[:] = 0.0
            bd[:] = 0.0
            if mc:
                buh[:] = 0.0
                bvh[:] = 0.0
                bdh[:] = 0.0
                _correct_field_adjoint(ub, ufree, big_u, big_uh, bu, buh, big_u, big_v, bu, bv,
                                       AT_U, 0.0, 0.5, c, gu)
                _correct_field_adjoint(vb, vfree, big_v, big_vh, bv, bvh, big_u, big_v, bu, bv,
                                       AT_V, 0.5, 0.0, c, gv)
                if has_d:
                    _correct_field_adjoint(db, fluid, big_d, big_dh, bd, bdh, big_u, big_v, bu,
                                           bv, AT_CELL, 0.5, 0.5, c, gd)
                    _unpad_d(bdh, db, px, py)
                _unpad_u(buh, ub, sides)
                _unpad_v(bvh, vb, sides)
                _fold(ub, vb, ukind, vkind)
            _advect_field_adjoint(ub, ufree, big_u, bu, big_u, big_v, bu, bv, AT_U, 0.0, 0.5, c,
                                  gu, u, keep)
            _advect_field_adjoint(vb, vfree, big_v, bv, big_u, big_v, bu, bv, AT_V, 0.5, 0.0, c,
                                  gv, v, keep)
            if has_d:
                _advect_field_adjoint(db, fluid, big_d, bd, big_u, big_v, bu, bv, AT_CELL, 0.5,
                                      0.5, c, gd, d1, keep)
            _unpad_u(bu, ub, sides)
            _unpad_v(bv, vb, sides)
            if has_d:
                _unpad_d(bd, db, px, py)
            # the parameters' terms, now that the advected fields are at hand:
            # ν: kdiff ⟨w, Δ_h u⟩ over the free faces, u the velocity the Laplacian acted on (the
            # advected one; implicit: the viscous step's solution); the buoyancy:
            # Δt ⟨ū_v, ρ̄⟩ with ū_v the cotangent of the forces
            if want_p:
                if keep:
                    _refresh(u, v, ukind, vkind)
                if implicit:
                    _viscosity(u, v, big_u1, big_v1, kd, sides, lid, ukind, vkind, implicit,
                               uidx, vidx, vfac, big_uh, big_vh, vrhs, vsol, vscratch, vtmp)
                _pad_u(u, big_u1, sides, lid)
                _pad_v(v, big_v1, sides, lid)
                s = 0.0 * kd
                for i in range(nx1):
                    for j in range(ny):
                        if ukind[i, j] == FREE:
                            s += wu[i, j] * _laplacian_u(big_u1, i, j, px)
                for i in range(nx):
                    for j in range(ny + 1):
                        if vkind[i, j] == FREE:
                            s += wv[i, j] * _laplacian_v(big_v1, i, j, py)
                            if has_d:
                                lo, hi = _buoyancy_cells(j, ny, py)
                                pbar[1] += dt * gvb[i, j] * 0.5 * (d1[i, lo] + d1[i, hi])
                pbar[0] += kdiff * s
            # the boundary values
            _fold(ub, vb, ukind, vkind)
            out[:] = 0.0
            for i in range(nx1):
                for j in range(ny):
                    if ukind[i, j] == FREE:
                        out[0, i, j] = ub[i, j]
                    elif want_p and ukind[i, j] == FIXED:
                        pbar[2] += ub[i, j] * uprof[i, j]
            for i in range(nx):
                for j in range(ny + 1):
                    if vkind[i, j] == FREE:
                        out[1, i, j] = vb[i, j]
                    elif want_p and vkind[i, j] == FIXED:
                        pbar[2] += vb[i, j] * vprof[i, j]
            if has_d:
                for i in range(nx):
                    for j in range(ny):
                        if fluid[i, j]:
                            out[2, i, j] = db[i, j]
            if cmap[k] >= 0:
                out += cot[cmap[k], bi]


# ------------------------------------------------------------------ geometry
def cylinder(nx: int, ny: int, center: tuple[float, float], radius: float) -> np.ndarray:
    """Solid-cell mask (nx, ny) of a disc: the cells whose centres lie within ``radius`` of
    ``center``, all in cell widths from the lower left corner."""
    x = np.arange(nx)[:, None] + 0.5 - center[0]
    y = np.arange(ny)[None, :] + 0.5 - center[1]
    return x**2 + y**2 <= radius**2


class _Geometry:
    """Face kinds, inflow profiles, fluid cells and the factorised pressure matrix of a scene;
    raises :class:`UserError` for a geometry that cannot be projected."""

    def __init__(self, name: str, nx: int, ny: int, sides: tuple[int, ...], solid: np.ndarray,
                 profile: str):
        self.fluid = ~solid
        if not self.fluid.any():
            raise UserError(f"{name}: the obstacle covers every cell; leave at least one fluid "
                            "cell")
        px, py = sides[0] == PERIODIC, sides[2] == PERIODIC
        ukind = np.zeros((nx + 1, ny), dtype=np.int8)
        vkind = np.zeros((nx, ny + 1), dtype=np.int8)
        uprof = np.zeros((nx + 1, ny))
        vprof = np.zeros((nx, ny + 1))
        shape_x = _profile(profile, ny)
        shape_y = _profile(profile, nx)
        for i in range(nx + 1):
            lo, hi = _face_cells(i, nx, px)
            for j in range(ny):
                ukind[i, j], uprof[i, j] = _face_kind(
                    name, i, nx, self.fluid[lo, j] if lo >= 0 else None,
                    self.fluid[hi, j] if hi >= 0 else None, sides[0], sides[1], shape_x[j],
                    "left" if i == 0 else "right")
        for j in range(ny + 1):
            lo, hi = _face_cells(j, ny, py)
            for i in range(nx):
                vkind[i, j], vprof[i, j] = _face_kind(
                    name, j, ny, self.fluid[i, lo] if lo >= 0 else None,
                    self.fluid[i, hi] if hi >= 0 else None, sides[2], sides[3], shape_y[i],
                    "bottom" if j == 0 else "top")
        self.ukind, self.vkind, self.uprof, self.vprof = ukind, vkind, uprof, vprof
        self.ufree, self.vfree = ukind == FREE, vkind == FREE
        self.cell_index = np.full((nx, ny), -1, dtype=np.int64)
        self.cell_index[self.fluid] = np.arange(int(self.fluid.sum()))
        # the free faces, numbered u's first: the unknowns of an implicit viscous step
        nu_free = int(self.ufree.sum())
        self.uidx = np.full((nx + 1, ny), -1, dtype=np.int64)
        self.uidx[self.ufree] = np.arange(nu_free)
        self.vidx = np.full((nx, ny + 1), -1, dtype=np.int64)
        self.vidx[self.vfree] = nu_free + np.arange(int(self.vfree.sum()))
        self.sides = sides
        self.matrix, self.factors = self._factorise(name, nx, ny, px, py)

    def velocity_laplacian(self) -> sp.csr_matrix:
        """A: the 5-point Laplacian (times h²) of the velocity on its free faces (numbered by
        ``uidx``, ``vidx``) as the kernels apply it, ghost layers, periodic copies and outflow
        mirrors included, with every fixed face and lid speed zero: the explicit viscous step
        adds kd (A u + b), b the part the boundary values and lids contribute. Symmetric."""
        nx, ny = self.ukind.shape[0] - 1, self.ukind.shape[1]
        sides = self.sides
        px, py = sides[0] == PERIODIC, sides[2] == PERIODIC
        rows, cols, vals = [], [], []

        def u_face(a, b):  # padded u entry (a, b): its face's unknown and sign, or None
            if b == 0:
                j, sign = (ny - 1 if py else 0), _ghost_sign(sides[2])
            elif b == ny + 1:
                j, sign = (0 if py else ny - 1), _ghost_sign(sides[3])
            else:
                j, sign = b - 1, 1.0
            i = 0 if self.ukind[a, j] == COPY else a
            return (self.uidx[i, j], sign) if self.ukind[i, j] == FREE else None

        def v_face(a, b):  # padded v entry (a, b)
            if a == 0:
                i, sign = (nx - 1 if px else 0), _ghost_sign(sides[0])
            elif a == nx + 1:
                i, sign = (0 if px else nx - 1), _ghost_sign(sides[1])
            else:
                i, sign = a - 1, 1.0
            j = 0 if self.vkind[i, b] == COPY else b
            return (self.vidx[i, j], sign) if self.vkind[i, j] == FREE else None

        def add(row, entries):
            for entry, weight in entries:
                if entry is not None:
                    rows.append(row)
                    cols.append(entry[0])
                    vals.append(weight * entry[1])

        for i, j in np.argwhere(self.ufree):
            im, ip = _neighbours(i, nx, px)
            add(self.uidx[i, j], [(u_face(im, j + 1), 1.0), (u_face(ip, j + 1), 1.0),
                                  (u_face(i, j), 1.0), (u_face(i, j + 2), 1.0),
                                  (u_face(i, j + 1), -4.0)])
        for i, j in np.argwhere(self.vfree):
            jm, jp = _neighbours(j, ny, py)
            add(self.vidx[i, j], [(v_face(i, j), 1.0), (v_face(i + 2, j), 1.0),
                                  (v_face(i + 1, jm), 1.0), (v_face(i + 1, jp), 1.0),
                                  (v_face(i + 1, j), -4.0)])
        n = int(self.ufree.sum() + self.vfree.sum())
        return sp.csr_matrix((vals, (rows, cols)), shape=(n, n))

    def _factorise(self, name, nx, ny, px, py):
        """M = −D G on the fluid cells, pinned once in each region without an outflow."""
        ci, n = self.cell_index, int(self.fluid.sum())
        rows, cols, diag = [], [], np.zeros(n)
        dirichlet = np.zeros(n, dtype=bool)
        influx = np.zeros(n)

        def link(kind, a, b, prof):
            # a face between cell a (below/left) and cell b (above/right), either may be -1;
            # a fixed face carries prof (per unit inflow speed) from a into b
            if kind != FREE:
                if a >= 0:
                    influx[a] -= prof
                if b >= 0:
                    influx[b] += prof
                return
            for q in (a, b):
                if q >= 0:
                    diag[q] += 1.0
            if a >= 0 and b >= 0:
                rows.extend((a, b))
                cols.extend((b, a))
            else:
                dirichlet[a if a >= 0 else b] = True

        for i in range(nx + 1):
            lo, hi = _face_cells(i, nx, px)
            for j in range(ny):
                if self.ukind[i, j] != COPY:
                    link(self.ukind[i, j], ci[lo, j] if lo >= 0 else -1,
                         ci[hi, j] if hi >= 0 else -1, self.uprof[i, j])
        for j in range(ny + 1):
            lo, hi = _face_cells(j, ny, py)
            for i in range(nx):
                if self.vkind[i, j] != COPY:
                    link(self.vkind[i, j], ci[i, lo] if lo >= 0 else -1,
                         ci[i, hi] if hi >= 0 else -1, self.vprof[i, j])
        adjacency = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
        count, label = connected_components(adjacency, directed=False)
        for region in range(count):
            cells = np.nonzero(label == region)[0]
            if dirichlet[cells].any():
                continue
            net = influx[cells].sum()
            if abs(net) > 1e-9 * max(1.0, np.abs(influx[cells]).sum()):
                raise UserError(
                    f"{name}: the inflow puts a net flux of {net:.6g} (per unit inflow_speed, "
                    "in cell widths) into a region of fluid with no outflow, which cannot stay "
                    "incompressible; give that region an outflow side, or make the inflow a wall")
            diag[cells[0]] += 1.0
        matrix = (sp.csc_matrix((-np.ones(len(rows)), (rows, cols)), shape=(n, n))
                  + sp.diags(diag)).tocsc()
        return matrix, _lu_factors(matrix)


def _lu_factors(matrix: sp.spmatrix) -> tuple[np.ndarray, ...]:
    """The factors :func:`_solve` takes, of a symmetric positive definite ``matrix``: a
    symmetric minimum-degree ordering without pivoting (half the fill of the default column
    ordering on a 2n × n channel)."""
    lu = splu(sp.csc_matrix(matrix), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
              options={"SymmetricMode": True})
    lower, upper = lu.L.tocsc(), lu.U.tocsc()
    lower.sort_indices()
    upper.sort_indices()
    lstrict = sp.tril(lower, -1).tocsc()
    ustrict = sp.triu(upper, 1).tocsc()
    return (lstrict.indptr.astype(np.int64), lstrict.indices.astype(np.int64),
            lstrict.data, ustrict.indptr.astype(np.int64),
            ustrict.indices.astype(np.int64), ustrict.data, upper.diagonal().copy(),
            lu.perm_r.astype(np.int64), lu.perm_c.astype(np.int64))


def _no_factors() -> tuple[np.ndarray, ...]:
    """Factors and a matrix of no unknowns, typed as the implicit viscous step's: the explicit
    step's kernels take them and read nothing."""
    indptr, index, values = np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros(0)
    return (indptr, index, values, indptr, index, values, values, index, index, indptr, index,
            values)


def _profile(profile: str, n: int) -> np.ndarray:
    """Inflow profile across a side of n faces, of mean 1 (the flux is inflow_speed times the
    side's length): 1, or the parabola s (1 − s) at the face centres s, scaled."""
    if profile == "uniform":
        return np.ones(n)
    s = (np.arange(n) + 0.5) / n
    return s * (1.0 - s) / np.mean(s * (1.0 - s))


def _face_kind(name, i, n, fluid_lo, fluid_hi, side_lo, side_hi, prof, where):
    """Kind and inflow value (per unit speed, positive along the axis) of face i of n."""
    if 0 < i < n:
        return (FREE if fluid_lo and fluid_hi else FIXED), 0.0
    side = side_lo if i == 0 else side_hi
    cell = fluid_hi if i == 0 else fluid_lo
    if side == PERIODIC:
        if i == n:
            return COPY, 0.0
        return (FREE if fluid_lo and fluid_hi else FIXED), 0.0
    if side == OUTFLOW:
        return (FREE if cell else FIXED), 0.0
    if side == INFLOW:
        if not cell and prof != 0.0:
            raise UserError(f"{name}: an obstacle covers the {where} inflow; move the obstacle "
                            "off the inflow side or make that side a wall")
        return FIXED, prof if i == 0 else -prof
    return FIXED, 0.0


# ------------------------------------------------------------------ the stepper
@register
class Incompressible2D(Stepper):
    """Incompressible Navier–Stokes on a staggered grid with walls, lids, inflow, outflow,
    periodic sides and obstacles: semi-Lagrangian advection (or MacCormack), explicit or
    implicit viscosity, an optional smoke density with Boussinesq buoyancy and an exact pressure
    projection (factorised once); parameters ``nu``, ``buoyancy`` (with density),
    ``inflow_speed`` (with an inflow side)."""

    name = "incompressible2d-sl"
    point_cost = 40.0
    # Semi-Lagrangian interpolation switches cells as a backtrace moves: the checker's
    # differences start from a 3 % change so that their largest steps rarely cross a switch.
    check_perturbation = 0.03
    space = {
        "nx": Choice((3, 5, 8)),
        "ny": Choice((3, 4, 6)),
        "boundaries": Choice((
            "inflow outflow wall wall", "wall wall wall lid", "periodic periodic slip slip",
            "periodic periodic periodic periodic", "outflow inflow slip lid",
            "wall slip inflow outflow", "periodic periodic inflow outflow",
        )),
        "profile": Choice(PROFILES),
        "obstacle": Choice((None, "box")),
        "density": Choice((False, True)),
        "viscosity": Choice(VISCOSITIES),
        "nu": Range(0.005, 0.05),
        "buoyancy": Range(-1.0, 1.0),
        "inflow_speed": Range(0.5, 1.5),
        "dt": Range(0.01, 0.05),
    }

    def __init__(
        self,
        nx: int = 32,
        ny: int = 32,
        length: float = 1.0,
        dt: float = 0.01,
        nu: float = 0.01,
        boundaries: str = "wall wall wall lid",
        lid_speed: float = 1.0,
        inflow_speed: float = 1.0,
        profile: str = "uniform",
        obstacle: np.ndarray | str | None = None,
        density: bool = False,
        buoyancy: float = 0.0,
        advection: str = "semi-lagrangian",
        viscosity: str = "explicit",
    ):
        name = self.name
        nx = validate.integer(name, "nx", nx, ge=1, why="cells along x")
        ny = validate.integer(name, "ny", ny, ge=1, why="cells along y")
        self.nx, self.ny = nx, ny
        self.length = validate.number(name, "length", length, gt=0, why="the box's x extent")
        self.h = self.length / nx
        self.dt = validate.number(name, "dt", dt, gt=0)
        self.lid_speed = validate.number(name, "lid_speed", lid_speed)
        nu = validate.number(name, "nu", nu, ge=0, why="the kinematic viscosity")
        inflow_speed = validate.number(name, "inflow_speed", inflow_speed)
        buoyancy = validate.number(name, "buoyancy", buoyancy)
        self.density = validate.flag(name, "density", density)
        self.profile = validate.choice(name, "profile", profile, PROFILES)
        self.advection = validate.choice(name, "advection", advection, ADVECTIONS)
        self.viscosity = validate.choice(name, "viscosity", viscosity, VISCOSITIES)
        self.boundaries = self._sides(boundaries)
        self.sides = np.array([SIDES.index(s) for s in self.boundaries], dtype=np.int64)
        # a lid moves along its side: bottom/top lids move in +x, left/right lids in +y
        self.lid = np.array([self.lid_speed if s == "lid" else 0.0 for s in self.boundaries])
        if abs(self.lid_speed) * self.dt / self.h > MAX_COURANT and "lid" in self.boundaries:
            raise ValueError(
                f"{name}: dt = {self.dt:g} is beyond the advective limit for the lid: "
                f"dt ≤ h/|lid_speed| = {MAX_COURANT * self.h / abs(self.lid_speed):.6g} "
                "(Courant number 1: the semi-Lagrangian backtrace may cross one cell at most)")
        solid = self._obstacle(obstacle)
        self.solid = solid
        self.geometry = _Geometry(name, nx, ny, tuple(self.sides), solid, self.profile)
        self._fluid_cells = int(self.geometry.fluid.sum())
        self.has_inflow = "inflow" in self.boundaries
        self._peak_profile = float(max(np.abs(self.geometry.uprof).max(),
                                       np.abs(self.geometry.vprof).max()))
        self.grid_shape = (nx + 1, ny + 1)
        self.channels = 3 if self.density else 2
        self.control_shape = (self.channels, nx + 1, ny + 1)
        names, values = ["nu"], [nu]
        if self.density:
            names.append("buoyancy")
            values.append(buoyancy)
        if self.has_inflow:
            names.append("inflow_speed")
            values.append(inflow_speed)
        self.param_names, self.param_values = tuple(names), tuple(values)
        self.check_params(np.array(values))
        if self.viscosity == "implicit":
            self._laplacian = self.geometry.velocity_laplacian()
            self._viscous_factors(nu)
        px, py = self.sides[0] == PERIODIC, self.sides[2] == PERIODIC
        self._geo_u = np.array([0.0, nx, px, 1.0, ny, py])
        self._geo_v = np.array([1.0, nx, px, 0.0, ny, py])
        self._geo_d = np.array([1.0, nx, px, 1.0, ny, py])

    def _sides(self, boundaries: Any) -> tuple[str, ...]:
        name = self.name
        if not isinstance(boundaries, str):
            raise TypeError(f"{name}: boundaries must be a string of four side kinds (left "
                            f"right bottom top), got {type(boundaries).__name__}")
        sides = tuple(boundaries.split())
        bad = [s for s in sides if s not in SIDES]
        if len(sides) != 4 or bad:
            raise ValueError(
                f"{name}: boundaries must name four sides (left right bottom top), each one of "
                f"{', '.join(SIDES)}; got {boundaries!r}")
        for a, b, axis in ((0, 1, "left and right"), (2, 3, "bottom and top")):
            if (sides[a] == "periodic") != (sides[b] == "periodic"):
                raise ValueError(f"{name}: boundaries: periodic sides come in pairs; make both "
                                 f"{axis} periodic or neither (got {boundaries!r})")
        return sides

    def _obstacle(self, obstacle: Any) -> np.ndarray:
        nx, ny, name = self.nx, self.ny, self.name
        if obstacle is None:
            return np.zeros((nx, ny), dtype=bool)
        if isinstance(obstacle, str):
            kind = validate.choice(name, "obstacle", obstacle, OBSTACLES)
            if kind == "cylinder":  # the wake scene's disc: a quarter of the height across
                return cylinder(nx, ny, (ny / 2, ny / 2), ny / 8)
            solid = np.zeros((nx, ny), dtype=bool)  # a box over the middle third
            x0, y0 = max(1, nx // 3), max(1, ny // 3)
            solid[x0: max(x0 + 1, 2 * nx // 3), y0: max(y0 + 1, 2 * ny // 3)] = True
            return solid
        mask = np.asarray(obstacle)
        if mask.dtype != bool or mask.shape != (nx, ny):
            raise ValueError(f"{name}: obstacle must be None, one of {', '.join(OBSTACLES)} or a "
                             f"boolean mask of shape ({nx}, {ny}) (True: solid cell), got "
                             f"{mask.dtype} of shape {mask.shape}")
        return mask.copy()

    @classmethod
    def default(cls) -> Incompressible2D:
        return cls(nx=8, ny=6, dt=0.02, nu=0.02, boundaries="inflow outflow wall wall",
                   profile="parabolic", obstacle="box", density=True, buoyancy=0.5)

    @classmethod
    def benchmark_scene(cls, n: int, viscosity: str = "explicit") -> Incompressible2D:
        """The wake behind a cylinder in a channel of 2n × n cells, with smoke."""
        n = validate.integer(cls.name, "n", n, ge=4)
        return cls(nx=2 * n, ny=n, length=2.0, dt=0.5 / n, nu=0.001,
                   boundaries="inflow outflow slip slip", obstacle="cylinder", density=True,
                   buoyancy=0.1, viscosity=viscosity)

    def check_params(self, p: np.ndarray) -> None:
        nu = validate.number(self.name, "nu", p[0], ge=0, why="the kinematic viscosity")
        if self.viscosity == "explicit" and nu * self.dt / self.h**2 > MAX_DIFFUSION:
            raise ValueError(
                f"{self.name}: dt = {self.dt:g} with nu = {nu:g} is beyond the explicit "
                f"viscosity's stability limit: dt ≤ h²/(4 nu) = "
                f"{MAX_DIFFUSION * self.h**2 / nu:.6g} (h = {self.h:g}); or "
                "viscosity=\"implicit\", which has no such limit")
        if self.has_inflow:
            speed = abs(float(p[-1])) * self._peak_profile
            if speed * self.dt / self.h > MAX_COURANT:
                raise ValueError(
                    f"{self.name}: dt = {self.dt:g} is beyond the advective limit for the "
                    f"inflow: dt ≤ h/(peak inflow speed) = {MAX_COURANT * self.h / speed:.6g} "
                    "(Courant number 1: the semi-Lagrangian backtrace may cross one cell at "
                    "most)")

    def courant_number(self, u: np.ndarray) -> float:
        """The largest Courant number (speed · Δt / h) of a batch of states (B, C, nx + 1,
        ny + 1): above 1 a backtrace crosses more than one cell and may jump a solid one cell
        thick (see the module's notes on limits; the solver does not refuse such states)."""
        u = np.asarray(u)
        if not u.shape[0]:
            return 0.0
        top = max(np.abs(u[:, 0, :, : self.ny]).max(), np.abs(u[:, 1, : self.nx]).max())
        return float(top) * self.dt / self.h

    def random_state(
        self, rng: np.random.Generator, batch: int = 1, dtype: Any = np.float64
    ) -> np.ndarray:
        """Velocities uniform in ± min(1, ½ h/Δt) and (with density) a density in [0, 1]; the
        spare entries zero."""
        u = np.zeros(self.state_shape(batch))
        top = min(1.0, 0.5 * MAX_COURANT * self.h / self.dt)
        u[:, 0, :, : self.ny] = rng.uniform(-top, top, (batch, self.nx + 1, self.ny))
        u[:, 1, : self.nx, :] = rng.uniform(-top, top, (batch, self.nx, self.ny + 1))
        if self.density:
            u[:, 2, : self.nx, : self.ny] = rng.uniform(0.0, 1.0, (batch, self.nx, self.ny))
        return u.astype(dtype)

    def divergence(self, u: np.ndarray) -> np.ndarray:
        """The discrete divergence (B, nx, ny) of states u (B, C, nx + 1, ny + 1), in 1/time,
        on the fluid cells (zero in solid cells)."""
        u = np.asarray(u)
        nx, ny = self.nx, self.ny
        div = (np.diff(u[:, 0, :, :ny], axis=1) + np.diff(u[:, 1, :nx, :], axis=2)) / self.h
        return np.where(self.geometry.fluid, div, 0.0)

    def solve_pressure(self, rhs: np.ndarray) -> np.ndarray:
        """M⁻¹ rhs (one value per fluid cell, in the order of ``geometry.cell_index``): the
        solve the projection and its adjoint run, with the scene's factors."""
        rhs = np.ascontiguousarray(rhs, dtype=np.float64)
        x, scratch = np.zeros_like(rhs), np.zeros_like(rhs)
        _solve(rhs, x, scratch, *self.geometry.factors)
        return x

    # ---------------------------------------------------------------- kernels
    def _kernel_args(self, dtype: np.dtype, p: np.ndarray) -> tuple:
        """The kernels' arguments after the state cotangents: the parameters (ν, b, inflow
        speed; zero where the scene has none), then the scene's constants in the state's real
        dtype (cached per dtype: a controller steps the scene once per call)."""
        full = np.zeros(3, dtype=p.dtype)
        full[0] = p[0]
        if self.density:
            full[1] = p[1]
        if self.has_inflow:
            full[2] = p[-1]
        cache = self.__dict__.setdefault("_constants", {})
        constants = cache.get(dtype)
        if constants is None:
            g = self.geometry
            real = np.dtype(np.float64) if dtype.kind == "c" else dtype
            constants = cache[dtype] = (
                real.type(self.dt), real.type(self.dt / self.h), real.type(self.dt / self.h**2),
                self.sides, self.lid.astype(real), g.ukind, g.vkind, g.uprof.astype(real),
                g.vprof.astype(real), g.fluid, g.ufree, g.vfree, g.cell_index, self._geo_u,
                self._geo_v, self._geo_d, g.factors, self.advection == "maccormack",
                self.viscosity == "implicit", g.uidx, g.vidx)
        if self.viscosity == "implicit":
            vfac = self._viscous_factors(float(np.real(p[0])))
        else:
            vfac = _no_factors()
        return (full, *constants, vfac)

    def _viscous_factors(self, nu: float) -> tuple[np.ndarray, ...]:
        """The implicit viscous step's factors of I − kd A (kd = ν Δt/h², A the Laplacian of
        the free faces) and A's CSR arrays: factorised on construction and again when a call
        brings another ν (the last one is kept)."""
        cached = self.__dict__.get("_viscous")
        if cached is not None and cached[0] == nu:
            return cached[1]
        a = self._laplacian
        if a.shape[0] == 0:  # no free face: nothing to solve
            factors = _no_factors()
        else:
            kd = self.dt / self.h**2 * nu
            factors = (*_lu_factors(sp.identity(a.shape[0]) - kd * a),
                       a.indptr.astype(np.int64), a.indices.astype(np.int64),
                       a.data.astype(np.float64))
        self._viscous = (nu, factors)
        return factors

    def _work(self, dtype: np.dtype, adjoint: bool = False) -> tuple:
        """The forward step's fields: u, v, ρ; their padded step inputs; u, v padded after the
        advection, the advected ρ; the pressure solve's right-hand side, solution and scratch;
        the padded semi-Lagrangian results (MacCormack; the implicit viscous step's scratch
        after the advection); the implicit viscous step's right-hand side, solution and two
        scratch vectors (empty when explicit). With ``adjoint``, also the reverse step's
        cotangents: of u, v, ρ, of the padded u, v, ρ, of the pressure and of the padded
        semi-Lagrangian results; the viscous step's weights for u and v and the cotangent of
        the forces on v. All zero."""
        nx, ny = self.nx, self.ny
        solve = np.result_type(dtype, np.float64)

        def fields():
            return (np.zeros((nx + 1, ny), dtype), np.zeros((nx, ny + 1), dtype),
                    np.zeros((nx, ny), dtype))

        def padded():
            return (np.zeros((nx + 1, ny + 2), dtype), np.zeros((nx + 2, ny + 1), dtype),
                    np.zeros((nx + 2, ny + 2), dtype))

        def pressure():
            return np.zeros(self._fluid_cells, solve)

        free = int(self.geometry.ufree.sum() + self.geometry.vfree.sum())
        viscous = [np.zeros(free if self.viscosity == "implicit" else 0, solve)
                   for _ in range(4)]
        work = (*fields(), *padded(), *padded()[:2], np.zeros((nx, ny), dtype), pressure(),
                pressure(), pressure(), *padded(), *viscous)
        if not adjoint:
            return work
        return work, (*fields(), *padded(), pressure(), *padded(), *fields()[:2],
                      np.zeros((nx, ny + 1), dtype))

    def _forward(self, states, n, ctrl, p):
        ins_forward(states, n, ctrl, *self._kernel_args(states.dtype, p),
                    self._work(states.dtype))

    def _adjoint(self, states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p):
        full = np.zeros(3)
        pfull, *args = self._kernel_args(ubar.dtype, p)
        ins_adjoint(states, ctrl, pfull, cot, cmap, ubar, cbar, full, want_p, *args,
                    *self._work(ubar.dtype, adjoint=True))
        if want_p:
            pbar[0] += full[0]
            if self.density:
                pbar[1] += full[1]
            if self.has_inflow:
                pbar[-1] += full[2]

