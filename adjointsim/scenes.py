"""A solver built from a scene: a problem's keyword defaults with a user's ``scene`` table (the
``[scene]`` of ``--config``, ``--scene KEY=VALUE``) over them, checked by the solver itself."""

from __future__ import annotations

import inspect
from typing import Any

from . import registry
from .stepper import Stepper

#: how numpy's ValueErrors begin when an array's size or a dimension cannot be indexed
_NUMPY_TOO_LARGE = ("Maximum allowed size exceeded", "Maximum allowed dimension exceeded",
                    "array is too big")


def build(solver: str | type[Stepper], scene: dict[str, Any],
          fixed: dict[str, Any] | None = None) -> Stepper:
    """The solver (a registered name or class) built from its keywords ``scene`` and ``fixed``
    (those the caller's problem relies on, not a user's to change). A key the solver does not
    take, a fixed key in ``scene``, or a value the solver's own checks refuse is a ValueError
    of one line naming the key (and what is accepted)."""
    cls = registry.get(solver) if isinstance(solver, str) else solver
    fixed = fixed or {}
    takes = [k for k in inspect.signature(cls).parameters if k not in fixed]
    for key in scene:
        if key in fixed:
            raise ValueError(f"scene key {key!r} is fixed to {fixed[key]!r} here; the scene "
                             f"keys are {', '.join(takes)}")
        if key not in takes:
            raise ValueError(f"scene key {key!r}: {cls.name} takes {', '.join(takes)}")
    try:
        return cls(**scene, **fixed)
    except TypeError as e:  # a value of the wrong type: the solver's message names the key
        raise ValueError(str(e)) from None
    except ValueError as e:
        # numpy's words for an array too large to index name no key; like a grid too large
        # to allocate, it is a size the machine cannot hold
        if not str(e).startswith(_NUMPY_TOO_LARGE):
            raise
        raise MemoryError(f"{cls.name} with {scene} asks for arrays larger than numpy can "
                          "index") from None
