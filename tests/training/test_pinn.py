"""The PINNs (train/pinn.py, train/pinns/, cli/pinn.py): problems, the training run on the
engine, checkpoints and kill/resume, bad input, the command's run lifecycle (--resume,
--overwrite, --config) and tiny end-to-end studies. Tiny networks and point sets: seconds."""

import json
import math

import pytest
import torch

import adjointsim.run
from adjointsim.cli import main as cli
from adjointsim.errors import RunExists, UserError
from adjointsim.run import read_history
from adjointsim.train import pinn, pinns
from adjointsim.train.pinn import PinnConfig, make_problem, train_run
from adjointsim.train.pinns.poisson import Poisson

TINY = {"width": 6, "depth": 2, "collocation": 40, "edge_points": 6, "log_every": 2}
TINY_ARGS = ["--width", "6", "--depth", "2", "--collocation", "40", "--edge-points", "6",
             "--log-every", "2", "--no-progress"]


def _cfg(**kw):
    return PinnConfig(**{**TINY, "epochs": 12, "k": 2, **kw})


def test_problem_matches_the_note():
    cfg = PinnConfig(k=3)
    p = make_problem(cfg)
    assert p.x_col.shape == (2500, 2) and p.x_bc.shape == (400, 2)
    # 100 points on each edge in turn: x = 0, x = 1, y = 0, y = 1
    edges = p.x_bc.view(4, 100, 2)
    for e, (axis, value) in enumerate(((0, 0.0), (0, 1.0), (1, 0.0), (1, 1.0))):
        assert (edges[e, :, axis] == value).all()
    # every collocation point lies on the 100 × 100 grid, none twice
    assert len({tuple(r) for r in (p.x_col * 99).round().int().tolist()}) == 2500
    assert sum(m.numel() for m in p.model().parameters()) == 10401
    w = 3 * math.pi
    assert p.analytic_weights()["res"] == pytest.approx(1 / (1 + w**4))
    assert p.milestones(30001) == [10000, 20000, 30000]
    # the exact solution solves the equation: Δu = f with u = cos(ωx) sin(ωy)
    x = p.x_col[:5].double().requires_grad_(True)
    u = p.exact(x).sum()
    g = torch.autograd.grad(u, x, create_graph=True)[0]
    lap = sum(torch.autograd.grad(g[:, i].sum(), x, retain_graph=True)[0][:, i] for i in (0, 1))
    torch.testing.assert_close(lap, p.source(x)[:, 0], rtol=1e-10, atol=1e-8)


def test_taylor_and_autograd_routes_give_the_same_laplacian():
    p = make_problem(_cfg(width=7, depth=3))
    model = p.model().double()
    x = p.x_col.double()
    torch.testing.assert_close(model.laplacian(x, "taylor"), model.laplacian(x, "autograd"),
                               rtol=1e-10, atol=1e-10)


def test_run_writes_history_plots_and_refuses_to_overwrite(tmp_path):
    out = tmp_path / "run"
    result = train_run(_cfg(weighting="id"), out, progress=False)
    assert math.isfinite(result["rel_l2"]) and not result["diverged"]
    assert result["weights"]["res"] == 1.0 and result["weights"]["bc"] != 1.0
    hist = read_history(out / "history.csv")
    assert [h["epoch"] for h in hist] == [0, 2, 4, 6, 8, 10, 12]
    assert {"loss/res", "loss/bc", "weight/res", "weight/bc", "rel_l2"} <= set(hist[0])
    assert hist[-1]["rel_l2"] == pytest.approx(result["rel_l2"])
    refreshes = read_history(out / "weights.csv")  # ID refreshes every 5 epochs, from 0
    assert [r["step"] for r in refreshes] == [0, 0, 5, 10]
    assert refreshes[-1]["bc"] == pytest.approx(result["weights"]["bc"])
    assert refreshes[-1]["spread/res"] > 0
    for name in ("field.png", "history.png"):
        assert (out / name).stat().st_size > 1000
    with pytest.raises(RunExists, match="finished run"):
        train_run(_cfg(weighting="id"), out, progress=False)
    assert train_run(_cfg(weighting="id"), out, resume=True, progress=False) == result
    # resuming it under another configuration does not pass its result off as the new one's
    with pytest.raises(RunExists, match="holds a run of epochs = 12; pass as much or more"):
        train_run(_cfg(weighting="id", epochs=3), out, resume=True, progress=False)
    with pytest.raises(RunExists, match="differs in seed"):
        train_run(_cfg(weighting="id", seed=3), out, resume=True, progress=False)


