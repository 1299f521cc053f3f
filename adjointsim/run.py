"""The run lifecycle shared by every training and fitting command.

A run lives in one directory: ``config.json``, ``checkpoint.pt``, ``history.csv``, its plots and,
once finished, ``result.json``. This module holds what every command does the same way:

- the config: a dataclass with :class:`Config` mixed in, loaded from TOML and flags, every key
  checked for its type and against the command's table of accepted values (:class:`Interval`,
  a tuple of choices, or a rule in words), errors naming the key;
- what the run engine (``adjointsim.engine``) compares and reads: :func:`differing`,
  :func:`read_result`, :func:`holds_run`, :func:`discard`;
- the history: :func:`write_history`, :func:`read_history` and one plot, :func:`plot_history`.

The checkpoint format (a SHA-256 digest over the contents) is the torch layer's
``adjointsim.train.checkpoint``; nothing here imports torch.
"""

from __future__ import annotations

import csv
import dataclasses
import difflib
import io
import json
import math
import os
import tomllib
import types
import typing
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from .errors import ConfigTypeError, DamagedFileError, RunExists, UserError
from .files import log_axis, pyplot, save_figure, write_text


# ----------------------------------------------------------------------------- the config
@dataclass(frozen=True)
class Interval:
    """Accepted numbers: lo ≤ x ≤ hi (open ends excluded), always finite."""

    lo: float
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = False

    def __contains__(self, x: float) -> bool:
        return (math.isfinite(x) and (x > self.lo if self.lo_open else x >= self.lo)
                and (x < self.hi if self.hi_open else x <= self.hi))

    def __str__(self) -> str:
        if self.hi == math.inf:
            return f"{'>' if self.lo_open else '≥'} {_num(self.lo)}"
        return (f"in {'(' if self.lo_open else '['}{_num(self.lo)}, {_num(self.hi)}"
                f"{')' if self.hi_open else ']'}")


def _num(x: float) -> str:
    return str(x) if isinstance(x, int) else f"{x:g}"


#: seeds: numpy's SeedSequence takes non-negative integers, torch.manual_seed up to 2⁶⁴ − 1
SEEDS = Interval(0, 2**63 - 1)
_TYPE_NAMES = {int: "an integer", float: "a finite number", str: "a string", list: "a list",
               bool: "true or false", dict: "a table of KEY = VALUE"}


