"""Poisson at the paper's HIG batch (``poisson64``), the study's ``paper-batch`` size, and the
rows of a HIG study still running."""

from __future__ import annotations

import json

from adjointsim.cli import main
from adjointsim.run import read_history
from adjointsim.train.higs import make_problem
from adjointsim.train.studies import hig as study


def test_poisson64_is_poisson_with_hig_and_gn_at_batch_64():
    ours, theirs = make_problem("poisson64", 0, "tiny"), make_problem("poisson", 0, "tiny")
    for opt in ("hig", "gn"):
        # the reference's lr 0.01 on ½ Σ_batch is 0.01 · b/2 on the batch mean
        assert ours.settings[opt] == {"batch": 64, "lr": 0.32, "tau": 1e-5}
    assert ours.settings["adam"] == theirs.settings["adam"] == {"batch": 64, "lr": 3e-4}
    assert all((a == b).all() for a, b in zip(ours.test, theirs.test))
    cells = study.cells("paper-batch", None)
    assert [c["id"] for c in cells[:3]] == ["poisson64-adam-s0", "poisson64-gn-s0",
                                            "poisson64-hig-s0"]
    assert {c["budget"] for c in cells} == {3600.0} and len(cells) == 9


def test_collect_tabulates_the_evaluations_a_study_has_reached(tmp_path):
    cells = study.cells("tiny", 1)
    study.run_cell(cells[0], tmp_path / cells[0]["id"])  # the others not started
    rows = study.collect(tmp_path, "tiny", 1)
    history = read_history(tmp_path / cells[0]["id"] / "history.csv")
    assert [r["id"] for r in rows] == [cells[0]["id"]]
    assert rows[0]["updates"] == history[-1]["update"] > 0
    assert rows[0]["test_loss"] == history[-1]["test_loss"]
    assert set(rows[0]["loss_at"]) == {str(m) for m in cells[0]["marks"]}
    assert main(["study", "hig", "--size", "tiny", "--seeds", "1", "--out", str(tmp_path),
                 "--so-far"]) == 0
    rows = json.loads((tmp_path / "rows-so-far.json").read_text())
    assert [r["id"] for r in rows] == [cells[0]["id"]]
    assert "median over seeds" in (tmp_path / "table.txt").read_text()
    assert (tmp_path / "hig.png").exists()
