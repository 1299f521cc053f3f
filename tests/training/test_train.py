"""The training layer: unroll modes, NOG never runs an adjoint, WIG gradients, resumable
training (killed and resumed), atomic and validated files."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from adjointsim.errors import RunExists, UserError
from adjointsim.train import bridge
from adjointsim.train import data as datamod
from adjointsim.train.checkpoint import load_checkpoint, save_checkpoint
from adjointsim.train.model import NeuralStepper
from adjointsim.train.problems import get_problem
from adjointsim.train.trainer import TrainConfig, build_model, train
from adjointsim.train.unroll import unrolled_loss


def _checkpoint(path):
    """A run's checkpoint (the engine's layout: config, state, history)."""
    return load_checkpoint(path, ("config", "state", "history"))


def _weights(path):
    return _checkpoint(path)["state"]["model"]


def _batch(path, m, dtype=torch.float64):
    split = datamod.load(path).splits["train"]
    frames = torch.from_numpy(split.trajectories[:4, : m + 1]).to(dtype)
    return frames, torch.from_numpy(split.params[:4]), torch.from_numpy(split.conditions[:4])


def _model(setup="correction", correction="parallel"):
    cfg = TrainConfig(setup=setup, correction=correction, width=4, blocks=1, dtype="float64")
    return build_model(cfg)


@pytest.mark.parametrize("correction", ["parallel", "sequential"])
def test_nog_never_runs_the_solver_adjoint_and_wig_does(tiny, correction):
    model = _model(correction=correction)
    frames, params, cond = _batch(tiny, 3)
    before = bridge.ADJOINT_CALLS["count"]
    unrolled_loss(model, frames, params, cond, "NOG").backward()
    assert bridge.ADJOINT_CALLS["count"] == before
    unrolled_loss(model, frames, params, cond, "WIG").backward()
    assert bridge.ADJOINT_CALLS["count"] > before


def test_combined_mode_by_name_is_refused(tiny):
    """C's update needs flow.backward; a plain loss.backward() would silently be g_R / 2."""
    frames, params, cond = _batch(tiny, 2)
    with pytest.raises(ValueError, match=r"mode 'C' needs a GradientFlow"):
        unrolled_loss(_model(), frames, params, cond, "C")


def test_wig_gradient_matches_finite_differences(tiny):
    model = _model()
    frames, params, cond = _batch(tiny, 3)
    w = model.net.encode.weight
    loss = unrolled_loss(model, frames, params, cond, "WIG")
    (grad,) = torch.autograd.grad(loss, w)
    direction = torch.randn_like(w)
    eps = 1e-6
    with torch.no_grad():
        w += eps * direction
        plus = unrolled_loss(model, frames, params, cond, "WIG")
        w -= 2 * eps * direction
        minus = unrolled_loss(model, frames, params, cond, "WIG")
        w += eps * direction
    fd = (plus - minus) / (2 * eps)
    assert float((grad * direction).sum()) == pytest.approx(float(fd), rel=1e-6)


def test_nog_gradient_ignores_the_temporal_chain(tiny):
    """NOG's gradient equals the sum of one-step gradients taken at the model's own states."""
    model = _model()
    frames, params, cond = _batch(tiny, 3)
    loss = unrolled_loss(model, frames, params, cond, "NOG")
    g_nog = torch.autograd.grad(loss, model.net.decode.weight)[0]
    total = torch.zeros_like(g_nog)
    u = frames[:, 0]
    for s in range(1, 4):
        out = model(u.detach(), params, cond)
        part = torch.mean((out - frames[:, s]) ** 2) / 3
        total += torch.autograd.grad(part, model.net.decode.weight)[0]
        u = out
    torch.testing.assert_close(g_nog, total)


def test_mixed_parameters_in_a_batch_use_their_own_solvers(tiny):
    model = _model()
    frames, params, cond = _batch(tiny, 1)
    assert len(set(params.tolist())) > 1
    together = model.solve(frames[:, 0], params)
    for i in range(len(params)):
        alone = model.solve(frames[i : i + 1, 0], params[i : i + 1])
        torch.testing.assert_close(together[i : i + 1], alone)


