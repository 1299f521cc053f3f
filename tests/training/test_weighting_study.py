"""The ``weighting`` study (train/studies/weighting.py): its cells per size, the tiny size end to
end through ``adjointsim study`` (every problem, the guidance controller's tracking loss as its
measure), reuse of finished cells, the KS row's coefficient error and the report's tables.
Tiny networks: seconds."""

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
    schemes = ("uniform", "inverse-dirichlet")
    assert {(r["problem"], r.get("k"), r["weighting"], r["seed"]) for r in rows} == {
        (p, 1 if p == "poisson" else None, w, 0) for w in schemes
        for p in ("poisson", "sobolev", "ks-inverse", "guidance")}
    for r in rows:
        assert set(ROW) <= set(r) and math.isfinite(r["rel_l2"]) and r["wall_s"] > 0
        assert r["metric"] == study.METRICS[r["problem"]]
    guidance = {r["weighting"]: r for r in rows if r["problem"] == "guidance"}
    assert guidance["uniform"]["weights"] is None
    assert set(guidance["inverse-dirichlet"]["weights"]) == {"tracking", "control"}
    for g in guidance.values():  # the measure is the tracking term of the test loss
        assert g["rel_l2"] + g["control"] == pytest.approx(g["test_loss"], rel=1e-5)
    text = (out / "table.md").read_text()
    for p in study.METRICS:
        assert f"## {study.TITLES[p]}: {study.METRICS[p]}" in text
    for name in ("weighting", "weighting-sobolev", "weighting-ks-inverse",
                 "weighting-guidance"):
        assert (out / f"{name}.png").stat().st_size > 1000

    def refuse(*a, **kw):
        raise AssertionError("a finished cell was run again")

    monkeypatch.setattr(study, "train_cell", refuse)
    monkeypatch.setattr(study, "train_controller", refuse)
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
    assert {c["problem"] for c in full} == {"poisson", "sobolev", "ks-inverse", "guidance"}
    assert len({c["id"] for c in full}) == len(full)
    quick = study.cells("quick", None)
    assert {c["weighting"] for c in quick} == set(RULES)
    # Poisson at one seed (the committed cells, unchanged), the other problems at three
    assert {c["seed"] for c in quick if c["problem"] == "poisson"} == {0}
    assert {(c["problem"], c["seed"]) for c in quick if c["problem"] != "poisson"} == {
        (p, s) for p in ("sobolev", "ks-inverse", "guidance") for s in range(3)}
    assert {"id": "poisson-k6-config-s0", "problem": "poisson", "k": 6, "weighting": "config",
            "seed": 0, "epochs": 3000} in quick
    assert {(c["id"], c["seed"]) for c in study.cells("quick", 2)} >= {
        ("poisson-k1-uniform-s1", 1), ("guidance-mgda-s1", 1)}


def test_k6_size_has_five_seeds_for_the_schemes_near_id_and_three_for_the_others():
    seeds = {}
    for c in study.cells("k6", None):
        assert (c["problem"], c["k"], c["epochs"]) == ("poisson", 6, 30001)
        seeds.setdefault(c["weighting"], []).append(c["seed"])
    far = {"mgda", "gradnorm", "softadapt", "relobralo"}
    assert seeds == {w: list(range(3 if w in far else 5)) for w in RULES}
    # --seeds replaces the per-scheme counts too
    assert len(study.cells("k6", 2)) == 2 * len(RULES)
    reduced = study.cells("reduced", 1)
    assert {(c["k"], c["epochs"]) for c in reduced} == {(k, 3000) for k in range(1, 6)}
    assert len(reduced) == 5 * len(RULES)


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
    assert "| inverse-dirichlet | 2.00e-02 [1.0e-02, 4.0e-02] |" in text
    assert "| inverse-dirichlet | **1.00e-01** |" in text
    assert "- k=2: below inverse-dirichlet (2.00e-02): mgda (2.00e-03)" in text
    assert "- sobolev: below inverse-dirichlet (1.00e-01): none" in text
    assert text.index("## Poisson PINN") < text.index("## Sobolev training")
    assert (tmp_path / "weighting.png").stat().st_size > 1000
    assert (tmp_path / "weighting-sobolev.png").stat().st_size > 1000