def test_ctrl_c_inside_an_update_resumes_without_repeating_it(tmp_path, monkeypatch):
    import os
    import signal

    straight = train_run(_cfg(weighting="id"), tmp_path / "a", progress=False, plot=False)
    real, calls = torch.optim.lr_scheduler.MultiStepLR.step, []

    def step(self, *args, **kwargs):
        real(self, *args, **kwargs)
        calls.append(1)
        if len(calls) == 7:  # after the parameter update, before the epoch is counted
            os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(torch.optim.lr_scheduler.MultiStepLR, "step", step)
    with pytest.raises(KeyboardInterrupt):
        train_run(_cfg(weighting="id"), tmp_path / "b", progress=False, plot=False)
    monkeypatch.setattr(torch.optim.lr_scheduler.MultiStepLR, "step", real)
    again = train_run(_cfg(weighting="id"), tmp_path / "b", resume=True, progress=False,
                      plot=False)
    assert again["rel_l2"] == straight["rel_l2"] and again["weights"] == straight["weights"]


def test_interrupted_run_resumes_to_the_same_result(tmp_path, monkeypatch):
    straight = train_run(_cfg(weighting="maxavg"), tmp_path / "a", progress=False, plot=False)
    real, calls = Poisson.losses, []

    def interrupt(self, model, route="taylor", terms=()):
        calls.append(1)
        if len(calls) == 7:
            raise KeyboardInterrupt
        return real(self, model, route)

    monkeypatch.setattr(Poisson, "losses", interrupt)
    with pytest.raises(KeyboardInterrupt, match="--resume"):
        train_run(_cfg(weighting="maxavg"), tmp_path / "b", progress=False, plot=False)
    monkeypatch.setattr(Poisson, "losses", real)
    with pytest.raises(RunExists, match="--resume"):
        train_run(_cfg(weighting="maxavg"), tmp_path / "b", progress=False, plot=False)
    with pytest.raises(RunExists, match="run of another configuration .*differs in seed"):
        train_run(_cfg(weighting="maxavg", seed=1), tmp_path / "b", resume=True, progress=False)
    again = train_run(_cfg(weighting="maxavg"), tmp_path / "b", resume=True, progress=False,
                      plot=False)
    assert again["rel_l2"] == straight["rel_l2"] and again["weights"] == straight["weights"]
    assert again["phases"] == straight["phases"]
    for name in ("history.csv", "weights.csv"):  # bit-identical rows, but for the timing
        rows = [[{k: v for k, v in h.items() if k != "seconds"}
                 for h in read_history(tmp_path / d / name)] for d in ("a", "b")]
        assert rows[0] == rows[1] and len(rows[0]) > 3, name


def test_threads_may_change_on_resume_and_runs_recorded_without_the_key_are_kept(tmp_path):
    straight = train_run(_cfg(), tmp_path / "a", progress=False, plot=False)
    train_run(_cfg(), tmp_path / "b", progress=False, plot=False)
    out = tmp_path / "b"
    (out / "result.json").unlink()  # stopped before its result, written before threads was a key
    config = json.loads((out / "config.json").read_text())
    del config["threads"]
    (out / "config.json").write_text(json.dumps(config))
    again = train_run(_cfg(threads=2), out, resume=True, progress=False, plot=False)
    assert again["rel_l2"] == straight["rel_l2"] and again["threads"] == 2
    finished = json.loads((out / "result.json").read_text())
    del finished["threads"]
    (out / "result.json").write_text(json.dumps(finished))
    assert train_run(_cfg(), out, resume=True, progress=False)["rel_l2"] == again["rel_l2"]
    with pytest.raises(RunExists, match="differs in seed"):
        train_run(_cfg(seed=1), out, resume=True, progress=False)


