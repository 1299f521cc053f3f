"""The Dask study runner (adjointsim.runner) on one machine: a 2-worker local cluster, a
worker killed mid-cell, a failing cell, a rerun that runs nothing, a real `dask scheduler`
and `dask worker` reached by --cluster and by DASK_SCHEDULER_ADDRESS, addresses where no
scheduler answers, rows (reused or damaged) that lack results or that the study's report
cannot read, and a study directory locked while a study runs in it.

The cells are the test-only study in tests/_runner_cells.py (importable by worker processes).
"""

from __future__ import annotations

import gc
import http.server
import json
import os
import re
import signal
import socket
import socketserver
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import _runner_cells  # noqa: F401  (registers the "runner-test" study)
import pytest

from adjointsim import runner
from adjointsim.cli import main

TESTS = Path(__file__).resolve().parent


def _calls(out: Path) -> list[str]:
    return (out / "calls.log").read_text().split("\n")[:-1]


def test_local_cluster_retries_reports_failures_and_reruns_nothing(tmp_path, monkeypatch, capsys):
    # the runner gives one thread itself, to torch and to the solvers
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.delenv("ADJOINTSIM_THREADS", raising=False)
    out = tmp_path / "study"
    out.mkdir()
    (out / "FAIL").touch()
    argv = ["study", "runner-test", "--size", "tiny", "--out", str(out), "--jobs", "2",
            "--cluster", "local", "--no-progress"]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "cell raises failed: ValueError: boom in cell raises\n" in err
    assert "1 cell(s) failed, 5 finished" in err
    rows = json.loads((out / "rows.json").read_text())
    assert [r["id"] for r in rows] == ["ok-0", "ok-1", "ok-2", "ok-3", "dies"]
    # Worker processes (not this one), one torch and one solver thread each, every row file
    # written: the two started, and the nanny's replacement for the one the "dies" cell kills,
    # which may take cells too when the machine is slow.
    pids = {r["pid"] for r in rows}
    assert len(pids) in (2, 3) and os.getpid() not in pids
    assert all(r["threads"] == 1 and r["solver_threads"] == 1 for r in rows)
    assert not any(r["shows_progress"] for r in rows)  # a worker's bars reach no terminal
    assert all(json.loads((out / r["id"] / "row.json").read_text()) == r for r in rows)
    assert not (out / "raises" / "row.json").exists()
    assert (out / "table.txt").read_text().count("\n") == 5
    # The killed worker's cell ran again and resumed from its checkpoint after epoch 2.
    dies = next(r for r in rows if r["id"] == "dies")
    assert dies["resumed_from"] == 2 and (out / "dies" / "died-once").exists()
    calls = _calls(out)
    assert sum(c.startswith("dies ") for c in calls) == 2
    assert sum(c.startswith("raises ") for c in calls) == 2  # --retries 1
    # A rerun runs only the failed cell (here, to save starting a cluster); the next one
    # starts no cluster at all.
    (out / "FAIL").unlink()
    assert main([*argv, "--cluster", "none"]) == 0
    assert [c.split()[0] for c in _calls(out)[len(calls):]] == ["raises"]
    calls = _calls(out)

    def no_cluster(*args, **kwargs):
        raise AssertionError("a rerun of a finished study must not start a cluster")

    monkeypatch.setattr(runner, "_dask_client", no_cluster)
    assert main(argv) == 0
    assert _calls(out) == calls
    assert len(json.loads((out / "rows.json").read_text())) == 6


