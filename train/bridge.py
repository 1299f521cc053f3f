"""The torch bridge: a stepper's fused rollout as a ``torch.autograd.Function``.

Tensors cross to numba without copies (``Tensor.numpy()`` shares memory). The backward pass
calls the stepper's hand-written adjoint, never autograd through the solver. When no input
needs a gradient (evaluation, ``torch.no_grad()``, NOG's detached solver calls) the forward
stores nothing; otherwise it keeps the trajectory, or only checkpoints when ``checkpoint`` is
set, so that the backward pass does not recompute it.

A closed loop calls the solver once per step, so the per-call cost matters: the inputs are
validated once, in the forward call (the stepper's own checks of shape, dtype and finiteness,
the parts of :meth:`Stepper.prepare`; the bridge adds only the torch-specific ones: type,
device, contiguity), and both passes take the stepper's fast path
(:meth:`Stepper.rollout_prepared`, :meth:`Stepper.vjp_prepared`), which does not check them
again. Everything is checked before the rollout runs, ``checkpoint`` included (which the stepper
would check only when the backward pass starts), whether or not a backward pass follows.

States, controls and parameters are tensors or NumPy arrays (NumPy in, tensor out: an array is
taken as :meth:`Stepper.rollout` takes it, without a copy when it is C-contiguous, and gets no
gradient); anything else (a list, a float) is refused with a ``TypeError`` naming the input.

The adjoint is once-differentiable: differentiating through the backward pass
(``create_graph=True`` followed by a backward through the gradient, as in a gradient penalty,
a Hessian-vector product or ``gradgradcheck``) raises a clear error instead of silently
treating the solver's second derivatives as zero.
"""

from __future__ import annotations

import functools
import numbers
import warnings
from typing import NamedTuple

import numpy as np
import torch
from torch._C import _functions as _torch_functions

from adjointsim import Stepper
from adjointsim.stepper import FLOAT_DTYPES

#: counts adjoint sweeps, so tests can prove that a training mode never ran one
ADJOINT_CALLS = {"count": 0}


def _as_numpy(t: torch.Tensor | None, what: str, dtype: torch.dtype | None) -> np.ndarray | None:
    """The torch-side checks (the stepper checks shape, dtype and finiteness itself)."""
    if t is None:
        return None
    if not t.is_cpu:
        raise ValueError(
            f"{what} is on {t.device}; adjointsim's solvers run on the CPU: pass {what}.cpu()"
        )
    if dtype is None:
        if t.dtype not in (torch.float32, torch.float64):
            raise TypeError(
                f"{what} has dtype {t.dtype}; expected torch.float32 or torch.float64"
            )
    elif t.dtype != dtype:
        raise TypeError(
            f"{what} has dtype {t.dtype} but the state is {dtype}; cast it with .to({dtype})"
        )
    if not t.is_contiguous():
        raise ValueError(f"{what} is not contiguous; pass {what}.contiguous()")
    return t.detach().numpy()


def _check_steps(n: object) -> int:
    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 0:
        raise ValueError(
            f"the number of steps n must be a non-negative integer, not {n!r} "
            f"({type(n).__name__})"
        )
    return int(n)


def check_checkpoint(stepper: Stepper, checkpoint: int | None) -> int | None:
    """``checkpoint``, after the check :meth:`Stepper.vjp` makes of it, with its message.

    The stepper checks it only in :meth:`Stepper.vjp_prepared`, as the reverse sweep starts:
    through the bridge, after the whole rollout, or never under ``torch.no_grad()``. A sweep of
    zero steps over an empty batch makes that check and calls no kernel, so it is checked here
    before anything runs, in the stepper's words."""
    if checkpoint is not None:
        u = np.zeros(stepper.state_shape(0))
        controls = np.zeros((0, 0, *(stepper.control_shape or ())))
        params = np.zeros(len(stepper.param_names))
        cmap = np.zeros(1, dtype=np.int64)
        stepper.vjp_prepared(u, 0, controls, params, u[None], cmap, checkpoint=checkpoint)
    return checkpoint


class _Saved(NamedTuple):
    """What the backward pass of one stepper's rollout needs (validated, private copies)."""

    stepper: Stepper
    n: int
    u0: np.ndarray  # (B, C, *grid)
    controls: np.ndarray  # (n, B, *control_shape), or a zero-length first axis
    params: np.ndarray
    trajectory: np.ndarray | None  # u_0 .. u_{n-1}, or None to recompute from checkpoints
    checkpoint: int | None


