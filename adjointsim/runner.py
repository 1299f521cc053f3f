"""One runner for every study: each cell of a study is a task on a Dask distributed cluster.

A study (:class:`Study`, registered once with :func:`register_study`) lists its cells, runs one
cell in its own run directory and tabulates the finished rows. :func:`run` sends the unfinished
cells to

- ``cluster="local"``: a ``LocalCluster`` started in this process with ``jobs`` single-threaded
  worker processes (no dashboard), stopped at the end;
- ``cluster="tcp://HOST:PORT"``: an existing scheduler (``dask scheduler`` / ``dask worker``),
  once it has answered as one within :data:`CONNECT_TIMEOUT` + :data:`ANSWER_TIMEOUT` seconds,
  after checking that every worker runs this project's code and writes where we read;
- ``cluster="none"``: this process, one cell after another (for debugging);
- ``cluster=None``: ``$DASK_SCHEDULER_ADDRESS`` if set, else ``"local"``.

A cell is finished when its ``OUT/<id>/row.json`` exists; the runner writes it (atomically, on
the worker) from what ``run_cell`` returns, so a rerun submits only unfinished cells, and a
retried task (an exception, or a worker that died) starts ``run_cell`` again in the same
directory, where it resumes from its own checkpoint. Failures are reported per cell while the
others finish; :class:`CellsFailed` carries both. A row file is checked when it is read back
(JSON, of its cell's configuration, holding results, with the study's declared
:attr:`Study.row_keys`) and so is every row that ``reuse`` would adopt, all of them (and the
study's report of them) before any is copied. While cells run or rows are adopted, the study
directory is locked (``OUT/.study.lock``): a second study there is refused.

Dask is imported only inside the functions that need it, so other commands do not pay for it.
No torch import here either: the worker gets one thread through the environment.
"""

from __future__ import annotations

import asyncio
import contextvars
import hashlib
import importlib
import json
import math
import os
import re
import shlex
import socket
import sys
import tempfile
import threading
import time
import uuid
import warnings
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

from tqdm.auto import tqdm

from adjointsim import parallel
from adjointsim.errors import UserError
from adjointsim.files import Keys, short, unfit, write_text

if TYPE_CHECKING:
    from distributed import Client

ROW_FILE = "row.json"
LOCK_FILE = ".study.lock"
_ONE_THREAD = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
# Seconds to get a connection to a scheduler (Dask retries a refused one meanwhile: a scheduler
# may still be starting), and then at most this much longer for its answer. Dask leaves its
# handshake without a timeout, so a server that accepts and never answers would hang the study.
CONNECT_TIMEOUT = 10.0
ANSWER_TIMEOUT = 2.0
_SCHEMES = ("tcp", "tls", "ws", "wss", "ucx")
# what adjointsim.files.json_text adds to a row holding non-finite numbers (a --json file)
_NOTE_KEYS = frozenset({"non_finite"})

RowKeys = Keys

# on while this process runs cells with the study's progress bar on (``cluster="none"``); off
# on a Dask worker, whose bars would not reach the study's terminal
_RUNS_SHOW = contextvars.ContextVar("runs_show_progress", default=False)


def runs_show_progress() -> bool:
    """Whether a cell's runs show their own progress bars, below the study's bar of cells: on
    where the study runs its cells in this process with its progress on (``cluster="none"``),
    so that a cell of hours (an ensemble taking turns) shows the updates it reaches; off on a
    Dask worker. A study's ``run_cell`` and ``run_group`` pass it as their runs' ``progress``."""
    return _RUNS_SHOW.get()


def runs(cells: list[dict], run_dirs: list[Path]) -> float:
    """A part's cost unless its study says otherwise: its number of runs."""
    return len(cells)


@dataclass(frozen=True)
class Study:
    """A grid of independent cells: ``cells(size, seeds)`` lists them (each a dict with an
    ``id``), ``run_cell(cell, out)`` runs one in its own directory and returns its row, and
    ``report(rows, out)`` writes the tables and plots and returns the text to print.

    ``row_keys``: the keys every finished row holds besides its cell's, each with its type
    (``float`` also admits an int, and null, which a non-finite number is written as), or a
    function of the cell giving them when cells differ. Declared, it is checked on every row
    read back or reused; without it, a reused row must hold what the other rows of cells of its
    kind (the same keys and text values) all hold, and under each key a value of the kind the
    study's other rows hold there. Either way a row holds some result besides its cell's keys,
    and rows are adopted only once the study's ``report`` has run on them.

    ``so_far(out, size, seeds)``: the rows of the cells under the study directory ``out`` that
    have started, finished or not (what a running or stopped study has reached, for
    :func:`so_far`); studies whose cells run for hours declare it.

    ``pack`` (with ``run_group``): the keys in which cells may differ and still train together
    as one ensemble (``("seed",)``, say), or a function of the cell that gives them; the runner
    submits one task per group of cells equal in every other key, and ``run_group(cells,
    run_dirs)`` returns their rows in order. A group with finished cells runs only the others;
    each cell still gets its own row file.

    ``turns`` (with ``pack``): the keys that split a group into parts taking turns inside its
    task (an ensemble per mode, say: ``("mode",)``). In one process the group stays one task;
    on a cluster of k workers its parts are dealt into up to k tasks, the costliest part first
    to the task with the least cost so far, so that they train side by side; ``turn_cost(cells,
    run_dirs)`` gives what is left of a part (by default its number of cells; a study that
    resumes can count what its runs still have to do, so that a rerun deals afresh)."""

    name: str
    sizes: tuple[str, ...]
    cells: Callable[[str, int | None], list[dict]]
    run_cell: Callable[[dict, Path], dict]
    report: Callable[[list[dict], Path], str]
    prepare: Callable[[str, Path], dict] | None = None
    row_keys: RowKeys | Callable[[dict], RowKeys] | None = None
    pack: tuple[str, ...] | Callable[[dict], tuple[str, ...]] = ()
    run_group: Callable[[list[dict], list[Path]], list[dict]] | None = None
    turns: tuple[str, ...] = ()
    turn_cost: Callable[[list[dict], list[Path]], float] = runs
    so_far: Callable[[Path, str, int | None], list[dict]] | None = None

    def expected_keys(self, cell: dict) -> RowKeys | None:
        """The declared result keys of ``cell``'s row, or None if the study declares none."""
        return self.row_keys(cell) if callable(self.row_keys) else self.row_keys