class Config:
    """Mixed into a run's config dataclass: :meth:`load` from TOML and overrides, and
    :meth:`validate` against :attr:`ACCEPTED`, one entry per field (a tuple of choices, an
    :class:`Interval`, or a rule in words that :meth:`check` enforces)."""

    ACCEPTED: ClassVar[dict[str, tuple | Interval | str]] = {}

    @classmethod
    def load(cls, path: str | Path | None = None, recorded: dict | None = None,
             **overrides: Any) -> Any:
        """A config from a TOML file (optional) with keyword overrides (None means unset);
        unknown keys, wrong types and values outside :attr:`ACCEPTED` fail naming the key.
        ``recorded`` (a run's ``config.json``, to continue it) stands in for the defaults: the
        file and the overrides are laid over its keys of this config (any other is an
        earlier version's, left out); a key it lacks takes its default."""
        known = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
        values: dict[str, Any] = {k: v for k, v in (recorded or {}).items() if k in known}
        file: dict[str, Any] = {}
        if path is not None:
            try:
                with open(path, "rb") as f:
                    file = tomllib.load(f)
            except FileNotFoundError:
                raise FileNotFoundError(f"no config file at {path}") from None
            except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
                raise UserError(f"{path} is not valid TOML: {e}") from None
            except OSError as e:
                raise UserError(f"cannot read config {path}: {e.strerror or e}") from None
        for layer in (file, overrides):
            for key, value in layer.items():
                if value is None:
                    continue
                # a table (the scene) takes the later layer's keys over the earlier's, one by one
                if isinstance(value, dict) and isinstance(values.get(key), dict):
                    value = {**values[key], **value}
                values[key] = value
        for key in values:
            if key not in known:
                close = difflib.get_close_matches(key, known, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise UserError(f"unknown config option {key!r}{hint}; valid options: "
                                f"{', '.join(known)}")
        needed = [f.name for f in dataclasses.fields(cls)  # type: ignore[arg-type]
                  if f.name not in values and f.default is dataclasses.MISSING
                  and f.default_factory is dataclasses.MISSING]
        if needed:
            key = needed[0]
            what = f"; accepted: {cls.accepted(key)}" if key in cls.ACCEPTED else ""
            raise UserError(f"config key {key!r} is needed{what}")
        cfg = cls(**values)
        given = {k for layer in (file, overrides) for k, v in layer.items() if v is not None}
        kept = set(recorded or ()) - given  # a wrong value there is the run file's, not the user's

        def where(key: str) -> str:
            if key in kept:
                return " in the run's config.json"
            return f" in {path}" if path is not None else ""

        cfg.validate(where)
        return cfg

    def validate(self, where: str | Callable[[str], str] = "") -> None:
        """Check every field's type and accepted values, then :meth:`check`; ints given for
        float fields become floats. ``where`` (or ``where(key)``) says where a value came
        from, for the messages."""
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            key, value = f.name, getattr(self, f.name)
            at = where(key) if callable(where) else where
            expected, optional = unwrap(hints[key])
            if value is None and optional:
                continue
            if expected is float and type(value) is int:
                value = float(value)
                setattr(self, key, value)
            # bool is an int to Python, never to a config
            wrong_bool = isinstance(value, bool) and expected is not bool
            if not isinstance(value, expected) or wrong_bool:
                raise ConfigTypeError(
                    f"config key {key!r}{at}: {value!r} ({type(value).__name__}) is not "
                    f"{_TYPE_NAMES[expected]}; accepted: {self.accepted(key)}")
            rule = self.ACCEPTED.get(key)
            if isinstance(rule, tuple) and value not in rule:
                raise UserError(f"config key {key!r}{at}: {value!r} is not one of "
                                f"{', '.join(map(str, rule))}")
            if isinstance(rule, Interval) and value not in rule:
                raise UserError(f"config key {key!r}{at}: {value!r} is not "
                                f"{self.accepted(key)}")
            if isinstance(rule, str) and expected is str and not value:
                raise UserError(f"config key {key!r}{at}: needs {rule}")
        self.check(where("") if callable(where) else where)

    def check(self, where: str) -> None:
        """Rules that tie keys together, or that :attr:`ACCEPTED` states in words."""

    @classmethod
    def accepted(cls, key: str) -> str:
        """What ``key`` accepts, in words."""
        rule = cls.ACCEPTED[key]
        if isinstance(rule, tuple):
            return "one of " + ", ".join(map(str, rule))
        if isinstance(rule, Interval):
            kind, _ = unwrap(typing.get_type_hints(cls)[key])
            return f"{_TYPE_NAMES[kind]} {rule}"
        return rule

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)  # type: ignore[call-overload]


def scene_pairs(pairs: Iterable[str]) -> dict[str, Any]:
    """``--scene KEY=VALUE`` flags as a table; a VALUE is read as TOML reads it (``0.01``,
    ``64``, ``true``, ``"periodic"``; a bare word is a string)."""
    scene: dict[str, Any] = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or not key.strip() or not text.strip():
            raise UserError(f"--scene {pair!r} is not KEY=VALUE (for example --scene nu=0.01)")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        scene[key.strip()] = value
    return scene


def unwrap(hint: Any) -> tuple[type, bool]:
    """(the type, whether None is accepted) of an annotation like ``int`` or ``int | None``."""
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return args[0], True
    return (typing.get_origin(hint) or hint), False


