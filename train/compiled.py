"""The ``compile`` config key of the training commands: one update's loss through
``torch.compile``.

The solvers enter a loss as the bridge's custom operators (:mod:`adjointsim.train.bridge`), so a
loss of several solver steps traces into one graph; the network's layers around them are what a
backend can speed up. ``aot_eager`` runs torch's own kernels on the traced graph (the eager
numbers to the bit: a check of the tracing, not a speed-up); ``inductor`` generates code for
the layers (a C++ compiler on CPU) and may reorder their arithmetic (round-off differences).
Compiling costs seconds to minutes on the first update and again on each new shape (a longer
unroll of a curriculum stage), so it pays only over long runs: the commands default to
``off``. The model itself is not wrapped, so its ``state_dict`` and the checkpoints are the
same whatever the key says.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import torch

#: the accepted values of the ``compile`` key: off (eager), or a ``torch.compile`` backend
BACKENDS = ("off", "aot_eager", "inductor")

#: why mode C (a gradient flow over a doubled batch) is refused with compiling: its bottom
#: stream takes each step's control as a new leaf kept aside for the backward pass, which breaks
#: the traced graph at every step (compiling would only add tracing to an eager loop)
DOUBLED_ERROR = ("mode C's doubled batch breaks the compiled graph at every step (each control "
                 "becomes a new leaf kept for the backward pass); choose compile = off, or a "
                 "mode R, M, S or N")

F = TypeVar("F", bound=Callable)


def compiled(fn: F, backend: str) -> F:
    """``fn`` (a loss: tensors in, tensors out) as the ``compile`` key ``backend`` says: itself
    for ``off``, else ``torch.compile``'d with that backend. Shapes stay static (a new batch
    size or unroll length compiles once more) and a graph break falls back to eager for that
    piece, so every loss a command builds runs, compiled as far as it can be."""
    if backend not in BACKENDS:
        raise ValueError(f"compile backend {backend!r} is not one of {', '.join(BACKENDS)}")
    if backend == "off":
        return fn
    return torch.compile(fn, backend=backend, dynamic=False)  # type: ignore[return-value]