_STUDIES: dict[str, Study] = {}


def register_study(study: Study) -> None:
    """Make ``study`` known by its name (re-registering the same name replaces it, so a module
    imported twice, e.g. by a worker, is harmless)."""
    _STUDIES[study.name] = study


def get_study(name: str) -> Study:
    if name not in _STUDIES:
        raise ValueError(f"unknown study {name!r}; choose from {sorted(_STUDIES)}")
    return _STUDIES[name]


class CellsFailed(RuntimeError):
    """Some cells failed (after their retries); the others finished.

    ``failures`` holds ``(cell id, one-line error)``, ``rows`` the finished rows.
    """

    def __init__(self, study: str, failures: list[tuple[str, str]], rows: list[dict]):
        self.failures = failures
        self.rows = rows
        lines = "; ".join(f"{cid}: {msg}" for cid, msg in failures)
        super().__init__(f"{study}: {len(failures)} of {len(failures) + len(rows)} cells "
                         f"failed ({lines})")


def run(
    study_name: str,
    out: str | Path,
    size: str,
    seeds: int | None,
    cluster: str | None = "local",
    jobs: int = 2,
    retries: int = 1,
    progress: bool = True,
    report: bool = True,
    reuse: str | Path | None = None,
) -> list[dict]:
    """Run every unfinished cell of a study, write ``OUT/rows.json`` and (if ``report``) the
    study's report of the finished rows.

    ``reuse``: a JSON list of rows of an earlier run (its ``rows.json`` or ``--json`` file,
    e.g. committed from another machine); a cell with a row there is finished, once that row
    is checked to be of the same configuration and copied to ``OUT/<id>/row.json``. A file
    that does not fit (rows of another study, or one unfit row) is refused whole.

    Returns the rows in cell order; raises :class:`CellsFailed` (after writing what finished)
    if any cell failed.
    """
    study = get_study(study_name)
    if size not in study.sizes:
        raise ValueError(f"unknown study size {size!r} for {study_name}; "
                         f"choose from {list(study.sizes)}")
    if jobs < 1:
        raise ValueError(f"--jobs must be ≥ 1, not {jobs}")
    if retries < 0:
        raise ValueError(f"--retries must be ≥ 0, not {retries}")
    cluster = resolve_cluster(cluster)
    out = Path(out).resolve()
    cells = study.cells(size, seeds)
    _check_ids(cells, study_name)
    rows = _finished_rows(study, cells, out)
    adopted = _reusable(study, cells, size, reuse, rows) if reuse is not None else {}
    failures: list[tuple[str, str]] = []
    if adopted or any(c["id"] not in rows for c in cells):
        with ExitStack() as stack:
            stack.enter_context(study_lock(out))
            # another study may have finished cells here before this one took the lock
            rows = _finished_rows(study, cells, out)
            for cell_id, row in adopted.items():
                if cell_id not in rows:
                    (out / cell_id).mkdir(exist_ok=True)
                    write_text(out / cell_id / ROW_FILE, dumps(row))
                    rows[cell_id] = row
            todo = [c for c in cells if c["id"] not in rows]
            if todo:
                _run_cells(stack, study, todo, size, out, cluster, jobs, retries, progress, rows,
                           failures)
    finished = [rows[c["id"]] for c in cells if c["id"] in rows]
    write_text(out / "rows.json", dumps(finished))
    if finished and report:
        write_report(study_name, finished, out)
    if failures:
        order = {c["id"]: i for i, c in enumerate(cells)}
        raise CellsFailed(study_name, sorted(failures, key=lambda f: order[f[0]]), finished)
    return finished


