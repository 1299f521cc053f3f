"""Checkpoints that know when they are damaged: :func:`save_checkpoint` writes atomically with
the SHA-256 digest of the contents (every tensor's dtype, shape and bytes, and every other
value), and :func:`load_checkpoint` verifies it. Checkpoints from before digests load with a
warning and get one at their next save. Every torch command's runs use these two."""

from __future__ import annotations

import hashlib
import warnings
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import torch

from adjointsim.errors import DamagedFileError, RunExists
from adjointsim.files import atomic_path


def _digest(payload: Any) -> str:
    """SHA-256 of a checkpoint's contents: each tensor's dtype, shape and bytes, and the repr of
    every other value, in order (pickling round-trips both exactly)."""
    h = hashlib.sha256()

    def walk(x: Any) -> None:
        if isinstance(x, torch.Tensor):
            t = x.detach().cpu().contiguous()
            h.update(f"T{t.dtype}{tuple(t.shape)}".encode())
            h.update(t.reshape(-1).view(torch.uint8).numpy())
        elif isinstance(x, list) and all(map(_plain, x)):  # the history: one repr, 3-4x faster
            h.update(b"R" + repr(x).encode() + b";")
        elif isinstance(x, dict):
            h.update(b"{")
            for k, v in x.items():
                walk(k)
                walk(v)
            h.update(b"}")
        elif isinstance(x, list | tuple):
            h.update(b"[" if isinstance(x, list) else b"(")
            for v in x:
                walk(v)
            h.update(b"]")
        else:
            h.update(repr(x).encode() + b";")

    walk(payload)
    return h.hexdigest()


def _plain(x: Any) -> bool:
    """A scalar, or a dict of scalars (no tensor inside)."""
    if isinstance(x, dict):
        return all(type(k) in _SCALARS and type(v) in _SCALARS for k, v in x.items())
    return type(x) in _SCALARS


_SCALARS = (int, float, str, bool, type(None))


def save_checkpoint(payload: dict, path: str | Path) -> None:
    """Write atomically, with the digest :func:`load_checkpoint` verifies."""
    with atomic_path(path) as tmp:
        torch.save({**payload, "sha256": _digest(payload)}, tmp)


def load_checkpoint(path: str | Path, keys: Iterable[str] = ("model",),
                    recover: str = "delete it and train again") -> dict:
    """Read a checkpoint, check it holds ``keys`` and verify its digest; a damaged one gets an
    error ending in ``recover``, what to do."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # torch raises many types for damaged files
        raise DamagedFileError(
            f"{path} is not a readable checkpoint ({type(e).__name__}: {e}); {recover}"
        ) from None
    if not isinstance(ckpt, dict) or not set(keys) <= set(ckpt):
        missing = sorted(set(keys) - set(ckpt)) if isinstance(ckpt, dict) else sorted(keys)
        raise DamagedFileError(f"{path} is not a checkpoint of this command's runs (it lacks "
                               f"{', '.join(missing)}); choose another --out, or {recover}")
    digest = ckpt.pop("sha256", None)
    if digest is None:
        warnings.warn(f"{path} has no digest (written before checkpoints had one), so damage "
                      "to it cannot be detected; it gets one when the run saves again",
                      stacklevel=2)
    elif digest != _digest(ckpt):
        raise DamagedFileError(
            f"{path} is damaged: its contents do not match the SHA-256 digest stored with them "
            f"(a flipped bit on disk or an edited file); {recover}"
        )
    return ckpt


def restore(module: Any, state: dict, path: Path) -> None:
    """Load ``state`` (a model's or an optimiser's, from the checkpoint at ``path``) into
    ``module``; one written for another layout (an older version's layer names) is
    ``RunExists`` saying what to do, not a traceback."""
    try:
        module.load_state_dict(state)
    except (RuntimeError, KeyError, ValueError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise RunExists(f"{path} does not fit this version's {type(module).__name__} ({first}); "
                        "start the run again with --overwrite, or into another --out") from None


class _Store:
    """The torch layer's checkpoint format, for the run engine
    (:class:`adjointsim.engine.CheckpointStore`)."""

    @staticmethod
    def save(payload: dict, path: Path) -> None:
        save_checkpoint(payload, path)

    @staticmethod
    def load(path: Path, keys: Iterable[str], recover: str) -> dict:
        return load_checkpoint(path, keys, recover)


#: what a torch problem names as its ``STORE``
STORE = _Store()
