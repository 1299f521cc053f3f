"""The stabilised-BPTT study's ``budget`` size and the rows of a study still running."""

from __future__ import annotations

import json

from adjointsim.cli import main
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
    # quantum's loop compiled where the mode allows (C's doubled batch cannot be), one runner
    # task per task all the same
    assert {(c["task"], c["mode"], c.get("compile")) for c in cells} == {
        ("guidance", m, None) for m in "RMC"} | {("quantum", "R", "inductor"),
                                                 ("quantum", "M", "inductor"),
                                                 ("quantum", "C", None)}
    for task in ("guidance", "quantum"):
        assert len({tuple((k, v) for k, v in sorted(c.items())
                          if k not in ("id", *stablebptt.pack(c)))
                    for c in cells if c["task"] == task}) == 1


def test_collect_tabulates_the_epochs_a_study_has_reached(tmp_path, capsys):
    cells = stablebptt.cells("tiny", None)
    stablebptt.run_cell(cells[0], tmp_path / cells[0]["id"])  # the other cell not started
    rows = stablebptt.collect(tmp_path, "tiny")
    history = read_history(tmp_path / cells[0]["id"] / "history.csv")
    assert [r["id"] for r in rows] == [cells[0]["id"]]
    assert rows[0]["epochs"] == rows[0]["epochs_planned"] == len(history) == 1
    assert rows[0]["test_loss"] == history[-1]["test_loss"]
    assert main(["study", "stablebptt", "--size", "tiny", "--out", str(tmp_path),
                 "--so-far"]) == 0
    assert json.loads((tmp_path / "rows-so-far.json").read_text())[0]["epochs"] == 1
    assert not (tmp_path / "rows.json").exists()  # --reuse adopts finished rows only
    assert "final test loss" in (tmp_path / "table.txt").read_text()
    assert (tmp_path / "stablebptt-cartpole.png").exists()
    assert "final test loss" in capsys.readouterr().out


def test_rows_so_far_compare_the_modes_at_the_epoch_every_cell_has_reached(tmp_path):
    r, c = stablebptt.cells("tiny", None)
    stablebptt.run_cell({**r, "epochs": 3}, tmp_path / r["id"])  # R ahead of C
    stablebptt.run_cell(c, tmp_path / c["id"])
    rows = {x["mode"]: x for x in stablebptt.collect(tmp_path, "tiny")}
    history = read_history(tmp_path / r["id"] / "history.csv")
    assert rows["R"]["epochs"] == rows["C"]["epochs"] == 1
    assert (rows["R"]["epochs_reached"], rows["C"]["epochs_reached"]) == (3, 1)
    assert rows["R"]["test_loss"] == history[0]["test_loss"] != history[-1]["test_loss"]
    assert len(rows["R"]["test_history"]) == 3
    text = stablebptt.report(list(rows.values()), tmp_path)
    assert "cartpole 1: compared at epoch 1 of 1; reached R/none 3, C/none 1" in text


def test_so_far_names_the_studies_that_can_and_an_empty_directory(tmp_path, capsys):
    assert main(["study", "stablebptt", "--size", "tiny", "--out", str(tmp_path),
                 "--so-far"]) == 2
    err = capsys.readouterr().err
    assert "holds no started cell of the stablebptt study" in err and "Traceback" not in err
    assert main(["study", "pinn-poisson", "--size", "tiny", "--out", str(tmp_path),
                 "--so-far"]) == 2
    err = capsys.readouterr().err
    assert "cannot tabulate unfinished cells" in err
    assert "hig" in err and "ks-curves" in err and "stablebptt" in err


def test_the_budget_modes_take_turns_and_equal_their_runs_in_one_go(tmp_path, monkeypatch):
    """Where cells take turns, one task of the runner holds every mode; the ensemble furthest
    behind advances first, a turn at a time (a mode started ahead waits until the others
    catch up; a turn stops a run short of the epochs its config records), and the runs end
    where uninterrupted ones do."""
    assert {stablebptt.pack(c) for c in stablebptt.cells("budget", None)} == {
        ("seed", "clip", "mode", "compile")}
    assert stablebptt.pack(stablebptt.cells("tiny", None)[0]) == ("seed", "clip")
    cells = [{**c, "epochs": 3, "turn": 1} for c in stablebptt.cells("tiny", None)]
    assert [c["mode"] for c in cells] == ["R", "C"]
    dirs = [tmp_path / "turns" / c["id"] for c in cells]
    # R ahead: started by an earlier sitting, stopped at epoch 1 of the 3 its config records
    assert stablebptt.train_ensemble([stablebptt._config(cells[0], dirs[0])], until=1) == [None]
    calls = []
    real = stablebptt.train_ensemble

    def logged(cfgs, **kw):
        calls.append((cfgs[0].mode, kw.get("until")))
        return real(cfgs, **kw)

    monkeypatch.setattr(stablebptt, "train_ensemble", logged)
    rows = stablebptt.run_group(cells, dirs)
    assert calls == [("C", 1), ("R", 2), ("C", 2), ("R", 3), ("C", 3), ("R", None),
                     ("C", None)]
    monkeypatch.undo()
    for cell, row in zip(cells, rows):
        whole = stablebptt.run_cell(cell, tmp_path / "whole" / cell["id"])
        assert row["test_loss"] == whole["test_loss"]
        assert row["test_history"] == whole["test_history"] and len(row["test_history"]) == 3



def _deal_quantum(out, reached: dict[str, int]) -> list[list[str]]:
    """The quantum budget's modes as the runner deals them to two workers, with each mode's
    runs at the epoch ``reached`` gives (a history of that many rows in ``out``)."""
    from adjointsim import runner

    quantum = [c for c in stablebptt.cells("budget", None) if c["task"] == "quantum"]
    for c in quantum:
        (out / c["id"]).mkdir(parents=True)
        rows = "".join(f"{e},1.0\n" for e in range(1, reached[c["mode"]] + 1))
        (out / c["id"] / "history.csv").write_text("epoch,test_loss\n" + rows)
    study = runner.get_study("stablebptt")
    shares = [share for _, _, (_, share, _) in runner._tasks(study, quantum, out, 2)]
    return sorted(sorted({c["mode"] for c in share}) for share in shares)


def test_two_workers_get_the_quantum_modes_in_shares_of_equal_cost(tmp_path):
    """At the start R's ensemble of 6 compiled runs costs about as much as C's 3 eager ones: R
    and M go to one worker, C to the other."""
    assert _deal_quantum(tmp_path, {"R": 0, "M": 0, "C": 0}) == [["C"], ["M", "R"]]


def test_a_resumed_study_deals_what_is_left(tmp_path):
    """With C nearly done and R furthest behind, R has a worker to itself and M joins C."""
    assert _deal_quantum(tmp_path, {"R": 720, "M": 760, "C": 915}) == [["C", "M"], ["R"]]
    assert stablebptt.turn_cost(
        [{"epochs": 1000}], [tmp_path / "nothing"]) == 1000 * (2.0 + 2.3)
