"""adjointsim study stability: bisection on Δt finds the FTCS diffusion limit 0.5 h²/ν that the
scheme states, and the sweep runs as cells of the study runner."""

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


def test_stability_report_of_schemes_without_grids_draws_their_panel(tmp_path):
    # oscillators-rk4 has no grid size: it is drawn in the panel of the schemes without one
    cell = stability.cells("tiny", None)[-1]
    assert cell["scheme"] == "oscillators-rk4" and cell["n"] is None
    text = stability.report([{**cell, **stability.run_cell(cell, tmp_path)}], tmp_path)
    assert "| oscillators-rk4 | – |" in text
    assert (tmp_path / "stability.md").is_file() and (tmp_path / "stability.png").is_file()


def test_every_scheme_is_in_the_larger_sizes():
    swept = {c["scheme"] for c in stability.cells("quick", None)}
    assert swept == set(stability.schemes()) == {c["scheme"] for c in
                                                 stability.cells("full", None)}