def _run_cells(stack: ExitStack, study: Study, todo: list[dict], size: str, out: Path,
               cluster: str, jobs: int, retries: int, progress: bool, rows: dict[str, dict],
               failures: list[tuple[str, str]]) -> None:
    """Run ``todo`` on ``cluster`` (its client and the progress bar entered on ``stack``),
    adding each finished row to ``rows`` and each failure to ``failures``."""
    # The cluster first: a remote one that is unreachable or unfit fails before the study's
    # shared inputs are made.
    client = (None if cluster == "none" else stack.enter_context(
        _dask_client(study, out, cluster, min(jobs, len(todo)), retries)))
    extra = study.prepare(size, out) if study.prepare is not None else {}
    todo = [{**c, **extra} for c in todo]
    bar = stack.enter_context(tqdm(total=len(todo), desc=f"{study.name} cells", unit="cell",
                                   disable=not progress))

    def done(cell_id: str, row: dict | None, error: str | None) -> None:
        if error is None:
            rows[cell_id] = row
        else:
            failures.append((cell_id, error))
            bar.write(f"{study.name}: cell {cell_id} failed: {error}")
        bar.update()

    if client is None:
        token = _RUNS_SHOW.set(progress)
        try:
            _run_here(study, todo, out, retries, done)
        finally:
            _RUNS_SHOW.reset(token)
    else:
        _run_on_dask(client, study, todo, out, retries, done)