def _forward(
    stepper: Stepper,
    n: int,
    u0: np.ndarray,
    controls: np.ndarray | None,
    params: np.ndarray | None,
    keep_all: bool,
    grad: bool,
    checkpoint: int | None = None,
) -> tuple[np.ndarray, _Saved | None]:
    """Validate once and roll out. Returns (u_n, or u_0 .. u_n if ``keep_all``; saved state).

    The returned array never shares memory with what the backward pass reverses, and the saved
    arrays never share memory with the caller's tensors: in-place edits after this call cannot
    change the gradient.
    """
    # Stepper.prepare minus its check of n, which the caller has made.
    u = stepper.check_state(u0, "u0")
    c = stepper.check_controls(controls, n, u)
    p = stepper.param_array(params, u.dtype)
    store = grad and checkpoint is None
    # Zero steps or an empty batch call no kernel: the stepper's fast path sees to that.
    states = stepper.rollout_prepared(u, n, c, p, keep="all" if keep_all or store else "last")
    if keep_all:
        out = states.copy() if store else states
    elif store:
        out = states[n]  # the backward pass reverses from u_0 .. u_{n-1} only: no copy needed
    else:
        out = states  # u_n, in the two-state buffer of an unstored rollout
    saved = None
    if grad:
        saved = _Saved(
            stepper, n, states[0] if store else u.copy(), c.copy(),
            p if params is None else p.copy(),  # the scene's own array is never written
            states[:n] if store else None, checkpoint,
        )
    return out, saved


@functools.lru_cache(maxsize=64)
def _cotangent_map(n: int, keep_all: bool) -> np.ndarray:
    """Row of each state's cotangent: every state's, or only u_n's (row 0)."""
    if keep_all:
        return np.arange(n + 1, dtype=np.int64)
    cmap = np.full(n + 1, -1, dtype=np.int64)
    cmap[n] = 0
    return cmap