@pytest.fixture
def scheduler(tmp_path):
    """A `dask scheduler` and one `dask worker` (a separate process tree) on 127.0.0.1."""
    file = tmp_path / "scheduler.json"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get(
        "PYTHONPATH", "")])}
    dask = str(Path(sys.executable).with_name("dask"))  # the `dask` command of this Python
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0",
                               "--no-dashboard", "--scheduler-file", str(file)], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              start_new_session=True)]
    try:
        deadline = time.monotonic() + 60
        while not file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        address = json.loads(file.read_text())["address"]
        procs.append(subprocess.Popen(
            [dask, "worker", address, "--nthreads", "1", "--nworkers", "1", "--no-dashboard"],
            env=env, cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            start_new_session=True))
        yield address
    finally:
        for p in procs:  # each leads its own process group (the worker's nanny spawns one)
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def test_existing_scheduler_by_flag_and_by_environment(scheduler, tmp_path, monkeypatch):
    # The flag wins over the environment.
    monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", "tcp://127.0.0.1:9")
    rows = runner.run("runner-test", tmp_path / "flag", "ok", 2, cluster=scheduler,
                      progress=False)
    assert [r["id"] for r in rows] == ["ok-0", "ok-1"]
    (pid,) = {r["pid"] for r in rows}
    assert pid != os.getpid() and rows[0]["threads"] == 1
    monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", scheduler)
    argv = ["study", "runner-test", "--size", "ok", "--seeds", "2", "--no-progress",
            "--out", str(tmp_path / "env")]
    assert main(argv) == 0
    assert [r["pid"] for r in json.loads((tmp_path / "env" / "rows.json").read_text())] == [
        pid, pid]
    assert not list((tmp_path / "env").glob(".probe-*"))
    # A study the workers cannot import is refused before any cell runs, saying so.
    (tmp_path / "mods").mkdir()
    (tmp_path / "mods" / "lonely_cells.py").write_text(
        "def run_cell(cell, run_dir):\n    return {}\n")
    monkeypatch.syspath_prepend(str(tmp_path / "mods"))
    import lonely_cells

    runner.register_study(runner.Study("runner-lonely", ("tiny",), _runner_cells.cells,
                                       lonely_cells.run_cell, _runner_cells.report))
    with pytest.raises(OSError, match="cannot import the study module lonely_cells"):
        runner.run("runner-lonely", tmp_path / "lonely", "tiny", 1, cluster=scheduler,
                   progress=False)
    assert not (tmp_path / "lonely" / "ok-0").exists()


def test_a_worker_address_and_ctrl_c_while_waiting_for_workers(scheduler, tmp_path,
                                                               monkeypatch):
    import distributed

    with distributed.Client(scheduler, timeout="30s") as client:
        client.wait_for_workers(1, timeout=60)
        worker = next(iter(client.scheduler_info()["workers"]))
    with pytest.raises(OSError, match=f"{worker} is a Dask worker, not the scheduler"):
        runner.run("runner-test", tmp_path / "w", "ok", 1, cluster=worker, progress=False)
    # Ctrl-C while the runner waits for workers: the client is closed there, not left to
    # Client.__del__ (which then times out with a traceback during a later run).
    closed = []
    close = distributed.Client.close
    monkeypatch.setattr(distributed.Client, "close",
                        lambda self, *a, **k: closed.append(self) or close(self, *a, **k))

    def interrupted(self, *args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(distributed.Client, "wait_for_workers", interrupted)
    with pytest.raises(KeyboardInterrupt):
        runner.run("runner-test", tmp_path / "c", "ok", 1, cluster=scheduler, progress=False)
    # closed (distributed may call close() again from within itself, under load)
    assert closed and all(c.status == "closed" for c in closed)


class _Silent(socketserver.BaseRequestHandler):
    """Accepts a connection and reads it to its end without a word."""

    def handle(self):
        try:
            while self.request.recv(65536):
                pass
        except OSError:
            pass


class _Quiet(http.server.BaseHTTPRequestHandler):
    def log_message(self, *args):
        pass


@contextmanager
def _listening(kind: str):
    """A server on 127.0.0.1 (a free port) that is not a Dask scheduler."""
    server = (socketserver.ThreadingTCPServer(("127.0.0.1", 0), _Silent) if kind == "silent"
              else http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Quiet))
    server.daemon_threads = True
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"tcp://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("kind", ["silent", "http"])
def test_a_server_that_is_no_scheduler_is_refused_in_seconds(kind, tmp_path, monkeypatch,
                                                              capsys):
    monkeypatch.setattr(runner, "CONNECT_TIMEOUT", 1.0)
    monkeypatch.setattr(runner, "ANSWER_TIMEOUT", 1.0)
    argv = ["study", "runner-test", "--size", "ok", "--seeds", "1", "--out", str(tmp_path),
            "--no-progress", "--cluster"]
    with _listening(kind) as address:
        start = time.monotonic()
        assert main([*argv, address]) == 2
        elapsed = time.monotonic() - start
    err = capsys.readouterr().err
    assert elapsed < 8, elapsed
    assert err.count("\n") == 1 and f"{address} " in err
    assert "not answer as a Dask scheduler" in err and "8786" in err
    gc.collect()  # a client left half made would raise from its __del__ here
    assert not (tmp_path / "ok-0").exists()


