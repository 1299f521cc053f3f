"""A test-only study for tests/core/test_runner.py, in a module of its own so that Dask worker
processes can import its functions (tests/core is on their path: spawned local workers inherit
sys.path, the test's `dask worker` subprocess gets PYTHONPATH).

Cells: "ok-K" do a little NumPy work; "dies" checkpoints one epoch at a time and kills its
worker process (os._exit) in epoch 2 on its first attempt; "raises" raises while the file
OUT/FAIL exists. Every call appends "id pid" to OUT/calls.log, so tests see what ran where.
Each row holds whether the cell's runs would show their progress bars, the worker's solver
threads and the threads its libraries take (``threads``): OMP_NUM_THREADS, which torch, MKL and
OpenBLAS read when imported, else every core. That torch itself then takes one thread is tested
in tests/training/test_runner_threads.py.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from adjointsim import parallel
from adjointsim.files import write_text
from adjointsim.runner import Study, register_study, runs_show_progress

EPOCHS = 4


def cells(size: str, seeds: int | None) -> list[dict]:
    """size "tiny": ok cells, "dies" and "raises"; size "ok": only ok cells."""
    n = 4 if seeds is None else seeds
    ok = [{"id": f"ok-{k}", "seed": k} for k in range(n)]
    return ok if size == "ok" else ok + [{"id": "dies"}, {"id": "raises"}]


def run_cell(cell: dict, run_dir: Path) -> dict:
    with open(run_dir.parent / "calls.log", "a") as log:
        log.write(f"{cell['id']} {os.getpid()}\n")
    row = {"pid": os.getpid(), "threads": int(os.environ.get("OMP_NUM_THREADS", os.cpu_count())),
           "solver_threads": parallel.threads(), "shows_progress": runs_show_progress()}
    if cell["id"] == "raises" and (run_dir.parent / "FAIL").exists():
        raise ValueError("boom in cell raises\nsecond line")
    if cell["id"] == "dies":
        ckpt = run_dir / "checkpoint.json"
        start = json.loads(ckpt.read_text())["epoch"] if ckpt.exists() else 0
        for epoch in range(start, EPOCHS):
            if epoch == 2 and not (run_dir / "died-once").exists():
                (run_dir / "died-once").touch()
                os._exit(1)
            write_text(ckpt, json.dumps({"epoch": epoch + 1}))
        return {**row, "resumed_from": start}
    a = np.random.default_rng(cell.get("seed", 0)).standard_normal((200, 200))
    for _ in range(20):
        a = np.sin(a @ a / 200)
    time.sleep(0.3)  # long enough that both workers take cells
    return {**row, "value": float(np.abs(a).sum())}


def report(rows: list[dict], out: Path) -> str:
    text = "\n".join(f"{r['id']} {r['pid']}" for r in rows)
    write_text(out / "table.txt", text + "\n")
    return text


register_study(Study("runner-test", ("tiny", "ok"), cells, run_cell, report))


def packed_cells(size: str, seeds: int | None) -> list[dict]:
    """Two kinds × ``seeds`` seeds: cells of one kind train as one group."""
    n = 3 if seeds is None else seeds
    return [{"id": f"{kind}-{k}", "kind": kind, "seed": k} for kind in ("a", "b") for k in range(n)]


def run_group(cells: list[dict], run_dirs: list[Path]) -> list[dict]:
    with open(run_dirs[0].parent / "calls.log", "a") as log:
        log.write(" ".join(c["id"] for c in cells) + "\n")
    # the kinds' rows differ in shape, as two problems' rows may
    return [{"pid": os.getpid(), "value": float(c["seed"]), "members": len(cells),
             **({"extra": 1} if c["kind"] == "b" else {})} for c in cells]


register_study(Study("runner-packed", ("ok",), packed_cells, run_cell, report,
                     pack=("seed",), run_group=run_group))


register_study(Study("runner-packed-by-cell", ("ok",), packed_cells, run_cell, report,
                     pack=lambda c: ("seed", "kind") if c["kind"] == "a" else ("seed",),
                     run_group=run_group))


register_study(Study("runner-turns", ("ok",), packed_cells, run_cell, report,
                     pack=("seed", "kind"), run_group=run_group, turns=("kind",)))
