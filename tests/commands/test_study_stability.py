"""adjointsim study stability: the tiny sweep runs as cells of the study runner and writes its
rows, table and figure; the upwind limit |a| Δt / h ≤ 1 is found where the scheme states it.
A study of the core starts without importing torch."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from adjointsim.cli import main


def test_stability_study(tmp_path, capsys):
    out = tmp_path / "st"
    argv = ["study", "stability", "--size", "tiny", "--cluster", "none", "--no-progress",
            "--out", str(out), "--json", str(tmp_path / "rows.json")]
    assert main(argv) == 0
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert [(r["scheme"], r["n"]) for r in rows] == [
        ("advection1d-upwind", 16), ("advection1d-upwind", 32), ("oscillators-rk4", None)]
    # Upwind: |a| Δt / h ≤ 1, so Δt ≤ h for a = 1 on the unit interval.
    for r in rows[:2]:
        assert r["stated"] == pytest.approx(1 / r["n"], rel=1e-3) and r["verdict"] == "ok"
    assert "| advection1d-upwind | 32 |" in (out / "stability.md").read_text()
    assert "| oscillators-rk4 | – |" in capsys.readouterr().out
    assert (out / "stability.png").stat().st_size > 0



def test_a_core_study_is_found_without_importing_torch():
    code = ("import sys\n"
            "from adjointsim.runner import get_study\n"
            "from adjointsim.train.studies import load\n"
            "load('stability')\n"
            "assert get_study('stability') and 'torch' not in sys.modules\n"
            "load('ks')\n"  # a study of the torch layer: every study is registered
            "assert get_study('ks') and get_study('fit-params')\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