# ----------------------------------------------------------------------------- the history
def write_history(path: str | Path, rows: Sequence[dict], fields: Sequence[str]) -> None:
    """``rows`` as CSV with the columns ``fields``, atomically."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(fields), extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    write_text(path, buf.getvalue())


def read_history(path: str | Path) -> list[dict]:
    """The rows of a history CSV, numbers as int or float, True/False as bool; a row with
    more or fewer fields than the header is a damaged file."""
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        rows = []
        for row in reader:
            extra = row.pop(None, [])  # csv's key for fields beyond the header
            given = sum(v is not None for v in row.values()) + len(extra)
            if given != len(row):
                raise DamagedFileError(
                    f"{path} is damaged: line {reader.line_num} has {given} fields, its header "
                    f"{len(row)}; restore the file, or start the run again with --overwrite")
            rows.append({k: _value(v) for k, v in row.items()})
        return rows


def _value(text: str) -> Any:
    if text in ("True", "False"):
        return text == "True"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def plot_history(path: str | Path, curves: dict[str, Sequence[dict]], x: str, y: str,
                 xlabel: str, ylabel: str, title: str = "", smooth: int = 0,
                 log: bool = True, ax: Any = None) -> None:
    """The history plot of every command: ``y`` against ``x``, one curve per label of
    ``curves``; with ``smooth`` > 1 each curve long enough gets its moving mean beside it, over
    ``smooth`` rows or a third of the curve if that is shorter (at least 3), named by that
    window. Non-finite values are left out; a curve of a few points shows them as dots. Drawn
    into ``ax`` when given (the caller saves)."""
    from matplotlib import ticker

    plt = pyplot()
    fig = None
    if ax is None:
        fig, ax = plt.subplots(figsize=(6, 3.5))
    whole = True
    for label, rows in curves.items():
        pts = [(r[x], r[y]) for r in rows
               if isinstance(r.get(y), int | float) and math.isfinite(r[y])]
        if not pts:
            continue
        xs, ys = zip(*pts)
        whole = whole and all(isinstance(v, int) for v in xs)
        k = min(smooth, len(ys) // 3)
        line, = ax.plot(xs, ys, lw=0.6 if k >= 3 else 1.2, alpha=0.4 if k >= 3 else 1.0,
                        marker="o" if len(ys) <= 20 else None, ms=3, label=label)
        if k >= 3:
            mean = [sum(ys[i - k + 1:i + 1]) / k for i in range(k - 1, len(ys))]
            ax.plot(xs[k - 1:], mean, color=line.get_color(),
                    label=f"{label}, moving mean of {k} points")
    if log:
        log_axis(ax)
    if whole:  # epochs, iterations: no tick between two of them
        ax.xaxis.set_major_locator(ticker.MaxNLocator(integer=True, steps=[1, 2, 5, 10],
                                                      min_n_ticks=1))
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title, fontsize=9)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7)
    if fig is not None:
        save_figure(fig, path, dpi=120)


# ----------------------------------------------------------------------------- the directory
def differing(ours: dict, theirs: dict, resumable: Iterable[str] = ()) -> list[str]:
    """The keys on which two configurations differ (a key only one has counts), apart from
    ``resumable`` ones: those a run may be continued with other values of (where it lives,
    its threads, when it stops), so a run recorded before such a key existed is the same run."""
    return sorted(k for k in ours.keys() | theirs.keys()
                  if ours.get(k) != theirs.get(k) and k not in resumable)


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


def holds_run(out: Path, config: dict, resumable: Iterable[str] = ()) -> bool:
    """Whether ``out`` holds a run of the command whose configs have ``config``'s keys (of any
    configuration; ``resumable`` ones may be missing): what ``--overwrite`` may discard.
    Somebody else's files never are."""
    try:
        theirs = json.loads((out / "config.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(theirs, dict) and _keys(theirs, resumable) == _keys(config, resumable)


def _keys(config: dict, resumable: Iterable[str]) -> set[str]:
    return set(config) - set(resumable)


def discard(out: Path, patterns: Iterable[str]) -> None:
    """``--overwrite``: remove the files of the run in ``out`` (those matching ``patterns``,
    with ``config.json``, ``checkpoint.pt`` and ``result.json``)."""
    for pattern in ("config.json", "checkpoint.pt", "result.json", *patterns):
        for old in out.glob(pattern):
            old.unlink()


def physical_memory() -> int | None:
    """This machine's memory in bytes (None where the system does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return None


def check_memory(need: int, what: str, fix: str) -> None:
    """The size guard of every command: refuse a run that needs more than this machine's
    memory before anything is allocated, saying how much ``what`` would need and ``fix``."""
    have = physical_memory()
    if have is not None and need > have:
        raise UserError(f"{what} need about {gib(need)} of memory, more than this machine's "
                        f"{gib(have)}; {fix}")


def gib(n: float) -> str:
    return f"{n / 2**30:,.1f} GiB"
