"""The run engine: one object owns a run directory from its claim to its result.

Every training and fitting command is a :class:`Problem` run by :func:`run`. A problem supplies
only what is its own: how it is built (network, optimiser, data), one update, its history
rows, its state for the checkpoint, its result and its plots. The engine does the rest, the
same way for every command:

- **the claim** (:meth:`RunDir.claim`): a directory is started fresh when it holds nothing of
  this run; with ``resume`` an unfinished run continues from its checkpoint and a finished one
  is returned as it is, or continued when an *extendable* key (a length: epochs, a budget) was
  raised; with ``overwrite`` a run of this command is discarded once the new one has been
  built. Somebody else's files, a run of another configuration and a run that was not to be
  continued are refused, naming the keys and the way out;
- **the files**: ``config.json`` when the run starts, ``checkpoint.pt`` (one payload layout:
  ``config``, ``state``, ``history``), the history CSVs written with every checkpoint, the
  plots, and ``result.json`` last (a run stopped while plotting resumes to write it);
- **the cadence**: a checkpoint at every boundary the problem reports (the end of an epoch, an
  evaluation), at least every :data:`SAVE_SECONDS` of wall time, on Ctrl-C (between two updates:
  an update is never cut in half) and at the finish;
- **the progress bar** and what Ctrl-C tells the user.

An ensemble is several problems trained together: :func:`run` takes a list of them and an
``ensemble`` factory that makes one vectorised updater of members at the same point; each
member keeps its own directory, claim, checkpoint, history and result.

The engine knows no torch: a problem names the checkpoint format it saves with
(:class:`CheckpointStore`; the torch layer's is ``adjointsim.train.checkpoint.STORE``).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Protocol

from .errors import DamagedFileError, Interrupted, RunExists, UserError
from .files import Keys, json_text, unfit, uninterrupted, write_json
from .run import Config, differing, discard, read_result, write_history

#: the longest wall time between two checkpoints of a running run, in seconds
SAVE_SECONDS = 30.0
CONFIG, CHECKPOINT, RESULT = "config.json", "checkpoint.pt", "result.json"


class CheckpointStore(Protocol):
    """How a problem's checkpoint is written and read (atomically, with a digest)."""

    def save(self, payload: dict, path: Path) -> None: ...

    def load(self, path: Path, keys: Iterable[str], recover: str) -> dict: ...


class Progress(Protocol):
    """What an update may tell the progress bar (a fit reports every iteration of its
    optimiser's own loop)."""

    def __call__(self, position: float, **postfix: Any) -> None: ...


