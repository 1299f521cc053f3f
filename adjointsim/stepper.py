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

A subclass whose adjoint kernel can reuse values its forward kernel computes (stage fields, say)
sets ``_records_tape = True`` and takes one more argument in each kernel:
``_forward(states, n, ctrl, p, record)`` with ``record`` true records them (only asked with
``S = n + 1``) and returns the tape, or None when it keeps none, and
``_adjoint(..., want_p, tape)`` gets that tape back with (a prefix of) the states it was recorded
for. A vjp records only when no parameter cotangents are wanted. The tape travels with the call,
never on the stepper, so that one stepper serves nested or concurrent sweeps.

Kernels are written so that they also run on complex arrays, with comparisons on ``.real``: the
verification harness uses the complex-step derivative as an exact tangent-linear model.
Everything else here (validation, checkpointing, non-finite detection) is shared.
"""

from __future__ import annotations

import numbers
import operator
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from math import comb
from typing import Any, ClassVar

import numba
import numpy as np

from . import parallel, validate

FLOAT_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))
#: smallest ``checkpoint`` budget: u_0 and the two-state buffer the forward kernel advances in
MIN_CHECKPOINT = 3


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
    """An input handed to a solver (a state, controls, a parameter, a cotangent, a stored
    trajectory) already holds NaN or Inf; the message names the input and, where it has steps,
    the first bad one."""


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
    """Base class of every solver. Subclasses set the class attributes and the two kernels.

    :meth:`rollout`, :meth:`step` and :meth:`vjp` validate their inputs on every call. A caller
    that runs and reverses the same inputs more than once, or that has validated them already
    (a closed loop calls the solver once per step), validates once and takes the fast path::

        u0, n, controls, params = stepper.prepare(u0, n, controls, params)
        traj = stepper.rollout_prepared(u0, n, controls, params, keep="all")
        cot, cmap = stepper.check_cotangents({-1: w}, n, u0)  # w: the cotangent of u_n
        g = stepper.vjp_prepared(u0, n, controls, params, cot, cmap, trajectory=traj)

    :meth:`prepare` (or its parts :meth:`check_state`, :meth:`check_controls`,
    :meth:`param_array`, and :meth:`check_cotangents` and :meth:`check_trajectory` for a vjp)
    returns the arrays the fast path takes; :meth:`rollout_prepared` and :meth:`vjp_prepared`
    check nothing about them, by design: they take what the checks refuse, such as the
    complex-step perturbations of the verification harness, and a closed loop pays for no check
    twice. So pass only what the checks returned (or arrays of the same form), and never write
    to them while a result still depends on them. The fast path gives bit for bit the results
    of the checked one; a rollout that blows up still raises :class:`NonFiniteStateError`, and a
    reverse sweep whose result is not finite a :class:`FloatingPointError` (or, when an input
    it was handed is not finite, a :class:`NonFiniteInputError` naming it).

    A stepper keeps no per-call state (only caches: coefficient tables, a reusable tape
    buffer), so one stepper serves nested sweeps and several threads at once.
    """

    #: registry name, e.g. ``"diffusion1d-ftcs"``
    name: ClassVar[str]
    #: scene options the property tests draw (constructor keyword -> Choice/Range)
    space: ClassVar[dict[str, Choice | Range]] = {}
    #: False when the kernels cannot run on complex arrays (the checker then uses
    #: Richardson-extrapolated finite differences as the tangent model)
    complex_step: ClassVar[bool] = True
    #: the change of the trajectory the checker's difference steps start from; a piecewise-
    #: smooth map (interpolation at backtraced points) lowers it so that the largest steps
    #: rarely cross a switch, where a difference stops being a derivative
    check_perturbation: ClassVar[float] = 0.1

    # Set by subclass constructors.
    grid_shape: tuple[int, ...]
    channels: int
    #: per-step, per-batch-element control shape; None when the scene has no control hook
    control_shape: tuple[int, ...] | None
    dt: float
    #: differentiable scene parameters and their values, in kernel order
    param_names: tuple[str, ...] = ()
    param_values: tuple[float, ...] = ()
    #: True when the kernels keep a tape (see the module docstring): a vjp without parameter
    #: cotangents then records one whenever it recomputes a segment whole with a state to spare
    _records_tape: ClassVar[bool] = False
    #: a batch of at least this many rows runs in chunks of at least as many (see
    #: :func:`adjointsim.parallel.chunks`)
    _min_chunk_rows: ClassVar[int] = 1
    #: ns per point-step on one core, roughly: only decides whether a call is worth splitting
    #: over threads (a stencil's is about 2, a spectral step's 10-16)
    point_cost: ClassVar[float] = 2.0

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
        """One step: ``u`` of shape (B, C, *grid), ``control`` of shape (B, *control_shape).

        An empty batch (B = 0) gives an empty result."""
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
        every state u_0 .. u_n, shape (n + 1, B, C, *grid). ``n = 0`` returns a copy of ``u0``
        (``keep="all"``: shape (1, B, C, *grid)); an empty batch (B = 0) an empty array of the
        same shape. Neither calls the kernels.
        """
        if keep not in ("last", "all"):
            raise ValueError(f"keep must be 'last' or 'all', not {keep!r}")
        return self.rollout_prepared(*self.prepare(u0, n, controls, params), keep=keep)

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
        shape (n + 1, B, C, *grid) (one per state), or a mapping from step index to the
        cotangent of that state: 0 .. n, or -(n + 1) .. -1 counting from the end (-1 is u_n);
        keys naming the same step are summed.

        ``checkpoint=s`` reverses the rollout holding at most ``s`` states (s ≥ 3) and
        recomputes the others with binomial checkpointing (Griewank & Walther's Revolve
        schedule), which is optimal in forward steps; see :class:`_AdjointSweep` for what is
        counted and the cost (about t·n forward steps where C(s - 2 + t, t) ≥ n). By default
        every state is kept. ``trajectory``, the states u_0 .. u_n of
        ``rollout(..., keep="all")`` with the same inputs, skips the forward pass.

        ``n = 0`` returns the cotangent of u_0 (and zero control and parameter cotangents); an
        empty batch (B = 0) returns empty cotangents and zero parameter cotangents. Neither
        calls the kernels.

        Every input is checked first (the state, the controls, the parameters, each cotangent,
        the trajectory): a NaN or Inf in one raises :class:`NonFiniteInputError` naming it and
        its first bad step, as the sweep would otherwise return NaN or, through a trajectory
        that a linear scheme's state cotangent never reads, a silently wrong parameter gradient.
        """
        u0, n, ctrl, p = self.prepare(u0, n, controls, params)
        wrt_params = validate.flag(self.name, "wrt_params", wrt_params)
        cot, cmap = self.check_cotangents(cotangents, n, u0)
        if trajectory is not None:
            trajectory = self.check_trajectory(trajectory, n, u0)
        g = self.vjp_prepared(u0, n, ctrl, p, cot, cmap, wrt_params, checkpoint, trajectory)
        return g if controls is not None else Cotangents(g.state, None, g.params)

    # ----------------------------------------------------------------- validate once ...
    def prepare(
        self,
        u0: np.ndarray,
        n: int,
        controls: np.ndarray | None = None,
        params: Mapping[str, float] | Sequence[float] | np.ndarray | None = None,
    ) -> tuple[np.ndarray, int, np.ndarray, np.ndarray]:
        """Validate a rollout's inputs once: ``(u0, n, controls, params)`` as the fast path
        (:meth:`rollout_prepared`, :meth:`vjp_prepared`) takes them.

        Raises what :meth:`rollout` raises for bad inputs. ``controls=None`` becomes an array
        with a zero-length first axis (an uncontrolled rollout); ``params`` becomes the
        parameter array of :meth:`param_array`, in the state's dtype."""
        u0 = self.check_state(u0, "u0")
        n = validate.count(self.name, "n", n, why="the number of steps")
        return u0, n, self.check_controls(controls, n, u0), self.param_array(params, u0.dtype)

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
            values = self._real_params(
                [params.get(k, v) for k, v in zip(self.param_names, self.param_values)]
            )
        else:
            values = self._real_params(params)
            if values.shape != (len(self.param_names),):
                raise ValueError(
                    f"{self.name} takes {len(self.param_names)} parameter(s) "
                    f"{list(self.param_names)}; got an array of shape {values.shape}"
                )
        if not np.all(np.isfinite(values)):
            bad = ", ".join(f"{k} = {v!r}" for k, v in zip(self.param_names, values.tolist())
                            if not np.isfinite(v))
            raise NonFiniteInputError(f"{self.name}: parameters must be finite, got {bad}")
        self.check_params(values)
        out = np.ascontiguousarray(values, dtype=dtype)
        if params is None:
            cache[dtype] = (self.param_values, out)
        return out

    def _real_params(self, params: Any) -> np.ndarray:
        """``params`` as float64, refusing what is not a real number: text, booleans, and
        complex values, which a cast would silently drop the imaginary part of (the
        complex-step checks pass theirs to the fast path instead). The error names the
        solver and each parameter refused."""
        values = np.asarray(params)
        if values.dtype.kind in "iuf":
            return values.astype(np.float64, copy=False)
        items = np.ravel(np.asarray(params, dtype=object)).tolist()
        bad = ", ".join(
            f"{k} = {v!r}" for k, v in zip(self.param_names, items)
            if isinstance(v, bool)
            or (not isinstance(v, numbers.Real) and not (isinstance(v, complex) and not v.imag))
        ) or f"values of dtype {values.dtype}"
        hint = ("pass the real part if that is what you mean" if values.dtype.kind == "c"
                else f"give a number for each of {list(self.param_names)}")
        raise TypeError(f"{self.name}: parameters must be real numbers, got {bad}; {hint}")

    def check_state(self, u: np.ndarray, what: str = "u0") -> np.ndarray:
        """``u`` as a C-contiguous float32 or float64 state of shape (B, C, *grid), after
        checking that it is one and finite (errors name it ``what``)."""
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

    def check_controls(self, controls: np.ndarray | None, n: int, u0: np.ndarray) -> np.ndarray:
        """The controls of an ``n``-step rollout from the checked state ``u0``, checked: shape
        (n, B, *control_shape), the state's dtype, finite. None gives the uncontrolled form, a
        zero-length first axis."""
        shape = self.control_shape
        if controls is None:
            return np.zeros((0, u0.shape[0], *(shape or ())), dtype=u0.dtype)
        if shape is None:
            raise ValueError(f"{self.name} has no control hook; pass controls=None")
        return self._check_per_step(
            controls, ("controls have", "controls hold"), (n, u0.shape[0], *shape), u0.dtype, n - 1,
            " = (steps, batch, *control_shape)", "cast them to the state's dtype", "",
        )

    def check_trajectory(self, trajectory: np.ndarray, n: int, u0: np.ndarray) -> np.ndarray:
        """The stored states u_0 .. u_n of an ``n``-step rollout from the checked state ``u0``
        (what ``rollout(..., keep="all")`` returns), checked: shape (n + 1, B, C, *grid), the
        state's dtype, finite, starting at ``u0`` (a trajectory of other inputs would give a
        wrong gradient without a word; its other states are not recomputed to check them)."""
        trajectory = self._check_per_step(
            trajectory, ("trajectory has", "trajectory holds"), (n + 1, *u0.shape), u0.dtype, n,
            f', the {n + 1} states u_0 .. u_{n} that rollout(..., keep="all") returns for the '
            "same inputs",
            'pass the rollout(..., keep="all") of this state',
            '; no rollout returns one: pass rollout(..., keep="all") of the same inputs, or no '
            "trajectory to have the states recomputed",
        )
        if not np.array_equal(trajectory[0], u0):
            raise ValueError(
                f"{self.name}: trajectory[0] is not u0, so the trajectory is of another rollout; "
                'pass rollout(..., keep="all") of the same inputs, or no trajectory to have the '
                "states recomputed"
            )
        return trajectory

    def _check_per_step(
        self, a: Any, what: tuple[str, str], expected: tuple[int, ...], dtype: np.dtype,
        last: int, meaning: str, dtype_fix: str, finite_fix: str,
    ) -> np.ndarray:
        """``a`` (one array per step) as a C-contiguous array of shape ``expected`` and dtype
        ``dtype``, finite; errors name it as ``what`` ("x has", "x holds") and end with the
        fixes given."""
        has, holds = what
        a = np.asarray(a)
        if a.shape != expected:
            raise ValueError(
                f"{self.name}: {has} shape {a.shape}; expected {expected}{meaning}"
            )
        if a.dtype != dtype:
            raise TypeError(
                f"{self.name}: {has} dtype {a.dtype} but the state is {dtype}; {dtype_fix}"
            )
        if not _all_finite(a):
            raise NonFiniteInputError(
                f"{self.name}: {holds} a non-finite value at {_first_bad(a, last)}{finite_fix}"
            )
        return np.ascontiguousarray(a)

    def check_cotangents(
        self, cotangents: np.ndarray | Mapping[int, np.ndarray], n: int, u0: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The cotangents of an ``n``-step rollout from the checked state ``u0``, in any form
        :meth:`vjp` takes, as :meth:`vjp_prepared` takes them: ``(rows, cmap)``, the distinct
        cotangents stacked (k, B, C, *grid) in the state's dtype, and for each state
        u_0 .. u_n the row of its cotangent, or -1 (int64, shape (n + 1,))."""
        if isinstance(cotangents, Mapping):
            rows: dict[int, np.ndarray] = {}
            for key, value in cotangents.items():
                k = _cotangent_step(key, n)
                a = self._cotangent(value, u0.shape, u0.dtype, k, key)
                rows[k] = rows[k] + a if k in rows else a  # keys naming one step add up
            steps = sorted(rows)
            cot = np.zeros((len(steps), *u0.shape), dtype=u0.dtype)
            for i, k in enumerate(steps):
                cot[i] = rows[k]
        else:
            c = np.asarray(cotangents)
            if c.shape == u0.shape:
                steps, cot = [n], self._cotangent(c, c.shape, u0.dtype, n)[None]
            elif c.shape == (n + 1, *u0.shape):
                steps = list(range(n + 1))
                cot = self._cotangent(c, c.shape, u0.dtype)
            else:
                raise ValueError(
                    f"{self.name}: cotangents have shape {c.shape}; expected {u0.shape} "
                    f"(the last state) or {(n + 1, *u0.shape)} (every state), or a dict "
                    "{step: array}"
                )
        cmap = np.full(n + 1, -1, dtype=np.int64)
        cmap[steps] = np.arange(len(steps))
        return np.ascontiguousarray(cot), cmap

    def _cotangent(
        self, value: Any, shape: tuple, dtype: np.dtype, step: int | None = None, key: Any = None
    ) -> np.ndarray:
        """``value`` as a finite real array of ``shape``, in the state's ``dtype``: the cotangent
        of u_step (given under ``key``, if any), or, with ``step`` None, the stacked cotangents
        of u_0 .. u_n. Errors name it; their words are only put together on a failure."""
        a = np.asarray(value)
        if a.shape != shape:
            what = _cotangent_name(step, key)
            raise ValueError(f"{self.name}: {what} has shape {a.shape}; expected {shape}")
        if a.dtype.kind not in "iuf":
            what = _cotangent_name(step, key)
            raise TypeError(f"{self.name}: {what} has dtype {a.dtype}; expected a real array")
        a = a.astype(dtype, copy=False)
        if not _all_finite(a):
            if step is None:
                step = int(np.argmin(np.isfinite(a).reshape(a.shape[0], -1).all(axis=1)))
                a = a[step]
            bad = np.unique(np.nonzero(~np.isfinite(a))[0]).tolist()
            raise NonFiniteInputError(
                f"{self.name}: {_cotangent_name(step, key)} has non-finite values in batch "
                f"element(s) {bad}"
            )
        return a

    # ----------------------------------------------------------------- ... then run fast
    def rollout_prepared(
        self,
        u0: np.ndarray,
        n: int,
        controls: np.ndarray,
        params: np.ndarray,
        keep: str = "last",
        check_finite: bool = True,
    ) -> np.ndarray:
        """:meth:`rollout` of inputs :meth:`prepare` returned, without checking them again.

        ``keep="all"`` returns u_0 .. u_n; anything else u_n, as a view into the rollout's
        two-state buffer. ``check_finite=False`` returns non-finite states as they came instead
        of raising :class:`NonFiniteStateError` (for probes of how far a scene stays stable).
        """
        keep_all = keep == "all"
        states = self._run(u0, n, controls, params, keep_all)
        # u_n (or the two-state buffer) suffices: non-finite values propagate.
        if check_finite and not _all_finite(states[-1] if keep_all else states):
            self._raise_nonfinite(states, keep_all, u0, controls, params, n)
        return states if keep_all else states[n % 2]

    def vjp_prepared(
        self,
        u0: np.ndarray,
        n: int,
        controls: np.ndarray,
        params: np.ndarray,
        cotangents: np.ndarray,
        cmap: np.ndarray,
        wrt_params: bool = False,
        checkpoint: int | None = None,
        trajectory: np.ndarray | None = None,
    ) -> Cotangents:
        """:meth:`vjp` of inputs :meth:`prepare` and :meth:`check_cotangents` returned, without
        checking them again.

        ``trajectory``: u_0 .. u_{n-1} (or more) of the rollout of these inputs, e.g. from
        ``rollout_prepared(..., keep="all")``. The control cotangents come back as an array
        even for an uncontrolled rollout (then with a zero-length first axis).

        Only the result is checked: a state or parameter cotangent that is not finite raises
        (naming the trajectory or the cotangents when one of them holds the NaN or Inf).
        """
        if checkpoint is not None and (
            isinstance(checkpoint, bool)
            or not isinstance(checkpoint, numbers.Integral)
            or checkpoint < MIN_CHECKPOINT
        ):
            raise ValueError(
                f"{self.name}: checkpoint must be an integer of at least {MIN_CHECKPOINT} "
                "stored states (u_0 and the two-state buffer the forward kernel advances in), not "
                f"{checkpoint!r}; pass None to keep every state"
            )
        dtype = np.result_type(u0, params, cotangents)
        last = cmap[n]
        ubar = cotangents[last].astype(dtype) if last >= 0 else np.zeros(u0.shape, dtype=dtype)
        cbar = np.zeros(controls.shape, dtype=dtype)
        pbar = np.zeros(len(self.param_names), dtype=np.float64)
        if n and u0.shape[0]:  # else nothing to reverse: no kernel call
            work = n * _points(u0.shape[1:]) * self.point_cost
            parts = parallel.chunks(u0.shape[0], work, self._min_chunk_rows, fixed=wrt_params)
            if len(parts) == 1:
                self._reverse(u0, n, controls, params, cotangents, cmap, ubar, cbar, pbar,
                              wrt_params, checkpoint, trajectory)
            else:
                # Each chunk of rows is reversed on its own, checkpoints and all: no trajectory
                # is copied between the threads.
                def run(rows: slice) -> np.ndarray:
                    part_ubar, part_cbar = ubar[rows].copy(), _rows(cbar, rows)
                    part_pbar = np.zeros_like(pbar)
                    self._reverse(
                        np.ascontiguousarray(u0[rows]), n, _rows(controls, rows), params,
                        _rows(cotangents, rows), cmap, part_ubar, part_cbar, part_pbar,
                        wrt_params, checkpoint, None if trajectory is None else trajectory[:, rows],
                    )
                    ubar[rows] = part_ubar
                    if cbar.shape[0]:
                        cbar[:, rows] = part_cbar
                    return part_pbar

                for part_pbar in parallel.map_chunks(run, parts):
                    pbar += part_pbar
        # The parameter cotangents too: a linear scheme's state cotangent never reads the
        # states, so a NaN in a trajectory shows only there.
        if not _all_finite(ubar) or (wrt_params and not _all_finite(pbar)):
            self._raise_nonfinite_sweep(u0, n, controls, params, cotangents, trajectory)
        return Cotangents(
            state=ubar,
            controls=cbar,
            params=dict(zip(self.param_names, pbar.tolist())) if wrt_params else None,
        )

    # ----------------------------------------------------------------- shared machinery
    def _reverse(
        self,
        u0: np.ndarray,
        n: int,
        controls: np.ndarray,
        params: np.ndarray,
        cotangents: np.ndarray,
        cmap: np.ndarray,
        ubar: np.ndarray,
        cbar: np.ndarray,
        pbar: np.ndarray,
        wrt_params: bool,
        checkpoint: int | None,
        trajectory: np.ndarray | None,
    ) -> None:
        """Reverse the n steps into ``ubar``, ``cbar`` and ``pbar``, in place."""
        if trajectory is not None:  # a closed loop's step lands here: no sweep to plan
            self._adjoint(np.ascontiguousarray(trajectory[:n]), controls, params, cotangents,
                          cmap[:n], ubar, cbar, pbar, wrt_params)
        else:
            budget = n + 2 if checkpoint is None else int(checkpoint)
            sweep = _AdjointSweep(
                self, controls, params, cotangents, cmap, ubar, cbar, pbar, wrt_params
            )
            try:
                sweep.reverse(u0.astype(ubar.dtype, copy=False), n, budget)
            except MemoryError as e:
                if checkpoint is not None:
                    raise
                raise self.keep_all_error(n, e) from None

    def keep_all_error(self, n: int, error: MemoryError) -> MemoryError:
        """The error of a reverse pass that could not keep the ``n + 1`` states of its rollout,
        naming the way around: binomial checkpointing."""
        return MemoryError(
            f"{self.name}: keeping the {n + 1} states of the rollout for the reverse pass needs "
            f"more memory than there is ({error}); pass checkpoint=s to hold at most s ≥ "
            f"{MIN_CHECKPOINT} states and recompute the others"
        )

    def _run(
        self, u0: np.ndarray, n: int, ctrl: np.ndarray, p: np.ndarray, keep_all: bool
    ) -> np.ndarray:
        """u_0 .. u_n (``keep_all``), or the ping-pong buffer holding u_n in slot n % 2 (one
        slot when n = 0). Every slot returned is written."""
        slots = n + 1 if keep_all else min(n + 1, 2)
        states = np.empty((slots, *u0.shape), dtype=np.result_type(u0, p))
        states[0] = u0
        if n and u0.shape[0]:  # zero steps or an empty batch: nothing for the kernels to do
            self._forward_rows(states, n, ctrl, p)
        return states

    def _forward_rows(self, states: np.ndarray, n: int, ctrl: np.ndarray, p: np.ndarray) -> None:
        """``_forward`` over the chunks of batch rows :func:`parallel.chunks` gives, on the
        solver threads."""
        work = n * _points(states.shape[2:]) * self.point_cost
        parts = parallel.chunks(states.shape[1], work, self._min_chunk_rows)
        if len(parts) == 1:
            self._forward(states, n, ctrl, p)
            return

        def run(rows: slice) -> None:
            part = np.empty((states.shape[0], rows.stop - rows.start, *states.shape[2:]),
                            dtype=states.dtype)
            part[0] = states[0, rows]
            self._forward(part, n, _rows(ctrl, rows), p)
            states[:, rows] = part

        parallel.map_chunks(run, parts)

    def _raise_nonfinite_sweep(
        self,
        u0: np.ndarray,
        n: int,
        ctrl: np.ndarray,
        p: np.ndarray,
        cot: np.ndarray,
        trajectory: np.ndarray | None,
    ) -> None:
        """Say why a reverse sweep of the fast path came out non-finite, and raise."""
        if trajectory is not None and not _all_finite(trajectory[:n]):
            raise NonFiniteInputError(
                f"{self.name}: the trajectory handed to vjp_prepared holds a non-finite value "
                f"at {_first_bad(trajectory[:n], n - 1)}"
            )
        if not _all_finite(cot):
            raise NonFiniteInputError(
                f"{self.name}: the cotangents handed to vjp_prepared hold a non-finite value "
                f"at {_first_bad(cot, len(cot) - 1, 'row')}"
            )
        self.rollout_prepared(u0, n, ctrl, p)  # raises if the forward rollout blows up
        raise FloatingPointError(
            f"{self.name}: the adjoint sweep became non-finite although the forward rollout "
            "stayed finite; the cotangents or the rollout length are too large"
        )

    def _raise_nonfinite(
        self,
        states: np.ndarray,
        keep_all: bool,
        u0: np.ndarray,
        ctrl: np.ndarray,
        p: np.ndarray,
        n: int,
    ) -> None:
        """Find the first non-finite step of a rollout that became non-finite, and raise.

        ``states`` is what :meth:`_run` returned for the ``n`` steps (for a ping-pong buffer,
        ``n`` bounds the replay).
        """
        offset = 0
        if not keep_all:
            # Replay in chunks that keep every state until one chunk holds the first bad step.
            u, chunk = u0, 256
            while offset < n:
                m = min(chunk, n - offset)
                c = ctrl[offset : offset + m] if ctrl.shape[0] else ctrl
                states = self._run(u, m, c, p, keep_all=True)
                if not _all_finite(states):
                    break
                u, offset = states[m], offset + m
            else:
                raise FloatingPointError(
                    f"{self.name}: the rollout of {n} steps became non-finite but its replay "
                    "stayed finite: the kernels are not deterministic for this input"
                )
        bad = ~np.isfinite(states).reshape(states.shape[0], -1).all(axis=1)
        first = int(np.argmax(bad))
        raise NonFiniteStateError(self.name, offset + first, float(np.abs(states[first - 1]).max()))


class _AdjointSweep:
    """Reverse a rollout within a budget of stored states by binomial checkpointing.

    What the budget counts: every state-sized array the sweep holds at once, namely u_0 (the
    caller's, kept as the first checkpoint), each stored checkpoint, and the forward kernel's
    buffer (two states while advancing between checkpoints, m while a segment of m steps is
    recomputed for one adjoint kernel call), including the moment an advanced state is copied
    out of that buffer into its checkpoint. Not counted: the adjoint state ū, the cotangents,
    the controls and their cotangents, and the kernels' own scratch (FFT work arrays, tapes).

    Schedule (Griewank & Walther, ACM TOMS 26, 2000), from the last stored state u_lo with the
    steps lo .. hi - 1 still to reverse: a segment that fits the free budget is recomputed
    whole and reversed by one adjoint call, and u_lo released. Otherwise, with S stored states
    allowed (the free budget minus the advancing buffer's second slot), u_j is stored at the
    split of :func:`_binomial_split` and the part after it is reversed first, with one state
    fewer. With no room left to store a state (S = 1), the input of the last step is
    recomputed from u_lo. This is Revolve with S = s - 2 stored states for a budget of s, so
    the forward steps number

        t·n - β(s - 1, t - 1),   β(a, b) = C(a + b, a),  t the least with β(s - 2, t) ≥ n,

    the fewest possible, plus, when the sweep records a tape (``record``), one step per
    segment recomputed whole with a slot to spare (which spares the adjoint kernel
    recomputing that segment's stages).
    """

    def __init__(self, stepper, ctrl, p, cot, cmap, ubar, cbar, pbar, want_p):
        self.stepper, self.ctrl, self.p = stepper, ctrl, p
        self.cot, self.cmap, self.ubar, self.cbar, self.pbar = cot, cmap, ubar, cbar, pbar
        self.want_p = want_p
        # Parameter cotangents need what a tape leaves out (e.g. the spectral stages).
        self.record = stepper._records_tape and not want_p

    def _controls(self, a: np.ndarray, lo: int, hi: int) -> np.ndarray:
        return a[lo:hi] if a.shape[0] else a

    def reverse_stored(self, inputs: np.ndarray, lo: int, hi: int, *tape: Any) -> None:
        """Reverse steps lo .. hi - 1 from their inputs (and the tape recorded with them)."""
        self.stepper._adjoint(
            inputs, self._controls(self.ctrl, lo, hi), self.p, self.cot, self.cmap[lo:hi],
            self.ubar, self._controls(self.cbar, lo, hi), self.pbar, self.want_p, *tape,
        )

    def _recorded(self, u: np.ndarray, lo: int, hi: int) -> tuple[np.ndarray, Any]:
        """u_lo .. u_hi and the tape the forward kernel recorded on the way."""
        states = np.empty((hi - lo + 1, *u.shape), dtype=np.result_type(u, self.p))
        states[0] = u
        tape = self.stepper._forward(states, hi - lo, self._controls(self.ctrl, lo, hi),
                                     self.p, True)
        return states, tape

    def _advance(self, u: np.ndarray, lo: int, hi: int) -> np.ndarray:
        """The ping-pong buffer after advancing u_lo to u_hi (in slot (hi - lo) % 2)."""
        return self.stepper._run(u, hi - lo, self._controls(self.ctrl, lo, hi), self.p, False)

    def reverse(self, u0: np.ndarray, n: int, budget: int) -> None:
        """Reverse the n steps from u_0 holding at most ``budget`` states (≥ 3, u_0 included)."""
        stored = [(u0, 0, budget - 1)]  # (u_lo, lo, states still free while it is stored)
        hi = n
        while hi > 0:
            u, lo, free = stored[-1]
            m = hi - lo
            if self.record and m < free:
                # A tape covers whole steps: recompute the last one too, with the slot to spare.
                inputs, tape = self._recorded(u, lo, hi)
                self.reverse_stored(inputs[:m], lo, hi, tape)
                del inputs, tape, stored[-1]  # released before the next buffer is allocated
                hi = lo
            elif m <= free:
                # The adjoint kernel needs the inputs u_lo .. u_{hi-1}: m - 1 steps.
                inputs = self.stepper._run(
                    u, m - 1, self._controls(self.ctrl, lo, hi - 1), self.p, keep_all=True
                )
                self.reverse_stored(inputs, lo, hi)
                del inputs, stored[-1]  # released before the next buffer is allocated
                hi = lo
            elif free == 2:
                ring = self._advance(u, lo, hi - 1)
                self.reverse_stored(ring[(m - 1) % 2][None], hi - 1, hi)
                del ring
                hi -= 1
            else:
                j = _binomial_split(m, free - 1)
                stored.append((self._advance(u, lo, lo + j)[j % 2].copy(), lo + j, free - 1))
            del u


def _points(row_shape: tuple[int, ...]) -> int:
    """Points in one batch row of shape (C, *grid)."""
    return int(np.prod(row_shape))


def _rows(a: np.ndarray, rows: slice) -> np.ndarray:
    """Rows ``rows`` of the batch axis (axis 1) of a per-step array, contiguous; an array
    with no steps (no controls, no control cotangents) as it is."""
    return np.ascontiguousarray(a[:, rows]) if a.shape[0] else a


def _binomial_split(m: int, snaps: int) -> int:
    """Where to store the next checkpoint when reversing m steps with ``snaps`` ≥ 2 stored
    states (the segment's start among them).

    With t the least repetition number such that β(snaps, t) = C(snaps + t, t) ≥ m, the part
    before the split then needs repetition number t - 1 and the part after it t (with one
    state fewer), which attains the optimum t·m - β(snaps + 1, t - 1) forward steps.
    """
    t = 1
    while comb(snaps + t, t) < m:
        t += 1
    return min(comb(snaps + t - 1, snaps), m - comb(snaps + t - 2, snaps - 1))


@numba.njit(cache=True, nogil=True)
def _all_finite(a: np.ndarray) -> bool:
    # Stops at the first NaN/Inf and makes no temporary: several times faster than
    # np.all(np.isfinite(a)) on the small states of a training step.
    for v in a.ravel():
        if not np.isfinite(v):
            return False
    return True


def _cotangent_step(key: Any, n: int) -> int:
    """The step a cotangent key names: 0 .. n, or -(n + 1) .. -1 counting from the end."""
    try:
        k = operator.index(key)
    except TypeError:
        raise TypeError(f"cotangent keys are integer step numbers, not {key!r}") from None
    if not -(n + 1) <= k <= n:
        raise ValueError(
            f"cotangent step {k} is outside the rollout: steps run from 0 (u_0) to {n} "
            f"(u_n), or from -{n + 1} to -1 counting from the end"
        )
    return k % (n + 1)


def _cotangent_name(step: int | None, key: Any) -> str:
    """How an error names the cotangent of u_step given under ``key`` (None: the stacked
    cotangents, or a key that is the step itself)."""
    if step is None:
        return "the cotangents"
    given = step if key is None else operator.index(key)
    return f"the cotangent of step {step}" + (f" (key {given})" if given != step else "")


def _first_bad(a: np.ndarray, last: int, axis: str = "step") -> str:
    """Where array ``a`` of shape (steps, B, ...), known to hold NaN or Inf, first does: its
    first non-finite step (of 0 .. ``last``; ``axis`` names them) and that step's non-finite
    batch elements."""
    bad = ~np.isfinite(a.reshape(a.shape[0], a.shape[1], -1)).all(axis=2)
    k = int(np.argmax(bad.any(axis=1)))
    return f"{axis} {k} (of 0..{last}), in batch element(s) {np.nonzero(bad[k])[0].tolist()}"
