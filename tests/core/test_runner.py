"""The Dask study runner (adjointsim.runner) on one machine: a 2-worker local cluster, a
worker killed mid-cell, a failing cell, a rerun that runs nothing, and a real `dask scheduler`
and `dask worker` reached by --cluster and by DASK_SCHEDULER_ADDRESS.

The cells are the test-only study in tests/_runner_cells.py (importable by worker processes).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import _runner_cells  # noqa: F401  (registers the "runner-test" study)
import pytest

from adjointsim import runner
from adjointsim.cli import main

TESTS = Path(__file__).resolve().parent


def _calls(out: Path) -> list[str]:
    return (out / "calls.log").read_text().split("\n")[:-1]


def test_local_cluster_retries_reports_failures_and_reruns_nothing(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)  # the runner gives one thread itself
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
    # Worker processes (not this one), one torch thread each, every row file written: the two
    # started, and the nanny's replacement for the one the "dies" cell kills, which may take
    # cells too when the machine is slow.
    pids = {r["pid"] for r in rows}
    assert len(pids) in (2, 3) and os.getpid() not in pids
    assert all(r["threads"] == 1 for r in rows)
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
