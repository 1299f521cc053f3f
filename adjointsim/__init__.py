"""adjointsim: numba PDE solvers with hand-written discrete adjoints.

No torch import here: the torch layer lives in the ``train`` package.
"""

from .parallel import set_threads, threads, using_threads
from .registry import all_classes, get, names, register
from .stepper import (
    Choice,
    Cotangents,
    NonFiniteInputError,
    NonFiniteStateError,
    Range,
    Stepper,
)

__all__ = [
    "Choice",
    "Cotangents",
    "NonFiniteInputError",
    "NonFiniteStateError",
    "Range",
    "Stepper",
    "all_classes",
    "get",
    "names",
    "register",
    "set_threads",
    "threads",
    "using_threads",
]
__version__ = "0.1.0"
