"""Ensembles: K members trained in one process equal their K separate runs."""

import pytest
import torch

from adjointsim.errors import UserError
from adjointsim.run import read_history
from adjointsim.train import control
from adjointsim.train.checkpoint import load_checkpoint
from adjointsim.train.ensemble import Stack, train_ensemble
from adjointsim.train.trainer import TrainConfig, train

CLIPS = ("none", "norm", "value", "none")
LRS = (1e-3, 1e-3, 1e-3, 3e-3)


def _cfg(tmp_path, where, seed, dtype, mode, epochs=1, train=100, batch=2, **kw):
    """50 updates in one epoch: few evaluations and files, so the test stays fast."""
    kw = {"clip": CLIPS[seed], "lr": LRS[seed]} | kw
    return control.ControlConfig(task="cartpole", level=2, mode=mode, seed=seed, epochs=epochs,
                                 train=train, test=4, batch=batch, dtype=dtype,
                                 out=str(tmp_path / where / f"s{seed}"), **kw)


def _max_rel(a: dict, b: dict) -> float:
    return max(float((a[n] - b[n]).abs().max() / b[n].abs().max()) for n in b)


@pytest.mark.parametrize(("dtype", "mode", "tol"), [
    ("float64", "C", 1e-10),
    pytest.param("float32", "R", 1e-4, marks=pytest.mark.slow),
])
def test_members_equal_their_separate_runs(tmp_path, dtype, mode, tol):
    ens = train_ensemble([_cfg(tmp_path, "ens", s, dtype, mode) for s in range(4)],
                         progress=False)
    for s in range(4):
        sep = control.train_controller(_cfg(tmp_path, "sep", s, dtype, mode), progress=False)
        a = load_checkpoint(tmp_path / "ens" / f"s{s}" / "checkpoint.pt", ("state",))["state"]
        b = load_checkpoint(tmp_path / "sep" / f"s{s}" / "checkpoint.pt", ("state",))["state"]
        assert _max_rel(a["net"], b["net"]) <= tol
        moments = {f"{i}{k}": v[k] for i, v in b["optimizer"]["state"].items()
                   for k in ("exp_avg", "exp_avg_sq")}
        assert _max_rel({f"{i}{k}": v[k] for i, v in a["optimizer"]["state"].items()
                         for k in ("exp_avg", "exp_avg_sq")}, moments) <= 10 * tol
        assert a["optimizer"]["state"][0]["step"] == b["optimizer"]["state"][0]["step"] == 50
        assert set(ens[s]) == set(sep) and ens[s]["clip"] == CLIPS[s]
        assert ens[s]["test_loss"] == pytest.approx(sep["test_loss"], rel=tol)
        (x,), (y,) = (read_history(tmp_path / w / f"s{s}" / "history.csv") for w in ("ens", "sep"))
        for key in ("batch_loss", "train_loss", "update_norm", "cos_mr"):
            assert x[key] == pytest.approx(y[key], rel=100 * tol, nan_ok=True)
        for name in ("rollout.png", "test_loss.png", "result.json", "config.json"):
            assert (tmp_path / "ens" / f"s{s}" / name).exists()
    # the members really differ (seed, clip, learning rate), so the check above can fail
    nets = [load_checkpoint(tmp_path / "ens" / f"s{s}" / "checkpoint.pt", ("state",))
            ["state"]["net"] for s in range(4)]
    assert all(_max_rel(nets[0], n) > 1e-3 for n in nets[1:])


def test_a_member_resumes_as_a_separate_run_and_an_ensemble_resumes(tmp_path):
    kw = {"train": 8, "batch": 4, "clip": "none", "lr": 1e-3}
    train_ensemble([_cfg(tmp_path, "ens", s, "float64", "M", epochs=1, **kw) for s in (0, 1)],
                   progress=False)
    # member 0 continues alone, member 1 together with a new member 2
    control.train_controller(_cfg(tmp_path, "ens", 0, "float64", "M", epochs=2, **kw),
                             resume=True, progress=False)
    train_ensemble([_cfg(tmp_path, "ens", s, "float64", "M", epochs=2, **kw) for s in (1, 2)],
                   resume=True, progress=False)
    for s in (0, 1, 2):
        control.train_controller(_cfg(tmp_path, "sep", s, "float64", "M", epochs=2, **kw),
                                 progress=False)
        a, b = (load_checkpoint(tmp_path / w / f"s{s}" / "checkpoint.pt", ("state",))
                for w in ("ens", "sep"))
        assert _max_rel(a["state"]["net"], b["state"]["net"]) <= 1e-10
        assert len(a["history"]) == 2