def test_non_finite_losses_skip_the_update_with_a_warning(tmp_path, monkeypatch):
    real, calls = Poisson.losses, []

    def flaky(self, model, route="taylor", terms=()):
        calls.append(1)
        terms = real(self, model, route)
        if len(calls) in (3, 4):
            terms["bc"] = terms["bc"] * math.nan
        return terms

    monkeypatch.setattr(Poisson, "losses", flaky)
    with pytest.warns(RuntimeWarning, match="non-finite loss"):
        result = train_run(_cfg(), tmp_path / "r", progress=False, plot=False)
    assert result["skipped"] == 2 and not result["diverged"] and math.isfinite(result["rel_l2"])


def test_lasting_non_finite_losses_end_the_run_as_diverged(tmp_path, monkeypatch, capsys):
    def broken(self, model, route="taylor", terms=()):
        return {"res": torch.tensor(math.inf), "bc": torch.tensor(1.0)}

    monkeypatch.setattr(Poisson, "losses", broken)
    with pytest.warns(RuntimeWarning):
        code = cli(["pinn", "poisson", *TINY_ARGS, "--epochs", "5", "--out", str(tmp_path)])
    assert code == 1 and "diverged" in capsys.readouterr().out
    result = json.loads((tmp_path / "result.json").read_text())
    assert result["diverged"] and result["skipped"] == pinn.MAX_SKIPS


def test_corrupt_checkpoint_is_a_clear_error(tmp_path):
    train_run(_cfg(), tmp_path, progress=False, plot=False)
    (tmp_path / "result.json").unlink()
    (tmp_path / "checkpoint.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a readable checkpoint"):
        train_run(_cfg(), tmp_path, resume=True, progress=False)


def test_damaged_run_files_are_clear_errors(tmp_path):
    train_run(_cfg(), tmp_path / "r", progress=False, plot=False)
    ckpt, result = tmp_path / "r" / "checkpoint.pt", tmp_path / "r" / "result.json"
    # a flipped bit in a weight: torch loads it, the digest does not
    weights = torch.load(ckpt, weights_only=False)["state"]["model"]
    raw = bytearray(ckpt.read_bytes())
    raw[raw.find(weights["mlp.net.0.weight"].numpy().tobytes()) + 1] ^= 1
    ckpt.write_bytes(bytes(raw))
    result.unlink()
    with pytest.raises(ValueError, match="damaged: .*SHA-256.*delete it"):
        train_run(_cfg(), tmp_path / "r", resume=True, progress=False)
    for text in ('{"problem": "pois', "[1, 2]", "{}"):
        result.write_text(text)
        with pytest.raises(RunExists, match="result.json is damaged"):
            train_run(_cfg(), tmp_path / "r", resume=True, progress=False)


def test_a_run_stopped_after_its_last_checkpoint_resumes_to_the_same_result(tmp_path):
    straight = train_run(_cfg(), tmp_path / "a", progress=False, plot=False)
    train_run(_cfg(), tmp_path / "b", progress=False, plot=False)
    (tmp_path / "b" / "result.json").unlink()  # Ctrl-C while plotting: no result yet
    again = train_run(_cfg(), tmp_path / "b", resume=True, progress=False, plot=False)
    assert again["phases"] == straight["phases"] and len(again["phases"]) == 1
    rows = [[{k: v for k, v in h.items() if k != "seconds"}
             for h in read_history(d / "history.csv")] for d in (tmp_path / "a", tmp_path / "b")]
    assert rows[0] == rows[1]