def test_prediction_setup_calls_no_solver(tiny):
    model = _model(setup="prediction")
    frames, params, cond = _batch(tiny, 2)
    unrolled_loss(model, frames, params, cond, "WIG").backward()
    assert model._solvers == {}


def test_bad_modes_and_setups():
    with pytest.raises(ValueError, match="unknown setup"):
        NeuralStepper(torch.nn.Identity(), "projection")
    with pytest.raises(ValueError, match="unknown config option"):
        TrainConfig.load(modee="WIG")
    with pytest.raises(ValueError, match="config key 'mode': 'BPTT' is not one of ONE, NOG"):
        TrainConfig.load(mode="BPTT")


def test_warmup_steps_carry_no_gradient_and_no_loss(tiny):
    """Pushforward: w steps without tape, then the loss of m steps from the reached state."""
    model = _model()
    frames, params, cond = _batch(tiny, 4)
    loss = unrolled_loss(model, frames, params, cond, "WIG", warmup=2)
    with torch.no_grad():
        u = model(model(frames[:, 0], params, cond), params, cond)
    shifted = torch.cat([u[:, None], frames[:, 3:]], dim=1)
    expected = unrolled_loss(model, shifted, params, cond, "WIG")
    torch.testing.assert_close(loss, expected)
    w = model.net.decode.weight
    torch.testing.assert_close(torch.autograd.grad(loss, w)[0],
                               torch.autograd.grad(expected, w)[0])


def test_truncated_bptt_interpolates_between_nog_and_wig(tiny):
    model = _model()
    frames, params, cond = _batch(tiny, 4)
    w = model.net.decode.weight

    def grad(mode, truncate=0):
        return torch.autograd.grad(unrolled_loss(model, frames, params, cond, mode,
                                                 truncate=truncate), w)[0]

    torch.testing.assert_close(grad("WIG", truncate=1), grad("NOG"))
    torch.testing.assert_close(grad("WIG", truncate=4), grad("WIG"))
    middle = grad("WIG", truncate=2)
    assert not torch.allclose(middle, grad("WIG")) and not torch.allclose(middle, grad("NOG"))


def test_curriculum_stages_and_one_scaling(tiny, tmp_path):
    from adjointsim.train.trainer import plan

    model = train(_config(tiny, tmp_path / "c", curriculum=[[1, 1e-3], [2, 1e-4]], epochs=1),
                  progress=False)
    assert model is not None
    history = _checkpoint(tmp_path / "c" / "checkpoint.pt")["history"]
    stages = sorted({(h["stage"], h["m"], h["lr"]) for h in history})
    assert stages == [(0, 1, 1e-3), (1, 2, 1e-4)]
    # ONE trains on single steps with the batch and the epochs scaled by the target m.
    one = plan(TrainConfig(mode="ONE", unroll=4, batch=2, epochs=1), lambda length: 100)
    wig = plan(TrainConfig(mode="WIG", unroll=4, batch=2, epochs=1), lambda length: 100)
    assert (one[0]["m"], one[0]["batch"]) == (1, 8) and wig[0]["batch"] == 2
    assert one[0]["iterations"] == 4 * one[0]["per_epoch"]


def _scale_loss_after(monkeypatch, calls: int, factor: float) -> None:
    """Make the trainer's loss (and its gradients) ``factor`` × larger from call calls + 1 on."""
    import adjointsim.train.trainer as trainer

    count = {"n": 0}

    def scaled(*args, **kw):
        count["n"] += 1
        return unrolled_loss(*args, **kw) * (factor if count["n"] > calls else 1.0)

    monkeypatch.setattr(trainer, "unrolled_loss", scaled)


def test_spiking_and_non_finite_updates_are_skipped(tiny, tmp_path, monkeypatch):
    import adjointsim.train.trainer as trainer

    # Gradients 10⁶× larger than before are skipped once the running mean exists (20 steps).
    _scale_loss_after(monkeypatch, 21, 1e6)
    real, calls = unrolled_loss, {"n": 0}
    cfg = _config(tiny, tmp_path / "s", epochs=30, checkpoint_every=1000, max_iterations=24)
    train(cfg, progress=False)
    ckpt = _checkpoint(tmp_path / "s" / "checkpoint.pt")
    assert [h["skipped"] for h in ckpt["history"]] == [False] * 21 + [True] * 3
    # A non-finite loss is never stepped on.

    def sometimes_nan(*args, **kw):
        calls["n"] += 1
        loss = real(*args, **kw)
        return loss * float("nan") if calls["n"] == 2 else loss

    monkeypatch.setattr(trainer, "unrolled_loss", sometimes_nan)
    train(_config(tiny, tmp_path / "n", max_iterations=3), progress=False)
    history = _checkpoint(tmp_path / "n" / "checkpoint.pt")["history"]
    assert [h["skipped"] for h in history] == [False, True, False]


