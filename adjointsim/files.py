"""Files that are never torn: atomic writes, strict JSON, plots written to files.

Atomic writes: a reader sees the old file or the whole new one, never a torn one.

The content goes to a temporary file beside the target, is flushed to disk, and is renamed
over the target (``os.replace`` is atomic on POSIX and Windows). On failure the temporary file
is removed and the target is left as it was.

JSON goes through :func:`json_text`: never NaN or Infinity (they are not JSON).
"""

from __future__ import annotations

import functools
import json
import math
import os
import signal
import threading
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        yield tmp
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the Agg backend: plots are written to files, on machines
    without a display too. Imported on first use: runs that draw nothing never load it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def log_axis(ax: Any, which: str = "y") -> None:
    """Put the ``which`` axis (``"x"`` or ``"y"``) of ``ax`` on a log scale with tick labels
    that read: powers of ten when the view holds three or more, else 1-2-5 or 1…9 multiples of
    them, else (a view too narrow for three of those) evenly spaced values; every label writes
    its tick exactly. matplotlib's own labels are missing in views under a decade, and repeat
    in narrow ones (seven ticks all "7.43×10⁻³")."""
    from matplotlib import ticker

    locator, formatter = _log_tickers()
    getattr(ax, f"set_{which}scale")("log")
    axis = ax.yaxis if which == "y" else ax.xaxis
    axis.set_major_locator(locator())
    axis.set_major_formatter(formatter())
    axis.set_minor_locator(locator(minor=True))
    axis.set_minor_formatter(ticker.NullFormatter())


@functools.cache
def _log_tickers() -> tuple[type, type]:
    """The locator and formatter of :func:`log_axis` (classes made on first use: matplotlib
    is only imported by runs that draw)."""
    import numpy as np
    from matplotlib import ticker

    def multiples(lo: float, hi: float, subs: tuple[float, ...]) -> list[float]:
        decades = range(math.floor(math.log10(lo)), math.ceil(math.log10(hi)) + 1)
        return [s * 10.0**e for e in decades for s in subs if lo <= s * 10.0**e <= hi]

    class Locator(ticker.LogLocator):
        """The ticks of :func:`log_axis`; ``minor``: the unlabelled ones between them."""

        def __init__(self, minor: bool = False):
            super().__init__(subs="auto" if minor else (1.0,))
            self.minor = minor

        def tick_values(self, vmin: float, vmax: float) -> Any:
            lo, hi = sorted((vmin, vmax))
            if not 0 < lo < hi < math.inf:
                return super().tick_values(vmin, vmax)
            if len(multiples(lo, hi, (1.0,))) >= 3:
                return super().tick_values(vmin, vmax)  # decades, and minor ticks between
            for subs, most in (((1.0, 2.0, 5.0), 8), (tuple(range(1, 10)), 9)):
                major = multiples(lo, hi, subs)
                if 3 <= len(major) <= most:
                    if not self.minor:
                        return np.array(major)
                    return np.array([t for t in multiples(lo, hi, tuple(range(1, 10)))
                                     if t not in major])
            if self.minor:
                return np.array([])
            return ticker.MaxNLocator(nbins=5, steps=[1, 2, 5, 10]).tick_values(lo, hi)

    def decimals(x: float) -> int:
        """The decimals that write ``x`` exactly (to 1e-9 of it): a label never rounds."""
        return next((d for d in range(16) if abs(round(x, d) - x) <= 1e-9 * abs(x)), 16)

    class Formatter(ticker.Formatter):
        """Each tick written exactly; evenly spaced ones with the same decimals throughout."""

        def set_locs(self, locs: Any) -> None:
            super().set_locs(locs)
            lo, hi = sorted(self.axis.get_view_interval())
            shown = [float(v) for v in locs if lo <= v <= hi and v > 0]
            self.scientific = any(not -3 <= math.floor(math.log10(v)) <= 3 for v in shown)
            self.uniform = None  # per tick (1, 2, 5, 10), unless evenly spaced (1.98, 1.99)
            steps = np.diff(shown)
            if steps.size > 1 and np.allclose(steps, steps[0], rtol=1e-6):
                self.uniform = max(decimals(self._split(v)[0]) for v in shown)

        def _split(self, x: float) -> tuple[float, int]:
            if not self.scientific:
                return x, 0
            exponent = math.floor(math.log10(x))
            return x / 10.0**exponent, exponent

        def __call__(self, x: float, pos: int | None = None) -> str:
            if not x > 0:
                return ""
            mantissa, exponent = self._split(x)
            text = f"{mantissa:.{decimals(mantissa) if self.uniform is None else self.uniform}f}"
            if not self.scientific:
                return text
            power = f"10^{{{exponent}}}"
            return (f"$\\mathdefault{{{power}}}$" if text == "1" else
                    f"$\\mathdefault{{{text}\\times{power}}}$")

    return Locator, Formatter


