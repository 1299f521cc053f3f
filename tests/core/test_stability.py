"""The stability study's pieces: bisection on Δt finds the FTCS diffusion limit 0.5 h²/ν that
the scheme states, the verdicts, the report and the sizes' schemes (the command, adjointsim
study stability, is tested in tests/commands/test_study_stability.py)."""

from __future__ import annotations

import pytest

from adjointsim import stability


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