def _config(tiny, out, **kw):
    base = dict(data=str(tiny), out=str(out), width=4, blocks=1, unroll=2, epochs=3, batch=2,
                checkpoint_every=3, mode="WIG", lr=1e-3)
    base.update(kw)
    return TrainConfig.load(**base)


def test_resume_after_interruption_gives_the_same_weights(tiny, tmp_path):
    full = train(_config(tiny, tmp_path / "a"), progress=False)
    cut = _config(tiny, tmp_path / "b", max_iterations=7)
    train(cut, progress=False)
    assert _checkpoint(tmp_path / "b" / "checkpoint.pt")["state"]["progress"]["total"] == 7
    assert not (tmp_path / "b" / "result.json").exists()  # stopped, not finished
    resumed = train(_config(tiny, tmp_path / "b"), resume=True, progress=False)
    for a, b in zip(full.state_dict().values(), resumed.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    for name in ("history.csv", "result.json"):
        assert (tmp_path / "a" / name).read_text().replace(str(tmp_path / "a"), "") == \
            (tmp_path / "b" / name).read_text().replace(str(tmp_path / "b"), "")
    assert (tmp_path / "b" / "training.png").exists()


def test_evaluating_an_unfinished_run_warns(tiny, tmp_path):
    from adjointsim.train.trainer import load_model

    train(_config(tiny, tmp_path / "cut", max_iterations=2), progress=False)
    with pytest.warns(UserWarning, match="unfinished run.*--resume"):
        load_model(tmp_path / "cut")
    train(_config(tiny, tmp_path / "cut"), resume=True, progress=False)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_model(tmp_path / "cut")


def test_resume_without_a_checkpoint_is_one_line(tiny, tmp_path):
    cmd = [sys.executable, "-m", "adjointsim.cli", "train", "--data", str(tiny), "--out",
           str(tmp_path / "none"), "--resume"]
    proc = subprocess.run(cmd, env={**os.environ, "TQDM_DISABLE": "1"}, capture_output=True,
                          text=True)
    assert proc.returncode == 2 and "holds no run to continue" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["ctrl-c", "kill"])
def test_an_interrupted_run_resumes_to_the_uninterrupted_weights(tiny, tmp_path, sig):
    """Ctrl-C saves a checkpoint between two updates, even before the first periodic one; a
    killed run continues from its last periodic checkpoint. Either way --resume ends with the
    weights of an uninterrupted run, to the bit."""
    every = "100000" if sig == signal.SIGINT else "2"
    args = ["--data", str(tiny), "--width", "4", "--blocks", "1", "--unroll", "2", "--epochs",
            "6", "--batch", "2", "--checkpoint-every", every, "--mode", "NOG"]
    env = {**os.environ, "TQDM_DISABLE": "1"}
    cmd = [sys.executable, "-m", "adjointsim.cli", "train"]
    subprocess.run(cmd + args + ["--out", str(tmp_path / "a")], check=True, env=env,
                   capture_output=True)
    proc = subprocess.Popen(cmd + args + ["--out", str(tmp_path / "b")], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    # Ctrl-C once the updates run; a kill once a periodic checkpoint exists
    started = tmp_path / "b" / ("config.json" if sig == signal.SIGINT else "checkpoint.pt")
    deadline = time.time() + 300
    while not started.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.02)
    if sig == signal.SIGINT:
        time.sleep(0.5)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=300)
    if sig == signal.SIGINT:
        assert proc.returncode == 130 and "--resume" in err and "checkpoint is saved" in err, err
    ckpt = tmp_path / "b" / "checkpoint.pt"
    assert not (tmp_path / "b" / "result.json").exists(), "it finished before the signal"
    subprocess.run(cmd + args + ["--out", str(tmp_path / "b"), "--resume"], check=True, env=env,
                   capture_output=True)
    a = _weights(tmp_path / "a" / "checkpoint.pt")
    b = _weights(ckpt)
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0)