def test_an_address_where_nothing_listens_is_refused_in_seconds(tmp_path, monkeypatch):
    monkeypatch.setattr(runner, "CONNECT_TIMEOUT", 1.0)
    address = f"tcp://127.0.0.1:{_free_port()}"
    start = time.monotonic()
    with pytest.raises(OSError, match=f"cannot reach a Dask scheduler at {address}: nothing "
                       "accepted a connection within 1 s"):
        runner.run("runner-test", tmp_path, "ok", 1, cluster=address, progress=False)
    assert time.monotonic() - start < 8


@pytest.mark.parametrize("address, says", [
    ("laptop", "no port"), ("tcp://127.0.0.1", "no port"), ("tcp://:8786", "no host"),
    ("tcp://127.0.0.1:abc", "port 'abc'"), ("127.0.0.1:99999", "port '99999'"),
    ("tcp://127.0.0.1:0", "port '0'"), ("tpc://127.0.0.1:8786", "scheme 'tpc'"),
    ("http://127.0.0.1:8787", "dashboard"), ("tcp://127.0.0.1:8786/x", "'/x'"),
    ("tcp://[::1:8786", "not an address"),
])
def test_a_malformed_address_is_refused_before_anything(address, says, tmp_path,
                                                        monkeypatch):
    with pytest.raises(ValueError,
                       match=f"--cluster '{re.escape(address)}': .*{says}.*tcp://HOST:8786"):
        runner.run("runner-test", tmp_path, "ok", 1, cluster=address, progress=False)
    monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", address)
    with pytest.raises(ValueError, match=r"\$DASK_SCHEDULER_ADDRESS '"):
        runner.resolve_cluster(None)
    assert runner.resolve_cluster("127.0.0.1:8786") == "127.0.0.1:8786"  # Dask's default tcp
    assert not list(tmp_path.iterdir())


def test_worker_problems_say_what_to_fix():
    here = {"version": "0.1.0", "source": "abc"}
    ok = {**here, "host": "a", "problems": []}
    assert runner.worker_problems(here, {"tcp://a:1": ok}) == []
    stale = {**ok, "source": "def", "host": "b"}
    lost = {**ok, "problems": ["cannot use the output directory /x (...)"]}
    problems = runner.worker_problems(here, {"tcp://b:1": stale, "tcp://c:1": lost})
    assert "worker tcp://b:1 (b) runs adjointsim 0.1.0 (source def)" in problems[0]
    assert "install the same code on every machine" in problems[0]
    assert problems[1].startswith("worker tcp://c:1 (a) cannot use the output directory")


def test_a_row_of_another_cell_is_refused(tmp_path):
    runner.execute(_runner_cells.run_cell, {"id": "ok-0", "seed": 0}, str(tmp_path / "ok-0"))
    assert runner.finished_row({"id": "ok-0", "seed": 0}, tmp_path / "ok-0")["seed"] == 0
    with pytest.raises(ValueError, match=r"another configuration \(differs in \['seed'\]\)"):
        runner.finished_row({"id": "ok-0", "seed": 1}, tmp_path / "ok-0")
    (tmp_path / "ok-0" / runner.ROW_FILE).write_text("[]")  # JSON, but not a row
    with pytest.raises(ValueError, match="is damaged"):
        runner.finished_row({"id": "ok-0", "seed": 0}, tmp_path / "ok-0")
    with pytest.raises(ValueError, match="choose from"):
        runner.run("no-such-study", tmp_path, "tiny", None)
    with pytest.raises(ValueError, match="--cluster 'laptop'"):
        runner.resolve_cluster("laptop")


