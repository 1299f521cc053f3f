"""Files that are never torn: atomic writes, strict JSON, plots written to files.

Atomic writes: a reader sees the old file or the whole new one, never a torn one.

The content goes to a temporary file beside the target, is flushed to disk, and is renamed
over the target (``os.replace`` is atomic on POSIX and Windows). On failure the temporary file
is removed and the target is left as it was.

JSON goes through :func:`json_text`: never NaN or Infinity (they are not JSON).
"""

from __future__ import annotations

import json
import math
import os
import signal
import threading
from collections.abc import Iterator
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


def save_figure(fig: Any, path: str | Path, dpi: int = 110) -> None:
    """Lay out a matplotlib figure, write it atomically (format from the suffix, PNG by
    default) and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=Path(path).suffix.lstrip(".") or "png")
    plt.close(fig)


@contextmanager
def uninterrupted() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) until the block ends, then raise it: an update and the counters
    that record it happen together, so the checkpoint written on the interrupt resumes without
    repeating or skipping one. Outside the main thread (a Dask worker's cell) signals cannot be
    caught, and the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
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
