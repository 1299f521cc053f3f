"""Gradient-flow modes (R/M/S/N/C, clipping), the closed loop, the control CLI and the study."""

import json
import os
import re
import signal

import numpy as np
import pytest
import torch

import adjointsim
import adjointsim.run
from adjointsim.cli import main as cli
from adjointsim.run import read_history
from adjointsim.train import checkpoint, control
from adjointsim.train.checkpoint import load_checkpoint
from adjointsim.train.model import NeuralStepper
from adjointsim.train.trainer import TrainConfig
from adjointsim.train.unroll import GradientFlow, canonical, clip_update, unrolled_loss


def _setup(task="cartpole", level=None, steps=12, batch=4, seed=0):
    """A short float64 loop with a random (not zero-initialised) controller."""
    t = control.get_task(task, level)
    t.steps = steps
    torch.manual_seed(seed)
    net = t.net().double()
    for m in net.modules():
        if isinstance(m, torch.nn.Linear | torch.nn.Conv1d):
            m.reset_parameters()
    x0 = torch.from_numpy(t.initial_states(np.random.default_rng(seed), batch))
    return t, net, x0


def _grads(task, net, x0, mode, gated=False):
    flow = GradientFlow(mode, gated=gated)
    loss = control.closed_loop(task, net, x0, flow)[0]
    return flow.backward(loss, list(net.parameters()))


@pytest.mark.parametrize("task", ["cartpole", "guidance"])
def test_combined_equals_two_pass_reference_and_the_sign_rule(task):
    t, net, x0 = _setup(task)
    g_m = _grads(t, net, x0, "M").grads  # two separate forward + backward passes
    g_r = _grads(t, net, x0, "R").grads
    c = _grads(t, net, x0, "C")  # one forward and one backward pass over a doubled batch
    gated = _grads(t, net, x0, "C", gated=True)  # one forward, two backward passes
    kept = masked = 0
    for a, b, got, gm, gr, ref in zip(g_m, g_r, c.grads, c.g_m, c.g_r, gated.grads):
        torch.testing.assert_close(gm, a, rtol=1e-10, atol=1e-14)
        torch.testing.assert_close(gr, b, rtol=1e-10, atol=1e-14)
        expected = torch.where(torch.sign(a) == torch.sign(b), a, torch.zeros_like(a))
        torch.testing.assert_close(got, expected, rtol=1e-10, atol=1e-14)
        torch.testing.assert_close(ref, expected, rtol=1e-10, atol=1e-14)
        agree = torch.sign(a) == torch.sign(b)
        kept += int((agree & (a != 0)).sum())
        masked += int((~agree).sum())
    assert kept > 0 and masked > 0  # the rule both keeps and drops components here
    assert not all(torch.allclose(a, b) for a, b in zip(g_m, g_r))  # M really differs from R


@pytest.mark.parametrize("mode", ["R", "M"])
def test_diagnosis_keeps_the_modes_own_update(mode):
    t, net, x0 = _setup("guidance", steps=6)
    plain = _grads(t, net, x0, mode)
    flow = GradientFlow(mode, diagnose=True)
    diag = flow.backward(control.closed_loop(t, net, x0, flow)[0], list(net.parameters()))
    for a, b in zip(plain.grads, diag.grads):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-14)
    assert -1 <= diag.cosine() <= 1 and plain.g_m is None


