"""Checks of scene (constructor) arguments, shared by every solver.

Each helper checks one argument and returns it converted (``float``, ``int``, ``bool``, the
chosen value, a float64 array). A value of the wrong type raises ``TypeError``, a value out of
range ``ValueError``; both messages name the solver, the argument, the value received and what
is accepted::

    diffusion1d-ftcs: dt must be a finite number > 0, got -0.1
    ks1d-etdrk4: n must be an even integer ≥ 4, got 7
    poisson2d: n must be an integer, got float 16.0

Use them at the top of a constructor, before the argument is used, and in ``check_params`` for
the constraints that also apply to parameters overridden per call::

    from .. import validate

    n = validate.integer(self.name, "n", n, ge=4, even=True)
    dt = validate.number(self.name, "dt", dt, gt=0)
    bc = validate.choice(self.name, "bc", bc, ("periodic", "dirichlet"))
    g = validate.array(self.name, "forcing", forcing, (1, n))

Numbers are ``int``/``float``/NumPy real scalars (or 0-d arrays), never ``bool`` or ``str``;
integers are ``int``/NumPy integers, never floats (``32.0`` is a TypeError: say ``32``). A count
(:func:`count`, such as the steps of a rollout) also takes a float with an integer value.
"""

from __future__ import annotations

import numbers
import operator
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["array", "choice", "count", "flag", "integer", "number"]


def _show(value: Any) -> str:
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    return repr(value)


def _bound(b: float) -> str:
    return str(int(b)) if float(b).is_integer() else repr(float(b))


def _bounds(gt: float | None, ge: float | None, lt: float | None, le: float | None) -> str:
    low = f"> {_bound(gt)}" if gt is not None else f"≥ {_bound(ge)}" if ge is not None else ""
    high = f"< {_bound(lt)}" if lt is not None else f"≤ {_bound(le)}" if le is not None else ""
    return " and ".join(b for b in (low, high) if b)


def _fail(solver: str, arg: str, wanted: str, value: Any, why: str) -> ValueError:
    note = f" ({why})" if why else ""
    return ValueError(f"{solver}: {arg} must be {wanted}, got {_show(value)}{note}")


def _wrong_type(solver: str, arg: str, wanted: str, value: Any) -> TypeError:
    return TypeError(
        f"{solver}: {arg} must be {wanted}, got {type(value).__name__} {_show(value)}"
    )


def number(
    solver: str,
    arg: str,
    value: Any,
    *,
    gt: float | None = None,
    ge: float | None = None,
    lt: float | None = None,
    le: float | None = None,
    why: str = "",
) -> float:
    """``value`` as a finite float within the given bounds (``gt``: >, ``ge``: ≥, ...).

    ``why`` (optional) is appended to the error in parentheses: the reason for the bound.
    """
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value[()]
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise _wrong_type(solver, arg, "a real number", value)
    x = float(value)
    ok = np.isfinite(x) and not (
        (gt is not None and not x > gt)
        or (ge is not None and not x >= ge)
        or (lt is not None and not x < lt)
        or (le is not None and not x <= le)
    )
    if not ok:
        bounds = _bounds(gt, ge, lt, le)
        raise _fail(solver, arg, "a finite number" + (f" {bounds}" if bounds else ""), x, why)
    return x


def integer(
    solver: str,
    arg: str,
    value: Any,
    *,
    ge: int | None = None,
    le: int | None = None,
    even: bool = False,
    why: str = "",
) -> int:
    """``value`` as an int, ≥ ``ge``, ≤ ``le`` and even if ``even``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise _wrong_type(solver, arg, "an integer", value)
    k = int(value)
    if (ge is not None and k < ge) or (le is not None and k > le) or (even and k % 2):
        bounds = _bounds(None, ge, None, le)
        wanted = ("an even integer" if even else "an integer") + (f" {bounds}" if bounds else "")
        raise _fail(solver, arg, wanted, k, why)
    return k


def count(solver: str, arg: str, value: Any, *, why: str = "") -> int:
    """``value`` as an int ≥ 0: an ``int``, a NumPy integer, anything with ``__index__``, or a
    float with an integer value (``3.0``: a count is often computed, say as ``T / dt``). Not a
    ``bool``, NaN or a fraction."""
    if type(value) is int:  # the common case, spared the ABC checks (a rollout counts its steps)
        k = value
    elif isinstance(value, np.ndarray) and value.ndim == 0:
        return count(solver, arg, value[()], why=why)
    elif isinstance(value, (bool, np.bool_)):
        raise _wrong_type(solver, arg, "a non-negative integer", value)
    elif isinstance(value, numbers.Real) and not isinstance(value, numbers.Integral):
        x = float(value)
        k = int(x) if x.is_integer() else -1
    else:
        try:
            k = operator.index(value)
        except TypeError:
            raise _wrong_type(solver, arg, "a non-negative integer", value) from None
    if k < 0:
        raise _fail(solver, arg, "a non-negative integer", value, why)
    return k


def flag(solver: str, arg: str, value: Any) -> bool:
    """``value`` as a bool (``True``/``False`` only: ``0``, ``"no"`` are not flags)."""
    if not isinstance(value, (bool, np.bool_)):
        raise _wrong_type(solver, arg, "True or False", value)
    return bool(value)


def choice(solver: str, arg: str, value: Any, choices: Sequence[Any], why: str = "") -> Any:
    """The entry of ``choices`` equal to ``value`` (of its type: ``numpy.str_`` matches ``str``,
    ``True`` does not match ``1``)."""
    for c in choices:
        flag_mismatch = isinstance(value, (bool, np.bool_)) != isinstance(c, (bool, np.bool_))
        if isinstance(value, type(c)) and not flag_mismatch and value == c:
            return c
    allowed = ", ".join(map(repr, choices))
    if not any(isinstance(value, type(c)) for c in choices):
        raise _wrong_type(solver, arg, f"one of {allowed}", value)
    raise _fail(solver, arg, f"one of {allowed}", value, why)


def array(solver: str, arg: str, value: Any, shape: tuple[int, ...]) -> np.ndarray:
    """``value`` as a finite float64 array of exactly ``shape`` (a new array, not a view)."""
    a = np.asarray(value)
    if a.dtype.kind not in "biuf" or a.dtype.kind == "b":
        raise TypeError(
            f"{solver}: {arg} must be a real array of shape {shape}, got dtype {a.dtype}"
        )
    if a.shape != tuple(shape):
        raise ValueError(f"{solver}: {arg} must have shape {tuple(shape)}, got shape {a.shape}")
    a = np.array(a, dtype=np.float64)
    bad = ~np.isfinite(a)
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(
            f"{solver}: {arg} must be finite; got {a[where]} at index {where} "
            f"({int(bad.sum())} non-finite value(s))"
        )
    return a