def test_rows_of_an_earlier_run_are_reused_not_rerun(tmp_path, capsys):
    """--reuse: the rows of a run elsewhere (its --json file) finish those cells here; a row
    of another configuration and an unreadable file are refused with the flag named."""
    first = tmp_path / "first"
    argv = ["study", "runner-test", "--size", "ok", "--seeds", "2", "--cluster", "none",
            "--no-progress"]
    assert main([*argv, "--out", str(first), "--json", str(tmp_path / "rows.json")]) == 0
    second = tmp_path / "second"
    assert main([*argv, "--seeds", "3", "--out", str(second),
                 "--reuse", str(tmp_path / "rows.json")]) == 0
    assert [c.split()[0] for c in _calls(second)] == ["ok-2"]  # only the cell not in the file
    rows = json.loads((second / "rows.json").read_text())
    assert rows[:2] == json.loads((tmp_path / "rows.json").read_text())
    bad = json.loads((tmp_path / "rows.json").read_text())
    bad[0]["seed"] = 5
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=r"--reuse .*bad.json: its row 'ok-0' is of another "
                       r"configuration \(differs in \['seed'\]\)"):
        runner.run("runner-test", tmp_path / "third", "ok", 2, cluster="none",
                   reuse=tmp_path / "bad.json")
    (tmp_path / "cut.json").write_text('[{"id": "ok-0"')
    with pytest.raises(ValueError, match="cannot read its rows"):
        runner.run("runner-test", tmp_path / "third", "ok", 2, cluster="none",
                   reuse=tmp_path / "cut.json")


def _study(out: Path, name: str, seeds: int, *extra: str) -> list[str]:
    return ["study", name, "--size", "ok", "--seeds", str(seeds), "--cluster", "none",
            "--no-progress", "--out", str(out), *extra]


@pytest.mark.parametrize("bad, says", [
    ({"id": "ok-2", "seed": 2, "pid": 1, "solver_threads": 1, "shows_progress": False},
     "lacks 'threads', 'value'"),
    ({"id": "ok-2", "seed": 2, "pid": 1, "threads": 1, "solver_threads": 1,
      "shows_progress": False, "value": "1.5"},
     "holds '1.5' under 'value' where the other rows hold a number"),
    ({"id": "ok-2", "seed": 2}, "holds no results, only its cell's configuration"),
])
def test_reused_rows_are_checked_whole_and_a_bad_one_copies_nothing(bad, says, tmp_path,
                                                                     capsys):
    """A reused row without the results the study's cells return (or with a value of another
    kind) would break every later run of the directory: refused before anything is copied,
    both into a directory with finished rows and into a new one."""
    good = tmp_path / "good.json"
    assert main(_study(tmp_path / "first", "runner-test", 3, "--json", str(good))) == 0
    rows = json.loads(good.read_text())
    (tmp_path / "bad.json").write_text(json.dumps([*rows[:2], bad]))
    for out in (tmp_path / "some", tmp_path / "fresh"):
        if out.name == "some":
            runner.run("runner-test", out, "ok", 1, cluster="none", progress=False)
        before = sorted(p.relative_to(out) for p in out.rglob("*")) if out.exists() else []
        capsys.readouterr()
        assert main(_study(out, "runner-test", 3, "--reuse", str(tmp_path / "bad.json"))) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1
        assert f"--reuse {tmp_path / 'bad.json'}: its row 'ok-2' {says}" in err
        assert "nothing was copied" in err and "remove" in err
        after = sorted(p.relative_to(out) for p in out.rglob("*")) if out.exists() else []
        assert after == before  # not even the good rows ok-0 and ok-1
    # The good file still finishes those cells without running them.
    assert main(_study(tmp_path / "fresh", "runner-test", 3, "--reuse", str(good))) == 0
    assert not (tmp_path / "fresh" / "calls.log").exists()


def test_a_damaged_row_in_the_study_directory_is_named_with_the_fix(tmp_path, capsys):
    out = tmp_path / "study"
    argv = _study(out, "runner-test", 3)
    assert main(argv) == 0
    row = json.loads((out / "ok-1" / "row.json").read_text())
    del row["pid"]  # a row of another version of the study, or edited by hand
    (out / "ok-1" / "row.json").write_text(json.dumps(row))
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert f"{out / 'ok-1' / 'row.json'} lacks 'pid'" in err and "delete" in err
    (out / "ok-1" / "row.json").write_text('{"id": "ok-1", "se')  # cut short
    (out / "ok-2" / "row.json").write_text("[]")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "2 row files are damaged" in err
    assert f"{out / 'ok-1' / 'row.json'} (not JSON" in err
    assert f"{out / 'ok-2' / 'row.json'} (a JSON list, not an object)" in err
    assert "delete them to run those cells again" in err
    calls = _calls(out)
    (out / "ok-1" / "row.json").unlink()
    (out / "ok-2" / "row.json").unlink()
    assert main(argv) == 0
    assert [c.split()[0] for c in _calls(out)[len(calls):]] == ["ok-1", "ok-2"]