def test_modes_stop_the_paths_they_name():
    """S: a final-step loss reaches only the last control; M and R reach every control;
    N cuts the physics chain so the state's cotangent only comes through the network."""
    t, net, x0 = _setup(steps=6)

    def control_grads(mode):
        flow = GradientFlow(mode)
        x, cs = x0, []
        for _ in range(t.steps):
            c = t.control(net(flow.net(x)))
            c.retain_grad()
            cs.append(c)
            x = adjointsim_step(t, flow.phys(x), c)
        loss = (1 - torch.cos(x[:, 0, 1:])).mean()
        loss.backward()
        return [0.0 if c.grad is None else float(c.grad.abs().sum()) for c in cs]

    s = control_grads("S")
    assert all(v == 0 for v in s[:-1]) and s[-1] > 0
    for mode in ("R", "M", "N"):
        assert all(v > 0 for v in control_grads(mode)), mode
    # M and R differ only by the network-input path: equal when that path carries nothing
    r, m = control_grads("R"), control_grads("M")
    assert r[-1] == pytest.approx(m[-1], rel=1e-12) and r[0] != pytest.approx(m[0], rel=1e-6)
    # N and R differ only by the physics path, which the last control's gradient does not take
    n = control_grads("N")
    assert r[-1] == pytest.approx(n[-1], rel=1e-12) and r[0] != pytest.approx(n[0], rel=1e-6)


def adjointsim_step(task, x, c):
    from adjointsim.train import bridge

    return bridge.step(task.solver, x, c)


def test_regular_mode_is_the_true_gradient():
    t, net, x0 = _setup(steps=8)
    g = _grads(t, net, x0, "R").grads
    w = list(net.parameters())[0]
    d = torch.randn_like(w)
    eps = 1e-6
    with torch.no_grad():
        w += eps * d
        plus = control.closed_loop(t, net, x0)[0]
        w -= 2 * eps * d
        minus = control.closed_loop(t, net, x0)[0]
        w += eps * d
    assert float((g[0] * d).sum()) == pytest.approx(float(plus - minus) / (2 * eps), rel=1e-6)


def test_clipping():
    g = [torch.tensor([3.0, -0.5]), torch.tensor([[-2.0]])]
    v = clip_update(g, "value")
    assert v[0].tolist() == [1.0, -0.5] and v[1].tolist() == [[-1.0]]
    n = clip_update(g, "norm")
    total = sum(float((a * a).sum()) for a in n) ** 0.5
    assert total == pytest.approx(1.0)
    assert float(n[0][0] / n[1][0, 0]) == pytest.approx(-1.5)  # direction kept
    small = [torch.tensor([0.1])]
    assert clip_update(small, "norm")[0].item() == pytest.approx(0.1)


def test_mode_names_and_bad_options():
    assert [canonical(m) for m in ("WIG", "NOG", "C")] == ["R", "S", "C"]
    with pytest.raises(ValueError, match="unknown gradient flow 'BPTT'; choose from WIG, NOG, R"):
        GradientFlow("BPTT")
    with pytest.raises(ValueError, match="ONE is a schedule"):
        GradientFlow("ONE")
    with pytest.raises(ValueError, match="unknown clip 'max'; choose from none, value, norm"):
        GradientFlow("C", clip="max")
    for mode in ("M", "C", "S", "R", "N"):  # the unrolled training takes every mode
        assert TrainConfig.load(mode=mode).mode == mode


@pytest.mark.parametrize("setup,form", [("correction", "parallel"), ("correction", "sequential"),
                                        ("prediction", "parallel")])
def test_unrolled_training_combined_mode_equals_two_passes(setup, form):
    """The same switch serves List et al.'s unrolled training."""
    torch.manual_seed(0)
    net = torch.nn.Conv1d(2, 1, 3, padding=1, padding_mode="circular").double()
    solver = adjointsim.get("diffusion1d-ftcs")(n=16)
    model = NeuralStepper(net, setup, lambda p: solver, form)
    frames = torch.randn(3, 4, 1, 16, dtype=torch.float64)
    params, cond = torch.zeros(3, dtype=torch.float64), torch.ones(3, dtype=torch.float64)
    ps = list(model.parameters())

    def update(mode, gated=False):
        flow = GradientFlow(mode, gated=gated)
        return flow.backward(unrolled_loss(model, frames, params, cond, flow), ps)

    m, r, c = update("M").grads, update("WIG").grads, update("C").grads
    for a, b, got, ref in zip(m, r, c, update("C", gated=True).grads):
        expected = torch.where(torch.sign(a) == torch.sign(b), a, 0 * a)
        torch.testing.assert_close(got, expected)
        torch.testing.assert_close(ref, expected)
    assert not torch.allclose(m[0], r[0])
    if setup == "prediction":  # no physics path: M is S
        torch.testing.assert_close(m[0], update("S").grads[0])
    nog, s = update("NOG").grads, update("S").grads
    for a, b in zip(nog, s):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


