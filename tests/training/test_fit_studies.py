"""The studies that set a fit (differentiable physics) against a PINN on PBDL's Burgers
problems: run through the runner into their own directories, nothing under docs/."""

import json


def _rows(path):
    return json.loads(path.read_text())


def test_burgers_studies_write_only_their_directory(tmp_path, monkeypatch):
    from adjointsim.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["study", "burgers-dp-pinn", "--size", "tiny", "--cluster", "none",
                 "--no-progress"]) == 0
    out = tmp_path / "runs" / "study-burgers-dp-pinn-tiny"
    result = _rows(out / "fit-burgers.json")
    assert set(result) >= {"rows", "pinn_config", "pinn_history", "dp_history"}
    methods = [r["method"] for r in result["rows"]]
    assert methods[:2] == ["DP, L-BFGS-B, 3 iterations", "DP, L-BFGS-B, 10 iterations"]
    # the PINN within DP's run time (which epoch depends on the timing) and at its end
    assert all(m.startswith("PINN, Adam, uniform weights, ") for m in methods[2:-1])
    assert methods[-2] == "PINN, Adam, uniform weights, 20 epochs"
    assert methods[-1] == "book's DP (phiflow/TF, 50 gradient steps)"
    assert all(set(r) == {"method", "misfit", "u0_mse", "seconds"} for r in result["rows"])
    assert (out / "fit-burgers.md").is_file() and (out / "fit-burgers.png").is_file()
    assert main(["study", "burgers-nu-dp-pinn", "--size", "tiny", "--cluster", "none",
                 "--no-progress"]) == 0
    out = tmp_path / "runs" / "study-burgers-nu-dp-pinn-tiny"
    rows = _rows(out / "fit-params-pinn.json")
    assert [(r["method"].split(" ")[0], r["noise"]) for r in rows] == [
        ("DP", 0.0), ("PINN,", 0.0), ("DP", 0.01), ("PINN,", 0.01)]
    assert all(set(r) == {"method", "noise", "nu", "rel_error", "seconds"} for r in rows)
    assert rows[0]["rel_error"] < 1e-10
    assert (out / "fit-params-pinn.md").is_file() and (out / "fit-params-pinn.png").is_file()
    assert not (tmp_path / "docs").exists()