def _backward(
    saved: _Saved, grad: np.ndarray, keep_all: bool, want_params: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Cotangents of (u0, controls, params) from the output's cotangent ``grad``."""
    stepper, n, u0, c, p, trajectory, checkpoint = saved
    cot = np.ascontiguousarray(grad)
    # The cotangents in the form check_cotangents gives, built directly: grad is the output's.
    g = stepper.vjp_prepared(
        u0, n, c, p, cot if keep_all else cot[None], _cotangent_map(n, keep_all), want_params,
        checkpoint, trajectory,
    )
    g_p = None
    if want_params:
        g_p = np.array([g.params[k] for k in stepper.param_names], dtype=grad.dtype)
    return g.state, g.controls, g_p


def _once_differentiable(names: list[str], grads: tuple, sources: tuple) -> tuple:
    """Let a second differentiation through the adjoint fail loudly, and only then.

    ``sources`` are the tensors the gradients depend on: the incoming cotangent and the node's
    inputs. Under ``create_graph=True`` the gradients come out of a node that raises when a
    backward pass reaches it and whose edges lead to every source, so any later backward pass
    that wants a gradient of a source through these gradients reaches it. torch's
    ``once_differentiable`` links its error node to fresh leaves instead and only when the
    cotangent requires grad: a gradient penalty on ``out.sum()`` would still lose its term, and
    ``gradgradcheck``, asking for gradients of the inputs, would get zeros. Graphs whose second
    backward does not pass through the solver are unaffected.
    """
    if not torch.is_grad_enabled():
        return grads
    tensors = [g for g in grads if g is not None]
    links = [s for s in sources if s is not None and s.requires_grad]
    if not tensors or not links:
        return grads
    solver = ", ".join(sorted(set(names)))
    error = _torch_functions.DelayedError(
        f"adjointsim.train.bridge ({solver}): the solver's backward pass is a hand-written "
        "discrete adjoint and is once-differentiable; second derivatives through it (a "
        "backward pass through a gradient taken with create_graph=True: gradient penalties, "
        "Hessian-vector products, gradgradcheck) are not available. Use a first-order "
        "objective, or finite differences of the gradient.",
        len(tensors) + len(links),
    )
    wrapped = iter(error(*tensors, *links))
    return tuple(None if g is None else next(wrapped) for g in grads)


def _from_numpy(x: object, what: str) -> torch.Tensor:
    """A NumPy array as a tensor sharing its memory (a copy only where the stepper would make
    one: a layout other than C order); any other type refused, naming the input ``what``."""
    if not isinstance(x, np.ndarray):
        kind = "None" if x is None else f"a {type(x).__name__}"
        raise TypeError(f"{what} is {kind}; pass a torch.Tensor or a NumPy array")
    if x.dtype not in FLOAT_DTYPES:
        raise TypeError(
            f"{what} is a NumPy array of dtype {x.dtype}; expected float32 or float64 "
            f"(convert with {what}.astype(np.float64))"
        )
    if not x.flags.c_contiguous:
        x = x.copy(order="C")
    if x.flags.writeable:
        return torch.from_numpy(x)
    # torch warns that a tensor cannot protect a read-only array; the bridge never writes to its
    # inputs, and the tensor does not leave it.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return torch.from_numpy(x)


def _torch_inputs(names: tuple[str, ...], *inputs: object) -> tuple:
    """The inputs as tensors (the first, the state, required; the others may be None), detached
    under ``torch.no_grad()``: a Function's forward sees its inputs' ``requires_grad`` in
    ``ctx.needs_input_grad`` even then, and would store the trajectory."""
    if inputs[0] is not None:
        for x in inputs:
            if x is not None and not isinstance(x, torch.Tensor):
                break
        else:  # tensors only, a closed loop's every step: nothing to convert
            if torch.is_grad_enabled():
                return inputs
            return tuple(None if x is None else x.detach() for x in inputs)
    converted = [
        x if isinstance(x, torch.Tensor) or (x is None and i) else _from_numpy(x, names[i])
        for i, x in enumerate(inputs)
    ]
    return _torch_inputs(names, *converted)


_ROLLOUT_INPUTS = ("u0", "controls", "params")
_STEP_INPUTS = ("u", "control", "params")


class _Config(NamedTuple):
    """The non-tensor arguments of one rollout node, passed as one (fewer arguments for torch's
    per-call argument handling)."""

    stepper: Stepper
    n: int
    keep_all: bool
    checkpoint: int | None
    step: bool  # controls of shape (B, ...) for one step, not (n, B, ...)


class _Rollout(torch.autograd.Function):
    @staticmethod
    def forward(ctx, cfg, u0, controls, params):
        u = _as_numpy(u0, "u0", None)
        c = _as_numpy(controls, "control" if cfg.step else "controls", u0.dtype)
        if cfg.step and c is not None:
            c = c[None]
        p = _as_numpy(params, "params", u0.dtype)
        grad = any(ctx.needs_input_grad)
        out, ctx.saved = _forward(cfg.stepper, cfg.n, u, c, p, cfg.keep_all, grad, cfg.checkpoint)
        # The inputs themselves (not their values: those are copied in ctx.saved), only to link
        # a second differentiation to them; inputs, so no reference cycle.
        ctx.cfg, ctx.inputs = cfg, (u0, controls, params)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad):
        ADJOINT_CALLS["count"] += 1
        _, want_u, want_c, want_p = ctx.needs_input_grad
        cfg = ctx.cfg
        g_u, g_c, g_p = _backward(ctx.saved, grad.detach().numpy(), cfg.keep_all, want_p)
        grads = (
            torch.from_numpy(g_u) if want_u else None,
            torch.from_numpy(g_c[0] if cfg.step else g_c) if want_c else None,
            torch.from_numpy(g_p) if want_p else None,
        )
        return (None, *_once_differentiable([cfg.stepper.name], grads, (grad, *ctx.inputs)))


def _check_partition(groups: list[tuple[Stepper, np.ndarray | slice]], batch: int) -> list:
    """Each group's rows (a slice stays a slice: a view, no gather), after checking that the
    groups cover every row of the batch exactly once."""
    indices, covered = [], []
    for i, (_, rows) in enumerate(groups):
        if isinstance(rows, slice):
            indices.append(rows)
            covered.append(np.arange(batch)[rows])
            continue
        idx = np.asarray(rows)
        if idx.dtype == bool:
            if idx.shape != (batch,):
                raise ValueError(
                    f"group {i}: a boolean row mask needs shape ({batch},), not {idx.shape}"
                )
            idx = np.flatnonzero(idx)
        elif idx.ndim != 1 or not (idx.size == 0 or np.issubdtype(idx.dtype, np.integer)):
            raise ValueError(
                f"group {i}: rows must be a slice, a 1-D integer array or a boolean mask, "
                f"not {idx.dtype} of shape {idx.shape}"
            )
        idx = idx.astype(np.intp, copy=False)
        outside = idx[(idx < 0) | (idx >= batch)]
        if outside.size:
            raise ValueError(
                f"group {i}: rows {sorted(set(outside.tolist()))} are outside the batch "
                f"0..{batch - 1}"
            )
        indices.append(idx)
        covered.append(idx)
    counts = np.bincount(np.concatenate([np.zeros(0, np.intp), *covered]), minlength=batch)
    missing, repeated = np.flatnonzero(counts == 0), np.flatnonzero(counts > 1)
    if missing.size or repeated.size:
        problems = []
        if missing.size:
            problems.append(f"rows {missing.tolist()} are in no group")
        if repeated.size:
            problems.append(f"rows {repeated.tolist()} are in more than one group")
        raise ValueError(
            "the groups must partition the batch (every row in exactly one group): "
            + "; ".join(problems)
        )
    return indices