@pytest.mark.parametrize("task,level", [("cartpole", 4), ("guidance", 0.001), ("quantum", 5)])
def test_tasks_shapes_and_parameter_counts(task, level):
    t = control.get_task(task, level)
    net = t.net().double()
    n = sum(p.numel() for p in net.parameters())
    assert n == {"cartpole": 11301, "guidance": 13004, "quantum": 11761}[task]
    x0 = torch.from_numpy(t.initial_states(np.random.default_rng(0), 3))
    out = t.control(net(x0))
    assert out.shape == (3, *t.solver.control_shape)
    assert float(out.detach().abs().max()) == 0.0  # zero-initialised last layer: c = 0 at the start


def test_quantum_initial_states_are_normalised_and_the_loss_sees_the_target():
    t = control.get_task("quantum", 3)
    x = t.initial_states(np.random.default_rng(1), 5)
    np.testing.assert_allclose(t.solver.h * (x**2).sum(axis=(1, 2)), 1.0, rtol=1e-12)
    target = np.stack([t.eigen[2], 0 * t.eigen[2]])[None]
    assert float(t.step_loss(torch.from_numpy(target), None, 0)) == pytest.approx(0.0, abs=1e-12)
    assert float(t.step_loss(torch.from_numpy(x), None, 0)) == pytest.approx(1.0, abs=1e-12)


def test_bad_inputs_name_the_problem():
    t, net, x0 = _setup(steps=2)
    wrong = torch.nn.Sequential(torch.nn.Flatten(), torch.nn.Linear(4, 2)).double()
    with pytest.raises(ValueError, match=r"output has shape \(4, 2\); expected \(batch, 1\)"):
        control.closed_loop(t, wrong, x0)
    nan_net = torch.nn.Sequential(torch.nn.Flatten(), torch.nn.Linear(4, 1)).double()
    with torch.no_grad():
        nan_net[1].bias.fill_(float("nan"))
    with pytest.raises(ValueError, match="non-finite"):
        control.closed_loop(t, nan_net, x0)
    bad = x0.clone()
    bad[1, 0, 0] = float("inf")
    with pytest.raises(ValueError, match="non-finite"):
        control.closed_loop(t, net, bad)
    with pytest.raises(ValueError, match=r"config key 'level': 5 is not one of 1, 2, 3, 4 \(the "
                       r"cartpole task's poles\)"):
        control.ControlConfig.load(level=5)
    with pytest.raises(ValueError, match="config key 'level': 2 is not one of 3, 4, 5"):
        control.ControlConfig.load(task="quantum", level=2)
    with pytest.raises(ValueError, match="'level': 0.5 is not one of 1.0, 0.1, 0.01"):
        control.ControlConfig.load(task="guidance", level=0.5)
    with pytest.raises(ValueError, match="'task': 'pendulum' is not one of cartpole, guidance"):
        control.ControlConfig.load(task="pendulum")
    with pytest.raises(ValueError, match="'mode': 'F' is not one of R, M, S, N, C"):
        control.ControlConfig.load(mode="F")
    with pytest.raises(ValueError, match=r"'epochs': 'ten' \(str\) is not an integer"):
        control.ControlConfig.load(epochs="ten")
    with pytest.raises(ValueError, match="'lr': inf is not a finite number > 0"):
        control.ControlConfig.load(lr=float("inf"))
    with pytest.raises(ValueError, match=r"'seed': -1 is not an integer in \[0, 9223372036"):
        control.ControlConfig.load(seed=-1)
    with pytest.raises(ValueError, match=r"'batch': 9 exceeds train \(8\)"):
        control.ControlConfig.load(train=8, batch=9)
    with pytest.raises(ValueError, match=r"10000000 × 256 = 2.56e\+09 training rollouts"):
        control.ControlConfig.load(epochs=10**7)