def test_adam_over_stacked_members_is_one_adam_per_member():
    torch.manual_seed(0)
    nets = [torch.nn.Linear(3, 2).double() for _ in range(3)]
    opts = [torch.optim.Adam(n.parameters(), lr=lr) for n, lr in zip(nets, (1e-2, 1e-3, 1e-2))]
    stack = Stack(nets, (1e-2, 1e-3, 1e-2))
    for step in range(6):
        active = [k for k in range(3) if (k, step % 3) != (1, 2)]  # member 1 skips some steps
        grads = [[torch.randn_like(p) for p in n.parameters()] for n in nets]
        for k in active:
            for p, g in zip(nets[k].parameters(), grads[k]):
                p.grad = g
            opts[k].step()
        stack.adam([torch.stack([grads[k][i] for k in active]) for i in range(2)], active)
    for k, net in enumerate(nets):
        for i, p in enumerate(net.parameters()):
            torch.testing.assert_close(stack.tensors[i][k], p.detach(), rtol=1e-13, atol=0)
    assert stack.steps == [6, 4, 6]


def test_members_must_share_everything_but_seed_clip_and_lr(tmp_path):
    cfgs = [_cfg(tmp_path, "a", 0, "float64", "R"), _cfg(tmp_path, "b", 1, "float64", "C")]
    with pytest.raises(UserError, match="differs .* in mode"):
        train_ensemble(cfgs, progress=False)
    same = [_cfg(tmp_path, "a", 0, "float64", "R"), _cfg(tmp_path, "a", 1, "float64", "R")]
    same[1].out = same[0].out
    with pytest.raises(UserError, match="run directories of their own"):
        train_ensemble(same, progress=False)


def test_seeds_ctrl_c_says_where_and_resume_takes_added_or_deleted_members(tmp_path, capsys,
                                                                            monkeypatch):
    """Ctrl-C names the ensemble's --out (the members' checkpoints are in its seedN folders);
    --resume continues the members that hold a run and starts a member added, or one whose
    folder was deleted, beside them: neither spelling of the command refuses it."""
    import shutil

    from adjointsim.cli import main
    from adjointsim.train import checkpoint

    out = tmp_path / "runs"
    args = ["control", "cartpole", "--mode", "R", "--epochs", "1", "--train", "4", "--test",
            "4", "--batch", "4", "--dtype", "float64", "--no-progress", "--out", str(out),
            "--seeds"]
    real = checkpoint.save_checkpoint

    def stop(*a, **kw):  # Ctrl-C right after the members' first checkpoints
        real(*a, **kw)
        if str(a[1]).startswith(str(out / "seed1")):
            raise KeyboardInterrupt

    monkeypatch.setattr(checkpoint, "save_checkpoint", stop)
    assert main([*args, "0", "1"]) == 130
    assert f"continue with the same command and --resume (--out {out})" in \
        capsys.readouterr().err
    monkeypatch.setattr(checkpoint, "save_checkpoint", real)
    assert main([*args, "0", "1", "--resume"]) == 0
    shutil.rmtree(out / "seed0")
    assert main([*args, "0", "1", "2", "--resume"]) == 0
    for s in (0, 1, 2):
        assert len(read_history(out / f"seed{s}" / "history.csv")) == 1
    assert main([*args, "0", "1", "2"]) == 2  # all finished: refused without --resume
    assert "holds a finished run" in capsys.readouterr().err
    assert main([*args, "7", "8", "--resume"]) == 2
    assert "no seed in" in capsys.readouterr().err


