"""The torch bridge: a stepper's fused rollout as torch operators.

Tensors cross to numba without copies (``Tensor.numpy()`` shares memory; a layout numba cannot
take, such as a transposed or strided view, is copied once, only then). The backward pass calls
the stepper's hand-written adjoint, never autograd through the solver. When no input needs a
gradient (evaluation, ``torch.no_grad()``, NOG's detached solver calls) the forward stores
nothing; otherwise it keeps the trajectory, or only the initial state when ``checkpoint`` is
set, so that the backward pass does not recompute it.

**Operators.** :func:`rollout`, :func:`step` and :func:`rollout_grouped` run the operators
``torch.ops.adjointsim.rollout`` and ``torch.ops.adjointsim.rollout_grouped`` (each with its
reverse sweep ``..._vjp``), defined with ``torch.library.custom_op``: a fake (meta)
implementation gives their output shapes to ``torch.compile``, which then traces a loss of
several solver steps into one graph (``fullgraph=True`` works; the forward and backward give
the eager numbers bit for bit), and the autograd and vmap rules are registered with the
operators, so ``torch.func.grad``, ``vjp``, ``jacrev`` and ``vmap`` work too. ``vmap`` maps its
dimension onto the solver's own batch: a vmapped rollout of B states is one solver call over
``V * B`` rows, not a loop (a batched parameter vector, or parameter cotangents per mapped
element, fall back to one call per element: the solver takes one parameter vector per call).

**Steppers as operator arguments.** An operator takes tensors, numbers and lists of them, not a
Python object such as a stepper. Each stepper the bridge sees is entered in a table of live
steppers (weakly: the table never keeps one alive) under an integer, its ``id``; the operators
take that integer and look the stepper up when they run. An autograd node holds its steppers
until its backward pass, so a stepper dropped between the forward and the backward pass is
still there. Under ``torch.compile`` the integer is a constant of the graph (taken at trace
time with ``torch.compiler.assume_constant_result``, guarded on the stepper object), so another
stepper compiles another graph; the compiled function's steppers are those it refers to.

**Eager cost.** A closed loop calls the solver once per step, so the per-call cost matters.
Outside ``torch.compile`` the functions apply a ``torch.autograd.Function`` that runs the same
kernels with the same autograd and vmap rules as the operators, without the dispatcher's
per-call cost (about as much again as the bridge's own; see ``benchmarks/bridge_overhead.py``);
under ``torch.compile`` (and whenever the tensors are a tracer's: fake or functional tensors)
they call the operators. The inputs are validated once, in the forward call (the stepper's own
checks of shape, dtype and finiteness, the parts of :meth:`Stepper.prepare`; the bridge adds
only the torch-specific ones: type, device), and both passes take the stepper's fast path
(:meth:`Stepper.rollout_prepared`, :meth:`Stepper.vjp_prepared`), which does not check them
again. Everything is checked before the rollout runs, ``checkpoint`` included (which the stepper
would check only when the backward pass starts), whether or not a backward pass follows, and
in a compiled graph too: the checks run in the operator, every call.

States, controls and parameters are tensors or NumPy arrays (NumPy in, tensor out: an array is
taken as :meth:`Stepper.rollout` takes it, without a copy when it is C-contiguous, and gets no
gradient); anything else (a list, a float) is refused with a ``TypeError`` naming the input.
What the backward pass reads never changes under the caller's hands: the trajectory is the
bridge's own, and controls or parameters that are tensors are saved as autograd saves any
input (an in-place edit before the backward pass makes it raise torch's error).

The adjoint is once-differentiable: differentiating through the backward pass
(``create_graph=True`` followed by a backward through the gradient, as in a gradient penalty,
a Hessian-vector product, ``gradgradcheck`` or ``torch.func.grad`` of a gradient) raises a
clear error instead of silently treating the solver's second derivatives as zero.
"""

from __future__ import annotations

import functools
import numbers
import warnings
import weakref
from collections.abc import Callable, Sequence

import numpy as np
import torch

from adjointsim import Stepper
from adjointsim.files import short
from adjointsim.stepper import FLOAT_DTYPES

#: counts adjoint sweeps, so tests can prove that a training mode never ran one
ADJOINT_CALLS = {"count": 0}

