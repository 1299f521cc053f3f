"""Cost of running a study through the Dask runner (adjointsim.runner), side by side in one run.

    python benchmarks/runner.py [--tiny 8] [--cells 6] [--seconds 15] [--repeats 3]

* engine overhead: a study of ``--tiny`` cells that do nothing, on a 2-worker local cluster
  (start, submit, gather, stop; the workers importing the project included) against the same
  cells run here (``--cluster none``). Target: ≤ 2 s.
* equal cells: ``--cells`` cells of about ``--seconds`` of one-thread torch work each, on the
  2-worker local cluster (cluster start included) against ``--cluster none`` (one torch thread
  here too). Target: local ≤ 0.6 × none. Cells of 15 s by default: the cells of the
  smallest real study (``study ks --quick``) take 10–40 s. Each worker's start (Python,
  distributed, torch: about 2.5 CPU s) is paid once, so shorter cells give a larger ratio
  (0.70 at 3 s).

Medians over ``--repeats`` (overhead) and the equal-cells runs alternate local / none.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from adjointsim import runner  # noqa: E402

# The cell functions live in this script (__main__): cloudpickle sends them to the workers by
# value, so the workers need not import this file.


def _cells(n: int, work: int, size: str, seeds: int | None) -> list[dict]:
    return [{"id": f"cell-{k}", "seed": k, "work": work} for k in range(n)]


def _tiny_cell(cell: dict, run_dir: Path) -> dict:
    return {"pid": os.getpid()}


def _torch_cell(cell: dict, run_dir: Path) -> dict:
    import torch

    torch.set_num_threads(1)
    a = torch.randn(256, 256, generator=torch.Generator().manual_seed(cell["seed"]))
    for _ in range(cell["work"]):
        a = torch.sin(a @ a) / 16
    return {"pid": os.getpid(), "sum": float(a.abs().sum())}


def _report(rows: list[dict], out: Path) -> str:
    return ""


def _register(name: str, n: int, work: int, run_cell) -> None:
    from functools import partial

    runner.register_study(runner.Study(name, ("tiny",), partial(_cells, n, work), run_cell,
                                       _report))


def _cpu() -> float:
    """CPU seconds of this process and its finished children (the local workers)."""
    return sum(r.ru_utime + r.ru_stime for r in (resource.getrusage(resource.RUSAGE_SELF),
                                                  resource.getrusage(resource.RUSAGE_CHILDREN)))


def _time(name: str, cluster: str) -> tuple[float, float]:
    """Wall and CPU seconds of one run of the study."""
    with tempfile.TemporaryDirectory() as out:
        start, cpu = time.perf_counter(), _cpu()
        runner.run(name, out, "tiny", None, cluster=cluster, jobs=2, progress=False)
        return time.perf_counter() - start, _cpu() - cpu


def _calibrate(seconds: float) -> int:
    """Matmul iterations that take about ``seconds`` on one thread here."""
    import torch

    torch.set_num_threads(1)
    cell = {"seed": 0, "work": 20}
    _torch_cell(cell, Path("."))
    start = time.perf_counter()
    _torch_cell(cell, Path("."))
    per = (time.perf_counter() - start) / 20
    return max(1, round(seconds / per))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tiny", type=int, default=8)
    parser.add_argument("--cells", type=int, default=6)
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    _register("bench-tiny", args.tiny, 0, _tiny_cell)
    # Yardstick for this machine's current load: what each worker process pays to start.
    start = time.perf_counter()
    subprocess.run([sys.executable, "-c", "import adjointsim.runner, distributed"], check=True)
    imports = time.perf_counter() - start
    local, here = [], []
    for _ in range(args.repeats):
        local.append(_time("bench-tiny", "local"))
        here.append(_time("bench-tiny", "none"))
    overhead = _median(local, 0) - _median(here, 0)

    work = _calibrate(args.seconds)
    _register("bench-equal", args.cells, work, _torch_cell)
    eq_local, eq_here = [], []
    for _ in range(max(1, args.repeats // 2)):
        eq_local.append(_time("bench-equal", "local"))
        eq_here.append(_time("bench-equal", "none"))
    ratio = _median(eq_local, 0) / _median(eq_here, 0)

    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; medians of "
          f"{args.repeats} (overhead) and {len(eq_local)} (equal cells) runs; a fresh Python "
          f"importing adjointsim.runner and distributed (what each worker pays) took "
          f"{imports:.2f} s")
    print("wall seconds (CPU seconds of this process and the workers in brackets)")
    print(f"{'study':<42} {'local, 2 workers':>18} {'--cluster none':>16} {'result':>20}")
    for label, a, b, result in (
        (f"{args.tiny} tiny cells (engine overhead)", local, here,
         f"overhead {overhead:.2f} s  (target ≤ 2 s)"),
        (f"{args.cells} equal cells (~{args.seconds:g} s torch, 1 thread)", eq_local, eq_here,
         f"local/none {ratio:.2f}  (target ≤ 0.6)"),
    ):
        print(f"{label:<42} {_median(a, 0):8.2f} ({_median(a, 1):6.2f}) "
              f"{_median(b, 0):7.2f} ({_median(b, 1):6.2f})  {result}")


def _median(runs: list[tuple[float, float]], which: int) -> float:
    return statistics.median(r[which] for r in runs)


if __name__ == "__main__":
    main()
