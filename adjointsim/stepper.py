"""The solver contract: a scene compiled into a batched stepper with a discrete adjoint.

A :class:`Stepper` is a configured scene (equation, grid, boundary conditions, coefficients,
forcing, control hook). It advances a batch ``u`` of shape ``(B, C, *grid)`` by ``n`` steps in
one compiled call and runs the discrete adjoint of those ``n`` steps in one more.

A subclass supplies two numba kernels through ``_forward`` and ``_adjoint``:

``_forward(states, n, ctrl, p)``
    ``states`` has shape ``(S, B, C, *grid)`` and holds ``u_0`` in ``states[0]``; the kernel
    writes ``u_{k+1} = step(u_k, ctrl[k]; p)`` into ``states[(k + 1) % S]``. ``S = n + 1`` keeps
    the whole trajectory, ``S = 2`` is a ping-pong buffer. ``ctrl`` has shape
    ``(n, B, *control_shape)``, or a zero-length first axis when the scene runs uncontrolled
    (then the control costs nothing).

``_adjoint(states, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p)``
    Reverses the ``m = states.shape[0]`` steps whose inputs are ``states[0..m-1]``. On entry
    ``ubar`` is the cotangent of ``u_m``; for ``k = m-1 .. 0`` it becomes
    ``(dS/du_k)^T ubar`` plus ``cot[cmap[k]]`` when ``cmap[k] >= 0``. It writes
    ``cbar[k] = (dS/dc_k)^T ubar`` when ``cbar`` is not empty, and, if ``want_p``, adds
    ``(dS/dp)^T ubar`` to ``pbar`` (float64, one entry per scene parameter).

Kernels are written so that they also run on complex arrays, with comparisons on ``.real``: the
verification harness uses the complex-step derivative as an exact tangent-linear model.
Everything else here (validation, checkpointing, non-finite detection) is shared.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numba
import numpy as np

FLOAT_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))


class NonFiniteStateError(FloatingPointError):
    """A rollout produced NaN or Inf; ``step`` is where it first appeared."""

    def __init__(self, solver: str, step: int, last_max: float):
        self.step = step
        super().__init__(
            f"{solver}: the state became non-finite at step {step} "
            f"(max |u| one step earlier: {last_max:.3g}). The scene is unstable for this input: "
            "reduce dt, lower the coefficients or check the initial state."
        )


class NonFiniteInputError(ValueError):
    """A state handed to a solver already holds NaN or Inf."""


@dataclass(frozen=True)
class Choice:
    """A discrete scene option, for the property-test strategies."""

    values: tuple


@dataclass(frozen=True)
class Range:
    """A continuous (``integer=False``) or integer scene option, for the property tests."""

    lo: float
    hi: float
    integer: bool = False


@dataclass(frozen=True)
class Cotangents:
    """What :meth:`Stepper.vjp` returns.

    ``state``: cotangent of the initial state. ``controls``: one per step and batch element, or
    None when the rollout ran uncontrolled. ``params``: one float per scene parameter (summed
    over the batch), or None when they were not asked for.
    """

    state: np.ndarray
    controls: np.ndarray | None
    params: dict[str, float] | None


class Stepper:
    """Base class of every solver. Subclasses set the class attributes and the two kernels."""

    #: registry name, e.g. ``"diffusion1d-ftcs"``
    name: ClassVar[str]
    #: scene options the property tests draw (constructor keyword -> Choice/Range)
    space: ClassVar[dict[str, Choice | Range]] = {}
    #: False when the kernels cannot run on complex arrays (the checker then uses
    #: Richardson-extrapolated finite differences as the tangent model)
    complex_step: ClassVar[bool] = True

    # Set by subclass constructors.
    grid_shape: tuple[int, ...]
    channels: int
    #: per-step, per-batch-element control shape; None when the scene has no control hook
    control_shape: tuple[int, ...] | None
    dt: float
    #: differentiable scene parameters and their values, in kernel order
    param_names: tuple[str, ...] = ()
    param_values: tuple[float, ...] = ()

    # ----------------------------------------------------------------- subclass hooks
    def _forward(self, states: np.ndarray, n: int, ctrl: np.ndarray, p: np.ndarray) -> None:
        raise NotImplementedError

    def _adjoint(
        self,
        states: np.ndarray,
        ctrl: np.ndarray,
        p: np.ndarray,
        cot: np.ndarray,
        cmap: np.ndarray,
        ubar: np.ndarray,
        cbar: np.ndarray,
        pbar: np.ndarray,
        want_p: bool,
    ) -> None:
        raise NotImplementedError

    def check_params(self, p: np.ndarray) -> None:
        """Raise ValueError if parameters ``p`` (real, kernel order) break a stability limit."""

    @classmethod
    def default(cls) -> Stepper:
        """A small scene for checks and benchmarks."""
        return cls()

    @classmethod
    def benchmark_scene(cls, n: int) -> Stepper:
        """The default scene at ``n`` points per axis (the benchmarks' size knob)."""
        return cls(n=n)

    def random_state(
        self, rng: np.random.Generator, batch: int = 1, dtype: Any = np.float64
    ) -> np.ndarray:
        """A random admissible state: smooth-ish, of order one."""
        return rng.standard_normal(self.state_shape(batch)).astype(dtype)

    def random_controls(
        self, rng: np.random.Generator, n: int, batch: int = 1, dtype: Any = np.float64
    ) -> np.ndarray:
        """Random per-step controls of order one."""
        if self.control_shape is None:
            raise ValueError(f"{self.name} has no control hook")
        return rng.standard_normal((n, batch, *self.control_shape)).astype(dtype)

    # ----------------------------------------------------------------- public API
    def state_shape(self, batch: int = 1) -> tuple[int, ...]:
        return (batch, self.channels, *self.grid_shape)

    @property
    def params(self) -> dict[str, float]:
        """The scene's differentiable parameters and their values."""
        return dict(zip(self.param_names, self.param_values))

    def step(
        self,
        u: np.ndarray,
        control: np.ndarray | None = None,
        params: Mapping[str, float] | Sequence[float] | np.ndarray | None = None,
    ) -> np.ndarray:
        """One step: ``u`` of shape (B, C, *grid), ``control`` of shape (B, *control_shape)."""
        ctrl = None if control is None else np.asarray(control)[None]
        return self.rollout(u, 1, ctrl, params)

    def rollout(
        self,
        u0: np.ndarray,
        n: int,
        controls: np.ndarray | None = None,
        params: Mapping[str, float] | Sequence[float] | np.ndarray | None = None,
        keep: str = "last",
    ) -> np.ndarray:
        """Advance ``u0`` by ``n`` steps in one compiled call.

        ``controls``: shape (n, B, *control_shape) or None. ``params`` overrides the scene's
        parameter values. ``keep="last"`` returns u_n (B, C, *grid); ``keep="all"`` returns
        every state u_0 .. u_n, shape (n + 1, B, C, *grid).
        """
        if keep not in ("last", "all"):
            raise ValueError(f"keep must be 'last' or 'all', not {keep!r}")
        u0 = self._check_state(u0, "u0")
        n = _check_steps(n)
        ctrl = self._check_controls(controls, n, u0)
        p = self.param_array(params, u0.dtype)
        states = self._run(u0, n, ctrl, p, keep_all=keep == "all")
        self._raise_if_nonfinite(states, keep == "all", u0, ctrl, p)
        return states if keep == "all" else states[n % 2]

    def vjp(
        self,
        u0: np.ndarray,
        n: int,
        cotangents: np.ndarray | Mapping[int, np.ndarray],
        controls: np.ndarray | None = None,
        params: Mapping[str, float] | Sequence[float] | np.ndarray | None = None,
        wrt_params: bool = False,
        checkpoint: int | None = None,
        trajectory: np.ndarray | None = None,
    ) -> Cotangents:
        """Cotangents of u0, the controls and (if ``wrt_params``) the scene parameters.

        ``cotangents`` is one array of the state's shape (the cotangent of u_n), an array of
        shape (n + 1, B, C, *grid) (one per state), or a mapping from step index (negative
        counts from n) to the cotangent of that state. ``checkpoint=s`` holds at most ``s``
        states at once (s ≥ 4) and recomputes the rest from checkpoints, nesting segments when
        one level does not fit (memory s states, about log_s(n) extra forward passes). By
        default every state is kept. ``trajectory``, the states u_0 .. u_n of
        ``rollout(..., keep="all")`` with the same inputs, skips the forward pass.
        """
        u0 = self._check_state(u0, "u0")
        n = _check_steps(n)
        ctrl = self._check_controls(controls, n, u0)
        p = self.param_array(params, u0.dtype)
        cot, cmap = self._check_cotangents(cotangents, n, u0)
        if trajectory is not None and (
            trajectory.shape != (n + 1, *u0.shape) or trajectory.dtype != u0.dtype
        ):
            raise ValueError(
                f"{self.name}: trajectory has shape {trajectory.shape} and dtype "
                f"{trajectory.dtype}; expected {(n + 1, *u0.shape)} and {u0.dtype}, "
                'as returned by rollout(..., keep="all")'
            )
        return self._vjp(
            u0, n, ctrl, p, cot, cmap, wrt_params, checkpoint, controls is not None, trajectory
        )

    # ----------------------------------------------------------------- shared machinery
    def param_array(
        self,
        params: Mapping[str, float] | Sequence[float] | np.ndarray | None,
        dtype: Any,
    ) -> np.ndarray:
        """Scene parameters in kernel order, as an array of the state's ``dtype``, checked
        against the scheme's stability limits.

        The scene's own values (``params=None``) are checked once per dtype and the array is
        reused (a controller asks for them every step): do not write to it."""
        if params is None:
            cache = self.__dict__.setdefault("_param_arrays", {})
            hit = cache.get(dtype)
            if hit is not None and hit[0] == self.param_values:
                return hit[1]
            values = np.array(self.param_values, dtype=np.float64)
        elif isinstance(params, Mapping):
            unknown = set(params) - set(self.param_names)
            if unknown:
                raise ValueError(
                    f"{self.name} has no parameter(s) {sorted(unknown)}; "
                    f"its parameters are {list(self.param_names)}"
                )
            values = np.array(
                [params.get(k, v) for k, v in zip(self.param_names, self.param_values)],
                dtype=np.float64,
            )
        else:
            values = np.asarray(params, dtype=np.float64)
            if values.shape != (len(self.param_names),):
                raise ValueError(
                    f"{self.name} takes {len(self.param_names)} parameter(s) "
                    f"{list(self.param_names)}; got an array of shape {values.shape}"
                )
        if not np.all(np.isfinite(values)):
            raise ValueError(f"{self.name}: parameters {values} must be finite")
        self.check_params(values)
        out = np.ascontiguousarray(values, dtype=dtype)
        if params is None:
            cache[dtype] = (self.param_values, out)
        return out

    def _check_state(self, u: np.ndarray, what: str) -> np.ndarray:
        u = np.asarray(u)
        if u.dtype not in FLOAT_DTYPES:
            raise TypeError(
                f"{self.name}: {what} has dtype {u.dtype}; expected float32 or float64 "
                f"(convert with {what}.astype(np.float64))"
            )
        expected = (self.channels, *self.grid_shape)
        if u.ndim != len(expected) + 1 or u.shape[1:] != expected:
            dims = ", ".join(map(str, expected))
            raise ValueError(
                f"{self.name}: {what} has shape {u.shape}; expected (B, {dims})"
                " = (batch, channels, *grid)"
            )
        if not _all_finite(u):
            bad = np.unique(np.nonzero(~np.isfinite(u))[0]).tolist()
            raise NonFiniteInputError(
                f"{self.name}: {what} has non-finite values in batch element(s) {bad}"
            )
        return np.ascontiguousarray(u)

    def _check_controls(self, controls: np.ndarray | None, n: int, u0: np.ndarray) -> np.ndarray:
        shape = self.control_shape
        if controls is None:
            return np.zeros((0, u0.shape[0], *(shape or ())), dtype=u0.dtype)
        if shape is None:
            raise ValueError(f"{self.name} has no control hook; pass controls=None")
        c = np.asarray(controls)
        expected = (n, u0.shape[0], *shape)
        if c.shape != expected:
            raise ValueError(
                f"{self.name}: controls have shape {c.shape}; expected {expected} "
                "= (steps, batch, *control_shape)"
            )
        if c.dtype != u0.dtype:
            raise TypeError(
                f"{self.name}: controls have dtype {c.dtype} but the state is {u0.dtype}; "
                "cast them to the state's dtype"
            )
        if not _all_finite(c):
            raise ValueError(f"{self.name}: controls contain non-finite values")
        return np.ascontiguousarray(c)

    def _check_cotangents(
        self, cotangents: np.ndarray | Mapping[int, np.ndarray], n: int, u0: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Stack the cotangents and map each step index to its row (or -1)."""
        if isinstance(cotangents, Mapping):
            items = {}
            for k, v in cotangents.items():
                kk = int(k) + (n + 1 if int(k) < 0 else 0)
                if not 0 <= kk <= n:
                    raise ValueError(f"cotangent step {k} is outside the rollout 0..{n}")
                items[kk] = v
            steps = sorted(items)
            arrays = [items[k] for k in steps]
        else:
            c = np.asarray(cotangents)
            if c.shape == u0.shape:
                steps, arrays = [n], [c]
            elif c.shape == (n + 1, *u0.shape):
                steps, arrays = list(range(n + 1)), list(c)
            else:
                raise ValueError(
                    f"{self.name}: cotangents have shape {c.shape}; expected {u0.shape} "
                    f"(the last state) or {(n + 1, *u0.shape)} (every state), or a dict "
                    "{step: array}"
                )
        for a in arrays:
            if np.shape(a) != u0.shape:
                raise ValueError(
                    f"{self.name}: a cotangent has shape {np.shape(a)}; expected {u0.shape}"
                )
        cot = np.ascontiguousarray(np.stack(arrays).astype(u0.dtype, copy=False))
        cmap = np.full(n + 1, -1, dtype=np.int64)
        cmap[steps] = np.arange(len(steps))
        return cot, cmap

    def _run(
        self, u0: np.ndarray, n: int, ctrl: np.ndarray, p: np.ndarray, keep_all: bool
    ) -> np.ndarray:
        states = np.empty((n + 1 if keep_all else 2, *u0.shape), dtype=np.result_type(u0, p))
        states[0] = u0
        self._forward(states, n, ctrl, p)
        return states

    def _vjp(
        self,
        u0: np.ndarray,
        n: int,
        ctrl: np.ndarray,
        p: np.ndarray,
        cot: np.ndarray,
        cmap: np.ndarray,
        wrt_params: bool,
        checkpoint: int | None,
        controlled: bool,
        trajectory: np.ndarray | None = None,
    ) -> Cotangents:
        if checkpoint is not None and checkpoint < 4:
            raise ValueError(f"checkpoint must hold at least 4 states, not {checkpoint}")
        dtype = np.result_type(u0, p, cot)
        ubar = np.zeros(u0.shape, dtype=dtype)
        if cmap[n] >= 0:
            ubar += cot[cmap[n]]
        cbar = np.zeros(ctrl.shape, dtype=dtype)
        pbar = np.zeros(len(self.param_names), dtype=np.result_type(np.float64, dtype))
        budget = n + 2 if checkpoint is None else int(checkpoint)
        sweep = _AdjointSweep(self, ctrl, p, cot, cmap, ubar, cbar, pbar, wrt_params)
        if trajectory is not None:
            sweep.reverse_stored(np.ascontiguousarray(trajectory[:n]), 0, n)
        else:
            sweep.reverse(u0.astype(dtype, copy=False), 0, n, budget)
        if not _all_finite(ubar):
            self._raise_if_nonfinite(self._run(u0, n, ctrl, p, keep_all=False), False, u0, ctrl, p)
            raise FloatingPointError(
                f"{self.name}: the adjoint sweep became non-finite although the forward rollout "
                "stayed finite; the cotangents or the rollout length are too large"
            )
        return Cotangents(
            state=ubar,
            controls=cbar if controlled else None,
            params=dict(zip(self.param_names, pbar.tolist())) if wrt_params else None,
        )

    def _raise_if_nonfinite(
        self, states: np.ndarray, keep_all: bool, u0: np.ndarray, ctrl: np.ndarray, p: np.ndarray
    ) -> None:
        """Zero cost when the rollout stayed finite; otherwise find the first bad step."""
        if _all_finite(states[-1] if keep_all else states):
            return
        offset = 0
        if not keep_all:
            # Replay in chunks that keep every state until one chunk holds the first bad step.
            u, chunk = u0, 256
            while True:
                c = ctrl[offset : offset + chunk] if ctrl.shape[0] else ctrl
                m = c.shape[0] if ctrl.shape[0] else chunk
                states = self._run(u, m, c, p, keep_all=True)
                if not _all_finite(states):
                    break
                u, offset = states[m], offset + m
        bad = ~np.isfinite(states).reshape(states.shape[0], -1).all(axis=1)
        first = int(np.argmax(bad))
        raise NonFiniteStateError(self.name, offset + first, float(np.abs(states[first - 1]).max()))


class _AdjointSweep:
    """Reverse a rollout segment by segment within a budget of stored states.

    A segment whose states fit the budget is recomputed from its start state with every state
    kept, then reversed by one adjoint kernel call. A longer one is cut into k pieces whose
    start states are stored on a forward pass; the pieces are reversed last to first with the
    budget that remains, recursively, so at most ``budget`` states are alive at once.
    """

    def __init__(self, stepper, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p):
        self.stepper, self.ctrl, self.p = stepper, ctrl, p
        self.cot, self.cmap, self.ubar, self.cbar, self.pbar = cot, cmap, ubar, cbar, pbar
        self.want_p = want_p

    def _controls(self, a: np.ndarray, lo: int, hi: int) -> np.ndarray:
        return a[lo:hi] if a.shape[0] else a

    def reverse_stored(self, inputs: np.ndarray, lo: int, hi: int) -> None:
        self.stepper._adjoint(
            inputs, self._controls(self.ctrl, lo, hi), self.p, self.cot, self.cmap[lo:hi],
            self.ubar, self._controls(self.cbar, lo, hi), self.pbar, self.want_p,
        )

    def reverse(self, u_start: np.ndarray, lo: int, hi: int, budget: int) -> None:
        m = hi - lo
        if m == 0:
            return
        c = self._controls(self.ctrl, lo, hi)
        if m + 2 <= budget:  # the m + 1 states and the start state they copy
            trajectory = self.stepper._run(u_start, m, c, self.p, keep_all=True)
            self.reverse_stored(trajectory[:m], lo, hi)
            return
        if budget <= 3:
            # No room for a nested level: recompute each step's input from the segment start.
            for j in range(m - 1, -1, -1):
                c = self._controls(self.ctrl, lo, lo + j)
                ring = self.stepper._run(u_start, j, c, self.p, False)
                self.reverse_stored(ring[j % 2][None], lo + j, lo + j + 1)
            return
        k = _pieces(m, budget)
        bounds = [lo + (m * i) // k for i in range(k + 1)]
        starts, u = [u_start], u_start
        for a0, a in zip(bounds[:-2], bounds[1:-1]):
            ring = self.stepper._run(u, a - a0, self._controls(self.ctrl, a0, a), self.p, False)
            u = ring[(a - a0) % 2].copy()
            starts.append(u)
        del ring, u  # only the stored starts may stay alive while the pieces are reversed
        for i in range(k - 1, -1, -1):
            # Pieces already reversed have released their start states.
            self.reverse(starts.pop(), bounds[i], bounds[i + 1], budget - i)


def _pieces(m: int, budget: int) -> int:
    """Fewest pieces so that one more level fits, else half the budget (and recurse).

    Piece i is reversed with ``budget - i`` states, so k ≤ budget - 2 leaves the last piece
    at least 3.
    """
    for k in range(2, budget - 1):
        if -(-m // k) + 2 <= budget - (k - 1):
            return k
    return max(2, min(budget - 2, budget // 2))


@numba.njit(cache=True)
def _all_finite(a: np.ndarray) -> bool:
    # Stops at the first NaN/Inf and makes no temporary: several times faster than
    # np.all(np.isfinite(a)) on the small states of a training step.
    for v in a.ravel():
        if not np.isfinite(v):
            return False
    return True


def _check_steps(n: int) -> int:
    if int(n) != n or n < 0:
        raise ValueError(f"the number of steps must be a non-negative integer, not {n!r}")
    return int(n)
