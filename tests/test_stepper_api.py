"""The shared contract: validation messages, non-finite detection, cotangent forms, the CLI."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

import adjointsim
from adjointsim import NonFiniteStateError
from adjointsim.cli import main

FTCS = adjointsim.get("diffusion1d-ftcs")


def test_unknown_solver_lists_the_registered_ones():
    with pytest.raises(KeyError, match="diffusion1d-ftcs"):
        adjointsim.get("no-such-solver")


def test_bad_state_shape_and_dtype_say_what_is_expected():
    s = FTCS(n=16)
    with pytest.raises(ValueError, match=r"expected \(B, 1, 16\)"):
        s.rollout(np.zeros((2, 16)), 1)
    with pytest.raises(TypeError, match="expected float32 or float64"):
        s.rollout(np.zeros((2, 1, 16), dtype=np.int64), 1)
    bad = np.zeros((3, 1, 16))
    bad[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match=r"non-finite values in batch element\(s\) \[1\]"):
        s.rollout(bad, 1)


def test_bad_controls_and_params():
    s = FTCS(n=16)
    u = np.zeros((2, 1, 16))
    with pytest.raises(ValueError, match=r"expected \(3, 2, 1, 16\)"):
        s.rollout(u, 3, controls=np.zeros((3, 1, 16)))
    with pytest.raises(TypeError, match="dtype"):
        s.rollout(u, 3, controls=np.zeros((3, 2, 1, 16), dtype=np.float32))
    with pytest.raises(ValueError, match="its parameters are"):
        s.rollout(u, 1, params={"viscosity": 1.0})
    with pytest.raises(ValueError, match=r"parameters must be finite, got nu = nan$"):
        s.rollout(u, 1, params={"nu": np.nan})
    with pytest.raises(ValueError, match="keep must be"):
        s.rollout(u, 1, keep="some")


def test_stability_limit_names_the_largest_stable_dt():
    s = FTCS(n=16, nu=1.0)
    limit = 0.5 * s.h**2
    with pytest.raises(ValueError, match=r"largest stable Δt is ([0-9.e-]+)") as err:
        FTCS(n=16, nu=1.0, dt=1.01 * limit)
    stated = float(re.search(r"largest stable Δt is ([0-9.e-]+)", str(err.value)).group(1))
    assert stated == pytest.approx(limit, rel=1e-5)
    with pytest.raises(ValueError, match="stability limit"):
        s.rollout(np.zeros((1, 1, 16)), 1, params={"nu": 3.0})


def test_blow_up_reports_the_first_non_finite_step():
    s = FTCS(n=16, nu=1.0)
    n = 1999
    u = np.random.default_rng(0).standard_normal((1, 1, 16))
    ctrl = np.zeros((n, 1, 1, 16))
    ctrl[600:] = 1e308  # finite controls whose accumulated effect overflows
    traj = np.empty((n + 1, 1, 1, 16))
    traj[0] = u
    with np.errstate(all="ignore"):
        s._forward(traj, n, ctrl, np.array([1.0]))
    first = int(np.argmax(~np.isfinite(traj).reshape(n + 1, -1).all(axis=1)))
    assert 256 < first < n  # exercises the chunked replay
    with pytest.raises(NonFiniteStateError, match=f"non-finite at step {first} ") as err:
        with np.errstate(all="ignore"):
            s.rollout(u, n, controls=ctrl)
    assert err.value.step == first


def test_cotangent_forms_agree():
    s = FTCS(n=12)
    rng = np.random.default_rng(1)
    u = rng.standard_normal((2, 1, 12))
    n = 5
    every = rng.standard_normal((n + 1, 2, 1, 12))
    as_dict = s.vjp(u, n, {k: every[k] for k in range(n + 1)}).state
    np.testing.assert_allclose(s.vjp(u, n, every).state, as_dict, rtol=1e-14)
    last = s.vjp(u, n, every[n]).state
    np.testing.assert_allclose(s.vjp(u, n, {-1: every[n]}).state, last, rtol=1e-14)
    with pytest.raises(ValueError, match="outside the rollout"):
        s.vjp(u, n, {n + 1: every[0]})


def test_zero_steps_is_identity():
    s = FTCS(n=12)
    u = np.random.default_rng(2).standard_normal((1, 1, 12))
    np.testing.assert_array_equal(s.rollout(u, 0), u)
    np.testing.assert_array_equal(s.vjp(u, 0, u).state, u)


def test_checkpoint_budget_names_its_minimum():
    s = FTCS(n=12)
    u = np.random.default_rng(3).standard_normal((1, 1, 12))
    for bad in (2, 4.5, True):
        with pytest.raises(ValueError, match="at least 3 stored states"):
            s.vjp(u, 5, u, checkpoint=bad)
    np.testing.assert_allclose(s.vjp(u, 5, u, checkpoint=3).state, s.vjp(u, 5, u).state,
                               rtol=1e-14)


def test_cli_list_and_json(capsys):
    assert main(["gradcheck", "--list"]) == 0
    assert "diffusion1d-ftcs" in capsys.readouterr().out.split()
    assert main(["gradcheck", "diffusion1d-ftcs", "--steps", "10", "--json"]) == 0
    out = capsys.readouterr().out
    rows = json.loads(out)
    assert {r["wrt"] for r in rows} == {"state", "controls", "nu"}
    keys = {"solver", "wrt", "dot_rel_err", "dot_ref_err", "dot_bound", "taylor_rate",
            "fd_rel_err", "fd_ref_err", "fd_bound", "passed", "reason"}
    assert all(set(r) == keys and r["passed"] for r in rows)


def test_cli_rejects_unknown_names(capsys):
    assert main(["gradcheck", "nope"]) == 2
    assert "unknown solver" in capsys.readouterr().err


def test_ci_runs_the_readme_commands():
    root = Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text()
    ci = (root / ".ci" / "run").read_text()
    commands = [line for line in ci.splitlines() if line.startswith("python3 -m")]
    assert commands, "no commands in .ci/run"
    for line in commands:
        assert line in readme, f".ci/run runs {line!r}, which the README does not show"
