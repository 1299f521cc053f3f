"""The ``weighting`` study (train/studies/weighting.py): its cells per size, the tiny size end to
end through ``adjointsim study``, reuse of finished cells, the KS row's coefficient error and
the report's table. Tiny networks: seconds."""

import json
import math

import pytest

import adjointsim.train.studies.weighting as study
from adjointsim.cli import main as cli
from adjointsim.train.weighting import RULES

ROW = ("problem", "weighting", "seed", "epochs", "rel_l2", "metric", "wall_s", "train_s",
       "diverged")


def _tiny(tmp_path, capsys):
    out, rows = tmp_path / "study", tmp_path / "rows.json"
    args = ["study", "weighting", "--size", "tiny", "--cluster", "none", "--out", str(out),
            "--json", str(rows), "--no-progress"]
    assert cli(args) == 0
    capsys.readouterr()
    return args, out, json.loads(rows.read_text())


def test_tiny_size_runs_end_to_end_and_reuses_finished_cells(tmp_path, capsys, monkeypatch):
    args, out, rows = _tiny(tmp_path, capsys)
    assert {(r["problem"], r["k"], r["weighting"], r["seed"]) for r in rows} == {
        ("poisson", 1, w, 0) for w in ("uniform", "inverse-dirichlet")}
    for r in rows:
        assert set(ROW) <= set(r) and math.isfinite(r["rel_l2"]) and r["wall_s"] > 0
    assert "| inverse-dirichlet |" in (out / "table.md").read_text()
    assert (out / "weighting.png").stat().st_size > 1000

    def refuse(*a, **kw):
        raise AssertionError("a finished cell was run again")

    monkeypatch.setattr(study, "train_run", refuse)
    assert cli(args) == 0
    assert json.loads((tmp_path / "rows.json").read_text()) == rows


def test_sizes_skip_the_poisson_only_schemes_elsewhere():
    full = study.cells("full", None)
    assert {c["weighting"] for c in full} == set(RULES)
    for c in full:
        if c["problem"] != "poisson":
            assert "k" not in c and c["weighting"] not in ("ntk", "epsilon-optimal")
    k6 = [c for c in full if c.get("k") == 6]
    assert len(k6) == 3 * len(RULES) and {c["epochs"] for c in k6} == {30001}
    assert {c["problem"] for c in full} == {"poisson", "sobolev", "ks-inverse"}
    assert len({c["id"] for c in full}) == len(full)
    quick = study.cells("quick", None)
    assert {c["weighting"] for c in quick} == set(RULES) and {c["seed"] for c in quick} == {0}


def test_ks_inverse_row_measures_the_coefficients(tmp_path):
    cell = {"id": "ks", "problem": "ks-inverse", "weighting": "uniform", "seed": 0,
            "epochs": 3, **study.SIZES["tiny"]["net"]}
    row = study.run_cell(cell, tmp_path)
    err = math.hypot(row["alpha"] - 1, row["beta"] - 1) / math.sqrt(2)
    assert row["rel_l2"] == pytest.approx(err) and row["u_rel_l2"] > 0
    assert row["metric"] == study.METRICS["ks-inverse"]


def test_table_takes_medians_and_names_schemes_below_inverse_dirichlet(tmp_path):
    def row(w, s, err, problem="poisson"):
        return {"problem": problem, "weighting": w, "seed": s, "epochs": 10, "rel_l2": err,
                **({"k": 2} if problem == "poisson" else {})}

    rows = [row("inverse-dirichlet", s, e) for s, e in enumerate((1e-2, 2e-2, 4e-2))]
    rows += [row("mgda", s, e) for s, e in enumerate((1e-3, None, 3e-3))]
    rows += [row("uniform", 0, 0.5, "sobolev"), row("inverse-dirichlet", 0, 0.1, "sobolev")]
    text = study.report(rows, tmp_path)
    assert "| mgda | **2.00e-03 [1.0e-03, 3.0e-03] (1 div.)** |" in text
    assert "| inverse-dirichlet | 2.00e-02 [1.0e-02, 4.0e-02] | **1.00e-01** |" in text
    assert "- k=2: below inverse-dirichlet (2.00e-02): mgda (2.00e-03)" in text
    assert "- sobolev: below inverse-dirichlet (1.00e-01): none" in text
    assert (tmp_path / "weighting.png").stat().st_size > 1000