def test_corrupt_files_get_clear_errors(tiny, tmp_path):
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not an hdf5 file")
    with pytest.raises(ValueError, match="regenerate"):
        datamod.load(bad)
    ckpt = tmp_path / "checkpoint.pt"
    ckpt.write_bytes(b"\x00" * 10)
    with pytest.raises(ValueError, match="not a readable checkpoint"):
        load_checkpoint(ckpt)


def _flip_bit(path, offset, bit):
    with open(path, "r+b") as f:
        f.seek(offset)
        byte = f.read(1)[0]
        f.seek(offset)
        f.write(bytes([byte ^ (1 << bit)]))


def test_a_flipped_bit_in_a_dataset_is_detected(tiny, tmp_path):
    """one flipped exponent bit (|u| 3.35 → 4.6e19) used to load without complaint."""
    import shutil

    import h5py

    damaged = tmp_path / "damaged.h5"
    shutil.copy(tiny, damaged)
    with h5py.File(damaged, "r") as f:
        d = f["train/trajectories"]
        assert d.fletcher32
        values = d[...].reshape(-1)
        k = int(np.flatnonzero(np.abs(values) > 1)[0])  # exponent 0x40/0x3f: the flip is finite
        offset = d.id.get_chunk_info(0).byte_offset
        assert k * 4 < d.id.get_chunk_info(0).size
    _flip_bit(damaged, offset + 4 * k + 3, 5)
    with pytest.raises(ValueError, match=r"damaged: the checksum of train/trajectories does not "
                       r"match.*regenerate it with `adjointsim data ks --size tiny --out"):
        datamod.load(damaged)


def test_datasets_without_checksums_load_with_a_warning(tiny, tmp_path):
    import h5py

    old = tmp_path / "old.h5"
    with h5py.File(tiny, "r") as src, h5py.File(old, "w") as dst:
        for key, value in src.attrs.items():
            dst.attrs[key] = value
        dst.attrs["format_version"] = 1
        for name in src:
            for key in src[name]:
                dst.create_dataset(f"{name}/{key}", data=src[name][key][...])
    with pytest.warns(UserWarning, match="predates checksums.*adjointsim data ks --size tiny"):
        ds = datamod.load(old)
    np.testing.assert_array_equal(ds.splits["train"].trajectories,
                                  datamod.load(tiny).splits["train"].trajectories)


def test_a_flipped_bit_in_a_checkpoint_is_detected(tiny, tmp_path):
    """a flipped bit in a checkpoint's tensors used to load without complaint."""
    train(_config(tiny, tmp_path / "r", setup="prediction", max_iterations=1), progress=False)
    path = tmp_path / "r" / "checkpoint.pt"
    weights = _weights(path)
    name = max(weights, key=lambda k: weights[k].numel())
    raw = path.read_bytes()
    offset = raw.find(weights[name].numpy().tobytes())
    assert offset > 0
    _flip_bit(path, offset + 3 * weights[name].element_size(), 0)  # the 4th element's mantissa
    loaded = torch.load(path, weights_only=False)  # torch itself does not notice
    assert not torch.equal(loaded["state"]["model"][name], weights[name])
    with pytest.raises(ValueError, match="damaged: its contents do not match the SHA-256 digest"):
        _checkpoint(path)
    with pytest.raises(ValueError, match="damaged: .*--overwrite"):  # what to do
        train(_config(tiny, tmp_path / "r", setup="prediction", max_iterations=1),
              resume=True, progress=False)
    # A checkpoint from before digests loads with a warning.
    del loaded["sha256"]
    loaded["state"]["model"][name] = weights[name]
    torch.save(loaded, path)
    with pytest.warns(UserWarning, match="no digest"):
        _checkpoint(path)


def test_dataset_from_another_configuration_is_refused(tiny, tmp_path):
    import shutil

    import h5py

    stale = tmp_path / "stale.h5"
    shutil.copy(tiny, stale)
    with h5py.File(stale, "a") as f:
        f.attrs["config"] = f.attrs["config"].replace('"warmup_frames": 200', '"warmup_frames": 50')
    with pytest.raises(ValueError, match="another configuration.*regenerate"):
        datamod.load(stale)


