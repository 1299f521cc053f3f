"""adjointsim stability: bisection on Δt finds the FTCS diffusion limit 0.5 h²/ν that the scheme
states, and the sweep runs as cells of the study runner."""

from __future__ import annotations

import json

import pytest

from adjointsim import stability
from adjointsim.cli import main


def test_ftcs_limit_found_and_stated():
    row = stability.run_cell({"scheme": "diffusion1d-ftcs", "n": 16, "steps": 400}, None)
    exact = 0.5 * (1 / 16) ** 2 / 0.1  # ν Δt / h² ≤ 1/2
    assert row["stated"] == pytest.approx(exact, rel=1e-3)
    assert exact / 1.02 <= row["found"] <= 1.05 * exact and row["verdict"] == "ok"


@pytest.mark.parametrize("stated, found, verdict", [
    (1.0, 1.01, "ok"), (1.0, 0.5, "stated too large"), (1.0, 3.0, "conservative"),
    (None, 2.0, "missing"), (None, None, "unconditional"), (1.0, None, "conservative")])
def test_verdicts(stated, found, verdict):
    assert stability.verdict(stated, found) == verdict


def test_stability_command(tmp_path):
    out = tmp_path / "st"
    argv = ["stability", "advection1d-upwind", "--size", "tiny", "--cluster", "none",
            "--out", str(out), "--json", str(tmp_path / "rows.json")]
    assert main(argv) == 0
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert [r["n"] for r in rows] == [16, 32]
    # Upwind: |a| Δt / h ≤ 1, so Δt ≤ h for a = 1 on the unit interval.
    for r in rows:
        assert r["stated"] == pytest.approx(1 / r["n"], rel=1e-3) and r["verdict"] == "ok"
    assert "| advection1d-upwind | 32 |" in (out / "stability.md").read_text()
    assert (out / "stability.png").stat().st_size > 0
    assert main(["stability", "poisson2d", "--cluster", "none"]) == 2  # no time step


def test_stability_command_without_grids_names_no_plot(tmp_path, capsys):
    # oscillators-rk4 has no grid size: no plot is drawn, so none is announced
    out = tmp_path / "osc"
    assert main(["stability", "oscillators-rk4", "--size", "tiny", "--cluster", "none",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"table: {out / 'stability.md'}" in printed
    assert not (out / "stability.png").exists() and "stability.png" not in printed