class _GroupedRollout(torch.autograd.Function):
    @staticmethod
    def forward(ctx, groups, n, u0):
        u = _as_numpy(u0, "u0", None)
        indices = _check_partition(groups, u.shape[0])
        grad = ctx.needs_input_grad[2]
        out = np.empty_like(u)
        ctx.saved, ctx.u0 = [], u0
        for (stepper, _), rows in zip(groups, indices, strict=True):
            part, saved = _forward(stepper, n, u[rows], None, None, False, grad)
            out[rows] = part
            ctx.saved.append((rows, saved))
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad):
        cot = grad.detach().numpy()
        out = np.empty(cot.shape, dtype=cot.dtype)
        ADJOINT_CALLS["count"] += 1
        for rows, saved in ctx.saved:
            out[rows] = _backward(saved, cot[rows], False, False)[0]
        names = [saved.stepper.name for _, saved in ctx.saved]
        grads = _once_differentiable(names, (torch.from_numpy(out),), (grad, ctx.u0))
        return (None, None, *grads)


def rollout_grouped(
    groups: list[tuple[Stepper, np.ndarray | slice]], u0: torch.Tensor | np.ndarray, n: int
) -> torch.Tensor:
    """Differentiable rollout of a batch whose rows belong to different scenes.

    ``groups`` pairs each stepper with the batch rows it advances (a slice, an integer array or
    a boolean mask; together a partition of the batch, checked), e.g. one KS domain size each.
    It is one autograd node whatever the number of groups: a batch mixing six scenes pays
    torch's per-node cost once, not six times, and needs no gather or scatter in torch.
    ``u0`` is a tensor or a NumPy array (see the module docstring); the result is a tensor.
    """
    return _GroupedRollout.apply(groups, _check_steps(n), *_torch_inputs(("u0",), u0))


def rollout(
    stepper: Stepper,
    u0: torch.Tensor | np.ndarray,
    n: int,
    controls: torch.Tensor | np.ndarray | None = None,
    params: torch.Tensor | np.ndarray | None = None,
    keep: str = "last",
    checkpoint: int | None = None,
) -> torch.Tensor:
    """Differentiable ``stepper.rollout``: gradients reach ``u0``, ``controls`` and ``params``.

    ``params`` is 1-D, in ``stepper.param_names`` order (e.g. a learnable viscosity); None
    uses the scene's values. Each input is a tensor or a NumPy array (an array gets no
    gradient; see the module docstring); the result is a tensor. ``keep="all"`` returns
    u_0 .. u_n; ``checkpoint`` bounds the number of states held for the backward pass (see
    :meth:`Stepper.vjp`), checked here even when no backward pass follows. ``n = 0`` returns
    a copy of ``u0`` (shape (1, B, ...) with ``keep="all"``).
    """
    if keep not in ("last", "all"):
        raise ValueError(f"keep must be 'last' or 'all', not {keep!r}")
    n, checkpoint = _check_steps(n), check_checkpoint(stepper, checkpoint)
    cfg = _Config(stepper, n, keep == "all", checkpoint, False)
    return _Rollout.apply(cfg, *_torch_inputs(_ROLLOUT_INPUTS, u0, controls, params))


def step(
    stepper: Stepper,
    u: torch.Tensor | np.ndarray,
    control: torch.Tensor | np.ndarray | None = None,
    params: torch.Tensor | np.ndarray | None = None,
) -> torch.Tensor:
    """Differentiable single step; ``control`` has shape (B, *control_shape). Tensors or NumPy
    arrays in (see :func:`rollout`), a tensor out."""
    return _Rollout.apply(
        _Config(stepper, 1, False, None, True), *_torch_inputs(_STEP_INPUTS, u, control, params)
    )