@contextmanager
def study_lock(out: Path) -> Iterator[None]:
    """Hold the study directory ``out`` (created if need be) for this process: a second study
    there is refused with one line naming the first. The lock is the operating system's
    (``flock`` on ``OUT/.study.lock``) and goes with the process holding it, so the file left
    by a killed study is taken over by the next. (Where there is no ``flock``, on Windows,
    nothing is locked.)"""
    try:
        import fcntl
    except ImportError:
        yield
        return
    out.mkdir(parents=True, exist_ok=True)
    path = out / LOCK_FILE
    with open(os.open(path, os.O_RDWR | os.O_CREAT, 0o644), "r+") as file:
        try:
            fcntl.flock(file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = file.read().strip() or "another process"
            raise UserError(f"{out} is in use by another study ({holder}); wait for it to "
                            "finish, or give another --out") from None
        file.truncate()
        file.write(f"pid {os.getpid()} on {socket.gethostname()}, since "
                   f"{time.strftime('%Y-%m-%d %H:%M:%S')}\n")
        file.flush()
        try:
            yield
        finally:
            fcntl.flock(file, fcntl.LOCK_UN)


def resolve_cluster(cluster: str | None) -> str:
    """``None`` means ``$DASK_SCHEDULER_ADDRESS`` if set, else ``"local"``; a given value
    wins over the environment. An address must be ``[SCHEME://]HOST:PORT`` (tcp without a
    scheme, as for Dask)."""
    given = "--cluster"
    if cluster is None:
        cluster = os.environ.get("DASK_SCHEDULER_ADDRESS") or "local"
        if cluster != "local":
            given = "$DASK_SCHEDULER_ADDRESS"
    if cluster in ("local", "none"):
        return cluster
    problem = _address_problem(cluster)
    if problem:
        raise UserError(f"{given} {cluster!r}: {problem}; give local, none or a scheduler "
                        "address such as tcp://HOST:8786")
    return cluster


def _address_problem(address: str) -> str | None:
    scheme, sep, location = address.partition("://")
    if not sep:
        scheme, location = "tcp", address
    if scheme in ("http", "https"):
        return ("an http address is a dashboard's, not the scheduler's (`dask scheduler` "
                "prints both; the scheduler's port is 8786 by default)")
    if scheme not in _SCHEMES:
        return f"scheme {scheme!r} is not one of {', '.join(_SCHEMES)}"
    try:
        parts = urlsplit(f"//{location}")
    except ValueError as e:  # an unbalanced IPv6 bracket, say
        return f"not an address ({e})"
    if parts.path or parts.query or parts.fragment:
        return f"{location[len(parts.netloc):]!r} follows HOST:PORT"
    if not parts.hostname:
        return "no host before :PORT"
    try:
        port = parts.port
    except ValueError:
        port = 0
    if port is None:
        return "no port after the host"
    if not 1 <= port <= 65535:
        return f"port {parts.netloc.rpartition(':')[2]!r} is not a number from 1 to 65535"
    return None


def finished_row(cell: dict, run_dir: Path) -> dict | None:
    """The cell's row if ``run_dir`` holds a finished one; refuses a damaged row or a row of
    another cell."""
    row, problem = _read_row(cell, run_dir, None)
    if problem is not None:
        raise ValueError(f"{run_dir / ROW_FILE} is damaged ({problem}); delete it to run the "
                         "cell again")
    return row


def _read_row(cell: dict, run_dir: Path, expected: RowKeys | None
              ) -> tuple[dict | None, str | None]:
    """The cell's row in ``run_dir`` (None if it has none), or what is wrong with the file;
    refuses a row of another configuration."""
    path = run_dir / ROW_FILE
    if not path.exists():
        return None, None
    try:
        row = json.loads(path.read_text())
    except ValueError as e:
        return None, f"not JSON: {e}"
    if not isinstance(row, dict):
        return None, f"a JSON {type(row).__name__}, not an object"
    differ = _differs(cell, row)
    if differ:
        raise ValueError(f"{path} holds a result of another configuration (differs in "
                         f"{differ}); use another --out, or delete {run_dir} to redo the cell")
    problem = _resultless(cell, row) or (unfit(row, expected) if expected is not None
                                         else None)
    return (None, problem) if problem else (row, None)


def _finished_rows(study: Study, cells: list[dict], out: Path) -> dict[str, dict]:
    """The finished rows under ``out`` by cell id; refuses, naming every one, damaged row
    files (their cells are not rerun silently: a row may hold hours of work, and the user
    decides whether it is lost)."""
    rows, damaged = {}, []
    for cell in cells:
        row, problem = _read_row(cell, out / cell["id"], study.expected_keys(cell))
        if problem is not None:
            damaged.append((out / cell["id"] / ROW_FILE, problem))
        elif row is not None:
            rows[cell["id"]] = row
    if len(damaged) == 1:
        (path, problem), = damaged
        raise UserError(f"{path} is damaged ({problem}); delete it to run that cell again")
    if damaged:
        listed = "; ".join(f"{path} ({problem})" for path, problem in damaged)
        raise UserError(f"{len(damaged)} row files are damaged: {listed}; delete them to run "
                        "those cells again: rm " + " ".join(shlex.quote(str(p))
                                                            for p, _ in damaged))
    return rows


def _differs(cell: dict, row: dict) -> list[str]:
    """The cell's keys whose values the row does not hold."""
    return sorted(k for k, v in cell.items() if _jsonable(v) != row.get(k))


def _reusable(study: Study, cells: list[dict], size: str, path: str | Path,
              finished: dict[str, dict]) -> dict[str, dict]:
    """The rows of ``path`` that finish cells without a row yet, by cell id, once every one
    is checked (its configuration, its results, the study's report of it with the finished
    rows): one unfit row refuses them all, before any is copied (a row copied into a run
    directory stays there)."""
    given = _rows_file(path)
    ids = [c["id"] for c in cells]
    if given and not set(ids) & {r["id"] for r in given}:
        raise UserError(f"--reuse {path}: none of its rows ({_listed([r['id'] for r in given])})"
                        f" is a cell of study {study.name} at size {size} "
                        f"({_listed(ids)}); give the rows of an earlier run of this study")
    by_id = {r["id"]: r for r in given}
    adopted: dict[str, dict] = {}
    for cell in cells:
        row = by_id.get(cell["id"])
        if row is None or cell["id"] in finished:
            continue
        differ = _differs(cell, row)
        if differ:
            raise UserError(f"--reuse {path}: its row {cell['id']!r} is of another "
                            f"configuration (differs in {differ}); it belongs to another "
                            "size or version of the study")
        adopted[cell["id"]] = row
    refused = _unfit_rows(study, cells, adopted, {**finished, **adopted})
    if not refused and adopted:
        rows = [{**finished, **adopted}[i] for i in ids if i in finished or i in adopted]
        error = _report_error(study, rows)
        if error is not None:
            named = _breaking(study, rows, error) or list(adopted)
            refused = [(named[0], f"breaks the study's report ({_one_line(error)})"),
                     *((cid, "") for cid in named[1:])]
    if refused:
        (first, problem), *more = refused
        others = (f"; and {len(more)} more row{'s' * (len(more) > 1)} "
                  f"({_listed([cid for cid, _ in more])})" if more else "")
        raise UserError(f"--reuse {path}: its row {first!r} {problem}{others}; nothing was "
                        "copied: give a --json or rows.json file of a run of this version of "
                        "the study, or remove these rows from it to run their cells here")
    return adopted


def _rows_file(path: str | Path) -> list[dict]:
    """The rows of a ``--reuse`` file: a JSON list of objects, each with its own cell id."""
    try:
        given = json.loads(Path(path).read_text())
        if not (isinstance(given, list) and all(isinstance(r, dict) for r in given)):
            raise ValueError("not a JSON list of rows")
    except (OSError, ValueError) as e:
        raise UserError(f"--reuse {path}: cannot read its rows ({e}); give a rows.json or "
                        "--json file of an earlier run of this study") from None
    seen: set[str] = set()
    for number, row in enumerate(given, 1):
        cid = row.get("id")
        problem = ("has no cell id (a text under 'id')" if not isinstance(cid, str)
                   else f"repeats the id {cid!r}" if cid in seen else None)
        if problem:
            raise UserError(f"--reuse {path}: its row number {number} {problem}; give a "
                            "rows.json or --json file of an earlier run of this study")
        seen.add(cid)
    return given


def _listed(ids: list[str], most: int = 5) -> str:
    return ", ".join(ids[:most]) + (f", ... ({len(ids)} in all)" if len(ids) > most else "")


def _unfit_rows(study: Study, cells: list[dict], candidates: dict[str, dict],
                known: dict[str, dict]) -> list[tuple[str, str]]:
    """``(cell id, what is wrong)`` for each candidate row, in cell order: a row without
    results, or one unfit for the study's declared keys, or else for the other ``known`` rows
    (which all come from one study): what all rows of cells of its kind hold, it holds, and
    under each key it holds a value of the kind the other rows hold there."""
    groups: dict[frozenset, list[dict]] = {}
    for cell in cells:
        if cell["id"] in known:
            groups.setdefault(_kind_of(cell), []).append(known[cell["id"]])
    peers = {sig: _Peers(rows) for sig, rows in groups.items()}
    kinds = _ValueKinds([known[c["id"]] for c in cells if c["id"] in known])
    refused = []
    for cell in cells:
        row = candidates.get(cell["id"])
        if row is None:
            continue
        expected = study.expected_keys(cell)
        problem = _resultless(cell, row) or (
            unfit(row, expected) if expected is not None
            else peers[_kind_of(cell)].unfit(row) or kinds.unfit(row))
        if problem:
            refused.append((cell["id"], problem))
    return refused


def _resultless(cell: dict, row: dict) -> str | None:
    """Says so if ``row`` holds nothing besides its cell's keys."""
    if set(row) <= set(cell) | _NOTE_KEYS:
        return "holds no results, only its cell's configuration"
    return None


def _kind_of(cell: dict) -> frozenset:
    """Cells of one kind return rows of one shape: the same keys and the same text values (a
    problem's or a scheme's name may change what a row holds; a seed or a size does not)."""
    return frozenset((k, v if isinstance(v, str) else None) for k, v in cell.items()
                     if k != "id")


class _Peers:
    """What rows of one kind hold: how many hold each key."""

    def __init__(self, rows: list[dict]):
        self.n = len(rows)
        self.holding = Counter(k for r in rows for k in r if k not in _NOTE_KEYS)

    def unfit(self, row: dict) -> str | None:
        """What ``row`` (one of the rows) lacks that all the others hold."""
        others = self.n - 1
        missing = [k for k, n in self.holding.items() if n == others and k not in row]
        if others and missing:
            return f"lacks {', '.join(map(repr, missing))}, which the other rows hold"
        return None


class _ValueKinds:
    """The rows holding each kind of value (number, string, list, ...) under each key, across
    the rows of a study; nulls (non-finite numbers) aside."""

    def __init__(self, rows: list[dict]):
        self.holders: dict[str, dict[str, list[str]]] = {}
        for row in rows:
            for key, value in row.items():
                if key not in _NOTE_KEYS and value is not None:
                    self.holders.setdefault(key, {}).setdefault(_kind(value), []).append(
                        row["id"])

    def unfit(self, row: dict) -> str | None:
        """A value of ``row`` (one of the rows) of a kind no other row holds there, where the
        others agree on one kind; with a single other row, either may be the damaged one."""
        for key, value in row.items():
            if key in _NOTE_KEYS or value is None:
                continue
            kind = _kind(value)
            others = {k: [i for i in ids if i != row["id"]]
                      for k, ids in self.holders.get(key, {}).items()}
            others = {k: ids for k, ids in others.items() if ids}
            if kind in others or len(others) != 1:
                continue
            (other_kind, ids), = others.items()
            if len(ids) == 1:
                return (f"holds {short(value)} under {key!r} where row {ids[0]!r} holds a "
                        f"{other_kind} (one of the two is damaged)")
            return f"holds {short(value)} under {key!r} where the other rows hold a {other_kind}"
        return None


def _kind(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, int | float):
        return "number"
    return {str: "string", list: "list", dict: "object"}.get(type(value), type(value).__name__)


def in_turns(groups: list[Any], reached: Callable[[Any], int], total: Callable[[Any], int],
             chunk: int, advance: Callable[[Any, int], None]) -> None:
    """Train ``groups`` (a study's ensembles, say) in turns of ``chunk`` units (updates,
    epochs) until each reaches its ``total``: the group furthest behind goes next, to the next
    multiple of ``chunk`` (``advance(group, to)``), so a study stopped at any time has every
    group at about the same point, and groups that start behind catch up first. A group that
    stops short of where it was sent (a run that diverged and ended) gets no more turns."""
    ended: list[Any] = []
    while todo := [g for g in groups if reached(g) < total(g) and g not in ended]:
        group = min(todo, key=reached)
        to = min((reached(group) // chunk + 1) * chunk, total(group))
        advance(group, to)
        if reached(group) < to:
            ended.append(group)


def so_far(study_name: str, out: str | Path, size: str, seeds: int | None = None) -> list[dict]:
    """The rows of every started cell of a study in ``out``, finished or not, written to
    ``OUT/rows-so-far.json`` (``rows.json`` holds finished rows only, which ``--reuse``
    adopts); the report of them is :func:`write_report`'s."""
    study = get_study(study_name)
    if size not in study.sizes:
        raise ValueError(f"unknown study size {size!r} for {study_name}; "
                         f"choose from {list(study.sizes)}")
    if study.so_far is None:
        able = sorted(name for name, s in _STUDIES.items() if s.so_far is not None)
        raise UserError(f"the {study_name} study cannot tabulate unfinished cells (--so-far); "
                        f"run it to the end, or use --so-far with {', '.join(able)}")
    out = Path(out).resolve()
    rows = study.so_far(out, size, seeds)
    if not rows:
        raise UserError(f"{out} holds no started cell of the {study_name} study (size {size}); "
                        "give the --out and --size it runs with")
    write_text(out / "rows-so-far.json", dumps(rows))
    return rows


def write_report(study_name: str, rows: list[dict], out: Path) -> str:
    """The study's report of ``rows`` (written under ``out``; its text returned). Rows the
    report fails on (damaged, or of another version of the study) are named, with the
    command that removes them so that a rerun runs their cells again, in place of the
    report's traceback."""
    study = get_study(study_name)
    try:
        return study.report(rows, out)
    except Exception as e:
        named = _breaking(study, rows, e)
        if not named:
            raise
        paths = [out / cid / ROW_FILE for cid in named]
        listed = _listed([str(p) for p in paths])
        what = (f"{listed} {'lacks' if len(paths) == 1 else 'lack'} {e.args[0]!r}, which the "
                "study's report reads" if isinstance(e, KeyError)
                else f"the study's report fails on {listed} ({_one_line(e)})")
        raise UserError(f"{what}: damaged rows, or rows of another version of the study; "
                        "delete them to run their cells again: rm "
                        + " ".join(shlex.quote(str(p)) for p in paths)) from None


def _report_error(study: Study, rows: list[dict]) -> Exception | None:
    """What the study's report of ``rows`` raises (run in a directory of its own), if
    anything."""
    with tempfile.TemporaryDirectory(prefix="adjointsim-report-") as tmp:
        try:
            study.report(rows, Path(tmp))
        except Exception as e:  # what it is, the caller says
            return e
    return None


def _breaking(study: Study, rows: list[dict], error: Exception) -> list[str]:
    """The ids of the rows that the report's ``error`` comes from: those lacking the key of a
    KeyError, or else the rows holding a value of a kind the other rows do not hold there
    (see :class:`_ValueKinds`) without which the report runs, one alone if one will do; empty
    if neither."""
    if isinstance(error, KeyError) and len(error.args) == 1:
        lacking = [r["id"] for r in rows if error.args[0] not in r]
        if lacking:
            return lacking
    kinds = _ValueKinds(rows)
    odd = [r["id"] for r in rows if kinds.unfit(r)]
    # one of them alone first: of two rows disagreeing on a kind, only one may be damaged
    for named in [*([cid] for cid in odd), odd]:
        if named and _report_error(study, [r for r in rows if r["id"] not in named]) is None:
            return named
    return []


def dumps(obj: Any) -> str:
    """JSON without NaN/Infinity (non-finite numbers become null)."""
    return json.dumps(_jsonable(obj), indent=2, allow_nan=False)


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "tolist") and not isinstance(obj, (str, bytes)):  # NumPy arrays, scalars
        return _jsonable(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _check_ids(cells: list[dict], study_name: str) -> None:
    seen: set[str] = set()
    for cell in cells:
        cid = cell.get("id")
        if not isinstance(cid, str) or not cid or "/" in cid or cid.startswith("."):
            raise ValueError(f"study {study_name}: cell id {cid!r} is not a directory name")
        if cid in seen:
            raise ValueError(f"study {study_name}: two cells share the id {cid!r}")
        seen.add(cid)


def execute(run_cell: Callable[[dict, Path], dict], cell: dict, run_dir: str) -> dict:
    """One cell, on a worker (or here): run it, then write its row atomically, so that a row
    file exists only for a cell that finished. A finished cell is not run again (Dask
    recomputes a task whose result was lost with a dead worker before the client got it)."""
    run_dir_path = Path(run_dir)
    row = finished_row(cell, run_dir_path)
    if row is not None:
        return row
    run_dir_path.mkdir(parents=True, exist_ok=True)
    row = _jsonable({**cell, **run_cell(cell, run_dir_path)})
    write_text(run_dir_path / ROW_FILE, dumps(row))
    return row


def execute_group(run_group: Callable[[list[dict], list[Path]], list[dict]], cells: list[dict],
                  out: str) -> list[dict]:
    """A group of cells as :func:`execute` runs one: the unfinished ones together, then each
    row written atomically."""
    dirs = [Path(out) / c["id"] for c in cells]
    rows = [finished_row(c, d) for c, d in zip(cells, dirs)]
    todo = [i for i, r in enumerate(rows) if r is None]
    if todo:
        for i in todo:
            dirs[i].mkdir(parents=True, exist_ok=True)
        for i, row in zip(todo, run_group([cells[i] for i in todo], [dirs[i] for i in todo])):
            rows[i] = _jsonable({**cells[i], **row})
            write_text(dirs[i] / ROW_FILE, dumps(rows[i]))
    return rows


def _tasks(study: Study, todo: list[dict], out: Path,
           workers: int) -> list[tuple[list[dict], Callable, tuple]]:
    """What to submit to ``workers`` workers: per cell, or per group where the study packs
    cells (a group's parts dealt among the workers where the study names its ``turns``)."""
    if not study.pack:
        return [([c], execute, (study.run_cell, c, str(out / c["id"]))) for c in todo]
    groups: dict[tuple, list[dict]] = {}
    for c in todo:
        free = study.pack(c) if callable(study.pack) else study.pack
        key = tuple((k, str(v)) for k, v in sorted(c.items()) if k not in ("id", *free))
        groups.setdefault(key, []).append(c)
    return [(share, execute_group, (study.run_group, share, str(out)))
            for g in groups.values()
            for share in _deal(g, study.turns, workers,
                               lambda part: study.turn_cost(part, [out / c["id"] for c in part]))]


def _deal(group: list[dict], turns: tuple[str, ...], workers: int,
          cost: Callable[[list[dict]], float] = len) -> list[list[dict]]:
    """``group`` in up to ``workers`` shares: its parts (cells equal under ``turns``) kept
    whole, the costliest first to the share of least cost so far; each share in the group's
    order."""
    parts: dict[tuple, list[dict]] = {}
    for c in group:
        parts.setdefault(tuple(str(c.get(k)) for k in turns), []).append(c)
    if not turns or workers < 2 or len(parts) < 2:
        return [group]
    shares: list[list[dict]] = [[] for _ in range(min(workers, len(parts)))]
    loads = [0.0] * len(shares)
    for part in sorted(parts.values(), key=cost, reverse=True):
        k = loads.index(min(loads))
        shares[k].extend(part)
        loads[k] += cost(part)
    order = {c["id"]: i for i, c in enumerate(group)}
    return [sorted(share, key=lambda c: order[c["id"]]) for share in shares]


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def _run_here(study: Study, todo: list[dict], out: Path, retries: int, done) -> None:
    for cells, work, args in _tasks(study, todo, out, workers=1):
        for attempt in range(retries + 1):
            try:
                rows = work(*args)
            except Exception as e:  # reported per cell; the others still run
                if attempt == retries:
                    for cell in cells:
                        done(cell["id"], None, _one_line(e))
            else:
                for cell, row in zip(cells, rows if study.pack else [rows]):
                    done(cell["id"], row, None)
                break


def _worker_execute(work: Callable, *args: Any) -> dict | list[dict]:
    # Before the cell imports torch (the nanny sets these too; a bare worker may not). One
    # solver thread too: the workers already use every core between them.
    os.environ.update(_ONE_THREAD)
    parallel.set_threads(1)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(1)
    return work(*args)


@contextmanager
def _dask_client(study: Study, out: Path, cluster: str, workers: int, retries: int):
    """A client of a local cluster of ``workers`` processes started here (closed on exit) or
    of the scheduler at ``cluster`` (after checking its workers)."""
    import logging

    import dask
    from distributed import Client, LocalCluster

    # A worker that dies running a task counts as a failure of that task: retried as often as
    # an exception is (this holds for the in-process scheduler; a remote one keeps its own
    # distributed.scheduler.allowed-failures, 3 by default). The nanny's environment replaces
    # Dask's default, which also sets MALLOC_TRIM_THRESHOLD_: that makes glibc mmap every
    # tensor over 128 kB, and 256² torch matmul cells ran 1.3-1.6x slower with it (measured).
    with dask.config.set({"distributed.scheduler.allowed-failures": retries,
                          "distributed.nanny.pre-spawn-environ": _ONE_THREAD}):
        if cluster == "local":
            with warnings.catch_warnings():
                # without a dashboard the scheduler still serves /health on 8787 or, when a
                # second study holds that port, on a random one, with a warning that is noise
                warnings.filterwarnings("ignore", "Port 8787 is already in use")
                local = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                     dashboard_address=None, silence_logs=logging.CRITICAL)
            with local, Client(local) as client:
                yield client
        else:
            client = _connect(cluster)
            try:  # Ctrl-C included: a client left open times out in its __del__, later
                _wait_for_workers(client, cluster)
                check_workers(client, out, study)
                yield client
            finally:
                client.close()


def _run_on_dask(client, study: Study, todo: list[dict], out: Path, retries: int,
                 done) -> None:
    from distributed import as_completed
    from distributed.client import FutureCancelledError

    futures = {}
    tasks = _tasks(study, todo, out, workers=sum(client.nthreads().values()))
    for i, (cells, work, args) in enumerate(tasks):
        # cells start in the study's order (higher priority first): a study stopped early
        # has the cells it lists first
        f = client.submit(_worker_execute, work, *args,
                          key=f"{study.name}-{cells[0]['id']}-{uuid.uuid4().hex[:8]}",
                          retries=retries, pure=False, priority=len(tasks) - i)
        futures[f] = cells
    for f in as_completed(futures):
        ids = [c["id"] for c in futures[f]]
        try:
            result = f.result()
            for cid, row in zip(ids, result if study.pack else [result]):
                done(cid, row, None)
        except FutureCancelledError:
            for cid in ids:
                done(cid, None, "cancelled (the scheduler or its workers went away)")
        except Exception as e:
            for cid in ids:
                done(cid, None, _describe_failure(e, retries))


def _describe_failure(exc: BaseException, retries: int) -> str:
    if type(exc).__name__ == "KilledWorker":
        return (f"its worker process died (killed, out of memory or os._exit) on each of "
                f"{retries + 1} attempts")
    return _one_line(exc)


class ClusterError(OSError):
    """No usable scheduler at the given address (the message says what to check)."""


def _connect(address: str):
    """A client of the scheduler at ``address``, once it has answered as one."""
    from distributed import Client

    _ask_scheduler(address)
    try:
        return Client(address, timeout=CONNECT_TIMEOUT + ANSWER_TIMEOUT)
    except (OSError, TimeoutError) as e:
        raise ClusterError(f"cannot reach a Dask scheduler at {address} ({_one_line(e)}); "
                           "start one with `dask scheduler` and give its address "
                           "(tcp://HOST:8786)") from None


def _wait_for_workers(client, address: str) -> None:
    try:
        client.wait_for_workers(1, timeout=30)
    except (TimeoutError, OSError):
        raise ClusterError(f"the scheduler at {address} has no workers; start some with "
                           f"`dask worker {address} --nthreads 1` on each machine") from None


def _ask_scheduler(address: str) -> None:
    """Refuse ``address`` unless a Dask scheduler answers there within CONNECT_TIMEOUT +
    ANSWER_TIMEOUT seconds. Asked on an event loop of its own, in a thread of its own, so a
    caller's running loop (a notebook's) is no obstacle; the thread ends by the deadline."""
    outcome: dict[str, Any] = {}

    def ask() -> None:
        try:
            outcome["identity"] = asyncio.run(asyncio.wait_for(
                _identity(address), CONNECT_TIMEOUT + ANSWER_TIMEOUT))
        except Exception as e:  # raised below, in the caller's thread
            outcome["error"] = e

    from distributed.comm import CommClosedError

    thread = threading.Thread(target=ask, name="adjointsim-ask-scheduler", daemon=True)
    thread.start()
    thread.join()
    error, identity = outcome.get("error"), outcome.get("identity")
    check = ("check the address: a scheduler listens on port 8786 by default (8787 is its "
             "dashboard) and `dask scheduler` prints it")
    if isinstance(error, TimeoutError):
        raise ClusterError(f"{address} accepts connections but does not answer as a Dask "
                           f"scheduler within {CONNECT_TIMEOUT + ANSWER_TIMEOUT:g} s; "
                           f"{check}")
    if isinstance(error, CommClosedError):  # after connecting: connect() retries it before
        raise ClusterError(f"{address} closed the connection and does not answer as a Dask "
                           f"scheduler ({_one_line(error)}); {check}")
    if isinstance(error, OSError):  # Dask's connect gave up: refused, unrouted, unknown host
        # its comm errors read "in <TCPConnector object at 0x...>: ConnectionRefusedError: ..."
        cause = (" (" + re.sub(r"^in <[^>]*>: ", "", str(error.__cause__)) + ")"
                 if error.__cause__ else "")
        raise ClusterError(f"cannot reach a Dask scheduler at {address}: nothing accepted a "
                           f"connection within {CONNECT_TIMEOUT:g} s{cause}; check the host "
                           "and port, and that `dask scheduler` runs there")
    if error is not None:
        raise ClusterError(f"{address} does not answer as a Dask scheduler "
                           f"({_one_line(error)}); {check}")
    kind = identity.get("type") if isinstance(identity, dict) else None
    if kind in ("Worker", "Nanny"):
        raise ClusterError(f"{address} is a Dask {kind.lower()}, not the scheduler; give "
                           "the scheduler's address (the one `dask worker` was given)")
    if kind != "Scheduler":
        raise ClusterError(f"{address} does not answer as a Dask scheduler (it says "
                           f"{short(identity)}); {check}")


async def _identity(address: str) -> Any:
    from distributed.comm import connect
    from distributed.security import Security

    # connect() retries until CONNECT_TIMEOUT, then shakes hands without a timeout of its own
    comm = await connect(address, timeout=CONNECT_TIMEOUT,
                         **Security().get_connection_args("client"))
    try:
        await comm.write({"op": "identity", "reply": True})
        return await comm.read()
    finally:
        comm.abort()


@cache
def source_fingerprint() -> dict:
    """This installation's version and a hash of its source files (every package under
    ``adjointsim``: the solvers, the torch layer, the networks, the command line), so that a
    worker running other code, even uncommitted edits, is found before any work."""
    import importlib.util

    import adjointsim

    digest = hashlib.sha256()
    # find_spec locates the subpackages without importing them (no torch here)
    for package in ("adjointsim", "adjointsim.train", "adjointsim.nets", "adjointsim.cli"):
        spec = importlib.util.find_spec(package)
        for root in spec.submodule_search_locations or ():
            for path in sorted(Path(root).rglob("*.py")):
                digest.update(f"{package}/{path.relative_to(root)}".encode())
                digest.update(path.read_bytes())
    return {"version": adjointsim.__version__, "source": digest.hexdigest()[:16]}


def probe_worker(out: str, token: str, module: str) -> dict:
    """Run on each worker: its code version, whether it can import the study and whether it
    writes into the same ``out`` directory as the client (it must read the client's token)."""
    import socket

    info = {**source_fingerprint(), "host": socket.gethostname(), "problems": []}
    try:
        importlib.import_module(module)
    except Exception as e:
        info["problems"].append(f"cannot import the study module {module} ({_one_line(e)})")
    try:
        probe = Path(out) / f".probe-{socket.gethostname()}-{os.getpid()}"
        write_text(probe, "ok")
        probe.unlink()
        if (Path(out) / ".runner-token").read_text() != token:
            raise OSError("it sees another directory of that name")
    except OSError as e:
        info["problems"].append(f"cannot use the output directory {out} ({_one_line(e)}); "
                                "it must be one shared directory (same path) on every machine")
    return info


def worker_problems(local: dict, probes: dict[str, dict]) -> list[str]:
    """What is wrong with each worker, compared with this process (empty if nothing)."""
    problems = []
    for address, info in sorted(probes.items()):
        where = f"worker {address} ({info.get('host', '?')})"
        if info["version"] != local["version"] or info["source"] != local["source"]:
            problems.append(
                f"{where} runs adjointsim {info['version']} (source {info['source']}), this "
                f"process {local['version']} (source {local['source']}): install the same "
                "code on every machine (same commit, same edits) and restart the workers")
        problems += [f"{where} {p}" for p in info["problems"]]
    return problems


def check_workers(client: Client, out: Path, study: Study) -> None:
    out.mkdir(parents=True, exist_ok=True)
    token = uuid.uuid4().hex
    write_text(out / ".runner-token", token)
    try:
        probes = client.run(probe_worker, str(out), token, study.run_cell.__module__)
    except Exception as e:
        raise OSError(f"the workers cannot run this project's code ({_one_line(e)}); install "
                      "it on every machine (python3 -m pip install -e .) with the same "
                      "Python packages and restart the workers") from None
    finally:
        (out / ".runner-token").unlink(missing_ok=True)
    problems = worker_problems(source_fingerprint(), probes)
    if problems:
        raise OSError("; ".join(problems))