def test_toml_config(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('task = "guidance"\nlevel = 0.01\nmode = "M"\n[scene]\ndt = 0.05\n')
    cfg = control.ControlConfig.load(path, seed=3, scene={"evaders": 3})
    assert (cfg.task, cfg.level, cfg.mode, cfg.seed) == ("guidance", 0.01, "M", 3)
    assert cfg.scene == {"drivers": 2, "evaders": 3, "dt": 0.05}  # the task's, the file's, ours
    assert control.ControlConfig.load(task="cartpole", level=2.0).level == 2  # as the task spells
    path.write_text('task = "quantum"\n')
    assert control.ControlConfig.load(path).level == 3  # the easiest
    path.write_text('epochs = "many"\n')
    with pytest.raises(ValueError, match=r"config key 'epochs' in .*c.toml: 'many' \(str\) is "
                       "not an integer"):
        control.ControlConfig.load(path)
    path.write_text("epochs = [\n")
    with pytest.raises(ValueError, match="is not valid TOML"):
        control.ControlConfig.load(path)


def test_cli_trains_resumes_and_refuses_to_overwrite(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["control", "cartpole", "--epochs", "1", "--train", "4", "--test", "4", "--batch",
            "4", "--out", str(out), "--no-progress", "--dtype", "float64"]
    assert cli(args) == 0
    rows = read_history(out / "history.csv")
    assert len(rows) == 1 and list(rows[0]) == list(control.HISTORY_KEYS)
    assert (out / "test_loss.png").exists() and (out / "rollout.png").exists()
    assert cli(args) == 2
    assert "holds a finished run" in capsys.readouterr().err
    # more epochs with --resume continue the same run
    assert cli([*args[:3], "2", *args[4:], "--resume"]) == 0
    assert len(read_history(out / "history.csv")) == 2
    # fewer epochs than the run holds: refused, and the finished run's files stay as they were
    before = (out / "result.json").read_text()
    assert cli([*args[:3], "1", *args[4:], "--resume"]) == 2
    assert "holds a run of epochs = 2; pass as much or more" in capsys.readouterr().err
    assert (out / "result.json").read_text() == before
    # the same run under another spelling of its directory or thread count still resumes
    assert cli([*args[:3], "3", *args[4:-4], str(out) + "/", *args[-3:], "--threads", "2",
                "--resume"]) == 0
    assert len(read_history(out / "history.csv")) == 3
    assert cli([*args[:3], "3", *args[4:], "--lr", "0.01", "--resume"]) == 2
    assert "differs in lr" in capsys.readouterr().err
    # stopped after the last checkpoint but before result.json: --resume writes it
    (out / "result.json").unlink()
    assert cli([*args[:3], "3", *args[4:], "--resume"]) == 0
    assert json.loads((out / "result.json").read_text())["epochs"] == 3
    assert cli(["control", "guidance", "--poles", "2"]) == 2
    assert "'poles': applies to the cartpole task, not guidance" in capsys.readouterr().err
    err = _one_line(capsys, "control", "cartpole", "--mode", "X", "--out", tmp_path / "x")
    assert "argument --mode: invalid choice: 'X'" in err


def test_cli_keeps_other_files_and_tells_how_to_continue(tmp_path, capsys, monkeypatch):
    args = ["control", "cartpole", "--epochs", "1", "--train", "4", "--test", "4", "--batch",
            "4", "--no-progress", "--dtype", "float64", "--out"]
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "config.json").write_text('{"owner": "someone else"}')
    assert cli([*args, str(theirs)]) == 2
    assert "holds another command's run or other files" in capsys.readouterr().err
    assert (theirs / "config.json").read_text() == '{"owner": "someone else"}'
    done = tmp_path / "done"
    assert cli([*args, str(done)]) == 0
    (done / "checkpoint.pt").unlink()
    assert cli([*args[:3], "2", *args[4:], str(done), "--resume"]) == 2
    assert "finished run without its checkpoint" in capsys.readouterr().err
    (tmp_path / "afile").write_text("")
    assert cli([*args, str(tmp_path / "afile")]) == 2
    assert "cannot write the run to --out" in capsys.readouterr().err
    real = checkpoint.save_checkpoint

    def stop(*a, **kw):  # Ctrl-C right after the first checkpoint
        real(*a, **kw)
        raise KeyboardInterrupt

    monkeypatch.setattr(checkpoint, "save_checkpoint", stop)
    assert cli([*args, str(tmp_path / "stopped")]) == 130
    assert f"and --resume (--out {tmp_path / 'stopped'})" in capsys.readouterr().err
    monkeypatch.setattr(checkpoint, "save_checkpoint", real)
    assert cli([*args, str(tmp_path / "stopped"), "--resume"]) == 0



SMALL = ["--train", "4", "--test", "4", "--batch", "4", "--no-progress", "--dtype", "float64"]


def _one_line(capsys, *argv):
    assert cli([str(a) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("adjointsim control: ") and err.count("\n") == 1, err
    return err


def _without_seconds(rows):
    return [{k: v for k, v in r.items() if k != "seconds"} for r in rows]


def test_ctrl_c_between_updates_resumes_to_the_uninterrupted_run(tmp_path, monkeypatch):
    """Ctrl-C inside an update is held until the update ends; the checkpoint saved there
    (mid-epoch) resumes to the weights and history of an uninterrupted run."""
    args = ["control", "cartpole", "--epochs", "2", "--train", "12", "--test", "4", "--batch",
            "4", "--no-progress", "--dtype", "float64", "--out"]
    assert cli([*args, str(tmp_path / "a")]) == 0
    real, calls = control.closed_loop, []

    def interrupted(*a, **kw):
        calls.append(1)
        if len(calls) == 7:  # epoch 1: updates 1-3, evaluations 4-5; epoch 2: updates 6-8
            os.kill(os.getpid(), signal.SIGINT)
        return real(*a, **kw)

    monkeypatch.setattr(control, "closed_loop", interrupted)
    assert cli([*args, str(tmp_path / "b")]) == 130
    monkeypatch.setattr(control, "closed_loop", real)
    state = load_checkpoint(tmp_path / "b" / "checkpoint.pt", ("state",))["state"]
    assert (state["epoch"], state["step"], len(state["losses"])) == (1, 2, 2)
    assert cli([*args, str(tmp_path / "b"), "--resume"]) == 0
    a, b = (load_checkpoint(tmp_path / run / "checkpoint.pt", ("state",))["state"]["net"]
            for run in "ab")
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0)
    assert (_without_seconds(read_history(tmp_path / "a" / "history.csv"))
            == _without_seconds(read_history(tmp_path / "b" / "history.csv")))


def test_resume_needs_a_checkpoint_and_overwrite_starts_again(tmp_path, capsys):
    out = tmp_path / "run"
    base = ["control", "cartpole", "--epochs", "1", *SMALL]
    err = _one_line(capsys, *base, "--out", out, "--resume")
    assert "holds no run to continue" in err and not out.exists()
    assert cli([str(a) for a in [*base, "--out", out]]) == 0
    # --overwrite discards the finished run and trains the new configuration from scratch,
    # as in a new directory
    assert cli([str(a) for a in [*base, "--seed", "1", "--out", out, "--overwrite"]]) == 0
    assert cli([str(a) for a in [*base, "--seed", "1", "--out", tmp_path / "new"]]) == 0
    assert json.loads((out / "config.json").read_text())["seed"] == 1
    new = json.loads((tmp_path / "new" / "result.json").read_text())
    assert json.loads((out / "result.json").read_text())["test_loss"] == new["test_loss"]
    assert len(read_history(out / "history.csv")) == 1
    err = _one_line(capsys, *base, "--out", out, "--overwrite", "--resume")  # one or the other
    assert "not allowed with argument" in err
    # somebody else's files are not discarded
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "config.json").write_text('{"owner": "someone else"}')
    err = _one_line(capsys, *base, "--out", theirs, "--overwrite")
    assert "holds another command's run or other files" in err
    assert (theirs / "config.json").read_text() == '{"owner": "someone else"}'


def test_config_file_names_the_wrong_key(tmp_path, capsys):
    path = tmp_path / "c.toml"
    path.write_text('task = "cartpole"\nepochs = "ten"\n')
    err = _one_line(capsys, "control", "cartpole", "--config", path, "--out", tmp_path / "r")
    assert "config key 'epochs'" in err and "'ten' (str) is not an integer" in err
    path.write_text("lr = 0.01\nbatchsize = 4\n")
    err = _one_line(capsys, "control", "cartpole", "--config", path, "--out", tmp_path / "r")
    assert "unknown config option 'batchsize'" in err


def test_help_lists_the_choices(capsys):
    with pytest.raises(SystemExit) as e:
        cli(["control", "--help"])
    assert e.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for shown in ("--mode {R,M,S,N,C}", "--clip {none,value,norm}", "--poles {1,2,3,4}",
                  "--control-weight {1.0,0.1,0.01,0.001}", "--target {3,4,5}", "--level LEVEL",
                  "--scene KEY=VALUE", "--resume", "--overwrite", "--config FILE.toml",
                  "--seed", "--threads", "--no-progress", "inverse-dirichlet", ",id,"):
        assert shown in text, shown
    # every registered task, and its level flag, is offered
    assert "{" + ",".join(control.TASKS.names()) + "}" in text
    for name, cls in control.TASKS.items():
        assert f"--{cls.key.replace('_', '-')} {{" in text and f"{name}: {cls.about}" in text


def test_absurd_sizes_are_refused_before_anything_is_drawn(tmp_path, capsys, monkeypatch):
    def never(*a, **kw):
        raise AssertionError("allocated")

    monkeypatch.setattr(control, "initial_states", never)
    monkeypatch.setattr(control.Task, "initial_states", never)
    out = tmp_path / "big"
    err = _one_line(capsys, "control", "cartpole", "--train", "1000000000", "--out", out)
    assert "'train'" in err and ("GiB of memory" in err or "training rollouts" in err)
    err = _one_line(capsys, "control", "quantum", "--epochs", "1000000", "--out", out)
    assert "1000000 × 256 = 2.56e+08 training rollouts of 128 steps" in err
    monkeypatch.setattr(adjointsim.run, "physical_memory", lambda: 2**30)
    err = _one_line(capsys, "control", "quantum", "--train", "100000", "--out", out)
    assert "need about 1.9 GiB of memory" in err and "this machine's 1.0 GiB" in err
    assert not out.exists()


def test_study_grids():
    from adjointsim.train.studies import stablebptt

    tasks = control.TASKS.names()  # every registered task, the paper's three among them
    quick = stablebptt.cells("quick", None)
    assert len(quick) == len(tasks) * 2 * 4 and len({c["id"] for c in quick}) == len(quick)
    hardest = stablebptt.cells("hardest", None)
    assert {(c["task"], c["level"]) for c in hardest} == {
        (t, control.TASKS.get(t).levels[-1]) for t in tasks} >= {
        ("cartpole", 4), ("guidance", 0.001), ("quantum", 5)}
    assert {c["mode"] for c in hardest} == {"R", "M", "C"} and len(hardest) == len(tasks) * 9
    assert {c["epochs"] for c in hardest if c["task"] == "quantum"} == {20}  # a costly task
    assert {c["epochs"] for c in hardest if c["task"] == "cartpole"} == {60}
    full = stablebptt.cells("full", 1)
    assert len(full) == sum(len(control.TASKS.get(t).levels) for t in tasks) * 4 * 3
    assert {(c["train"], c["test"], c["batch"]) for c in full} == {(256, 256, 8)}


def test_tiny_study_end_to_end(tmp_path):
    from adjointsim import runner
    from adjointsim.train.studies import load_all

    load_all()
    rows = runner.run("stablebptt", tmp_path, "tiny", None, cluster="none", progress=False)
    assert {(r["mode"], r["task"]) for r in rows} == {("R", "cartpole"), ("C", "cartpole")}
    for r in rows:
        assert {"task", "level", "mode", "clip", "seed", "test_loss"} <= set(r)
        assert np.isfinite(r["test_loss"])
    assert (tmp_path / "stablebptt-cartpole.png").exists()
    text = (tmp_path / "table.txt").read_text()
    # the summary: R and C with their ratios to the untrained loss, C against R on 1 seed
    assert re.search(r"cartpole +1 none +\S+ \[\d\.\d{3}\] +\S+ \[\d\.\d{3}\] +[01]/1 +-\n", text)
    json.loads((tmp_path / "rows.json").read_text())


def test_a_diverged_run_says_so_and_claims_no_rollout(tmp_path, capsys):
    out = tmp_path / "run"
    assert cli([str(a) for a in ["control", "cartpole", "--lr", "1e8", "--epochs", "2", *SMALL,
                                 "--out", out, "--json", tmp_path / "r.json"]]) == 1
    said = capsys.readouterr().out
    assert "diverged" in said and "rollout.png" not in said and "test_loss.png" in said
    result = json.loads((out / "result.json").read_text())
    assert result["diverged"] is True and result["test_loss"] is None
    assert not (out / "rollout.png").exists() and (out / "test_loss.png").exists()
    assert json.loads((tmp_path / "r.json").read_text())["diverged"] is True


def test_weighting_alias_and_scene_are_recorded(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["control", "guidance", "--mode", "R", "--weighting", "id", "--control-weight",
            "0.01", "--scene", "dt=0.05", "--epochs", "1", *SMALL, "--out", out]
    assert cli([str(a) for a in args]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["weighting"] == "inverse-dirichlet" and config["level"] == 0.01
    assert config["scene"] == {"drivers": 2, "evaders": 4, "dt": 0.05}
    result = json.loads((out / "result.json").read_text())
    assert set(result["weights"]) == {"tracking", "control"} and result["control_weight"] == 0.01
    # the recorded run resumes under the same spellings: finished, returned as it is
    assert cli([str(a) for a in [*args, "--resume"]]) == 0
    # the solver checks the scene, naming the key; the task's level is not a scene key
    err = _one_line(capsys, "control", "guidance", "--scene", "dt=-1", "--out", tmp_path / "x")
    assert "config key 'scene': guidance: dt must be a finite number > 0, got -1" in err
    err = _one_line(capsys, "control", "cartpole", "--scene", "masses=2", "--out", tmp_path / "x")
    assert "scene key 'masses': cartpole takes dt, gravity, pole_mass" in err
    err = _one_line(capsys, "control", "cartpole", "--scene", "poles=2", "--out", tmp_path / "x")
    assert "'poles' is the cartpole task's level; pass --poles" in err
    err = _one_line(capsys, "control", "cartpole", "--level", "2", "--poles", "3", "--out",
                    tmp_path / "x")
    assert "--level and --poles" in err
    assert not (tmp_path / "x").exists()