@pytest.mark.parametrize("row_keys", [
    {"pid": int, "threads": int, "value": float},
    lambda cell: {"pid": int, "value": float} if cell["id"].startswith("ok") else {"pid": int},
], ids=["mapping", "per-cell"])
def test_a_study_may_declare_its_row_keys(row_keys, tmp_path, capsys):
    """Declared keys and types hold for every row: rows that all lack a key (an older version
    of the study) are refused too, and a damaged row is found before any cell runs."""
    runner.register_study(runner.Study("runner-declared", ("ok",), _runner_cells.cells,
                                       _runner_cells.run_cell, _runner_cells.report,
                                       row_keys=row_keys))
    old = [{"id": f"ok-{k}", "seed": k, "pid": 1, "threads": 1} for k in range(2)]
    (tmp_path / "old.json").write_text(json.dumps(old))
    out = tmp_path / "study"
    argv = _study(out, "runner-declared", 2)
    assert main([*argv, "--reuse", str(tmp_path / "old.json")]) == 2
    assert "its row 'ok-0' lacks 'value'; and 1 more row (ok-1)" in capsys.readouterr().err
    assert not out.exists() or not list(out.rglob("row.json"))
    assert main(argv) == 0
    row = json.loads((out / "ok-0" / "row.json").read_text())
    (out / "ok-0" / "row.json").write_text(json.dumps({**row, "value": None}))  # a NaN: fine
    assert main(argv) == 0
    (out / "ok-0" / "row.json").write_text(json.dumps({**row, "value": [1.0]}))
    calls = _calls(out)
    assert main(argv) == 2
    assert (f"{out / 'ok-0' / 'row.json'} is damaged (holds [1.0] under 'value', not a "
            "float); delete it to run that cell again" in capsys.readouterr().err)
    assert _calls(out) == calls


def test_rows_of_cells_of_different_kinds_are_checked_apart_when_reused(tmp_path):
    """A row is compared with rows of its own kind only: kind a's rows lack b's key "extra",
    and with one seed each a-0 would otherwise be the one row lacking what the others hold.
    Within a kind the check still holds."""
    runner.run("runner-packed", tmp_path / "first", "ok", 2, cluster="none", progress=False)
    rows = json.loads((tmp_path / "first" / "rows.json").read_text())
    (tmp_path / "one.json").write_text(json.dumps([r for r in rows if r["seed"] == 0]))
    runner.run("runner-packed", tmp_path / "again", "ok", 1, cluster="none", progress=False,
               reuse=tmp_path / "one.json")
    assert not (tmp_path / "again" / "calls.log").exists()
    bad = [{k: v for k, v in r.items() if (r["id"], k) != ("b-1", "value")} for r in rows]
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="its row 'b-1' lacks 'value'"):
        runner.run("runner-packed", tmp_path / "fresh", "ok", 2, cluster="none",
                   progress=False, reuse=tmp_path / "bad.json")


def test_a_packed_study_runs_one_task_per_group_and_only_the_unfinished_members(tmp_path):
    """Cells equal but in the pack keys go to run_group together; each still gets its row
    file, and a rerun with more seeds trains only the new members, as one group per kind."""
    out = tmp_path / "study"
    runner.run("runner-packed", out, "ok", 2, cluster="none", progress=False)
    assert _calls(out) == ["a-0 a-1", "b-0 b-1"]
    rows = {r["id"]: r for r in json.loads((out / "rows.json").read_text())}
    assert rows["b-1"] == {"id": "b-1", "kind": "b", "seed": 1, "pid": os.getpid(), "value": 1.0,
                           "members": 2, "extra": 1}
    assert all((out / i / "row.json").exists() for i in rows)
    runner.run("runner-packed", out, "ok", 3, cluster="none", progress=False)
    assert _calls(out)[2:] == ["a-2", "b-2"]
    assert json.loads((out / "a-0" / "row.json").read_text())["members"] == 2