# ----------------------------------------------------------------------------- neural steppers
def _stepper(tiny, tmp_path, where, seed, mode, setup="correction", **kw):
    """A tiny net over a few dozen updates (ONE: its batch × m, so fewer)."""
    kw = {"lr": 3e-3 if seed == 2 else 1e-3, "epochs": 3.0, "stride": 8} | kw
    return TrainConfig(data=str(tiny), out=str(tmp_path / where / f"s{seed}"), setup=setup,
                       mode=mode, seed=seed, width=4, blocks=1, unroll=2, batch=2,
                       dtype="float64", lr_decay_every=10, checkpoint_every=1000, **kw)


def _stepper_checkpoints(tmp_path, where, seed):
    ckpt = load_checkpoint(tmp_path / where / f"s{seed}" / "checkpoint.pt", ("state", "history"))
    return ckpt["state"]["model"], ckpt


@pytest.mark.parametrize(("mode", "setup", "kw"), [
    ("WIG", "correction", {}),
    ("NOG", "correction", {"rollback": 1.01, "lr": 0.05}),
    ("ONE", "correction", {}),
    ("C", "prediction", {"spike_factor": 1.2}),
])
def test_stepper_members_equal_their_separate_runs(tiny, tmp_path, monkeypatch, mode, setup,
                                                   kw):
    from adjointsim.train import trainer

    monkeypatch.setattr(trainer, "ROLLBACK_WINDOW", 4)  # the guard acts within the run
    seeds, states = (0, 1, 2), []
    models = train_ensemble([_stepper(tiny, tmp_path, "ens", s, mode, setup, **kw)
                             for s in seeds], progress=False)
    weights = []
    for s, model in zip(seeds, models):
        train(_stepper(tiny, tmp_path, "sep", s, mode, setup, **kw), progress=False)
        a, ens = _stepper_checkpoints(tmp_path, "ens", s)
        b, sep = _stepper_checkpoints(tmp_path, "sep", s)
        assert _max_rel(a, b) <= 1e-10
        assert _max_rel(dict(model.state_dict()), b) <= 1e-10
        ens_at, sep_at = ens["state"]["progress"], sep["state"]["progress"]
        assert ens_at["total"] == sep_at["total"] >= 20
        for key in ("skipped", "rollbacks", "stage", "lr_scale"):
            assert ens_at[key] == sep_at[key]
        assert ([h["loss"] for h in ens["history"]]
                == pytest.approx([h["loss"] for h in sep["history"]], rel=1e-10, nan_ok=True))
        assert [h["skipped"] for h in ens["history"]] == [h["skipped"] for h in sep["history"]]
        for name in ("history.csv", "training.png", "config.json", "result.json"):
            assert (tmp_path / "ens" / f"s{s}" / name).exists()
        weights.append(a)
        states.append(ens_at)
    # the members really differ, and the guards acted (rolled back twice to one snapshot, or
    # skipped spikes of some members only), so the checks above can fail
    assert all(_max_rel(weights[0], w) > 1e-3 for w in weights[1:])
    if "rollback" in kw:
        assert max(s["rollbacks"] for s in states) >= 2
    if "spike_factor" in kw:
        assert 0 < sum(s["skipped"] > 0 for s in states) < len(states)


def test_a_stopped_stepper_ensemble_resumes_to_the_uninterrupted_one(tiny, tmp_path):
    """Stopped by max_iterations (saved there, not at a periodic checkpoint), then resumed:
    every member ends with the history and weights of the uninterrupted ensemble, to the bit."""
    train_ensemble([_stepper(tiny, tmp_path, "a", s, "WIG") for s in (0, 2)], progress=False)
    cut = [_stepper(tiny, tmp_path, "b", s, "WIG", max_iterations=7) for s in (0, 2)]
    assert train_ensemble(cut, progress=False)
    assert not any((tmp_path / "b" / f"s{s}" / "result.json").exists() for s in (0, 2))
    train_ensemble([_stepper(tiny, tmp_path, "b", s, "WIG") for s in (0, 2)], resume=True,
                   progress=False)
    for s in (0, 2):
        (wa, a), (wb, b) = (_stepper_checkpoints(tmp_path, w, s) for w in ("a", "b"))
        assert a["history"] == b["history"] and len(a["history"]) >= 20
        assert all(torch.equal(wa[k], wb[k]) for k in wa)


