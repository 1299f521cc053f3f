"""adjointsim gradcheck: the list of solvers, strict JSON rows with the checker's reference
errors, the table's error-estimate columns, and bad names and step counts refused in one line."""

import json

import pytest

from adjointsim.cli import main


def test_cli_list_and_json(capsys):
    assert main(["gradcheck", "--list"]) == 0
    assert "diffusion1d-ftcs" in capsys.readouterr().out.split()
    assert main(["gradcheck", "diffusion1d-ftcs", "--steps", "10", "--json", "-"]) == 0
    out = capsys.readouterr().out
    rows = json.loads(out)
    assert {r["wrt"] for r in rows} == {"state", "controls", "nu"}
    keys = {"solver", "wrt", "dot_rel_err", "dot_ref_err", "dot_bound", "taylor_rate",
            "fd_rel_err", "fd_ref_err", "fd_bound", "passed", "reason"}
    assert all(set(r) == keys and r["passed"] for r in rows)



def test_cli_rejects_unknown_names(capsys):
    assert main(["gradcheck", "nope"]) == 2
    assert "unknown solver" in capsys.readouterr().err



@pytest.mark.parametrize("steps", ["0", "-3"])
def test_cli_rejects_non_positive_steps(steps, capsys):
    assert main(["gradcheck", "diffusion1d-ftcs", "--steps", steps]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"--steps: must be ≥ 1, not {steps}" in err



def test_cli_json_is_strict_json_with_reference_errors(capsys):
    assert main(["gradcheck", "ks1d-etdrk1", "--steps", "5", "--json", "-"]) == 0

    def reject(constant):
        raise AssertionError(f"{constant} is not JSON")

    rows = json.loads(capsys.readouterr().out, parse_constant=reject)
    assert {r["wrt"] for r in rows} == {"state", "controls", "anti_diffusion", "hyper_diffusion"}
    assert all(r["passed"] and r["reason"] is None and r["dot_ref_err"] > 0 for r in rows)



def test_table_shows_reference_errors(capsys):
    assert main(["gradcheck", "ks1d-etdrk1", "--steps", "3"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert "ref" in out[1].split() and "error estimate" in out[0]