def test_a_finished_run_continues_to_more_epochs_as_the_longer_run(tmp_path, monkeypatch):
    monkeypatch.setattr(Poisson, "lr_steps", (5, 9))  # lr steps inside the tiny runs
    straight = train_run(_cfg(epochs=12, log_every=4), tmp_path / "a", progress=False,
                         plot=False)
    train_run(_cfg(epochs=7, log_every=4), tmp_path / "b", progress=False, plot=False)
    with pytest.raises(RunExists, match="continue it to more with --resume"):
        train_run(_cfg(epochs=12, log_every=4), tmp_path / "b", progress=False)
    with pytest.raises(RunExists, match="epochs = 7; pass as much or more"):
        train_run(_cfg(epochs=6, log_every=4), tmp_path / "b", resume=True, progress=False)
    longer = train_run(_cfg(epochs=12, log_every=4), tmp_path / "b", resume=True,
                       progress=False, plot=False)
    assert {k: v for k, v in longer.items() if k != "seconds"} == \
        {k: v for k, v in straight.items() if k != "seconds"}
    assert longer["phases"][0]["epoch"] == 12
    for name in ("history.csv", "weights.csv"):
        rows = [[{k: v for k, v in h.items() if k != "seconds"}
                 for h in read_history(tmp_path / d / name)] for d in ("a", "b")]
        assert rows[0] == rows[1], name
    # terms that join at fractions of the epochs: a longer run is another run
    seq = {"problem": "sequential", "epochs": 6}
    train_run(_cfg(**seq), tmp_path / "s", progress=False, plot=False)
    with pytest.raises(RunExists, match="differs in epochs"):
        train_run(_cfg(**{**seq, "epochs": 9}), tmp_path / "s", resume=True, progress=False)


