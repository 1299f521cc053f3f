"""Half-inverse gradients (HIG) and Gauss–Newton for networks trained through a solver.

Schnell, Holl & Thuerey, "Half-Inverse Gradients for Physical Deep Learning" (ICLR 2022). A
network f(x; θ) feeds a differentiable physics map y = P(f; c) (c: per-sample context, e.g. the
initial state) and a per-sample loss L(y, y*). For a batch of b samples, J = ∂y/∂θ stacks the
per-sample Jacobians row-wise, sample-major, into a (b·d_y) × |θ| matrix (columns: the
parameters in ``model.parameters()`` order), and g = ∂(Σ L / b)/∂y is stacked the same way.
With the thin SVD J = U Σ Vᵀ the update is

    Δθ = −η V Σ^(−κ) Uᵀ g,   singular values σ ≤ τ σ_max dropped (not clamped),

κ = ½ for HIG and κ = 1 for Gauss–Newton (the truncated pseudo-inverse), applied as plain SGD.

How J is formed. J = (∂P/∂f)(∂f/∂θ), and both factors are taken in **reverse mode**, one row per
output component of each sample: the physics factor by one call of the solver's hand-written
adjoint on a batch of b·d_y replicated rollouts whose cotangents are the unit vectors of y
(:class:`SolverPhysics`); then each of those rows, a cotangent of f, is pulled back through the
network by per-sample VJPs (``torch.func.vmap`` over ``torch.func.vjp``), which yields the rows
of J directly and never forms the b·d_f × |θ| network Jacobian. Forward mode would need one
tangent per control, b·d_f in all, for both factors. Rows per update, reverse vs forward:
oscillators b·d_y = 128·4 = 512 vs b·d_f = 128·96 = 12288 (24× fewer); quantum dipole
16·28 = 448 vs 16·384 = 6144 (14×); linear chain 32·4 = 128 vs 32·24 = 768 (6×); Poisson
64 vs 64 per sample (a tie; its physics, the 5-point Laplacian, is a plain torch function and
its Jacobian comes from ``torch.func.jacrev``, :class:`TorchPhysics`). Every problem here has
d_y ≤ d_f, so reverse mode is the one implemented.

Without J. When every parameter sits in an ``nn.Linear`` layer applied once per sample (all
the networks here), the Gram route never forms J: row (s, i) of J restricted to a layer is
δ ⊗ [h, 1] (δ: the row's cotangent at the layer's output, from one batched backward over the
b·d_y physics rows; h: the layer's input), so J Jᵀ and Jᵀ w come from per-layer products
(:class:`LayerFactors`), at Σ n_out instead of |θ| multiply-adds per Gram entry. Equal to the
explicit route to 1e-15 relative.

Where the time goes: on the oscillators nearly all of an update is the decomposition (the
eigendecomposition of the Gram matrix), a fifth the physics; the layer-factor route forms the
direction several times faster than the explicit J's Gram matrix or QR + SVD, and J itself
(``jacobian``, for the SVD route and for other networks) far faster than ``torch.func.jacrev``
through the same RK4 in plain torch. ``vmap(jacrev(...))`` through the bridge operator (its
vmap rule makes it one adjoint call over the same b·d_y rows) gives this J to the bit, but
slower on the oscillators (``python benchmarks/compile.py --tasks "" --jacobian PATH``): the
batched adjoint stays. ``python benchmarks/hig.py`` measures each part; the figures are on the
results page. The SVD of a wide J is taken as Jᵀ = QR followed by the
SVD of the small R.

The decomposition (``decomposition=``): ``"svd"`` is the one above, exact to round-off.
``"gram"`` takes the eigendecomposition J Jᵀ = U Λ Uᵀ (σ² = λ) of the small Gram matrix and
applies V Σ^(−κ) Uᵀ g = Jᵀ U Σ^(−κ−1) Uᵀ g: faster than QR + SVD with layer factors
(``python benchmarks/hig.py``), but λ carries an absolute
error of about ε λ_max, so singular values near τ σ_max lose about ε/τ² of relative accuracy:
against the SVD route the direction differs by 9.7e-5 (oscillators, τ = 1e-6), 1.6e-7
(quantum, τ = 1e-5) and 1e-13 (Poisson, well conditioned), relative. ``"auto"`` (the default) takes
``"gram"`` for a wide J whenever τ² ≥ 10³ ε of its dtype (τ ≥ 4.7e-7 in float64), so that the
dropped directions are resolved; otherwise (the linear chain's τ = 1e-10, float32) the SVD.
The Gram route never keeps a singular value below √(rows · ε) σ_max (round-off in λ), even
when asked to by a smaller τ.

A large Gram matrix (:data:`TRIDIAGONAL_ROWS` rows or more: Poisson at the paper's batch of 64,
4096 rows) is not decomposed whole (:class:`GramEigen`): its reduction to tridiagonal form
J Jᵀ = Q T Qᵀ (Householder reflectors, LAPACK ``sytrd``) and the eigenpairs of T = Z Λ Zᵀ (MRRR,
``stemr``) are what ``eigh`` computes too, but the n × n back-transformation U = Q Z, a third
or more of its time, is left out: the direction needs U only applied to a vector, Uᵀ g =
Zᵀ (Qᵀ g) and U c = Q (Z c), each n reflectors applied in O(n²). Equal to ``eigh``'s direction
to round-off (tested).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable

import numpy as np
import scipy.linalg
import torch
from torch.func import functional_call, jacrev, vjp, vmap

from adjointsim import Stepper

from . import bridge

Loss = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
DECOMPOSITIONS = ("auto", "svd", "gram")
#: "auto" takes the Gram route when τ² is at least this many ε of J's dtype
GRAM_MIN_TAU2_EPS = 1e3
#: Gram matrices of this many rows or more are decomposed without forming their eigenvectors
#: (:class:`GramEigen`); below, ``torch.linalg.eigh`` (the round-off of the committed studies)
TRIDIAGONAL_ROWS = 2048


class GramEigen:
    """The eigendecomposition J Jᵀ = U Λ Uᵀ of a symmetric matrix with U kept as factors:
    the Householder reflectors of its tridiagonal reduction (Q) and the eigenvectors of the
    tridiagonal matrix (Z), U = Q Z. :attr:`values` holds Λ ascending; :meth:`to_eigen` and
    :meth:`from_eigen` apply Uᵀ and U to a vector without forming U."""

    def __init__(self, gram: torch.Tensor):
        a = gram.detach().numpy()
        sytrd, sytrd_lwork = scipy.linalg.get_lapack_funcs(("sytrd", "sytrd_lwork"), (a,))
        lwork, info = sytrd_lwork(a.shape[0], lower=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"sytrd_lwork failed (info {info})")
        # lower: reflector i is I − τ_i v_i v_iᵀ with v_i = (0, …, 0, 1, c[i+2:, i])
        c, d, e, tau, info = sytrd(a, lower=1, lwork=int(lwork))
        if info != 0:
            raise np.linalg.LinAlgError(f"sytrd failed (info {info})")
        values, self.z = scipy.linalg.eigh_tridiagonal(d, e, lapack_driver="stemr")
        self.values = torch.from_numpy(values)
        self.c, self.tau, self.dtype = c, tau, gram.dtype

    def _reflect(self, x: np.ndarray, order: range) -> np.ndarray:
        x = x.copy()
        for i in order:
            if self.tau[i] != 0:
                v = self.c[i + 1:, i].copy()
                v[0] = 1.0
                x[i + 1:] -= self.tau[i] * v * (v @ x[i + 1:])
        return x

    def to_eigen(self, g: torch.Tensor) -> torch.Tensor:
        """Uᵀ g = Zᵀ Qᵀ g; Qᵀ = H_{n−1} ⋯ H_1 (each reflector symmetric)."""
        h = self._reflect(g.numpy(), range(len(self.tau)))
        return torch.from_numpy(self.z.T @ h)

    def from_eigen(self, w: torch.Tensor) -> torch.Tensor:
        """U w = Q Z w; Q = H_1 ⋯ H_{n−1}."""
        return torch.from_numpy(self._reflect(self.z @ w.numpy(), range(len(self.tau) - 1, -1,
                                                                         -1)))


class SolverPhysics:
    """y = final state of an ``n``-step controlled rollout, flattened to (b, d_y).

    The network output f (b, d_f) holds the per-step controls, step-major per sample
    (d_f = n · prod(control_shape)); ``initial(context)`` maps the per-sample context (b, ...)
    to the initial states (b, C, *grid); ``scale`` multiplies the output (units matter: HIG
    is not invariant to a rescaling of y). The forward pass goes through the torch bridge (so
    Adam can backpropagate through the adjoint); :meth:`jacobian` is the batched adjoint.
    """

    def __init__(
        self,
        stepper: Stepper,
        steps: int,
        initial: Callable[[torch.Tensor], torch.Tensor],
        scale: float = 1.0,
    ):
        if stepper.control_shape is None:
            raise ValueError(f"{stepper.name} has no control hook: the network cannot drive it")
        self.stepper, self.steps, self.initial = stepper, int(steps), initial
        self.scale = float(scale)
        self.control_size = int(np.prod(stepper.control_shape))

    def _controls(self, f: torch.Tensor) -> torch.Tensor:
        b = f.shape[0]
        if f.shape[1] != self.steps * self.control_size:
            raise ValueError(
                f"the network gives {f.shape[1]} outputs per sample; {self.stepper.name} over "
                f"{self.steps} steps takes {self.steps * self.control_size} controls"
            )
        c = f.reshape(b, self.steps, *self.stepper.control_shape).transpose(0, 1)
        return c.contiguous()

    def __call__(self, f: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        u0 = self.initial(context).to(f.dtype).contiguous()
        y = bridge.rollout(self.stepper, u0, self.steps, self._controls(f))
        return self.scale * y.reshape(f.shape[0], -1)

    def jacobian(self, f: torch.Tensor, context: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(y, ∂y/∂f) with shapes (b, d_y) and (b, d_y, d_f): one forward rollout of the batch,
        then one adjoint call over b·d_y replicated rollouts (its stored trajectory reused)."""
        b = f.shape[0]
        u0 = self.initial(context).to(f.dtype).contiguous().numpy()
        ctrl = self._controls(f.detach()).numpy()
        traj = self.stepper.rollout(u0, self.steps, ctrl, keep="all")
        d_y = int(np.prod(u0.shape[1:]))
        rows = b * d_y
        # Row r = s·d_y + i is sample s with the unit cotangent on its output component i.
        cot = np.zeros((rows, d_y), traj.dtype)
        cot[np.arange(rows), np.tile(np.arange(d_y), b)] = 1.0
        g = self.stepper.vjp(
            np.repeat(u0, d_y, axis=0),
            self.steps,
            cot.reshape(rows, *u0.shape[1:]),
            np.repeat(ctrl, d_y, axis=1),
            trajectory=np.repeat(traj, d_y, axis=1),
        )
        jac = g.controls.reshape(self.steps, b, d_y, self.control_size)
        jac = np.ascontiguousarray(jac.transpose(1, 2, 0, 3)).reshape(b, d_y, -1)
        y = self.scale * traj[-1].reshape(b, d_y)
        return torch.from_numpy(y), torch.from_numpy(self.scale * jac)