def save_figure(fig: Any, path: str | Path, dpi: int = 110) -> None:
    """Lay out a matplotlib figure, write it atomically (format from the suffix, PNG by
    default) and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=Path(path).suffix.lstrip(".") or "png")
    plt.close(fig)


#: the signals that stop a run cleanly: Ctrl-C, and the polite kill of ``kill`` and of batch
#: schedulers (the command line turns SIGTERM into Ctrl-C: :func:`stop_on_sigterm`)
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


@contextmanager
def stop_on_sigterm() -> Iterator[None]:
    """Within the block, SIGTERM stops the work as Ctrl-C does (a checkpoint, then exit),
    where it would otherwise kill the process between two checkpoints. Main thread only."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextmanager
def uninterrupted() -> Iterator[None]:
    """Hold a stop signal (Ctrl-C, and SIGTERM under :func:`stop_on_sigterm`) until the block
    ends, then raise KeyboardInterrupt: an update and the counters that record it happen
    together, so the checkpoint written on the interrupt resumes without repeating or skipping
    one. A signal ignored (SIGINT of a job started in the background) stays ignored. Outside
    the main thread (a Dask worker's cell) signals cannot be caught, and the block runs as it
    is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous = {s: signal.getsignal(s) for s in STOP_SIGNALS}
    caught = [s for s, handler in previous.items() if callable(handler)]
    for s in caught:
        signal.signal(s, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        for s in caught:
            signal.signal(s, previous[s])
    if held:
        raise KeyboardInterrupt


def write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def json_text(obj: Any, indent: int | None = 2) -> str:
    """Strict JSON of ``obj``: a non-finite float becomes null, and the object holding it (each
    row of a top-level list) gets a ``"non_finite"`` note mapping its path to the value."""

    def clean(x: Any, path: str, notes: dict) -> Any:
        if isinstance(x, float) and not math.isfinite(x):
            notes[path] = repr(x)
            return None
        if isinstance(x, dict):
            return {k: clean(v, f"{path}.{k}" if path else str(k), notes) for k, v in x.items()}
        if isinstance(x, list | tuple):
            return [clean(v, f"{path}[{i}]", notes) for i, v in enumerate(x)]
        return x

    def note(x: Any) -> Any:
        notes: dict = {}
        out = clean(x, "", notes)
        if notes:
            out = {**out, "non_finite": notes} if isinstance(out, dict) else out
        return out

    rows = [note(r) for r in obj] if isinstance(obj, list) else note(obj)
    return json.dumps(rows, indent=indent, allow_nan=False)


def write_json(path: str | Path, obj: Any) -> None:
    write_text(path, json_text(obj) + "\n")


#: the keys a JSON object must hold, each with its type or types (:func:`unfit`)
Keys = Mapping[str, type | tuple[type, ...]]


def unfit(obj: dict, expected: Keys) -> str | None:
    """What the JSON object ``obj`` (a result, a row) lacks of the ``expected`` keys, or its
    first value of another type; None if it holds them all. ``float`` also admits an int and
    null (JSON writes 2.0 as 2, and a non-finite number as null)."""
    missing = [k for k in expected if k not in obj]
    if missing:
        return f"lacks {', '.join(map(repr, missing))}"
    for key, types in expected.items():
        kinds = types if isinstance(types, tuple) else (types,)
        if not _fits(obj[key], kinds):
            names = " or ".join(t.__name__ for t in kinds)
            return f"holds {short(obj[key])} under {key!r}, not a {names}"
    return None


def _fits(value: Any, types: tuple[type, ...]) -> bool:
    if float in types:
        types = (*types, int, type(None))
    if isinstance(value, bool):
        return bool in types
    return isinstance(value, types)


def short(value: Any) -> str:
    """``repr(value)``, cut to 40 characters for a message."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."