#: the steppers the operators can name: id -> stepper, held weakly
_LIVE: weakref.WeakValueDictionary[int, Stepper] = weakref.WeakValueDictionary()


@torch.compiler.assume_constant_result
def _key(stepper: Stepper) -> int:
    """The integer the operators know ``stepper`` by (entered in the table on first use)."""
    if not isinstance(stepper, Stepper):
        what = (f"the class {stepper.__name__}" if isinstance(stepper, type)
                else f"{type(stepper).__name__} {short(stepper)}")
        raise TypeError(f"the solver given is {what}, not a scene of one; pass an instance, "
                        "such as adjointsim.get(name).default() or adjointsim.get(name)(n=...)")
    key = id(stepper)
    if _LIVE.get(key) is not stepper:
        _LIVE[key] = stepper
    return key


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


def _forward(
    stepper: Stepper,
    n: int,
    u0: np.ndarray,
    controls: np.ndarray | None,
    params: np.ndarray | None,
    keep_all: bool,
    grad: bool,
    checkpoint: int | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Validate once and roll out. Returns (u_n, or u_0 .. u_n if ``keep_all``; the tape).

    The tape is what the backward pass reverses from: u_0 .. u_{n-1} (u_0 alone when ``n`` is
    0 or ``checkpoint`` is set), or None when ``grad`` is False. The result never shares memory
    with the tape or with the caller's arrays: in-place edits after this call cannot change the
    gradient.
    """
    # Stepper.prepare minus its check of n, which the caller has made.
    u = stepper.check_state(u0, "u0")
    c = stepper.check_controls(controls, n, u)
    p = stepper.param_array(params, u.dtype)
    store = grad and checkpoint is None
    # Zero steps or an empty batch call no kernel: the stepper's fast path sees to that.
    try:
        states = stepper.rollout_prepared(u, n, c, p, keep="all" if keep_all or store else "last")
    except MemoryError as e:
        if keep_all or not store:  # the result itself is too large: a checkpoint would not help
            raise
        raise stepper.keep_all_error(n, e) from None
    if keep_all:
        out = states.copy() if store else states
    elif store:
        out = states[n].copy()  # u_n, apart from the tape u_0 .. u_{n-1}
    else:
        out = states  # u_n, in the two-state buffer of an unstored rollout
    tape = None
    if store:
        tape = states[: max(n, 1)]
    elif grad:
        tape = u.copy()[None]
    return out, tape


@functools.lru_cache(maxsize=64)
def _cotangent_map(n: int, keep_all: bool) -> np.ndarray:
    """Row of each state's cotangent: every state's, or only u_n's (row 0)."""
    if keep_all:
        return np.arange(n + 1, dtype=np.int64)
    cmap = np.full(n + 1, -1, dtype=np.int64)
    cmap[n] = 0
    return cmap


def _backward(
    stepper: Stepper,
    n: int,
    tape: np.ndarray,
    controls: np.ndarray,
    params: np.ndarray,
    grad: np.ndarray,
    keep_all: bool,
    want_params: bool,
    checkpoint: int | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Cotangents of (u0, controls, params) from the output's cotangent ``grad``."""
    cot = np.ascontiguousarray(grad)
    # The cotangents in the form check_cotangents gives, built directly: grad is the output's.
    g = stepper.vjp_prepared(
        tape[0], n, controls, params, cot if keep_all else cot[None],
        _cotangent_map(n, keep_all), want_params, checkpoint,
        tape if checkpoint is None else None,
    )
    g_p = None
    if want_params:
        g_p = np.array([g.params[k] for k in stepper.param_names], dtype=grad.dtype)
    return g.state, g.controls, g_p


def _second_derivative_error(names: Sequence[str]) -> RuntimeError:
    solver = ", ".join(sorted(set(names)))
    return RuntimeError(
        f"adjointsim.train.bridge ({solver}): the solver's backward pass is a hand-written "
        "discrete adjoint and is once-differentiable; second derivatives through it (a "
        "backward pass through a gradient taken with create_graph=True: gradient penalties, "
        "Hessian-vector products, gradgradcheck) are not available. Use a first-order "
        "objective, or finite differences of the gradient."
    )


# ------------------------------------------------------------------ operators
class _Operator:
    """One operator twice: ``torch.ops.adjointsim.<name>`` (a ``torch.library.custom_op``) and
    an ``autograd.Function`` over the same kernel, with the same fake, autograd and vmap rules.

    :meth:`__call__` takes the Function in eager mode (no dispatcher on the per-step path) and
    the operator wherever a tracer runs (``torch.compile``: dynamo, then AOTAutograd's fake and
    functional tensors)."""

    def __init__(
        self,
        name: str,
        kernel: Callable,
        fake: Callable,
        vmap: Callable,
        setup_context: Callable | None = None,
        backward: Callable | None = None,
    ) -> None:
        if backward is None:  # a reverse sweep: differentiating it again is refused
            setup_context, backward = _name_solvers, _refuse_backward
        self.kernel = kernel
        self.op = torch.library.custom_op(f"adjointsim::{name}", kernel, mutates_args=())
        self.op.register_fake(fake)
        self.op.register_vmap(vmap)
        self.op.register_autograd(backward, setup_context=setup_context)
        self.function = type(
            f"_{name.title().replace('_', '')}",
            (torch.autograd.Function,),
            {
                "forward": staticmethod(kernel),
                "setup_context": staticmethod(setup_context),
                "backward": staticmethod(backward),
                "vmap": staticmethod(vmap),
            },
        )

        # Function.apply binds the arguments to the forward's signature on every call (to fill
        # in defaults, which the kernels do not have), costing more than the rest of the call:
        # outside the torch.func transforms, the node is made without it.
        self.apply = super(torch.autograd.Function, self.function).apply

    def __call__(self, *args: object) -> tuple[torch.Tensor, ...]:
        if torch.compiler.is_compiling() or not all(
            type(a) in _EAGER for a in args if isinstance(a, torch.Tensor)
        ):
            return self.op(*args)
        if torch._C._are_functorch_transforms_active():
            return self.function.apply(*args)
        if not torch.is_grad_enabled():  # no node to record: the kernel alone
            return self.kernel(*args)
        return self.apply(*args)


#: tensor types that take the eager Function (others are a tracer's: fake, functional, proxy)
_EAGER = (torch.Tensor, torch.nn.Parameter)


def _name_solvers(ctx, inputs, output) -> None:
    ctx.names = _names(inputs)


def _refuse_backward(ctx, *grads):
    raise _second_derivative_error(ctx.names)


def _names(inputs: tuple) -> list[str]:
    """The solver names behind a reverse sweep's inputs (its first argument: key or keys)."""
    keys = inputs[0]
    return [_LIVE[k].name for k in (keys if isinstance(keys, (list, tuple)) else [keys])]


def _tape_shape(u_shape: Sequence, n: int, store: bool, checkpoint: int | None) -> tuple:
    """The tape's shape (see :func:`_forward`): (0, *u_shape) when nothing is stored."""
    if not store:
        return (0, *u_shape)
    return (1 if checkpoint is not None else torch.sym_max(n, 1), *u_shape)


# ---- rollout: (key, n, keep_all, checkpoint, step, store, u0, controls, params) -> (out, tape)
def _rollout_kernel(
    key: int, n: int, keep_all: bool, checkpoint: int | None, step: bool, store: bool,
    u0: torch.Tensor, controls: torch.Tensor | None, params: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor]:
    stepper = _LIVE[key]
    check_checkpoint(stepper, checkpoint)
    u = _as_numpy(u0, "u0", None)
    c = _as_numpy(controls, "control" if step else "controls", u0.dtype)
    if step and c is not None:
        c = c[None]
    p = _as_numpy(params, "params", u0.dtype)
    out, tape = _forward(stepper, n, u, c, p, keep_all, store, checkpoint)
    if tape is None:
        tape = np.empty((0, *u.shape), dtype=out.dtype)
    return torch.from_numpy(out), torch.from_numpy(tape)


def _rollout_fake(key, n, keep_all, checkpoint, step, store, u0, controls, params):
    out = u0.new_empty((n + 1, *u0.shape)) if keep_all else torch.empty_like(u0)
    return out, u0.new_empty(_tape_shape(u0.shape, n, store, checkpoint))


def _rollout_setup(ctx, inputs, output) -> None:
    key, n, keep_all, checkpoint, step, _, _, controls, params = inputs
    ctx.config = key, n, keep_all, checkpoint, step
    ctx.stepper = _LIVE[key]  # the table holds it weakly: alive until the backward pass
    ctx.set_materialize_grads(False)  # the tape gets no cotangent: none is made for it
    ctx.save_for_backward(output[1], controls, params)


def _rollout_backward(ctx, grad, _tape_grad):
    key, n, keep_all, checkpoint, step = ctx.config
    tape, controls, params = ctx.saved_tensors
    want_u, want_c, want_p = ctx.needs_input_grad[6:9]
    if grad is None or not (want_u or want_c or want_p):
        return (None,) * 9
    g_u, g_c, g_p = ROLLOUT_VJP(
        key, n, keep_all, checkpoint, step, want_p, tape, controls, params, grad
    )
    return (None,) * 6 + (
        g_u if want_u else None, g_c if want_c else None, g_p if want_p else None,
    )


# ---- its reverse sweep: (key, n, keep_all, checkpoint, step, want_p, tape, controls, params,
#      grad) -> (g_u0, g_controls, g_params); an absent input gets an empty cotangent
def _rollout_vjp_kernel(
    key: int, n: int, keep_all: bool, checkpoint: int | None, step: bool, want_p: bool,
    tape: torch.Tensor, controls: torch.Tensor | None, params: torch.Tensor | None,
    grad: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    ADJOINT_CALLS["count"] += 1
    stepper = _LIVE[key]
    u = tape.numpy()
    dtype = u.dtype
    if controls is None:
        c = np.zeros((0, u.shape[1], *(stepper.control_shape or ())), dtype=dtype)
    else:
        c = np.ascontiguousarray(controls.numpy()[None] if step else controls.numpy())
    p = (stepper.param_array(None, dtype) if params is None
         else np.ascontiguousarray(params.numpy()))
    g_u, g_c, g_p = _backward(stepper, n, u, c, p, grad.numpy(), keep_all, want_p, checkpoint)
    empty = torch.empty(0, dtype=grad.dtype)
    return (
        torch.from_numpy(g_u),
        empty if controls is None else torch.from_numpy(g_c[0] if step else g_c),
        torch.from_numpy(g_p) if want_p and params is not None else empty.clone(),
    )


def _rollout_vjp_fake(key, n, keep_all, checkpoint, step, want_p, tape, controls, params, grad):
    empty = grad.new_empty(0)
    return (
        grad.new_empty(grad.shape[1:] if keep_all else grad.shape),
        empty if controls is None else grad.new_empty(controls.shape),
        grad.new_empty(params.shape) if want_p and params is not None else empty.clone(),
    )


# ---- vmap: the mapped dimension joins the solver's batch
def _merge(x: torch.Tensor | None, dim: int | None, axis: int, size: int) -> torch.Tensor | None:
    """``x`` mapped along ``dim`` (or unmapped: repeated) with that dimension merged into its
    batch axis ``axis`` (of the unmapped shape), mapped index first: (.., V * B, ..)."""
    if x is None:
        return None
    if dim is None:
        x = x.unsqueeze(axis).expand(*x.shape[:axis], size, *x.shape[axis:])
    else:
        x = x.movedim(dim, axis)
    return x.flatten(axis, axis + 1)


def _split(x: torch.Tensor, axis: int, size: int) -> torch.Tensor:
    """The inverse of :func:`_merge`: (.., V * B, ..) -> (.., V, B, ..)."""
    return x.unflatten(axis, (size, x.shape[axis] // size))


def _per_element(apply: Callable, info, in_dims: tuple, args: tuple) -> tuple:
    """The fallback: one call per mapped element, results stacked along dimension 0."""
    outs = [
        apply(*(a.select(d, i) if isinstance(d, int) else a
                for a, d in zip(args, in_dims, strict=True)))
        for i in range(info.batch_size)
    ]
    return tuple(torch.stack(parts) for parts in zip(*outs, strict=True)), (0,) * len(outs[0])


def _rollout_vmap(info, in_dims, *args):
    key, n, keep_all, checkpoint, step, store, u0, controls, params = args
    d_u, d_c, d_p = in_dims[6:9]
    if d_p is not None:  # one parameter vector per solver call
        return _per_element(ROLLOUT, info, in_dims, args)
    size = info.batch_size
    u = _merge(u0, d_u, 0, size)
    c = _merge(controls, d_c, 0 if step else 1, size)
    out, tape = ROLLOUT(key, n, keep_all, checkpoint, step, store, u, c, params)
    return (_split(out, int(keep_all), size), _split(tape, 1, size)), (int(keep_all), 1)


def _rollout_vjp_vmap(info, in_dims, *args):
    key, n, keep_all, checkpoint, step, want_p, tape, controls, params, grad = args
    d_t, d_c, d_p, d_g = in_dims[6:10]
    if want_p or d_p is not None:  # parameter cotangents per mapped element: one call each
        return _per_element(ROLLOUT_VJP, info, in_dims, args)
    size = info.batch_size
    g_u, g_c, g_p = ROLLOUT_VJP(
        key, n, keep_all, checkpoint, step, want_p, _merge(tape, d_t, 1, size),
        _merge(controls, d_c, 0 if step else 1, size), params,
        _merge(grad, d_g, int(keep_all), size),
    )
    if controls is not None:
        return (_split(g_u, 0, size), _split(g_c, 0 if step else 1, size), g_p), (
            0, 0 if step else 1, None)
    return (_split(g_u, 0, size), g_c, g_p), (0, None, None)


ROLLOUT_VJP = _Operator("rollout_vjp", _rollout_vjp_kernel, _rollout_vjp_fake, _rollout_vjp_vmap)
ROLLOUT = _Operator("rollout", _rollout_kernel, _rollout_fake, _rollout_vmap,
                    _rollout_setup, _rollout_backward)


# ---- grouped rollout: (keys, rows, n, store, u0) -> (out, tape)
def _check_partition(rows_of_groups: Sequence[object], batch: int) -> list:
    """Each group's rows (a slice stays a slice: a view, no gather), after checking that the
    groups cover every row of the batch exactly once."""
    indices, covered = [], []
    for i, rows in enumerate(rows_of_groups):
        if isinstance(rows, slice):
            indices.append(rows)
            covered.append(np.arange(batch)[rows])
            continue
        idx = rows.numpy() if isinstance(rows, torch.Tensor) else np.asarray(rows)
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


def _grouped_kernel(
    keys: list[int], rows: list[torch.Tensor], n: int, store: bool, u0: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    u = _as_numpy(u0, "u0", None)
    indices = _check_partition(rows, u.shape[0])
    out = np.empty(u.shape, dtype=u.dtype)
    tape = np.empty(_tape_shape(u.shape, n, store, None), dtype=u.dtype)
    for key, idx in zip(keys, indices, strict=True):
        part, kept = _forward(_LIVE[key], n, u[idx], None, None, False, store)
        out[idx] = part
        if kept is not None:
            tape[:, idx] = kept
    return torch.from_numpy(out), torch.from_numpy(tape)


def _grouped_fake(keys, rows, n, store, u0):
    return torch.empty_like(u0), u0.new_empty(_tape_shape(u0.shape, n, store, None))


def _grouped_setup(ctx, inputs, output) -> None:
    ctx.config = inputs[:3]
    ctx.steppers = [_LIVE[k] for k in inputs[0]]  # alive until the backward pass
    ctx.set_materialize_grads(False)
    ctx.save_for_backward(output[1])


def _grouped_backward(ctx, grad, _tape_grad):
    rows = ctx.config[1]
    # The operator's rows are a list of tensors, and so must their (absent) cotangents be.
    no_rows = [None] * len(rows) if all(isinstance(r, torch.Tensor) for r in rows) else None
    if grad is None or not ctx.needs_input_grad[4]:
        return None, no_rows, None, None, None
    (tape,) = ctx.saved_tensors
    return None, no_rows, None, None, GROUPED_VJP(*ctx.config, tape, grad)[0]


def _grouped_vjp_kernel(
    keys: list[int], rows: list[torch.Tensor], n: int, tape: torch.Tensor, grad: torch.Tensor
) -> tuple[torch.Tensor]:
    ADJOINT_CALLS["count"] += 1
    cot, u = grad.numpy(), tape.numpy()
    out = np.empty(cot.shape, dtype=cot.dtype)
    for key, idx in zip(keys, _check_partition(rows, cot.shape[0]), strict=True):
        stepper = _LIVE[key]
        part = np.ascontiguousarray(u[:, idx])
        c = stepper.check_controls(None, n, part[0])
        p = stepper.param_array(None, part.dtype)
        out[idx] = _backward(stepper, n, part, c, p, cot[idx], False, False, None)[0]
    return (torch.from_numpy(out),)


def _grouped_vjp_fake(keys, rows, n, tape, grad):
    return (torch.empty_like(grad),)


def _grouped_vmap(info, in_dims, *args):
    return _per_element(GROUPED, info, in_dims, args)


def _grouped_vjp_vmap(info, in_dims, *args):
    return _per_element(GROUPED_VJP, info, in_dims, args)


GROUPED_VJP = _Operator("rollout_grouped_vjp", _grouped_vjp_kernel, _grouped_vjp_fake,
                        _grouped_vjp_vmap)
GROUPED = _Operator("rollout_grouped", _grouped_kernel, _grouped_fake, _grouped_vmap,
                    _grouped_setup, _grouped_backward)


# ------------------------------------------------------------------ the public functions
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


def _requires_grad(x: torch.Tensor | None) -> bool:
    """Whether ``x`` needs a gradient, looking through ``torch.func.vmap``'s wrappers: a mapped
    tensor reports ``requires_grad=False`` even when the tensor it wraps needs one (the vmap
    rule then records the node on the unwrapped tensors, so the tape must be kept for it)."""
    if x is None:
        return False
    while not x.requires_grad and torch._C._functorch.is_batchedtensor(x):
        x = torch._C._functorch.get_unwrapped(x)
    return x.requires_grad


def _torch_inputs(names: tuple[str, ...], *inputs: object) -> tuple[bool, tuple]:
    """Whether the backward pass needs a tape, and the inputs as tensors (the first, the
    state, required; the others may be None), detached when no gradient is wanted.

    NumPy arrays become tensors sharing their memory, copied when a gradient is wanted (then
    the backward pass reads them: autograd guards a tensor against in-place edits, not an
    array)."""
    converted = False
    if inputs[0] is None or not all(x is None or isinstance(x, torch.Tensor) for x in inputs):
        converted = True
        inputs = tuple(
            x if isinstance(x, torch.Tensor) or (x is None and i) else _from_numpy(x, names[i])
            for i, x in enumerate(inputs)
        )
    grad = torch.is_grad_enabled() and any(_requires_grad(x) for x in inputs)
    if not grad:
        return False, tuple(None if x is None else x.detach() for x in inputs)
    if converted:
        inputs = tuple(x if x is None or x.requires_grad else x.clone() for x in inputs)
    return True, inputs


_ROLLOUT_INPUTS = ("u0", "controls", "params")
_STEP_INPUTS = ("u", "control", "params")


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
    n = _check_steps(n)
    store, (u,) = _torch_inputs(("u0",), u0)
    keys = [_key(stepper) for stepper, _ in groups]
    rows = [r for _, r in groups]
    if torch.compiler.is_compiling():  # an operator takes tensors, not slices or arrays
        rows = [torch.arange(u.shape[0])[r] if isinstance(r, slice) else torch.as_tensor(r)
                for r in rows]
    return GROUPED(keys, rows, n, store, u)[0]


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
    gradient; see the module docstring), of any strides; the result is a tensor.
    ``keep="all"`` returns u_0 .. u_n; ``checkpoint`` bounds the number of states held for the
    backward pass (see :meth:`Stepper.vjp`), checked here even when no backward pass follows.
    ``n = 0`` returns a copy of ``u0`` (shape (1, B, ...) with ``keep="all"``).
    """
    if keep not in ("last", "all"):
        raise ValueError(f"keep must be 'last' or 'all', not {keep!r}")
    n = _check_steps(n)
    store, tensors = _torch_inputs(_ROLLOUT_INPUTS, u0, controls, params)
    return ROLLOUT(_key(stepper), n, keep == "all", checkpoint, False, store, *tensors)[0]


def step(
    stepper: Stepper,
    u: torch.Tensor | np.ndarray,
    control: torch.Tensor | np.ndarray | None = None,
    params: torch.Tensor | np.ndarray | None = None,
) -> torch.Tensor:
    """Differentiable single step; ``control`` has shape (B, *control_shape). Tensors or NumPy
    arrays in (see :func:`rollout`), a tensor out."""
    store, tensors = _torch_inputs(_STEP_INPUTS, u, control, params)
    return ROLLOUT(_key(stepper), 1, False, None, True, store, *tensors)[0]