@pytest.mark.parametrize("bad, message", [
    ({"warmup": -1}, "'warmup': -1 is not an integer ≥ 0"),
    ({"stride": 0}, "'stride': 0 is not an integer ≥ 1"),
    ({"checkpoint_every": 0}, "'checkpoint_every': 0 is not an integer ≥ 1"),
    ({"curriculum": [[1, 1e-3, 5]]}, "not an \\[m, lr\\] pair"),
    ({"curriculum": [[0, 1e-3]]}, "m an integer ≥ 1"),
])
def test_bad_config_values_are_named(bad, message):
    with pytest.raises(ValueError, match=message):
        TrainConfig.load(**bad)


def test_solver_blow_up_skips_the_update_instead_of_ending_the_run(tiny, tmp_path, monkeypatch):
    from adjointsim import NonFiniteStateError

    real = NeuralStepper.solve
    calls = {"n": 0}

    def blows_up_once(self, u, params, groups=None):
        calls["n"] += 1
        if calls["n"] == 3:
            raise NonFiniteStateError("ks1d-etdrk1", 1, 1e30)
        return real(self, u, params, groups)

    monkeypatch.setattr(NeuralStepper, "solve", blows_up_once)
    train(_config(tiny, tmp_path / "b", max_iterations=4), progress=False)
    history = _checkpoint(tmp_path / "b" / "checkpoint.pt")["history"]
    assert [h["skipped"] for h in history] == [False, True, False, False]


def test_dataset_write_is_atomic(tiny, tmp_path, monkeypatch):
    ds = datamod.load(tiny)
    target = tmp_path / "d.h5"
    datamod.save(ds, target)
    before = target.read_bytes()

    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr("h5py.Group.create_dataset", boom)
    with pytest.raises(RuntimeError, match="disk full"):  # the write failed, nothing else
        datamod.save(ds, target)
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["d.h5"]


def test_dataset_metadata_and_splits(tiny):
    ds = datamod.load(tiny)
    problem = get_problem("ks")
    assert set(ds.splits) == {"train", "interpolation", "extrapolation"}
    assert sorted(set(ds.splits["train"].params)) == list(problem.train_params)
    assert ds.splits["train"].trajectories.dtype == np.float32


def test_evaluation_rollout_keeps_going_when_one_trajectory_blows_up():
    from types import SimpleNamespace

    from adjointsim.train.evaluate import rollout

    class Growth(torch.nn.Module):
        """Row i is multiplied by its parameter each step."""

        def forward(self, u, params, conditions):
            return u * params.to(u.dtype)[:, None, None]

    traj = np.ones((3, 30, 1, 8), np.float32)
    split = SimpleNamespace(trajectories=traj, params=np.array([1.0, 10.0, 0.5]),
                            conditions=np.zeros(3))
    out = rollout(Growth(), split, 29, torch.float32)
    assert np.all(out[0] == 1.0) and np.allclose(out[2, 5], 0.5**5)
    # Row 1 passes 100× the reference's largest value at step 3: inf from there on.
    assert np.allclose(out[1, 2], 100.0) and np.all(np.isinf(out[1, 3:]))


def test_tiny_study_end_to_end_and_resumes(tmp_path):
    import json

    from adjointsim.cli import main
    from adjointsim.runner import run
    from adjointsim.train.studies import load_all

    load_all()
    out = tmp_path / "study"
    rows = run("ks", out, "tiny", None, cluster="none", progress=False)
    assert len(rows) == 6  # 2 setups × 3 modes × 1 seed
    for row in rows:
        assert row["setup"] in ("prediction", "correction") and row["mode"] in ("ONE", "NOG", "WIG")
        assert row["seed"] == 0 and np.isfinite(row["rel_error"])
        assert (out / f"{row['setup']}-{row['mode']}-seed0" / "checkpoint.pt").exists()
    assert (out / "study.png").stat().st_size > 0
    table = (out / "table.txt").read_text()
    assert "correction  WIG" in table and "coarse solver alone" in table
    # Everything finished is reused: running it again trains nothing and gives the same rows.
    stamp = (out / "correction-WIG-seed0" / "checkpoint.pt").stat().st_mtime_ns
    rows_path = tmp_path / "rows.json"
    assert main(["study", "ks", "--size", "tiny", "--out", str(out), "--json", str(rows_path),
                 "--cluster", "local"]) == 0  # nothing to run: no cluster is started
    assert json.loads(rows_path.read_text()) == rows == json.loads((out / "rows.json").read_text())
    assert (out / "correction-WIG-seed0" / "checkpoint.pt").stat().st_mtime_ns == stamp
    with pytest.raises(ValueError, match="unknown study size 'huge'"):
        run("ks", out, "huge", None, cluster="none")