class Problem:
    """One run of a command: subclass it and register nothing else.

    Class attributes say what the engine needs to know of the command: :attr:`RESUMABLE`
    config keys may change when a run is continued (where it lives, its threads), a larger
    value of an :attr:`EXTENDABLE` key continues a finished run (its length; None: no limit),
    :attr:`HISTORIES` names each history file and its columns, :attr:`RUN_FILES` the other
    files a run writes (discarded by ``overwrite``), :attr:`RESULT_KEYS` what a result must
    hold (each key with its type, checked when a finished run is read back). The methods
    below are what a run does; the defaults fit a problem without state.
    """

    RESUMABLE: ClassVar[tuple[str, ...]] = ("out", "threads")
    EXTENDABLE: ClassVar[tuple[str, ...]] = ()
    HISTORIES: ClassVar[dict[str, tuple[str, ...]]] = {}
    RUN_FILES: ClassVar[tuple[str, ...]] = ()
    RESULT_KEYS: ClassVar[Keys] = {}
    #: config keys added since earlier versions, and keys those versions had that are gone:
    #: a run of an earlier version is still this command's (refused with the keys it differs
    #: in, discarded by ``overwrite``), not somebody else's files
    ADDED: ClassVar[tuple[str, ...]] = ()
    RETIRED: ClassVar[tuple[str, ...]] = ()
    #: the progress bar's unit ("it", "epoch", "s")
    UNIT: ClassVar[str] = "it"
    #: the checkpoint format; None: the problem has no state to resume from (run again)
    STORE: ClassVar[CheckpointStore | None] = None
    #: whether an update is held together against Ctrl-C (an optimiser's whole loop is not)
    ATOMIC: ClassVar[bool] = True
    #: where this invocation stops short of the run's end (:func:`run`'s ``until``)
    until: float | None = None

    def __init__(self, config: Config, out: str | Path):
        self.config = config
        self.out = Path(out)
        #: set by the engine before the first update
        self.progress: Progress = lambda position, **postfix: None

    # what the run is
    def describe(self) -> str:
        """The progress bar's label."""
        return type(self).__name__

    def total(self) -> float:
        """How far the run goes, in :attr:`UNIT`."""
        raise NotImplementedError

    def position(self) -> float:
        """How far it has gone."""
        raise NotImplementedError

    def done(self) -> bool:
        return self.position() >= self.total() or self.paused()

    def paused(self) -> bool:
        """Whether the run stops here, before its end, at a limit of this invocation (``until``,
        an iteration cap): it is saved and left unfinished, to be continued with ``resume``."""
        return self.until is not None and self.until <= self.position() < self.total()

    # what it does
    def build(self) -> None:
        """Make the network, optimiser and data (after the claim, before a restore)."""

    def update(self) -> bool:
        """One update; whether it ended a boundary at which a checkpoint is due."""
        raise NotImplementedError

    def finish(self) -> dict:
        """The final evaluation: the result's own keys (the config is added)."""
        raise NotImplementedError

    def plot(self) -> None:
        """The finished run's plots, into :attr:`out`."""

    def postfix(self) -> dict[str, Any]:
        """What the progress bar shows beside the count."""
        return {}

    # what it keeps
    def state_dict(self) -> dict:
        """Everything a resumed run needs, but the history."""
        return {}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` (the checkpoint's path in ``self.out``, for messages)."""

    def histories(self) -> dict[str, list[dict]]:
        """The rows of each file of :attr:`HISTORIES`; the first is kept in the checkpoint."""
        return {}

    def load_histories(self, histories: dict[str, list[dict]]) -> None:
        """Restore :meth:`histories`."""

    def extend(self, recorded: dict) -> None:
        """A finished run continued to a larger :attr:`EXTENDABLE` value (``recorded`` holds
        the old ones): clear whatever marks it finished."""


class Updater(Protocol):
    """What the engine's loop drives: one problem, or an ensemble of problems at one point."""

    def done(self) -> bool: ...

    def update(self) -> bool: ...

    def sync(self) -> None: ...


class Single:
    """One problem as its own updater."""

    def __init__(self, problem: Problem):
        self.problem = problem

    def done(self) -> bool:
        return self.problem.done()

    def update(self) -> bool:
        return self.problem.update()

    def sync(self) -> None:
        """Nothing to bring back: the problem's state is its own."""


# ----------------------------------------------------------------------------- the claim
def started(out: str | Path) -> bool:
    """Whether ``out`` holds a run (its config, checkpoint or result): a study's cell passes
    this as ``resume``, to continue or return its run where one is and start one where not."""
    return any((Path(out) / name).exists() for name in (CONFIG, CHECKPOINT, RESULT))


def same_command(problem: Problem | type[Problem], keys: Iterable[str], theirs: dict) -> bool:
    """Whether ``theirs`` is a config of ``problem``'s command, whose configs have ``keys``:
    of this version or an earlier one (keys :attr:`Problem.ADDED` since may be missing,
    :attr:`Problem.RETIRED` ones may be there)."""
    keys = set(keys)
    missing = keys - set(theirs) - set(problem.RESUMABLE) - set(problem.ADDED)
    extra = set(theirs) - keys - set(problem.RETIRED)
    return not missing and not extra


def another_commands(out: Path, what: str | None = None) -> RunExists:
    """The refusal of a directory that holds no run of this command (``what`` it holds
    instead; by default another command's config.json)."""
    return RunExists(f"{out} holds another command's run or other files "
                     f"({what or 'a config.json of another command'}); choose another --out")


@dataclass
class Claim:
    """What a run directory holds for the run about to start: nothing to keep (``fresh``),
    a checkpoint to continue from, or a finished result to return."""

    checkpoint: dict | None = None
    result: dict | None = None
    discard: bool = False


class RunDir:
    """A problem's run directory and the one claim rule of every command."""

    def __init__(self, problem: Problem):
        self.problem = problem
        self.out = problem.out
        self.config = json.loads(json_text(problem.config.as_dict()))
        self.free = (*problem.RESUMABLE, *problem.EXTENDABLE)

    def recorded(self) -> dict | None:
        """The ``config.json`` in the directory (None: none, or not a JSON object)."""
        try:
            theirs = json.loads((self.out / CONFIG).read_text())
        except (OSError, ValueError, UnicodeDecodeError):
            return None
        return theirs if isinstance(theirs, dict) else None

    def ours(self, theirs: dict) -> bool:
        """Whether ``theirs`` is a config of this command (:func:`same_command`): what
        ``--overwrite`` may discard and ``--resume`` compares key by key."""
        return same_command(self.problem, self.config, theirs)

    def holds(self) -> bool:
        """Whether the directory holds a run (its config, checkpoint or result)."""
        return started(self.out)

    def claim(self, resume: bool, overwrite: bool) -> Claim:
        """The claim rule: see the module's doc. Nothing is written here."""
        if resume and overwrite:
            raise UserError("--resume continues a run and --overwrite discards it: pass one")
        out, again = self.out, "choose another --out, or start it again with --overwrite"
        theirs = self.recorded()
        if not self.holds():
            if out.is_dir() and any(not p.name.startswith(".") for p in out.iterdir()):
                raise RunExists(f"{out} holds other files and no run's config.json; choose a "
                                "new or empty --out")
            if resume:
                raise UserError(f"--resume: {out} holds no run to continue; run the command "
                                "without --resume to start it")
            return Claim()
        if theirs is None or not self.ours(theirs):
            unread = ("a config.json that cannot be read: if this is this command's run, the "
                      "file is damaged; restore it" if (out / CONFIG).exists()
                      else "no readable config.json")
            raise another_commands(out, unread if theirs is None else None)
        if overwrite:
            return Claim(discard=True)
        differ = differing(self.config, theirs, self.free)
        if differ:
            raise RunExists(f"{out} holds a run of another configuration (differs in "
                            f"{', '.join(differ)}); {again}")
        shorter = [k for k in self.problem.EXTENDABLE
                   if k in theirs and _less(self.config[k], theirs[k])]
        if shorter:
            was = ", ".join(f"{k} = {theirs[k]}" for k in shorter)
            raise RunExists(f"{out} holds a run of {was}; pass as much or more to continue it, "
                            f"or {again}")
        longer = [k for k in self.problem.EXTENDABLE if self.config[k] != theirs.get(k)]
        finished = (out / RESULT).exists()
        has_ckpt = (out / CHECKPOINT).exists() and self.problem.STORE is not None
        if not resume:
            if finished and longer:
                what = (f"a finished run ({', '.join(f'{k} = {theirs[k]}' for k in longer)}); "
                        f"continue it to more with --resume, or {again}")
            elif finished:
                what = f"a finished run; {again}"
            elif has_ckpt:
                what = f"an unfinished run; continue it with --resume, or {again}"
            else:  # stopped before its first checkpoint: nothing of it to keep
                return Claim()
            raise RunExists(f"{out} holds {what}")
        if finished and not longer:
            result = read_result(out / RESULT)
            missing = [k for k in self.config
                       if k not in result and k not in self.problem.RESUMABLE]
            problem = (f"lacks {', '.join(map(repr, missing))}" if missing
                       else unfit(result, self.problem.RESULT_KEYS))
            if problem:
                again = "from its checkpoint" if self.problem.STORE else "from the start"
                raise RunExists(f"{out / RESULT} is damaged (it {problem}); delete it to finish "
                                f"the run again {again}")
            return Claim(result=result)
        if not has_ckpt:
            if finished:
                raise RunExists(f"{out} holds a finished run without its checkpoint, which "
                                f"cannot be continued; {again}")
            return Claim()  # stopped before its first checkpoint: start it again
        keys = ("config", "state", *(() if not self.problem.HISTORIES else ("history",)))
        ckpt = self.problem.STORE.load(out / CHECKPOINT, keys,
                                       f"delete it, or {again}")
        if not isinstance(ckpt.get("config"), dict):
            raise DamagedFileError(f"{out / CHECKPOINT} holds no configuration; delete it, or "
                                   f"{again}")
        differ = differing(self.config, ckpt["config"], self.free)
        if differ:
            raise RunExists(f"{out / CHECKPOINT} was written by another configuration (differs "
                            f"in {', '.join(differ)}); {again}")
        return Claim(checkpoint=ckpt)

    # the files
    def start(self, claim: Claim) -> None:
        """The run begins: an overwritten run's files go, ``config.json`` is written."""
        self.out.mkdir(parents=True, exist_ok=True)
        if claim.discard:
            discard(self.out, (*self.problem.HISTORIES, *self.problem.RUN_FILES))
        write_json(self.out / CONFIG, self.config)

    def save(self) -> None:
        """The checkpoint (if the problem keeps one) and every history, atomically."""
        p = self.problem
        histories = p.histories()
        if p.STORE is not None:
            first = next(iter(p.HISTORIES), None)
            p.STORE.save({"config": self.config, "state": p.state_dict(),
                          "history": histories.get(first, []) if first else [],
                          **({"histories": {k: v for k, v in histories.items() if k != first}}
                             if len(p.HISTORIES) > 1 else {})},
                         self.out / CHECKPOINT)
        for name, fields in p.HISTORIES.items():
            write_history(self.out / name, histories.get(name, []), fields)

    def restore(self, ckpt: dict) -> None:
        p = self.problem
        first = next(iter(p.HISTORIES), None)
        histories = dict(ckpt.get("histories", {}))
        if first is not None:
            histories[first] = ckpt.get("history", [])
        p.load_state_dict(ckpt["state"])
        p.load_histories(histories)
        recorded = ckpt["config"]
        if any(self.config[k] != recorded.get(k) for k in p.EXTENDABLE):
            p.extend(recorded)
            (self.out / RESULT).unlink(missing_ok=True)

    def finish(self) -> dict:
        """The final evaluation, the last checkpoint and histories, the plots, result.json."""
        p = self.problem
        result = {**self.config, **p.finish()}
        self.save()
        p.plot()  # before result.json: a run stopped while plotting resumes to the plots
        write_json(self.out / RESULT, result)
        return result


def _less(a: Any, b: Any) -> bool:
    """Whether length ``a`` is shorter than ``b`` (None: no limit, longer than any)."""
    if b is None:
        return a is not None
    return isinstance(a, int | float) and isinstance(b, int | float) and a < b


# ----------------------------------------------------------------------------- the loop
def run(problems: Problem | Sequence[Problem], resume: bool = False, overwrite: bool = False,
        progress: bool = True,
        ensemble: Callable[[list[Problem]], Updater] | None = None,
        until: float | None = None) -> Any:
    """Run ``problems`` (one, or an ensemble's members) to their results; returns the result
    (one problem) or the list of results (None for a run :meth:`Problem.paused`). Every
    directory is claimed before any is written; members at the same point train together
    through ``ensemble`` (one vectorised updater), a member resumed from another point trains
    with the members at its point. ``until`` stops every run at that position (in its
    :attr:`Problem.UNIT`), saved and unfinished, without changing the length its config
    records: a study's turns."""
    single = isinstance(problems, Problem)
    members = [problems] if single else list(problems)
    if not members:
        raise UserError("an ensemble needs at least one member")
    for m in members:
        m.until = until
    dirs = [RunDir(p) for p in members]
    # --resume continues the members that hold a run; a member without one (a seed added, its
    # directory deleted) starts fresh beside them; nothing to continue at all is refused
    some = any(d.holds() for d in dirs)
    claims = [d.claim(resume and (d.holds() or not some), overwrite) for d in dirs]
    results: list[dict | None] = [c.result for c in claims]
    todo = [k for k, c in enumerate(claims) if c.result is None]
    for k in todo:
        members[k].build()
    with run_errors([dirs[k].out for k in todo]):  # an --out that cannot be written is named
        for k in todo:
            dirs[k].start(claims[k])
            if claims[k].checkpoint is not None:
                dirs[k].restore(claims[k].checkpoint)
        groups: dict[float, list[int]] = {}
        for k in todo:
            groups.setdefault(members[k].position(), []).append(k)
        for idx in groups.values():
            group = [members[k] for k in idx]
            updater = (ensemble(group) if ensemble is not None and len(group) > 1
                       else Single(group[0]) if len(group) == 1 else None)
            if updater is None:
                raise UserError(f"{type(group[0]).__name__} runs train one at a time")
            _loop(updater, group, [dirs[k] for k in idx], progress)
            for k in idx:
                if members[k].paused():
                    dirs[k].save()
                else:
                    results[k] = dirs[k].finish()
    return results[0] if single else results


def _loop(updater: Updater, group: list[Problem], dirs: list[RunDir], progress: bool) -> None:
    lead = group[0]
    bar = None
    if progress:
        from tqdm.auto import tqdm

        size = f" ×{len(group)}" if len(group) > 1 else ""
        bar = tqdm(total=_round(lead.total()), initial=_round(lead.position()),
                   unit=lead.UNIT, desc=lead.describe() + size, leave=False)

    def show(position: float, **postfix: Any) -> None:
        if bar is not None:
            if postfix:  # drawn by the update's refresh, which tqdm paces (a line per update else)
                bar.set_postfix(postfix, refresh=False)
            bar.update(_round(position) - bar.n)

    for p in group:
        p.progress = show

    def save() -> None:
        updater.sync()
        for d in dirs:
            d.save()

    last = time.monotonic()
    try:
        while not updater.done():
            if lead.ATOMIC:
                with uninterrupted():
                    boundary = updater.update()
            else:
                boundary = updater.update()
            show(lead.position(), **lead.postfix())
            if boundary or time.monotonic() - last > SAVE_SECONDS:
                with uninterrupted():
                    save()
                last = time.monotonic()
        updater.sync()
    except KeyboardInterrupt:
        if lead.STORE is not None:
            save()
        raise
    finally:
        if bar is not None:
            bar.close()


def _round(x: float) -> float:
    return x if isinstance(x, int) else round(x, 1)


class Saved(Interrupted):
    """Ctrl-C once the checkpoints are saved: ``--resume`` with ``--out`` :attr:`out` continues
    the run (an ensemble's members: the folders in it). The command line prints that command."""

    def __init__(self, message: str, out: Path):
        super().__init__(message)
        self.out = out


@contextmanager
def run_errors(outs: Sequence[Path]) -> Iterator[None]:
    """How the Ctrl-C and file errors of the runs in ``outs`` (one run, or an ensemble's
    members) reach the user: whether ``--resume`` applies (a checkpoint is saved) or the
    command is simply run again; a file that cannot be written names ``--out``."""
    try:
        yield
    except Interrupted:  # it says already what to do
        raise
    except KeyboardInterrupt:
        saved = [o for o in outs if (o / CHECKPOINT).exists()]
        if not saved:
            raise Interrupted("stopped before the first checkpoint: nothing to resume, run the "
                              "command again") from None
        where = saved[0] if len(outs) == 1 else saved[0].parent
        raise Saved(f"the checkpoint is saved; continue with the same command and "
                    f"--resume (--out {where})", where) from None
    except (RunExists, FileNotFoundError):
        raise
    except OSError as e:
        if e.filename is None or not any(_inside(Path(e.filename), o) for o in outs):
            raise
        raise OSError(f"cannot write the run to --out {outs[0]} ({e.strerror or e}); choose a "
                      "writable directory") from None


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.resolve().relative_to(folder.resolve())
    except ValueError:
        return False
    return True


def finite_or_none(x: float) -> float | None:
    """A number for result.json: JSON has no NaN or infinity."""
    return x if math.isfinite(x) else None
