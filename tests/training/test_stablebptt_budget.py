"""The stabilised-BPTT study's ``budget`` size and the rows of a study still running."""

from __future__ import annotations

import json

from adjointsim.run import read_history
from adjointsim.train.studies import stablebptt


def test_the_budget_size_is_the_papers_1000_epochs_at_the_hardest_levels():
    cells = stablebptt.cells("budget", None)
    assert {(c["task"], c["level"]) for c in cells} == {("guidance", 0.001), ("quantum", 5)}
    assert {(c["mode"], c["clip"]) for c in cells} == {("R", "none"), ("M", "none"),
                                                      ("C", "none"), ("R", "norm")}
    assert {c["seed"] for c in cells} == {0, 1, 2} and len(cells) == 24
    assert {(c["epochs"], c["train"], c["test"], c["batch"]) for c in cells} == {
        (1000, 256, 256, 8)}
    assert cells[0]["task"] == "guidance" and cells[-1]["task"] == "quantum"


def test_collect_tabulates_the_epochs_a_study_has_reached(tmp_path, capsys):
    cells = stablebptt.cells("tiny", None)
    stablebptt.run_cell(cells[0], tmp_path / cells[0]["id"])  # the other cell not started
    rows = stablebptt.collect(tmp_path, "tiny")
    history = read_history(tmp_path / cells[0]["id"] / "history.csv")
    assert [r["id"] for r in rows] == [cells[0]["id"]]
    assert rows[0]["epochs"] == rows[0]["epochs_planned"] == len(history) == 1
    assert rows[0]["test_loss"] == history[-1]["test_loss"]
    stablebptt.main([str(tmp_path), "--size", "tiny", "--to", str(tmp_path / "report")])
    assert json.loads((tmp_path / "report" / "rows.json").read_text())[0]["epochs"] == 1
    assert "final test loss" in (tmp_path / "report" / "table.txt").read_text()
    assert (tmp_path / "report" / "stablebptt-cartpole.png").exists()