class TorchPhysics:
    """A physics map written in torch, ``fn(f, context) -> y`` on batches (b, d_f) -> (b, d_y);
    its per-sample Jacobian comes from ``torch.func.jacrev``."""

    def __init__(self, fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]):
        self.fn = fn

    def __call__(self, f: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        return self.fn(f, context)

    def jacobian(self, f: torch.Tensor, context: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            y = self.fn(f, context)

        def single(fi: torch.Tensor, ci: torch.Tensor) -> torch.Tensor:
            return self.fn(fi[None], ci[None])[0]

        return y, vmap(jacrev(single))(f.detach(), context)


class LayerFactors:
    """J of a network whose parameters all sit in ``nn.Linear`` layers, each applied once per
    sample, kept as per-layer factors instead of a (b·d_y) × |θ| matrix.

    Row (s, i) of J restricted to layer l is δ ⊗ [h, 1]: δ = ∂y_{s,i}/∂z (the layer's output z),
    h = the layer's input for sample s. Hence J Jᵀ = Σ_l (D_l D_lᵀ) ⊙ (K_l ⊗ 1_{d_y × d_y}) with
    D_l the rows' δ (b·d_y × n_out) and K_l = H Hᵀ + 1 (b × b; + 1 only with a bias), and Jᵀ w
    is per layer Eᵀ [H, 1] with E_s = Σ_i w_{s,i} δ_{s,i}. That costs Σ n_out instead of |θ|
    per Gram entry: 156 against 2956 on the oscillators, 320 against 24896 on Poisson.
    """

    def __init__(self, layers: list[torch.nn.Linear], deltas: list[torch.Tensor],
                 inputs: list[torch.Tensor], params: list[torch.Tensor]):
        self.layers, self.inputs = layers, inputs
        self.d_y, self.b = deltas[0].shape[:2]
        self.deltas = deltas  # each (d_y, b, n_out)
        self.params = params
        self.shape = (self.b * self.d_y, sum(p.numel() for p in params))
        self.dtype = deltas[0].dtype

    def isfinite(self) -> torch.Tensor:
        """Per row of J: are its factors finite."""
        ok = torch.ones(self.b, self.d_y, dtype=torch.bool)
        for d, h in zip(self.deltas, self.inputs):
            ok &= torch.isfinite(d).all(dim=2).T & torch.isfinite(h).all(dim=1)[:, None]
        return ok.reshape(-1)

    def gram(self) -> torch.Tensor:
        rows, b, d_y = self.shape[0], self.b, self.d_y
        gram = torch.zeros(b, d_y, b, d_y, dtype=self.dtype)
        for layer, d, h in zip(self.layers, self.deltas, self.inputs):
            rows_d = d.transpose(0, 1).reshape(rows, -1)
            k = h @ h.T + (1.0 if layer.bias is not None else 0.0)
            gram += (rows_d @ rows_d.T).view(b, d_y, b, d_y) * k[:, None, :, None]
        return gram.view(rows, rows)

    def rmatvec(self, w: torch.Tensor) -> torch.Tensor:
        """Jᵀ w, flat in parameter order."""
        w = w.view(self.b, self.d_y)
        parts: dict[int, torch.Tensor] = {}
        for layer, d, h in zip(self.layers, self.deltas, self.inputs):
            e = torch.einsum("si,isn->sn", w, d)
            parts[id(layer.weight)] = e.T @ h
            if layer.bias is not None:
                parts[id(layer.bias)] = e.sum(dim=0)
        return torch.cat([parts[id(p)].reshape(-1) for p in self.params])

    def dense(self) -> torch.Tensor:
        """J itself, (b·d_y) × |θ|: a tall J's own SVD is cheaper than its Gram matrix's."""
        rows = self.shape[0]
        parts: dict[int, torch.Tensor] = {}
        for layer, d, h in zip(self.layers, self.deltas, self.inputs):
            d = d.transpose(0, 1)  # (b, d_y, n_out): rows sample-major, as in J
            parts[id(layer.weight)] = (d[..., None] * h[:, None, None, :]).reshape(rows, -1)
            if layer.bias is not None:
                parts[id(layer.bias)] = d.reshape(rows, -1)
        return torch.cat([parts[id(p)] for p in self.params], dim=1)


class _NotLayered(Exception):
    """The model is not a stack of Linear layers each applied once per sample."""


class HalfInverseGradients:
    """HIG (``kappa=0.5``) or Gauss–Newton (``kappa=1``) steps for ``model`` through ``physics``.

    ``physics`` is a :class:`SolverPhysics`, a :class:`TorchPhysics` or anything with the same
    ``__call__``/``jacobian`` pair; ``loss(y, target)`` returns the per-sample losses (b,).
    ``max_jacobian_mb`` bounds the largest matrix an update forms: J, or on the layer-factor
    route (the Gram route of a network of Linear layers, :meth:`layer_factors`) the Gram matrix
    J Jᵀ; a batch over it is refused before the matrix is formed. After each :meth:`step`,
    ``timing`` holds the seconds of its parts: ``network`` and ``physics`` (the two Jacobian
    factors), ``decomposition`` (with forming J Jᵀ) and ``apply``.
    """

    def __init__(
        self,
        model: torch.nn.Module,
        physics: SolverPhysics | TorchPhysics,
        loss: Loss,
        lr: float = 1.0,
        kappa: float = 0.5,
        tau: float = 1e-6,
        max_jacobian_mb: float = 1024.0,
        decomposition: str = "auto",
    ):
        for key, value in (("lr", lr), ("tau", tau), ("max_jacobian_mb", max_jacobian_mb)):
            if not (isinstance(value, int | float) and np.isfinite(value) and value >= 0):
                raise ValueError(f"HIG: {key} must be a finite number ≥ 0, not {value!r}")
        if not (isinstance(kappa, int | float) and np.isfinite(kappa)):
            raise ValueError(f"HIG: kappa must be a finite number (0.5 HIG, 1 GN), not {kappa!r}")
        if decomposition not in DECOMPOSITIONS:
            raise ValueError(f"HIG: unknown decomposition {decomposition!r}; choose from "
                             f"{', '.join(DECOMPOSITIONS)}")
        self.decomposition = decomposition
        self.model, self.physics, self.loss = model, physics, loss
        self.lr, self.kappa, self.tau = float(lr), float(kappa), float(tau)
        self.max_jacobian_mb = float(max_jacobian_mb)
        self.timing: dict[str, float] = {}

    # ------------------------------------------------------------------ pieces
    def _params(self) -> dict[str, torch.Tensor]:
        return {k: v.detach() for k, v in self.model.named_parameters()}

    def _check_size(self, rows: int, cols: int, dtype: torch.dtype,
                    what: str = "Jacobian") -> None:
        mb = rows * cols * torch.finfo(dtype).bits / 8 / 2**20
        if mb > self.max_jacobian_mb:
            raise MemoryError(
                f"HIG: the {what} would be {rows} × {cols} ({dtype}) = {mb:.3g} MB, over "
                f"max_jacobian_mb = {self.max_jacobian_mb:g}; lower the batch size (rows = "
                "batch · outputs per sample) or raise max_jacobian_mb"
            )

    def jacobian(
        self, x: torch.Tensor, context: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(y, J): physics outputs (b, d_y) and J = ∂y/∂θ of shape (b·d_y, |θ|)."""
        t0 = time.perf_counter()
        params = self._params()
        with torch.no_grad():
            f = functional_call(self.model, params, (x,))
        t1 = time.perf_counter()
        y, jp = self.physics.jacobian(f, context)
        t2 = time.perf_counter()
        b, d_y = jp.shape[:2]
        cols = sum(p.numel() for p in params.values())
        self._check_size(b * d_y, cols, f.dtype)

        def rows(xi: torch.Tensor, ci: torch.Tensor) -> dict[str, torch.Tensor]:
            _, pull = vjp(lambda p: functional_call(self.model, p, (xi[None],))[0], params)
            return vmap(pull)(ci)[0]

        parts = vmap(rows)(x, jp.to(f.dtype))
        jac = torch.cat([parts[k].reshape(b * d_y, -1) for k in params], dim=1)
        t3 = time.perf_counter()
        self.timing = {"network": (t1 - t0) + (t3 - t2), "physics": t2 - t1}
        return y, jac

    def layer_factors(
        self, x: torch.Tensor, context: torch.Tensor
    ) -> tuple[torch.Tensor, LayerFactors] | None:
        """(y, J as :class:`LayerFactors`), or None when the model is not a stack of Linear
        layers each applied once per sample (then :meth:`jacobian` forms J). A tall J
        (more rows than parameters) is refused by ``max_jacobian_mb`` as J, the Gram matrix
        otherwise."""
        params = list(self.model.parameters())
        layers = [m for m in self.model.modules() if isinstance(m, torch.nn.Linear)]
        owned = [id(p) for m in layers for p in m.parameters()]
        if not layers or len(set(owned)) < len(owned) or set(owned) != {id(p) for p in params}:
            return None  # parameters outside Linear layers, or shared by two
        t0 = time.perf_counter()
        inputs: dict[torch.nn.Module, torch.Tensor] = {}
        taps: dict[torch.nn.Module, torch.Tensor] = {}

        def tap(module: torch.nn.Module, args: tuple, out: torch.Tensor) -> torch.Tensor:
            # δ of the layer is the gradient at a zero added to its output
            if module in inputs or args[0].dim() != 2:
                raise _NotLayered
            inputs[module] = args[0].detach()
            taps[module] = torch.zeros_like(out, requires_grad=True)
            return out + taps[module]

        handles = [m.register_forward_hook(tap) for m in layers]
        try:
            with torch.enable_grad():
                f = self.model(x)
        except _NotLayered:
            return None
        finally:
            for h in handles:
                h.remove()
        if len(inputs) != len(layers):
            return None
        t1 = time.perf_counter()
        y, jp = self.physics.jacobian(f.detach(), context)
        t2 = time.perf_counter()
        rows, cols = jp.shape[0] * jp.shape[1], sum(p.numel() for p in params)
        if rows > cols:  # a tall J: formed from these factors, for its own SVD
            self._check_size(rows, cols, f.dtype)
        else:
            self._check_size(rows, rows, f.dtype, "Gram matrix J Jᵀ")
        # one batched backward for all d_y output components of every sample
        deltas = torch.autograd.grad(f, [taps[m] for m in layers],
                                     grad_outputs=jp.to(f.dtype).transpose(0, 1).contiguous(),
                                     is_grads_batched=True)
        factors = LayerFactors(layers, list(deltas), [inputs[m] for m in layers], params)
        self.timing = {"network": (t1 - t0) + (time.perf_counter() - t2), "physics": t2 - t1}
        return y, factors

    def direction(self, jac: torch.Tensor | LayerFactors, g: torch.Tensor) -> torch.Tensor:
        """V Σ^(−κ) Uᵀ g over the singular values above τ σ_max (zero if J = 0)."""
        finite = jac.isfinite() if isinstance(jac, LayerFactors) else torch.isfinite(jac).all(1)
        if not finite.all():
            bad = (~finite).nonzero().flatten().tolist()
            raise FloatingPointError(
                f"HIG: the Jacobian has non-finite entries in {len(bad)} of its {jac.shape[0]} "
                f"rows (first: {bad[:5]}); the network or the physics diverged on this batch: "
                "lower the learning rate, or resume from an earlier checkpoint"
            )
        rows, cols = jac.shape
        if isinstance(jac, LayerFactors) and rows > cols:
            jac = jac.dense()
        if isinstance(jac, LayerFactors):
            gram, pull = jac.gram(), jac.rmatvec
        elif rows <= cols and self._gram(jac.dtype):
            gram, pull = jac @ jac.T, lambda w: jac.T @ w
        else:
            gram = None
        if gram is not None:
            # J Jᵀ = U Λ Uᵀ, eigenvalues ascending; V Σ^(−κ) Uᵀ g = Jᵀ U Σ^(−κ−1) Uᵀ g
            large = rows >= TRIDIAGONAL_ROWS
            if large:
                eigen = GramEigen(gram)
                lam = eigen.values
            else:
                lam, u = torch.linalg.eigh(gram)
            s = lam.clamp(min=0.0).sqrt()
            if s.numel() == 0 or s[-1] == 0:
                return torch.zeros(cols, dtype=jac.dtype)
            # below √(rows·ε) σ_max an eigenvalue is round-off, whatever τ says
            floor = max(self.tau, (rows * torch.finfo(jac.dtype).eps) ** 0.5)
            keep = s > floor * s[-1]
            if large:
                scale = torch.zeros_like(s)
                scale[keep] = s[keep] ** (-self.kappa - 1.0)
                return pull(eigen.from_eigen(scale * eigen.to_eigen(g)))
            return pull(u[:, keep] @ (s[keep] ** (-self.kappa - 1.0) * (u[:, keep].T @ g)))
        if rows <= cols:
            # J is wide (b·d_y < |θ|): Jᵀ = QR, then the small SVD Rᵀ = U Σ Wᵀ gives
            # J = U Σ (QW)ᵀ. The same singular values to round-off as a direct SVD, measured
            # 3.5x faster at 512 × 2956 and 448 × 9484 (one thread).
            q, r = torch.linalg.qr(jac.T)
            u, s, wh = torch.linalg.svd(r.T)
        else:
            u, s, wh = torch.linalg.svd(jac, full_matrices=False)
        if s.numel() == 0 or s[0] == 0:
            return torch.zeros(cols, dtype=jac.dtype)
        keep = s > self.tau * s[0]
        delta = wh[keep].T @ (s[keep] ** (-self.kappa) * (u[:, keep].T @ g))
        return q @ delta if rows <= cols else delta

    def _gram(self, dtype: torch.dtype) -> bool:
        if self.decomposition != "auto":
            return self.decomposition == "gram"
        return self.tau**2 >= GRAM_MIN_TAU2_EPS * torch.finfo(dtype).eps

    def step(
        self, x: torch.Tensor, context: torch.Tensor, target: torch.Tensor
    ) -> float:
        """One update on the batch; returns the batch's mean loss before the update."""
        layered = None
        if self.decomposition != "svd" and self._gram(next(self.model.parameters()).dtype):
            layered = self.layer_factors(x, context)
        y, jac = layered if layered is not None else self.jacobian(x, context)
        t0 = time.perf_counter()
        y = y.detach().requires_grad_(True)
        loss = self.loss(y, target).mean()
        (g,) = torch.autograd.grad(loss, y)
        if not torch.isfinite(g).all():
            raise FloatingPointError("HIG: the loss gradient ∂L/∂y is not finite on this batch")
        t1 = time.perf_counter()
        delta = self.direction(jac, g.reshape(-1).to(jac.dtype))
        t2 = time.perf_counter()
        apply_update(self.model.parameters(), delta, -self.lr)
        # "apply" counts the loss gradient g and the parameter update
        self.timing.update(decomposition=t2 - t1, apply=(t1 - t0) + time.perf_counter() - t2)
        return float(loss.detach())


def apply_update(params: Iterable[torch.Tensor], delta: torch.Tensor, scale: float) -> None:
    """θ += scale · Δθ, Δθ flat in parameter order."""
    offset = 0
    with torch.no_grad():
        for p in params:
            n = p.numel()
            p.add_(delta[offset : offset + n].view_as(p), alpha=scale)
            offset += n
