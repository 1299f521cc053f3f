"""Threads: the one knob for the solvers' batch parallelism, and the split it drives.

Every stepper splits a large enough call into chunks of whole batch rows and runs the chunks on
a pool of threads (the kernels release the GIL). Rows never interact, so a state or state
cotangent is the same to the bit whatever the split; a sweep that sums parameter cotangents
over rows splits by the call's size alone and adds the chunks' sums in chunk order. Results are
bitwise the same for every thread count.

The count comes from, in order: :func:`set_threads` (or the ``using_threads`` context), the
environment variable ``ADJOINTSIM_THREADS``, and the cores this process may run on. Who sets
it, so that threads never outnumber cores:

- a direct library call uses every core;
- a command takes ``--threads N``: every core by default for the commands that only run
  solvers (``gradcheck``, ``bench``, ``fit``, ``data``); for the commands that run torch it
  is the config key ``threads`` (default 1, so that a run's numbers do not depend on the
  machine), which sets both torch's intra-op threads and the solver threads: the two take
  turns, each uses them all in its turn;
- a Dask worker of the study runner runs one solver thread and one torch thread (``--jobs``
  workers use ``--jobs`` cores).
"""

from __future__ import annotations

import operator
import os
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

ENVIRONMENT = "ADJOINTSIM_THREADS"
#: a chunk holds at least this much work, in ns (batch rows × steps × grid points × the
#: solver's cost of a point-step): below it the chunk's own cost (copies, a kernel call, a
#: thread's wake-up: tens to a hundred µs) would no longer be small
MIN_CHUNK_WORK = 400_000
#: the smallest grid whose transforms run on several threads at a batch of one (measured: a
#: 2D vorticity step at 512² gains 1.6x on 2 threads, at 256² and 128² it loses)
MIN_POINTS_INSIDE = 512 * 512
#: the most chunks of a split that must not depend on the thread count
FIXED_CHUNKS = 16

_lock = threading.Lock()
_chosen: int | None = None
_pools: dict[int, ThreadPoolExecutor] = {}
_inside = threading.local()


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the system reports one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def _check(n: object, what: str) -> int:
    """``n`` as an int if it is an integral number (a NumPy integer too) of at least 1; a
    bool or a float (even 2.0) is refused: it is a count of threads, not a measure."""
    try:
        count = None if isinstance(n, bool) else operator.index(n)
    except TypeError:
        count = None
    if count is None or count < 1:
        kind = "" if count is not None else f" (a {type(n).__name__})"
        raise ValueError(f"{what} must be a whole number of threads of at least 1, not "
                         f"{n!r}{kind}")
    return count


def threads() -> int:
    """The number of threads the solvers use now."""
    if _chosen is not None:
        return _chosen
    given = os.environ.get(ENVIRONMENT, "").strip()
    if given:
        try:
            return _check(int(given), f"the environment variable {ENVIRONMENT}")
        except ValueError:
            raise ValueError(
                f"the environment variable {ENVIRONMENT} must be a whole number of threads of "
                f"at least 1, not {given!r}; unset it to use every core"
            ) from None
    return available_cores()


def set_threads(n: int | None) -> None:
    """Use ``n`` threads in the solvers from now on (None: back to the default); any integral
    number (``np.int64(2)`` too), not a bool or a float."""
    global _chosen
    _chosen = None if n is None else _check(n, "threads")


@contextmanager
def using_threads(n: int | None) -> Iterator[None]:
    """Run the body with ``n`` solver threads, then restore the previous setting."""
    global _chosen
    before = _chosen
    set_threads(n)
    try:
        yield
    finally:
        _chosen = before


def chunks(batch: int, work_per_row: float, min_rows: int = 1, fixed: bool = False
           ) -> list[slice]:
    """How a call over ``batch`` rows of ``work_per_row`` ns each is split: slices of
    nearly equal size, one slice (no split) for a small call or a single thread.

    Rows never interact, so the states and state cotangents of a chunk are those the whole
    batch would get, whatever the split: a split into one chunk per thread changes no bit of
    them. A sum over rows (a parameter cotangent) is different: ``fixed`` splits by the call's
    size alone, into a power of two of at most ``FIXED_CHUNKS`` chunks, whatever the thread
    count. A batch of at least ``min_rows`` rows is split into chunks of at least ``min_rows``
    (for a kernel whose arithmetic changes with the batch size at that threshold)."""
    # A chunk's own calls stay on its thread (map_chunks runs them serially); a fixed split
    # stays as it is there, or a nested sum would depend on whether the caller ran threads.
    if inside_chunk() and not fixed:
        return [slice(0, batch)]
    most = batch // min_rows if batch >= min_rows else batch
    count = min(most, int(batch * max(work_per_row, 1) // MIN_CHUNK_WORK),
                FIXED_CHUNKS if fixed else threads())
    if count < 2:
        return [slice(0, batch)]
    if fixed:
        count = 1 << (count.bit_length() - 1)
    bounds = [batch * i // count for i in range(count + 1)]
    return [slice(lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:])]


def inside_chunk() -> bool:
    """True on a thread that runs one chunk of a split call (its own calls stay on it)."""
    return getattr(_inside, "active", False)


def threads_inside(batch: int, points: int) -> int:
    """Threads for the work inside one sample (the lines of a grid, a transform's lines) of a
    kernel call over ``batch`` rows of ``points`` grid points: every solver thread
    (:func:`threads`) for a call with fewer rows than threads, on a grid of at least
    ``MIN_POINTS_INSIDE`` points, that is not itself one chunk of a split call; else 1 (the
    split of the rows uses the threads then, and on smaller grids starting the transforms'
    threads costs more than they save).

    Only work whose arithmetic does not depend on the split goes on these threads (independent
    lines, never a sum), so the results are the same to the bit for every count."""
    count = threads()
    small = batch >= count or points < MIN_POINTS_INSIDE
    return 1 if small or inside_chunk() else count


def _pool(size: int) -> ThreadPoolExecutor:
    with _lock:
        pool = _pools.get(size)
        if pool is None:
            pool = _pools[size] = ThreadPoolExecutor(size, thread_name_prefix="adjointsim")
        return pool


def _run_inside(fn: Callable[[T], R], item: T) -> R:
    _inside.active = True
    try:
        return fn(item)
    finally:
        _inside.active = False


def map_chunks(fn: Callable[[T], R], items: Sequence[T]) -> list[R]:
    """``[fn(item) for item in items]``, on up to :func:`threads` threads, in item order.

    A call from inside a chunk (a solver run by another solver's kernel wrapper) runs serially,
    so the pool never waits on itself."""
    size = min(threads(), len(items))
    if size < 2 or inside_chunk():
        return [fn(item) for item in items]
    pool = _pool(size)
    return [f.result() for f in [pool.submit(_run_inside, fn, item) for item in items]]