def test_out_of_something_else_is_refused(tmp_path, capsys, monkeypatch):
    (tmp_path / "theirs").mkdir()
    (tmp_path / "theirs" / "config.json").write_text('{"precious": true}')
    with pytest.raises(RunExists, match="another command's run or other files"):
        train_run(_cfg(), tmp_path / "theirs", progress=False)
    assert (tmp_path / "theirs" / "config.json").read_text() == '{"precious": true}'
    (tmp_path / "afile").write_text("")
    assert cli(["pinn", "poisson", *TINY_ARGS, "--out", str(tmp_path / "afile")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot write the run to --out" in err[0]

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    real = pinn.PinnRun.update
    monkeypatch.setattr(pinn.PinnRun, "update", stop)
    args = ["pinn", "poisson", *TINY_ARGS, "--epochs", "4", "--out", str(tmp_path / "new")]
    assert cli(args) == 130  # Ctrl-C saves the checkpoint: the command says how to go on
    assert "the checkpoint is saved; continue with the same command and --resume" in \
        capsys.readouterr().err
    monkeypatch.setattr(pinn.PinnRun, "update", real)
    assert cli([*args, "--resume"]) == 0


def test_a_config_is_checked_before_anything_is_written(tmp_path):
    with pytest.raises(UserError, match="config key 'k': 7 is not an integer in"):
        train_run(_cfg(k=7), tmp_path / "r", progress=False)
    with pytest.raises(UserError, match="the sequential problem has no analytic weights"):
        train_run(_cfg(problem="sequential", weighting="ntk"), tmp_path / "r", progress=False)
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("args, message", [
    (["poisson", "--k", "7"], "config key 'k': 7 is not an integer in [1, 6]"),
    (["poisson", "--k", "0"], "config key 'k': 0 is not an integer in [1, 6]"),
    (["poisson", "--seed", "-1"], "config key 'seed': -1 is not an integer in [0, "),
    (["poisson", "--collocation", "1"], "config key 'collocation': 1 is not an integer in [2, "),
    (["poisson", "--alpha", "0"], "config key 'alpha': 0.0 is not a finite number in (0, 1]"),
    (["sobolev", "--weighting", "fixed"], "the sobolev problem has no analytic weights"),
    (["ks-inverse", "--route", "autograd"], "takes route 'taylor' only"),
])
def test_cli_bad_input_is_one_line(args, message, capsys, tmp_path):
    assert cli(["pinn", *args, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("args, message", [
    (["heat"], "invalid choice: 'heat'"),
    (["poisson", "--weighting", "gradnrom"], "invalid choice: 'gradnrom'"),
    (["poisson", "--epochs", "many"], "argument --epochs: 'many' is not an integer"),
    (["poisson", "--edge-points", "1e9"], "argument --edge-points: '1e9' is not an integer"),
    (["poisson", "--reference", "bc"], "invalid choice: 'bc'"),
])
def test_cli_malformed_flags_are_one_line(args, message, capsys, tmp_path):
    assert cli(["pinn", *args, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


def test_help_says_what_0_means_and_lists_the_choices(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "300")  # no wrapping inside the phrases looked for
    with pytest.raises(SystemExit) as e:
        cli(["pinn", "--help"])
    assert e.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    # every registered problem, with its own defaults
    assert pinns.PROBLEMS.names() == ["ks-inverse", "poisson", "sequential", "sobolev"]
    assert ("0: the problem's (ks-inverse 6000, poisson 30001, sequential 3000, sobolev 30001)"
            in text)
    assert "0: the problem's (ks-inverse 50, poisson 50, sequential 50, sobolev 64)" in text
    for choices in ("{ks-inverse,poisson,sequential,sobolev}", "{res,max}", "{taylor,autograd}",
                    "{uniform,epsilon-optimal,inverse-dirichlet,max-avg,mgda,gradnorm,softadapt,"
                    "relobralo,ntk,pcgrad,config,id,maxavg,analytic,fixed}"):
        assert choices in text
    for flag in ("--out", "--resume", "--overwrite", "--config", "--seed", "--threads",
                 "--no-progress"):
        assert flag in text


@pytest.mark.parametrize("args, message", [
    (["--width", "200000"], "config key 'width': 200000 is not an integer in [0, 4096]"),
    (["--edge-points", "1000000000"],
     "config key 'edge_points': 1000000000 is not an integer in [1, 100000]"),
    (["--depth", "100000"], "config key 'depth': 100000 is not an integer in [1, 100]"),
    (["--width", "4096", "--depth", "100"], "GiB of memory, more than this machine's 16.0 GiB"),
])
def test_absurd_sizes_are_refused_before_anything_is_allocated(args, message, capsys, tmp_path,
                                                               monkeypatch):
    def allocate(*args, **kwargs):
        raise AssertionError("allocated before the sizes were checked")

    monkeypatch.setattr(adjointsim.run, "physical_memory", lambda: 16 * 2**30)
    monkeypatch.setattr(pinns, "MLP", allocate)
    monkeypatch.setattr(Poisson, "__init__", allocate)
    assert cli(["pinn", "poisson", *args, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "x").exists()


def test_resume_without_a_checkpoint_is_one_line(tmp_path, capsys):
    for out in (tmp_path / "none", tmp_path):
        assert cli(["pinn", "poisson", *TINY_ARGS, "--resume", "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "holds no run to continue" in err[0]
    assert not (tmp_path / "none").exists()


def test_overwrite_discards_the_run_and_starts_again(tmp_path, capsys):
    args = ["pinn", "poisson", "--epochs", "4", *TINY_ARGS, "--out", str(tmp_path / "r")]
    assert cli(args) == 0
    first = json.loads((tmp_path / "r" / "result.json").read_text())
    assert cli([*args, "--epochs", "6"]) == 2
    assert "finished run (epochs = 4); continue it to more with --resume" in \
        capsys.readouterr().err
    assert cli([*args, "--epochs", "6", "--overwrite"]) == 0
    again = json.loads((tmp_path / "r" / "result.json").read_text())
    assert again["epochs"] == 6 and again["rel_l2"] != first["rel_l2"]
    assert read_history(tmp_path / "r" / "history.csv")[-1]["epoch"] == 6
    # the same as a run in an empty directory
    assert cli([*args[:-1], str(tmp_path / "fresh"), "--epochs", "6"]) == 0
    fresh = json.loads((tmp_path / "fresh" / "result.json").read_text())
    assert again["rel_l2"] == fresh["rel_l2"] and again["weights"] == fresh["weights"]
    # an unfinished run is discarded too; somebody else's files never are
    (tmp_path / "r" / "result.json").unlink()
    assert cli([*args, "--overwrite"]) == 0
    assert json.loads((tmp_path / "r" / "result.json").read_text())["epochs"] == 4
    (tmp_path / "theirs").mkdir()
    (tmp_path / "theirs" / "config.json").write_text('{"precious": true}')
    assert cli([*args[:-1], str(tmp_path / "theirs"), "--overwrite"]) == 2
    assert "another command's run or other files" in capsys.readouterr().err
    assert (tmp_path / "theirs" / "config.json").read_text() == '{"precious": true}'


def test_config_file_sets_every_key_and_names_a_wrong_type(tmp_path, capsys):
    cfg = tmp_path / "pinn.toml"
    cfg.write_text('problem = "poisson"\nk = 2\nweighting = "max-avg"\nepochs = 4\n'
                   "width = 6\ndepth = 2\ncollocation = 40\nedge_points = 6\nlr = 1\n")
    out = tmp_path / "r"
    assert cli(["pinn", "--config", str(cfg), "--lr", "0.002", "--no-progress",
                "--out", str(out)]) == 0
    config = json.loads((out / "config.json").read_text())
    assert (config["k"], config["weighting"], config["epochs"], config["lr"]) == (
        2, "max-avg", 4, 0.002)
    for toml, message in (
            ('k = "3"', "config key 'k' in {cfg}: '3' (str) is not an integer; accepted: an "
             "integer in [1, 6]"),
            ("edge_points = 1e9", "config key 'edge_points' in {cfg}: 1000000000.0 (float) is "
             "not an integer; accepted: an integer in [1, 100000]"),
            ("alpha = true", "config key 'alpha' in {cfg}: True (bool) is not a finite number"),
            ("colocation = 10", "unknown config option 'colocation' (did you mean "
             "'collocation'?)")):
        cfg.write_text(toml + "\n")
        assert cli(["pinn", "poisson", "--config", str(cfg), "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message.format(cfg=cfg) in err[0]


def test_cli_runs_and_refuses_a_finished_run(tmp_path, capsys):
    args = ["pinn", "poisson", "--k", "1", "--weighting", "analytic", "--epochs", "4",
            *TINY_ARGS, "--out", str(tmp_path)]
    assert cli(args) == 0
    assert "relative L2" in capsys.readouterr().out
    assert json.loads((tmp_path / "config.json").read_text())["weighting"] == "fixed"
    assert cli(args) == 2
    assert "finished run" in capsys.readouterr().err


def test_tiny_study_end_to_end(tmp_path):
    import adjointsim.train.studies.pinn as study
    from adjointsim.runner import run

    rows = run("pinn-poisson", tmp_path, "tiny", None, cluster="none", progress=False)
    assert {(r["k"], r["weighting"], r["seed"]) for r in rows} == {
        (k, w, 0) for k in (1, 2) for w in ("uniform", "inverse-dirichlet")}
    assert all(math.isfinite(r["rel_l2"]) for r in rows)
    text = (tmp_path / "table.txt").read_text()
    assert "inverse-dirichlet" in text and "ID at or below uniform" in text
    assert (tmp_path / "pinn-poisson.png").stat().st_size > 1000
    cell = study.cells("tiny", None)[0]
    assert study.run_cell(cell, tmp_path / cell["id"])["rel_l2"] == rows[0]["rel_l2"]


def test_sobolev_targets_are_the_derivatives_of_f():
    p = make_problem(PinnConfig(problem="sobolev", collocation=16))
    assert p.cfg.width == 64 and sum(m.numel() for m in p.model().parameters()) == 16897
    a, a2, lx, ly, phi, phi2 = (torch.as_tensor(v, dtype=torch.float64)
                               for v in (p.a, p.a2, p.l, p.l2, p.phi, p.phi2))
    x = (torch.rand(6, 2, dtype=torch.float64) * 2 * math.pi).requires_grad_(True)

    def f(x):
        return (a * a2 * torch.cos(lx * x[:, :1] + phi) * torch.sin(ly * x[:, 1:] + phi2)).sum(1)

    torch.testing.assert_close(p.target(0, x.detach())[:, 0], f(x).detach())
    cur = [f(x), f(x)]  # carried along x and along y
    for n in range(1, 5):
        cur = [torch.autograd.grad(c.sum(), x, create_graph=True)[0][:, i] for i, c in
               enumerate(cur)]
        torch.testing.assert_close(p.target(n, x.detach())[:, 0], (cur[0] + cur[1]).detach(),
                                   rtol=1e-10, atol=1e-8)


def test_sobolev_run_balances_five_terms(tmp_path):
    cfg = PinnConfig(problem="sobolev", weighting="id", epochs=6, width=6, depth=2,
                     collocation=30, log_every=3)
    result = train_run(cfg, tmp_path, progress=False, plot=False)
    assert set(result["weights"]) == {"f", "d1", "d2", "d3", "d4"}
    assert result["weights"]["d4"] == 1.0 and result["weights"]["f"] != 1.0
    assert "weight/d3" in read_history(tmp_path / "history.csv")[0]
    with pytest.raises(ValueError, match="no analytic weights"):
        make_problem(PinnConfig(problem="sobolev", weighting="analytic"))
    with pytest.raises(ValueError, match="route 'taylor' only"):
        make_problem(PinnConfig(problem="sobolev", route="autograd"))


@pytest.mark.slow
def test_quick_study_ranks_inverse_dirichlet_below_uniform(tmp_path):
    import adjointsim.train.studies.pinn  # noqa: F401
    from adjointsim.runner import run

    rows = run("pinn-poisson", tmp_path, "quick", None, cluster="none", progress=False)
    err = {(r["k"], r["weighting"]): r["rel_l2"] for r in rows}
    for k in (2, 4, 6):
        assert err[(k, "inverse-dirichlet")] < err[(k, "uniform")]


# ----------------------------------------------------------------------------- KS inverse
KS_TINY = {"problem": "ks-inverse", "width": 6, "depth": 2, "collocation": 30,
           "edge_points": 5, "log_every": 3}


def test_ks_inverse_data_are_the_solver_trajectory_and_phases_split_the_epochs():
    import numpy as np

    from adjointsim import registry

    p = make_problem(PinnConfig(**KS_TINY, epochs=9))
    scene = registry.get("ks1d-etdrk4")(n=64, length=22.0, dt=0.1)
    traj = scene.rollout(scene.random_state(np.random.default_rng(1234)), 100, keep="all")
    u = p.u_grid.reshape(p.shape)  # (x, t)
    torch.testing.assert_close(u[:, 37].double(), torch.from_numpy(traj[37, 0, 0]),
                               rtol=1e-6, atol=1e-6)
    assert p.grid[64 * 101 - 1].tolist() == pytest.approx([22 * 63 / 64, 10.0])
    assert [p.active(e) for e in (0, 2, 3, 5, 6, 8)] == [
        ("data",), ("data",), ("data", "periodic"), ("data", "periodic"),
        ("data", "periodic", "res"), ("data", "periodic", "res")]
    assert PinnConfig(problem="ks-inverse").epochs == 0
    cfg = PinnConfig(problem="ks-inverse")
    cfg.validate()
    assert cfg.epochs == 6000 and cfg.width == 50


def test_ks_inverse_residual_and_periodicity_equal_nested_autograd():
    p = make_problem(PinnConfig(**KS_TINY, epochs=9))
    model = p.model().double()
    with torch.no_grad():
        model.alpha.fill_(0.7)
        model.beta.fill_(1.3)
    for name in ("x_col", "left", "right"):
        setattr(p, name, getattr(p, name).double())
    got = p.losses(model, terms=("periodic", "res"))
    assert set(got) == {"periodic", "res"}  # data was not asked for: not computed

    def derivatives(x, axis, order):
        x = x.detach().requires_grad_(True)
        out = [model(x)[:, 0]]
        for _ in range(order):
            out.append(torch.autograd.grad(out[-1].sum(), x, create_graph=True)[0][:, axis])
        return out

    u, ux, uxx, _, uxxxx = derivatives(p.x_col, 0, 4)
    ut = derivatives(p.x_col, 1, 1)[1]
    res = ut + u * ux + 0.7 * uxx + 1.3 * uxxxx
    torch.testing.assert_close(got["res"], (res**2).mean(), rtol=1e-10, atol=1e-12)
    per = sum(((a - b) ** 2).mean() for a, b in zip(derivatives(p.left, 0, 3),
                                                    derivatives(p.right, 0, 3)))
    torch.testing.assert_close(got["periodic"], per, rtol=1e-10, atol=1e-12)


def test_ks_inverse_run_adds_terms_in_phases_and_learns_coefficients_last(tmp_path):
    result = train_run(PinnConfig(**KS_TINY, epochs=9, weighting="id"), tmp_path / "run",
                       progress=False)
    phases = result["phases"]
    assert [p["epoch"] for p in phases] == [3, 6, 9]
    assert [p["active"] for p in phases] == [["data"], ["data", "periodic"],
                                             ["data", "periodic", "res"]]
    # α and β enter the residual only: untouched until it joins
    for name in ("alpha", "beta"):
        assert phases[0][name] == phases[1][name] == 0.5 != phases[2][name], name
    assert set(result["coefficients"]) == {"alpha", "beta"}
    refreshes = read_history(tmp_path / "run" / "weights.csv")
    assert [r["step"] for r in refreshes] == [0, 0, 5]
    assert refreshes[1]["periodic"] == 1.0 and refreshes[1]["spread/periodic"] == ""
    # at step 5 (phase 2) the periodic term is balanced against data, the reference
    assert refreshes[2]["data"] == refreshes[2]["res"] == 1.0 != refreshes[2]["periodic"]
    hist = read_history(tmp_path / "run" / "history.csv")
    assert {"alpha", "beta", "loss/res"} <= set(hist[0])
    assert (tmp_path / "run" / "history.png").exists()


def test_ks_inverse_bad_options_are_named():
    with pytest.raises(ValueError, match="ks-inverse problem has no analytic weights"):
        make_problem(PinnConfig(problem="ks-inverse", weighting="fixed"))
    with pytest.raises(ValueError, match="route 'taylor' only"):
        make_problem(PinnConfig(problem="ks-inverse", route="autograd"))


def test_tiny_ks_inverse_study_tables_the_data_loss_by_phase(tmp_path):
    import adjointsim.train.studies.pinn  # noqa: F401 - registers the study
    from adjointsim.runner import run

    rows = run("pinn-ks-inverse", tmp_path, "tiny", None, cluster="none", progress=False)
    assert {(r["weighting"], r["seed"]) for r in rows} == {("uniform", 0),
                                                         ("inverse-dirichlet", 0)}
    assert all(len(r["data_by_phase"]) == 3 and 0 < r["beta"] for r in rows)
    text = (tmp_path / "table.txt").read_text()
    assert "end / after 1" in text and "inverse-dirichlet" in text
    assert (tmp_path / "pinn-ks-inverse.png").stat().st_size > 1000