@pytest.mark.parametrize("argv, size", [([], "full"), (["--quick"], "quick"),
                                        (["--size", "tiny"], "tiny")])
def test_study_command_sizes(argv, size):
    from adjointsim.cli import build_parser

    assert build_parser("study").parse_args(["study", "ks", *argv]).size == size


def test_rollback_guard_restores_the_best_weights_and_halves_the_rate(tiny, tmp_path,
                                                                     monkeypatch):
    # A runaway from update 301 on: the loss (and its gradients) 50x higher, gradually enough
    # for the spike cutoff (disabled here) to let it through.
    _scale_loss_after(monkeypatch, 300, 50.0)
    cfg = _config(tiny, tmp_path / "g", epochs=400, checkpoint_every=1000, max_iterations=400,
                  rollback=3.0, spike_factor=1e12, lr_decay=1.0)
    model = train(cfg, progress=False)
    ckpt = _checkpoint(tmp_path / "g" / "checkpoint.pt")
    progress = ckpt["state"]["progress"]
    assert progress["rollbacks"] == 1 and progress["lr_scale"] == 0.5
    # the weights are those of the best window, before the runaway
    for key, value in ckpt["state"]["kept"]["model"].items():
        assert torch.equal(model.state_dict()[key], value)
    assert len(ckpt["history"]) == 400 and ckpt["history"][-1]["lr"] == pytest.approx(1e-3)
    # the next update runs at half the rate
    train(_config(tiny, tmp_path / "g", epochs=400, checkpoint_every=1000, max_iterations=401,
                  rollback=3.0, spike_factor=1e12, lr_decay=1.0), resume=True, progress=False)
    history = _checkpoint(tmp_path / "g" / "checkpoint.pt")["history"]
    assert history[-1]["lr"] == pytest.approx(5e-4)


def test_rollback_option_is_checked_and_old_checkpoints_resume(tiny, tmp_path):
    with pytest.raises(UserError, match="'rollback'.*0 \\(off\\) or a number > 1"):
        _config(tiny, tmp_path / "r", rollback=0.5)
    train(_config(tiny, tmp_path / "old", max_iterations=2), progress=False)
    # a checkpoint written before the guard kept its state resumes with the guard's defaults
    path = tmp_path / "old" / "checkpoint.pt"
    ckpt = _checkpoint(path)
    for key in ("lr_scale", "best", "rollbacks"):
        del ckpt["state"]["progress"][key]
    del ckpt["state"]["kept"]
    save_checkpoint(ckpt, path)
    train(_config(tiny, tmp_path / "old", max_iterations=4), resume=True, progress=False)
    ckpt = _checkpoint(path)
    assert len(ckpt["history"]) == 4 and ckpt["state"]["progress"]["lr_scale"] == 1.0


def test_overwrite_never_discards_somebody_elses_files(tiny, tmp_path):
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "config.json").write_text('{"owner": "someone else"}')
    (theirs / "notes.txt").write_text("mine")
    for overwrite in (False, True):
        with pytest.raises(RunExists, match="another command's run or other files"):
            train(_config(tiny, theirs), overwrite=overwrite, progress=False)
    assert (theirs / "config.json").read_text() == '{"owner": "someone else"}'
    assert (theirs / "notes.txt").exists()


def test_the_study_table_shows_a_blown_up_model_as_nan():
    """A model whose rollout blew up has null measures in its row; the table still reports."""
    from adjointsim.train.studies.neural_steppers import table

    row = {"setup": "correction", "mode": "NOG", "seed": 0, "rel_error": None,
           "correlation_time": 1.0, "stable_fraction": 0.0,
           "interpolation": {"rel_error": None}, "extrapolation": {"rel_error": 0.1}}
    text = table([row, dict(row, seed=1, rel_error=0.1)])
    assert "nan 1.00e-01" in text


