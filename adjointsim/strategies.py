"""Hypothesis strategies over registered solvers (needs the ``dev`` extra's hypothesis).

Each stepper class declares its scene options in ``space`` (inside the scheme's stable range);
these strategies turn them into scenes and whole check cases, so the property tests cover every
registered solver without a hand-kept list.
"""

from __future__ import annotations

from hypothesis import strategies as st

from .stepper import Choice, Range, Stepper


def _option(spec: Choice | Range) -> st.SearchStrategy:
    if isinstance(spec, Choice):
        return st.sampled_from(spec.values)
    if spec.integer:
        return st.integers(int(spec.lo), int(spec.hi))
    return st.floats(spec.lo, spec.hi, allow_nan=False, allow_infinity=False)


def scenes(cls: type[Stepper]) -> st.SearchStrategy[Stepper]:
    """Scenes of ``cls`` drawn from its declared option space."""
    options = {k: _option(v) for k, v in cls.space.items()}
    return st.fixed_dictionaries(options).map(lambda kw: cls(**kw))


def check_cases(
    cls: type[Stepper], max_steps: int = 8, max_batch: int = 3
) -> st.SearchStrategy[tuple[Stepper, int, int, int]]:
    """(scene, steps, batch, seed) tuples for :func:`adjointsim.check.check_stepper`."""
    return st.tuples(
        scenes(cls),
        st.integers(1, max_steps),
        st.integers(1, max_batch),
        st.integers(0, 2**32 - 1),
    )
