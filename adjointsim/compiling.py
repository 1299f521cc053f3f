"""A word on stderr while numba compiles the solver kernels.

The first command to use a kernel compiles it and stores it in numba's on-disk cache
(``__pycache__`` beside the source, or ``NUMBA_CACHE_DIR``); later runs load it in
milliseconds. The first compile of a command's kernels takes 25 s (``adjointsim data ks``) to
45 s (``adjointsim train`` on KS: the solver, its adjoint and the FFTs), and a progress bar
started before it extrapolates that first step and claims hours. :func:`announce_compiles` says
so once per process, when numba starts compiling one of adjointsim's kernels; a kernel loaded
from the cache compiles nothing and says nothing.

It listens to numba's ``numba:compile`` event, which the dispatcher fires only after its
on-disk cache missed: no cache file is read here, and calls of compiled kernels cost nothing
more.
"""

from __future__ import annotations

import sys

from numba.core import event

NOTICE = ("compiling the solver kernels (about 30 s to a minute the first time; cached "
          "afterwards)")


class _Notice(event.Listener):
    """Writes :data:`NOTICE` the first time one of adjointsim's kernels is compiled."""

    said = False

    def on_start(self, ev: event.Event) -> None:
        if self.said:
            return
        kernel = getattr(ev.data.get("dispatcher"), "py_func", None)
        if getattr(kernel, "__module__", "").partition(".")[0] != "adjointsim":
            return  # numba compiling somebody else's function
        self.said = True
        from tqdm import tqdm

        tqdm.write(NOTICE, file=sys.stderr)  # above a running progress bar, not through it

    def on_end(self, ev: event.Event) -> None:
        pass


_notice: _Notice | None = None


def announce_compiles() -> None:
    """From now on, say :data:`NOTICE` on stderr, once per process, when numba starts
    compiling a kernel of adjointsim's (one not in its on-disk cache). Calling it again does
    nothing."""
    global _notice
    if _notice is None:
        _notice = _Notice()
        event.register("numba:compile", _notice)
