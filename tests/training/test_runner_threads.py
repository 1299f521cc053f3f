"""The study runner's workers give torch one thread: a cell that imports torch on a worker of
a local cluster finds one intra-op thread (and one solver thread), the machine's cores being
shared among the workers. The runner itself never imports torch (tests/core/test_runner.py)."""

from __future__ import annotations

import json
import os
from pathlib import Path

from adjointsim import parallel, runner


def _cells(size: str, seeds: int | None) -> list[dict]:
    return [{"id": "torch-0"}]


def _run_cell(cell: dict, run_dir: Path) -> dict:
    import torch

    return {"pid": os.getpid(), "threads": torch.get_num_threads(),
            "solver_threads": parallel.threads()}


def _report(rows: list[dict], out: Path) -> str:
    return ""


runner.register_study(runner.Study("runner-torch", ("tiny",), _cells, _run_cell, _report))


def test_a_worker_gives_torch_one_thread(tmp_path, monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.delenv("ADJOINTSIM_THREADS", raising=False)
    runner.run("runner-torch", tmp_path, "tiny", None, jobs=1, cluster="local", progress=False)
    (row,) = json.loads((tmp_path / "rows.json").read_text())
    assert row["pid"] != os.getpid()
    assert row["threads"] == 1 and row["solver_threads"] == 1