def test_training_gives_torch_and_the_solvers_the_threads_it_is_given(tiny, tmp_path,
                                                                      monkeypatch):
    from adjointsim import parallel
    from adjointsim.cli import main
    from adjointsim.train import trainer

    seen = []
    real = trainer.unrolled_loss

    def spy(*args, **kwargs):
        seen.append((parallel.threads(), torch.get_num_threads()))
        return real(*args, **kwargs)

    monkeypatch.setattr(trainer, "unrolled_loss", spy)
    before = torch.get_num_threads()
    try:
        assert main(["train", "--data", str(tiny), "--out", str(tmp_path / "run"), "--width",
                     "4", "--blocks", "1", "--unroll", "2", "--batch", "2", "--max-iterations",
                     "2", "--threads", "2", "--no-progress"]) == 0
    finally:
        parallel.set_threads(None)
        torch.set_num_threads(before)
    assert len(seen) == 2 and set(seen) == {(2, 2)}


def test_a_finished_run_has_its_result_and_is_returned_as_it_is(tiny, tmp_path):
    import json

    from adjointsim.nets import parameter_count
    from adjointsim.run import read_history

    out = tmp_path / "r"
    model = train(_config(tiny, out, rollback=2.0, checkpoint_every=100), progress=False)
    result = json.loads((out / "result.json").read_text())
    history = read_history(out / "history.csv")
    assert result["iterations"] == len(history) == 198 and result["rollbacks"] == 0
    assert result["skipped"] == sum(h["skipped"] for h in history)
    assert result["final_loss"] == history[-1]["loss"]
    assert result["parameters"] == parameter_count(model.net)
    assert result["rollback"] == 2.0 and result["scene"] == get_problem("ks").scene
    # --resume returns it as it is: nothing trained, nothing written, the same weights
    stamps = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    again = train(_config(tiny, out, rollback=2.0, checkpoint_every=100), resume=True,
                  progress=False)
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == stamps
    for a, b in zip(model.state_dict().values(), again.state_dict().values()):
        assert torch.equal(a, b)
    with pytest.raises(RunExists, match="finished run"):
        train(_config(tiny, out, rollback=2.0, checkpoint_every=100), progress=False)


def test_the_scene_comes_from_the_dataset(tmp_path, capsys):
    """`adjointsim data --scene` records the scene in the dataset; train builds its solver from
    it, records it in config.json, and refuses a scene key that disagrees, naming the
    dataset's."""
    import json

    from adjointsim.cli import main

    data = tmp_path / "n64.h5"
    assert main(["data", "ks", "--size", "tiny", "--scene", "n=64", "--out", str(data),
                 "--no-progress"]) == 0
    dataset = datamod.load(data)
    assert dataset.problem.scene == {"n": 64, "dt": 1.0, "substeps": 2}
    assert dataset.splits["train"].trajectories.shape[-1] == 64
    model = train(_config(data, tmp_path / "r", max_iterations=1), progress=False)
    assert model.solver(1.0).grid_shape == (64,)
    assert json.loads((tmp_path / "r" / "config.json").read_text())["scene"]["n"] == 64
    with pytest.raises(UserError, match=r"'scene': n = 48 conflicts with the scene of the "
                       r"dataset .*n64.h5 \(n = 64\)"):
        train(_config(data, tmp_path / "s", scene={"n": 48}), progress=False)
    assert not (tmp_path / "s").exists()
    # the solver's own validation, one line naming the key and what it accepts
    flags = ["--size", "tiny", "--out", str(tmp_path / "x.h5"), "--no-progress"]
    assert main(["data", "ks", *flags, "--scene", "n=31"]) == 2
    err = capsys.readouterr().err.strip()
    assert "n must be an even integer" in err and len(err.splitlines()) == 1
    assert main(["data", "ks", *flags, "--scene", "viscosity=1"]) == 2
    assert "scene key 'viscosity' is not one of the ks problem's (n, dt, substeps)" in \
        capsys.readouterr().err
    assert not (tmp_path / "x.h5").exists()
