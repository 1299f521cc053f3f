"""Atomic file writes: a reader sees the old file or the whole new one, never a torn one.

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
from collections.abc import Iterable, Iterator
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


def differing(ours: dict, theirs: dict) -> list[str]:
    """The keys on which two configurations differ (a key only one has counts)."""
    return sorted(k for k in ours.keys() | theirs.keys() if ours.get(k) != theirs.get(k))


class RunExists(FileExistsError):
    """The output directory holds a finished run, or an unfinished one without ``--resume``."""


def read_result(path: Path) -> dict:
    """A finished run's ``result.json``; a damaged one is ``RunExists`` saying what to do."""
    try:
        result = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as e:
        result = e
    if not isinstance(result, dict):
        raise RunExists(f"{path} is damaged (not a JSON object: {result!s:.80}); delete it to "
                        "finish the run again from its checkpoint")
    return result


def refuse_foreign(out: Path, config: dict) -> None:
    """``RunExists`` when ``out`` holds somebody else's files: a ``config.json`` that is not
    ``config`` (another run, or not a run), or files but no ``config.json`` at all."""
    path = out / "config.json"
    if not path.exists():
        if out.is_dir() and any(not p.name.startswith(".") for p in out.iterdir()):
            raise RunExists(f"{out} holds other files and no run's config.json; choose a new "
                            "or empty --out")
        return
    try:
        theirs = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError):
        theirs = None
    ours = json.loads(json_text(config))
    if theirs != ours:
        what = (f"differs in {', '.join(differing(ours, theirs))}" if isinstance(theirs, dict)
                else "is not a run's")
        raise RunExists(f"{out} holds another run or other files (its config.json {what}); "
                        "choose another --out")


@contextmanager
def run_errors(out: Path) -> Iterator[None]:
    """How a run's Ctrl-C and file errors reach its command's user: whether ``--resume``
    applies (a checkpoint exists) or the command is simply run again, and that ``--out``
    cannot be written, naming it."""
    try:
        yield
    except KeyboardInterrupt:
        from adjointsim.cli import Interrupted

        if not (out / "checkpoint.pt").exists():
            raise Interrupted("stopped before the first checkpoint: nothing to resume, run "
                              "the command again") from None
        raise Interrupted(f"the checkpoint is saved; continue with --resume --out {out}") \
            from None
    except RunExists:
        raise
    except OSError as e:  # the run directory cannot be made or written
        raise OSError(f"cannot write the run to --out {out} ({e.strerror or e}); choose a "
                      "writable directory") from None


def finished_result(out: Path, resume: bool, config: dict | None = None,
                    keys: Iterable[str] = ()) -> dict | None:
    """A run directory's claim rule: the finished run's ``result.json`` when resuming it, None
    when there is nothing to keep or an unfinished run to resume; otherwise ``RunExists``.
    With ``config``, a finished run whose result disagrees with it is ``RunExists`` too, and so
    is a directory without a run whose ``config.json`` is not ``config`` (somebody else's).
    A result without ``config``'s keys and ``keys`` is damaged."""
    result_path = out / "result.json"
    if result_path.exists():
        if resume:
            result = read_result(result_path)
            ours = json.loads(json_text(config or {}))
            missing = [k for k in (*ours, *keys) if k not in result]
            if missing:
                raise RunExists(f"{result_path} is damaged (it lacks {', '.join(missing)}); "
                                "delete it to finish the run again from its checkpoint")
            differ = sorted(k for k, v in ours.items() if result.get(k) != v)
            if differ:
                raise RunExists(f"{out} holds a finished run of another configuration "
                                f"(differs in {', '.join(differ)}); choose another --out")
            return result
        raise RunExists(f"{out} holds a finished run; choose another --out or delete it")
    if config is not None:
        refuse_foreign(out, config)
    if (out / "checkpoint.pt").exists() and not resume:
        raise RunExists(f"{out} holds an unfinished run; pass --resume to continue it")
    return None