def test_a_study_may_pack_each_cell_by_its_own_keys(tmp_path):
    """``pack`` as a function of the cell: cells of kind a may differ in kind too (here alone
    in their group), those of kind b in the seed only."""
    out = tmp_path / "study"
    runner.run("runner-packed-by-cell", out, "ok", 2, cluster="none", progress=False)
    assert _calls(out) == ["a-0 a-1", "b-0 b-1"]


def test_a_group_taking_turns_is_one_task_here_and_dealt_among_workers_on_a_cluster(tmp_path):
    """The parts of a group that take turns (here the kinds) train in one task in one process,
    and side by side, a task each, on a cluster of two workers; the rows are the same."""
    here, there = tmp_path / "here", tmp_path / "there"
    runner.run("runner-turns", here, "ok", 2, cluster="none", progress=False)
    assert _calls(here) == ["a-0 a-1 b-0 b-1"]
    runner.run("runner-turns", there, "ok", 2, cluster="local", jobs=2, progress=False)
    assert sorted(_calls(there)) == ["a-0 a-1", "b-0 b-1"]
    rows = [json.loads((d / "rows.json").read_text()) for d in (here, there)]
    assert [r["id"] for r in rows[0]] == [r["id"] for r in rows[1]]
    assert [r["members"] for r in rows[0]] == [4] * 4 and [r["members"] for r in rows[1]] == [2] * 4


def test_parts_are_dealt_whole_the_largest_first_to_the_emptiest_share():
    group = [{"id": f"{kind}{k}", "kind": kind} for kind, n in (("a", 1), ("b", 3), ("c", 2))
             for k in range(n)]
    ids = [[c["id"] for c in share] for share in runner._deal(group, ("kind",), 2)]
    assert ids == [["b0", "b1", "b2"], ["a0", "c0", "c1"]]
    assert len(runner._deal(group, ("kind",), 8)) == 3
    assert runner._deal(group, ("kind",), 1) == [group] == runner._deal(group, (), 4)
    # a's one cell costing 4: it goes first and alone, b (3) and c (2) share the other share
    double_a = [[c["id"] for c in share] for share in runner._deal(
        group, ("kind",), 2, lambda part: len(part) * (4 if part[0]["kind"] == "a" else 1))]
    assert double_a == [["a0"], ["b0", "b1", "b2", "c0", "c1"]]


@pytest.mark.parametrize("progress", [True, False])
def test_cells_run_here_show_their_runs_progress_as_the_study_does(progress, tmp_path):
    """With ``cluster="none"`` a cell's runs show their bars (an ensemble of hours taking
    turns shows the updates it reaches) exactly when the study shows its own, and only while
    the study runs."""
    runner.run("runner-test", tmp_path, "ok", 2, cluster="none", progress=progress)
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert [r["shows_progress"] for r in rows] == [progress, progress]
    assert not runner.runs_show_progress()


def test_groups_in_turns_advance_the_one_furthest_behind_and_drop_one_that_ends():
    at = {"x": 120, "y": 0, "z": 0}
    calls = []

    def advance(g, to):
        calls.append((g, to))
        at[g] = 70 if g == "z" else to  # z ends early (a run that diverged)

    runner.in_turns(["x", "y", "z"], at.get, lambda g: 250, 100, advance)
    assert calls == [("y", 100), ("z", 100), ("y", 200), ("x", 200), ("x", 250), ("y", 250)]
    assert at == {"x": 250, "y": 250, "z": 70}


def _summing_report(rows: list[dict], out: Path) -> str:
    """A report that adds the rows' values, as a study's table does."""
    return f"total {sum(r['value'] for r in rows):.3f}"


runner.register_study(runner.Study("runner-summing", ("ok",), _runner_cells.cells,
                                   _runner_cells.run_cell, _summing_report))


def _tree(out: Path) -> list[Path]:
    return sorted(p.relative_to(out) for p in out.rglob("*")) if out.exists() else []