def test_train_seeds_writes_one_run_per_seed_equal_to_the_ensemble(tiny, tmp_path, capsys):
    import json

    from adjointsim.cli import main

    flags = ["--data", str(tiny), "--width", "4", "--blocks", "1", "--unroll", "2", "--batch",
             "2", "--epochs", "1", "--stride", "8", "--dtype", "float64", "--no-progress"]
    out, rows = tmp_path / "runs", tmp_path / "rows.json"
    assert main(["train", *flags, "--out", str(out), "--seeds", "0", "2", "--json",
                 str(rows)]) == 0
    assert [(r["seed"], r["out"]) for r in json.loads(rows.read_text())] == [
        (0, str(out / "seed0")), (2, str(out / "seed2"))]
    train(TrainConfig(data=str(tiny), out=str(tmp_path / "sep"), seed=2, width=4, blocks=1,
                      unroll=2, batch=2, epochs=1.0, stride=8, dtype="float64"), progress=False)
    a, b = (load_checkpoint(d / "checkpoint.pt", ("state",))["state"]["model"]
            for d in (out / "seed2", tmp_path / "sep"))
    assert _max_rel(a, b) <= 1e-10
    for command in (["train", *flags], ["control", "cartpole"]):
        assert main([*command, "--out", str(tmp_path / "x"), "--seeds", "0", "1",
                     "--seed", "1"]) == 2
        assert "--seed and --seeds: pass one" in capsys.readouterr().err


def _resnet(kernel, dilations):
    from adjointsim.nets.resnet import ResNet

    return ResNet(2, 1, 1, width=5, blocks=3, kernel=kernel, dilations=dilations)


def _strided():
    """The quantum controller's kind: zero-padded strided convolutions, then a linear layer."""
    return torch.nn.Sequential(
        torch.nn.Conv1d(2, 6, 3, stride=2, padding=1), torch.nn.Tanh(),
        torch.nn.Conv1d(6, 4, 5, stride=3, padding=2), torch.nn.Tanh(),
        torch.nn.Flatten(), torch.nn.Linear(4 * 2, 3))


@pytest.mark.parametrize(("make", "blocks_of_rows"), [
    (lambda: _resnet(3, None), 1), (lambda: _resnet(5, (1, 2, 4)), 2), (_strided, 1),
    (_strided, 2)])
def test_batched_convolutions_equal_the_vmap_route(make, blocks_of_rows):
    """1D convolutions as batched matrix products (a circular ResNet with dilated blocks and
    wider kernels; zero-padded strided convolutions): the same outputs and gradients as each
    member's own network (the vmap route), for inputs in one or several blocks of members ×
    rows (C's doubled batch)."""
    torch.manual_seed(0)
    nets = [make().double() for _ in range(3)]
    batched, plain = Stack(nets, (1e-3,) * 3), Stack(nets, (1e-3,) * 3, batched=False)
    assert batched.plan is not None and plain.plan is None
    assert {op[0] for op in batched.plan} & {"resnet", "conv"}
    rows = 4
    x = torch.randn(blocks_of_rows * 3 * rows, 2, 11, dtype=torch.float64)
    outs, grads = [], []
    for stack in (batched, plain):
        leaves = stack.leaves()
        y = stack.net(leaves, rows)(x)
        outs.append(y)
        grads.append(torch.autograd.grad((y * torch.cos(y)).sum(), leaves))
    torch.testing.assert_close(outs[0], outs[1], rtol=1e-13, atol=1e-13)
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    # each member's rows are its own network's output
    member = nets[1](x.reshape(blocks_of_rows, 3, rows, 2, 11)[:, 1].reshape(-1, 2, 11))
    shape = outs[0].shape[1:]
    torch.testing.assert_close(
        outs[0].reshape(blocks_of_rows, 3, rows, *shape)[:, 1].reshape(-1, *shape), member)


def test_networks_the_batched_route_does_not_cover_run_under_vmap():
    from adjointsim.nets.resnet import ResNet

    walls = ResNet(1, 1, 1, width=3, blocks=1, padding="zeros")
    plane = ResNet(1, 1, 2, width=3, blocks=1)
    unpadded = torch.nn.Sequential(torch.nn.Conv1d(1, 2, 3), torch.nn.Flatten())
    for net in (walls, plane, unpadded):
        assert Stack([net, net], (1e-3,) * 2).plan is None
