"""adjointsim.fit: known answers, the misfit's gradient against finite differences, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

import adjointsim
from adjointsim.fit import FitError, fit, problem


def _trajectory(stepper, u0, n, controls=None):
    return stepper.rollout(u0, n, controls, keep="all")


def test_recovers_ks_coefficients_noise_free():
    ks = adjointsim.get("ks1d-etdrk2")(n=32, dt=0.1)
    u0 = ks.random_state(np.random.default_rng(0))
    traj = _trajectory(ks, u0, 20)
    r = fit(ks, {k: traj[k] for k in range(1, 21)}, wrt="params", u0=u0,
            params={"anti_diffusion": 1.2, "hyper_diffusion": 0.8},
            bounds={"hyper_diffusion": (0.1, None)}, tol=1e-30)
    for k, v in ks.params.items():
        assert abs(r.params[k] / v - 1) <= 1e-6, (k, r.params[k])
    assert r.history[0]["misfit"] > 1e3 * r.misfit
    assert r.history[-1]["iteration"] == len(r.history) - 1


@pytest.mark.parametrize(("wrt", "method"), [("state", "L-BFGS-B"), ("controls", "L-BFGS-B"),
                                            ("state", "BFGS")])
def test_recovers_initial_state_or_controls(wrt, method):
    heat = adjointsim.get("diffusion1d-ftcs")(n=16)
    rng = np.random.default_rng(1)
    u0 = heat.random_state(rng)
    ctrl = heat.random_controls(rng, 6)
    traj = _trajectory(heat, u0, 6, ctrl)
    obs = {k: traj[k] for k in range(1, 7)}
    known = {"u0": u0} if wrt == "controls" else {"controls": ctrl}
    r = fit(heat, obs, wrt=wrt, tol=1e-30, method=method, **known)
    np.testing.assert_allclose(r.state, u0, atol=1e-8)
    np.testing.assert_allclose(r.controls, ctrl, atol=1e-8)
    assert r.wrt == (wrt,)
    # a checkpointed adjoint gives the same objective and gradient
    prob = problem(heat, obs, wrt=wrt, **known)
    z = prob.z0 + rng.standard_normal(prob.z0.shape)
    f, g = prob.objective(z)
    fc, gc = problem(heat, obs, wrt=wrt, checkpoint=3, **known).objective(z)
    assert fc == pytest.approx(f, rel=1e-13)
    np.testing.assert_allclose(gc, g, rtol=1e-10, atol=1e-14 * np.abs(g).max())


@pytest.mark.parametrize("checkpoint", [None, 4])
def test_objective_gradient_matches_finite_differences(checkpoint):
    burgers = adjointsim.get("burgers1d-rusanov")(n=16, nu=0.1)
    rng = np.random.default_rng(2)
    u0 = burgers.random_state(rng)
    ctrl = 0.1 * burgers.random_controls(rng, 8)
    obs = {3: burgers.random_state(rng), 8: burgers.random_state(rng)}
    prob = problem(burgers, obs, wrt="state,controls,params", u0=u0, controls=ctrl,
                   params={"nu": 0.08}, tikhonov=0.3, smoothness=0.2, checkpoint=checkpoint)
    z = prob.z0 + 0.05 * rng.standard_normal(prob.z0.shape)
    f, g = prob.objective(z)
    d = rng.standard_normal(z.shape)
    h = 1e-5
    fd = (prob.objective(z + h * d)[0] - prob.objective(z - h * d)[0]) / (2 * h)
    assert abs(fd - g @ d) <= 1e-6 * abs(g @ d)
    assert prob.last["misfit"] > 0 and prob.last["reg"] > 0


def test_fit_rejects_bad_input():
    heat = adjointsim.get("diffusion1d-ftcs")(n=16)
    u = heat.random_state(np.random.default_rng(3))
    with pytest.raises(ValueError, match=r"step 3 has shape \(1, 16\)"):
        fit(heat, {3: u[0]}, u0=u)
    with pytest.raises(ValueError, match="step 9 is outside the rollout"):
        fit(heat, {9: u}, n=5, u0=u)
    with pytest.raises(ValueError, match="unknown wrt entry 'velocity'"):
        fit(heat, {2: u}, wrt="state,velocity")
    with pytest.raises(ValueError, match="non-finite"):
        fit(heat, {2: np.full_like(u, np.nan)})
    with pytest.raises(ValueError, match="not a gradient-based"):
        fit(heat, {2: u}, method="Nelder-Mead")
    for weight in ("1e-3", None):
        with pytest.raises(TypeError, match=f"tikhonov must be a finite number ≥ 0, not "
                                            f"{weight!r}"):
            fit(heat, {2: u}, tikhonov=weight)
    assert problem(heat, {2: u}, tikhonov=np.array(0.1)).objective  # a 0-d array is a number
    with pytest.raises(ValueError, match="not fitted"):
        fit(heat, {2: u}, bounds={"nu": (0, 1)})
    with pytest.raises(ValueError, match="u0 is needed"):
        fit(heat, {2: u}, wrt="nu")
    with pytest.raises(ValueError, match="no control hook"):
        fit(adjointsim.get("poisson2d")(), {1: np.zeros((1, 1, 16, 16))}, wrt="controls")
    with pytest.raises(ValueError, match=r"empty batch \(B = 0\)"):
        fit(heat, {2: u[:0]})

def test_maxiter_bounds_tnc():
    """TNC has no maxiter option (scipy warned and ignored it): its budget is maxfun."""
    import warnings

    heat = adjointsim.get("diffusion1d-ftcs")(n=16)
    u = heat.random_state(np.random.default_rng(5))
    obs = {4: heat.rollout(u, 4)}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = fit(heat, obs, method="TNC", maxiter=2, tol=1e-30)
    assert r.evaluations <= 2 + 2  # the budget, the start and the final record


def test_fit_reports_a_non_finite_start():
    burgers = adjointsim.get("burgers1d-rusanov")(n=16, nu=0.1)
    u0 = 50.0 * burgers.random_state(np.random.default_rng(4))
    with pytest.raises(FitError, match="non-finite at the starting guess"):
        fit(burgers, {40: np.zeros_like(u0)}, wrt="nu", u0=u0)


def _heat_nu():
    """A diffusion scene (ν = 0.1), its start and noise-free observations of 6 steps."""
    heat = adjointsim.get("diffusion1d-ftcs")(n=16)
    u = heat.random_state(np.random.default_rng(5))
    traj = heat.rollout(u, 6, keep="all")
    return heat, u, {k: traj[k] for k in range(1, 7)}


def test_fit_refuses_a_start_outside_its_bounds():
    """Moving the start onto a bound silently changes the problem (the optimiser used to stop
    there after 0 iterations, reporting success with a worse misfit)."""
    heat, u, obs = _heat_nu()
    with pytest.raises(ValueError, match=r"start of nu \(0\.1\) is outside its bounds "
                                         r"\(0\.2, 0\.5\).*params=\{'nu': \.\.\.\}.*wider"):
        fit(heat, obs, wrt="nu", u0=u, bounds={"nu": (0.2, 0.5)})
    with pytest.raises(ValueError, match=r"start of nu \(0\.04\) is outside its bounds "
                                         r"\(None, 0\.03\)"):
        problem(heat, obs, wrt="nu", u0=u, params={"nu": 0.04}, bounds={"nu": (None, 0.03)})


@pytest.mark.parametrize(("given", "message"), [
    ((0.5, 0.2), r"bounds of nu \(0\.5, 0\.2\) are reversed: lo 0\.5 > hi 0\.2"),
    ((float("nan"), 1.0), r"bounds of nu \(nan, 1\.0\) have a NaN"),
    ((float("inf"), None), r"bounds of nu \(inf, None\) exclude every value"),
    ((None, -float("inf")), r"bounds of nu \(None, -inf\) exclude every value"),
    (0.5, r"bounds of nu 0\.5 are not a pair"),
    (("0", 1), r"bounds of nu \('0', 1\) are not a pair"),
])
def test_fit_rejects_bad_bounds(given, message):
    heat, u, obs = _heat_nu()
    accepted = r"; accepted: \(lo, hi\), each a real number or None \(no bound\), lo ≤ hi$"
    with pytest.raises(ValueError, match=message + ".*" + accepted):
        fit(heat, obs, wrt="nu", u0=u, bounds={"nu": given})
    with pytest.raises(ValueError, match=r"bounds name nu, which is not fitted: bounds are "
                                         r"accepted for the fitted parameters \(none\)"):
        fit(heat, obs, wrt="state", u0=u, bounds={"nu": (0, 1)})


@pytest.mark.parametrize("method", ["L-BFGS-B", "TNC", "SLSQP", "trust-constr"])
def test_fit_reports_the_active_bounds(method):
    heat, u, obs = _heat_nu()
    r = fit(heat, obs, wrt="nu", u0=u, params={"nu": 0.05}, bounds={"nu": (-1, 0.08)},
            method=method)
    assert r.params["nu"] == pytest.approx(0.08, rel=1e-4)
    assert r.active_bounds == {"nu": "upper"} and r.start_active_bounds == {}
    # unbounded, or the optimum inside: no bound is active
    r = fit(heat, obs, wrt="nu", u0=u, params={"nu": 0.05}, bounds={"nu": (0, None)},
            method=method)
    assert r.active_bounds == {} and r.start_active_bounds == {}


def test_fit_says_why_it_stopped_at_the_start():
    heat, u, obs = _heat_nu()
    # on its upper bound, the misfit falls only beyond it
    r = fit(heat, obs, wrt="nu", u0=u, params={"nu": 0.05}, bounds={"nu": (None, 0.05)})
    assert r.iterations == 0 and r.params == {"nu": 0.05}
    assert r.misfit == r.history[0]["misfit"] > 0
    assert r.start_active_bounds == r.active_bounds == {"nu": "upper"}
    assert r.message.startswith("CONVERGENCE: NORM OF PROJECTED GRADIENT <= PGTOL; 0 "
                                "iterations: the stopping test already holds at the start")
    assert "on a bound at the start: nu (upper)" in r.message
    # at the truth (noise-free): nothing to improve
    r = fit(heat, obs, wrt="nu", u0=u)
    assert r.iterations == 0 and r.misfit == 0 and r.success
    assert "0 iterations: the stopping test already holds at the start (gradient norm 0)" \
        in r.message
    assert fit(heat, obs, wrt="nu", u0=u, maxiter=0).message == "maxiter = 0: the starting guess"


def test_fit_command(tmp_path, capsys):
    from adjointsim.cli import main
    from adjointsim.fit_run import demo_problem, write_observations

    out = tmp_path / "ks"
    assert main(["fit", "--demo", "ks-params", "--out", str(out), "--no-progress"]) == 0
    for name in ("config.json", "history.csv", "result.json", "fitted.h5", "fit.png",
                 "history.png", "observations.h5"):
        assert (out / name).is_file(), name
    result = json.loads((out / "result.json").read_text())
    assert max(result["param_rel_error"].values()) <= 1e-6
    assert result["active_bounds"] == result["start_active_bounds"] == {}
    rows = (out / "history.csv").read_text().splitlines()
    assert rows[0].startswith("iteration,misfit") and len(rows) == result["iterations"] + 2
    capsys.readouterr()
    assert main(["fit", "--demo", "ks-params", "--out", str(out), "--no-progress"]) == 2
    assert "holds a finished run" in capsys.readouterr().err
    # a file of one's own: the Burgers reconstruction from its file, a few iterations
    obs = tmp_path / "obs.h5"
    write_observations(obs, demo_problem("burgers"))
    assert main(["fit", "burgers1d-rusanov", "--observations", str(obs), "--maxiter", "5",
                 "--out", str(tmp_path / "b"), "--no-progress", "--no-plots"]) == 0
    assert json.loads((tmp_path / "b" / "result.json").read_text())["iterations"] == 5
    assert not (tmp_path / "b" / "fit.png").exists()
    import h5py

    with h5py.File(obs, "a") as f:  # an integer u0 is a real starting guess
        f["u0"] = np.zeros(f["states"].shape[1:], dtype=np.int64)
    assert main(["fit", "burgers1d-rusanov", "--observations", str(obs), "--maxiter", "1",
                 "--out", str(tmp_path / "int"), "--no-progress", "--no-plots"]) == 0
    complex_obs = tmp_path / "complex.h5"
    write_observations(complex_obs, demo_problem("burgers"))
    with h5py.File(complex_obs, "a") as f:
        states = f["states"][()]
        del f["states"]
        f["states"] = states.astype(np.complex128)
    text_param = tmp_path / "text-param.h5"
    write_observations(text_param, demo_problem("burgers"))
    with h5py.File(text_param, "a") as f:
        f.attrs["params"] = json.dumps({"nu": "abc"})
    bad_n = {}
    for name, value in (("text", "abc"), ("array", np.array([32, 32])), ("half", 31.5)):
        bad_n[name] = tmp_path / f"n-{name}.h5"
        write_observations(bad_n[name], demo_problem("burgers"))
        with h5py.File(bad_n[name], "a") as f:
            f.attrs["n"] = value
    for argv, message in [
        *[(["--observations", str(path)], f"{path}: attribute 'n' must be an integer ≥ 0, not ")
          for path in bad_n.values()],
        (["--observations", str(complex_obs)], "/states has dtype complex128"),
        (["--observations", str(obs), "--steps", "0"], "step 16 is outside the rollout"),
        (["--observations", str(text_param)], "'params': nu must be a number, not 'abc'"),
        (["ks1d-etdrk4", "--observations", str(obs)], "holds observations of 'burgers1d"),
        (["--observations", str(obs), "--wrt", "state,alpha"], "unknown wrt entry 'alpha'"),
        (["--observations", str(tmp_path / "none.h5")], "does not exist"),
        (["--observations", str(obs), "--bounds", "nu=1"], "NAME=LO:HI"),
        (["--observations", str(obs), "--noise", "0.1"], "--noise adds noise to a demo's"),
        (["--demo", "burgers", "--observations", str(obs)], "drop --observations"),
        ([], "give SOLVER --observations FILE.h5, or --demo"),
    ]:
        assert main(["fit", *argv, "--out", str(tmp_path / "x"), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err
    # every input is checked before anything is written
    assert not (tmp_path / "x").exists()


def test_fit_command_bounds(tmp_path, capsys):
    """A start outside its bounds, reversed, non-finite or unfitted bounds: one line, exit 2;
    the bounds active at the start and end in result.json and the summary."""
    from adjointsim.cli import main

    def fit_nu(*flags):
        demo = [] if "--demo" in flags else ["--demo", "burgers-nu"]
        return main(["fit", *demo, "--out", str(tmp_path / "nu"), "--no-progress",
                     "--no-plots", *flags])

    for flags, messages in [
        (["--bounds", "nu=0.008:0.01"],
         ["start of nu (0.006366197723675814) is outside its bounds nu=0.008:0.01",
          "--start nu=VALUE", "wider --bounds nu=LO:HI"]),
        (["--start", "nu=0.012"],
         ["start of nu (0.012) is outside its bounds nu=0:0.01 (the demo's)"]),
        (["--bounds", "nu=0.01:0.001"],
         ["bounds nu=0.01:0.001 are reversed", "LO ≤ HI"]),
        (["--bounds", "nu=nan:1"], ["bounds nu", "'nan' is not a finite number"]),
        (["--bounds", "alpha=0:1"],
         ["bounds name alpha, which is not a parameter (the parameters: nu)"]),
        (["--demo", "ks-params", "--wrt", "anti_diffusion", "--bounds", "hyper_diffusion=0:"],
         ["bounds name hyper_diffusion, which is not fitted", "fitted parameters anti_diffusion"]),
    ]:
        assert fit_nu(*flags) == 2, flags
        err = capsys.readouterr().err
        assert all(m in err for m in messages) and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "nu").exists()
    # a start on its lower bound, the truth below it: 0 iterations, and why
    assert fit_nu("--start", "nu=0.005", "--bounds", "nu=0.005:0.01") == 0
    result = json.loads((tmp_path / "nu" / "result.json").read_text())
    assert result["iterations"] == 0 and result["params"] == {"nu": 0.005}
    assert result["active_bounds"] == result["start_active_bounds"] == {"nu": "lower"}
    assert "0 iterations" in result["message"]
    out = capsys.readouterr().out
    assert "on a bound at the end: nu (lower)" in out and "0 iterations:" in out
    # a demo's own bounds apply to the parameters fitted
    assert main(["fit", "--demo", "ks-params", "--wrt", "state", "--maxiter", "1", "--out",
                 str(tmp_path / "ks"), "--no-progress", "--no-plots"]) == 0


def _fit(out, *flags):
    from adjointsim.cli import main

    return main(["fit", "--demo", "burgers-nu", "--maxiter", "3", "--out", str(out),
                 "--no-progress", "--no-plots", *flags])


def test_fit_resume_and_overwrite(tmp_path, capsys):
    """A fit keeps no checkpoint: --resume returns a finished fit as it is and starts an
    unfinished one again; --overwrite runs it again; a fit of another config is refused."""
    out = tmp_path / "nu"
    assert _fit(out, "--resume") == 2  # nothing there to resume
    assert "holds no run to continue" in capsys.readouterr().err and not out.exists()
    assert _fit(out, "--json", str(tmp_path / "r.json")) == 0
    first = (out / "result.json").read_text()
    assert json.loads((tmp_path / "r.json").read_text()) == json.loads(first)
    stamp = (out / "result.json").stat().st_mtime_ns
    assert _fit(out) == 2
    assert "holds a finished run" in capsys.readouterr().err
    assert _fit(out, "--resume") == 0  # returned as it is, not run again
    assert (out / "result.json").stat().st_mtime_ns == stamp
    assert "misfit" in capsys.readouterr().out
    # another configuration in the same directory: refused, resumed or not
    assert _fit(out, "--tikhonov", "0.1") == 2
    assert "differs in tikhonov" in capsys.readouterr().err
    assert _fit(out, "--tikhonov", "0.1", "--resume") == 2
    # interrupted before result.json: --resume starts it again, with the same result
    (out / "result.json").unlink()
    assert _fit(out, "--resume") == 0
    same = json.loads((out / "result.json").read_text())
    assert {**same, "seconds": 0} == {**json.loads(first), "seconds": 0}
    # --overwrite discards the fit there, even one of another configuration
    assert _fit(out, "--tikhonov", "0.1", "--overwrite") == 0
    assert json.loads((out / "config.json").read_text())["tikhonov"] == 0.1
    # a directory of somebody else's files is never a fit's
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    assert _fit(other) == 2 and _fit(other, "--overwrite") == 2
    assert (other / "notes.txt").read_text() == "mine"


def test_fit_config_file(tmp_path, capsys):
    from adjointsim.cli import main

    good = tmp_path / "fit.toml"
    good.write_text('demo = "burgers-nu"\nmaxiter = 2\nbounds = ["nu=0:0.02"]\n')
    out = tmp_path / "cfg"
    assert main(["fit", "--config", str(good), "--maxiter", "3", "--out", str(out),
                 "--no-progress", "--no-plots"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["maxiter"] == 3 and config["bounds"] == ["nu=0:0.02"]  # the flag wins
    capsys.readouterr()
    for text, key in [('demo = "burgers-nu"\nmaxiter = "five"\n', "'maxiter'"),
                      ('demo = "burgers-nu"\ntikhonov = true\n', "'tikhonov'"),
                      ('demo = "burgers-nu"\nbounds = "nu=0:1"\n', "'bounds'"),
                      ('demo = "heat"\n', "'demo'"),
                      ('demo = "burgers-nu"\nmaxiters = 3\n', "did you mean 'maxiter'")]:
        bad = tmp_path / "bad.toml"
        bad.write_text(text)
        assert main(["fit", "--config", str(bad), "--out", str(tmp_path / "y")]) == 2
        err = capsys.readouterr().err
        assert key in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "y").exists()


def _rows(path):
    return json.loads(path.read_text())


def test_fit_params_study_writes_only_its_directory(tmp_path, monkeypatch):
    """fit-params runs its cells through the runner (without torch) into its directory;
    nothing is written under docs/."""
    from adjointsim.fit_study import ROW_KEYS
    from adjointsim.runner import run

    monkeypatch.chdir(tmp_path)
    out = tmp_path / "runs" / "study-fit-params-tiny"
    run("fit-params", out, "tiny", None, cluster="none", progress=False)
    rows = _rows(out / "fit-params.json")
    assert [(r["problem"], r["noise"], r["parameter"]) for r in rows] == [
        ("ks-params", 0.0, "anti_diffusion"), ("ks-params", 0.0, "hyper_diffusion"),
        ("ks-params", 0.01, "anti_diffusion"), ("ks-params", 0.01, "hyper_diffusion"),
        ("burgers-nu", 0.0, "nu"), ("burgers-nu", 0.01, "nu")]
    assert all(tuple(r) == ROW_KEYS for r in rows)
    assert max(r["rel_error"] for r in rows if r["noise"] == 0) < 1e-10
    assert "| burgers-nu | nu |" in (out / "fit-params.md").read_text()
    assert (out / "fit-params.png").stat().st_size > 0
    assert not (tmp_path / "docs").exists()


def test_fit_demo_scene(tmp_path, capsys):
    """--scene (over a [scene] table) changes a demo's scene: checked by its solver, recorded
    whole in config.json, the observations made and fitted in it; a file names its own."""
    from adjointsim.cli import main
    from adjointsim.fit_demos import SCENES
    from adjointsim.fit_run import read_observations

    out = tmp_path / "nu"
    table = tmp_path / "scene.toml"
    table.write_text("[scene]\nnu = 0.004\nn = 64\n")
    assert _fit(out, "--config", str(table), "--scene", "nu=0.005") == 0
    scene = {**SCENES["burgers-nu"][1], "nu": 0.005, "n": 64}
    assert json.loads((out / "config.json").read_text())["scene"] == scene
    assert json.loads((out / "result.json").read_text())["config"] == scene
    obs = read_observations(out / "observations.h5", None)
    assert obs["config"] == scene and obs["states"].shape[-1] == 64
    assert obs["truth_params"] == {"nu": 0.005}
    capsys.readouterr()
    for flags, message in [
        (["--scene", "nu=-1"], "config key 'scene': burgers1d-rusanov: nu must be"),
        (["--scene", "mass=1"], "scene key 'mass': burgers1d-rusanov takes n, length"),
        (["--scene", "nu"], "--scene 'nu' is not KEY=VALUE"),
    ]:
        assert _fit(tmp_path / "x", *flags) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err
    assert main(["fit", "burgers1d-rusanov", "--observations", str(out / "observations.h5"),
                 "--scene", "nu=0.01", "--out", str(tmp_path / "x")]) == 2
    assert "--scene sets a demo's scene" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_fit_ctrl_c_means_run_it_again(tmp_path, capsys, monkeypatch):
    """A fit keeps no checkpoint: stopped, it says to run the command again, and that (with
    or without --resume) fits from the beginning."""
    from adjointsim import fit_run

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    out = tmp_path / "nu"
    with monkeypatch.context() as m:
        m.setattr(fit_run, "fit", stopped)
        assert _fit(out) == 130
    assert "nothing to resume, run the command again" in capsys.readouterr().err
    assert (out / "config.json").exists() and not (out / "result.json").exists()
    assert _fit(out) == 0 and (out / "result.json").exists()