def test_a_rows_file_that_does_not_fit_is_refused_whole(tmp_path, capsys):
    """Rows without cell ids, repeated ids, rows of another study, rows whose values the
    study's report cannot use (two rows disagreeing on a kind; a key all rows lack): each
    refused in one line, with nothing copied; the good file is then adopted."""
    good = tmp_path / "good.json"
    assert main(_study(tmp_path / "first", "runner-summing", 2, "--json", str(good))) == 0
    rows = json.loads(good.read_text())
    packed = tmp_path / "packed.json"
    runner.run("runner-packed", tmp_path / "packed", "ok", 1, cluster="none", progress=False)
    packed.write_text((tmp_path / "packed" / "rows.json").read_text())
    cases = {
        "listed": ([{**rows[0], "id": [rows[0]["id"]]}, rows[1]],
                   "its row number 1 has no cell id (a text under 'id')"),
        "twice": ([*rows, rows[1]], "its row number 3 repeats the id 'ok-1'"),
        "abc": ([{**rows[0], "value": "abc"}, rows[1]],
                "its row 'ok-0' holds 'abc' under 'value' where row 'ok-1' holds a number "
                "(one of the two is damaged)"),
        "unread": ([{k: v for k, v in r.items() if k != "value"} for r in rows],
                   "its row 'ok-0' breaks the study's report (KeyError: 'value'); and 1 more "
                   "row (ok-1)"),
    }
    out = tmp_path / "fresh"
    for name, (given, says) in cases.items():
        (tmp_path / f"{name}.json").write_text(json.dumps(given))
        assert main(_study(out, "runner-summing", 2, "--reuse",
                           str(tmp_path / f"{name}.json"))) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"--reuse {tmp_path / f'{name}.json'}: {says}" in err
        assert _tree(out) == []
    assert main(_study(out, "runner-summing", 2, "--reuse", str(packed))) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert ("none of its rows (a-0, b-0) is a cell of study runner-summing at size ok "
            "(ok-0, ok-1); give the rows of an earlier run of this study") in err
    assert main(_study(out, "runner-summing", 2, "--reuse", str(good))) == 0
    assert "total" in capsys.readouterr().out and not (out / "calls.log").exists()


def test_a_row_the_report_cannot_read_is_named_and_a_rerun_heals(tmp_path, capsys):
    """A row.json edited in the study directory: without results it is damaged before any
    cell runs; with a value the report cannot add, the report's failure names that row (not
    its sound neighbour) with the command that removes it; then a rerun runs that cell."""
    out = tmp_path / "study"
    argv = _study(out, "runner-summing", 2)
    assert main(argv) == 0
    path = out / "ok-1" / "row.json"
    row = json.loads(path.read_text())
    path.write_text(json.dumps({"id": "ok-1", "seed": 1}))
    capsys.readouterr()
    assert main(argv) == 2
    assert (f"{path} is damaged (holds no results, only its cell's configuration); delete it"
            in capsys.readouterr().err)
    path.write_text(json.dumps({**row, "value": "abc"}))
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert (f"the study's report fails on {path} (TypeError: unsupported operand" in err
            and err.rstrip().endswith(f"delete them to run their cells again: rm {path}"))
    calls = _calls(out)
    path.unlink()
    assert main(argv) == 0
    assert [c.split()[0] for c in _calls(out)[len(calls):]] == ["ok-1"]
    assert json.loads(path.read_text())["value"] == row["value"]


def test_a_study_directory_is_locked_while_a_study_runs_in_it(tmp_path, capsys):
    """A second study in the same directory is refused, naming the first; once that one is
    killed, its lock file is taken over and the study runs."""
    out = tmp_path / "study"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\n"
         "from pathlib import Path\n"
         "from adjointsim.runner import study_lock\n"
         "with study_lock(Path(sys.argv[1])):\n"
         "    print('held', flush=True)\n"
         "    time.sleep(120)\n", str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "held\n"
        argv = _study(out, "runner-test", 1)
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1
        assert (f"{out} is in use by another study (pid {holder.pid} on {socket.gethostname()}"
                in err and "wait for it to finish, or give another --out" in err)
        assert not (out / "ok-0").exists()
    finally:
        holder.kill()
        holder.wait()
    assert (out / runner.LOCK_FILE).exists()
    assert main(argv) == 0
    assert [c.split()[0] for c in _calls(out)] == ["ok-0"]
