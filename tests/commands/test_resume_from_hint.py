"""``--resume --out DIR`` alone continues a run with the configuration it recorded, in every
command that writes one: Ctrl-C prints the command that continues the run, and that exact
command finishes it as it was started (none of its flags repeated, a task or problem named by
the run). A flag given beside ``--resume`` changes only a key a run may change when continued
(a larger length continues a finished run); any other is refused, naming the key."""

from __future__ import annotations

import json
import os
import shlex
import signal

import pytest

from adjointsim import engine
from adjointsim.cli import main

#: each command's tiniest run with at least two updates, its flags far from the defaults
COMMANDS = {
    "train": ["train", "--data", "{tiny}", "--setup", "prediction", "--width", "2", "--blocks",
              "1", "--unroll", "2", "--batch", "4", "--stride", "8", "--epochs", "1"],
    "control": ["control", "cartpole", "--epochs", "2", "--train", "4", "--test", "4",
                "--batch", "4", "--dtype", "float64", "--lr", "0.002"],
    "hig": ["hig", "chain", "--size", "tiny", "--max-updates", "3", "--seed", "2"],
    "pinn": ["pinn", "poisson", "--width", "6", "--depth", "2", "--collocation", "40",
             "--edge-points", "6", "--log-every", "1", "--epochs", "3"],
}


def _ctrl_c_at_the_second_update(monkeypatch, signum: int = signal.SIGINT) -> None:
    """A real SIGINT (or ``signum``) in the middle of the second update: the engine holds it
    until the update ends, then saves the checkpoint and the history."""
    real, calls = engine.Single.update, []

    def update(self):
        calls.append(1)
        if len(calls) == 2:
            os.kill(os.getpid(), signum)
        return real(self)

    monkeypatch.setattr(engine.Single, "update", update)


def _printed_command(err: str, command: str) -> list[str]:
    """The command the interrupt message prints, as words after ``adjointsim``."""
    line = err.strip().splitlines()[-1]
    assert line.startswith(f"adjointsim {command}: interrupted; the checkpoint is saved"), err
    words = shlex.split(line.split("or just: ", 1)[1])
    assert words[:2] == ["adjointsim", command], line
    return words[1:]


@pytest.mark.parametrize("command", list(COMMANDS))
def test_ctrl_c_prints_a_command_that_finishes_the_run(command, tiny, tmp_path, capsys,
                                                       monkeypatch):
    out = tmp_path / "run dir"  # a space: the printed command quotes it
    args = [a.format(tiny=tiny) for a in COMMANDS[command]] + ["--no-progress", "--out", out]
    _ctrl_c_at_the_second_update(monkeypatch)
    assert main([str(a) for a in args]) == 130
    monkeypatch.undo()
    assert (out / "checkpoint.pt").is_file() and not (out / "result.json").exists()
    assert (out / "history.csv").is_file(), "the history is written before the command exits"
    recorded = json.loads((out / "config.json").read_text())

    printed = _printed_command(capsys.readouterr().err, command)
    assert printed == [command, "--resume", "--out", str(out)]
    code = main(printed)
    assert code == 0, capsys.readouterr().err
    result = json.loads((out / "result.json").read_text())
    assert {k: result[k] for k in recorded} == recorded


@pytest.mark.parametrize("command", ["control", "hig"])
def test_sigterm_stops_a_run_as_ctrl_c_does(command, tmp_path, capsys, monkeypatch):
    """``kill`` (or a batch scheduler's stop) saves the checkpoint too, and leaves SIGTERM as
    it was once the command returns."""
    out = tmp_path / "run"
    _ctrl_c_at_the_second_update(monkeypatch, signal.SIGTERM)
    assert main([*COMMANDS[command], "--no-progress", "--out", str(out)]) == 130
    monkeypatch.undo()
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
    assert (out / "checkpoint.pt").is_file() and not (out / "result.json").exists()
    printed = _printed_command(capsys.readouterr().err, command)
    assert main(printed) == 0 and (out / "result.json").is_file()


def test_an_ensembles_printed_command_names_its_seeds(tmp_path, capsys, monkeypatch):
    from adjointsim.train import checkpoint

    out = tmp_path / "runs"
    args = ["control", "cartpole", "--mode", "R", "--epochs", "1", "--train", "4", "--test",
            "4", "--batch", "4", "--dtype", "float64", "--no-progress", "--out", str(out),
            "--seeds", "0", "1"]
    real = checkpoint.save_checkpoint

    def stop(*a, **kw):  # Ctrl-C right after the members' first checkpoints
        real(*a, **kw)
        if str(a[1]).startswith(str(out / "seed1")):
            raise KeyboardInterrupt

    monkeypatch.setattr(checkpoint, "save_checkpoint", stop)
    assert main(args) == 130
    monkeypatch.undo()
    printed = _printed_command(capsys.readouterr().err, "control")
    assert printed == ["control", "--resume", "--out", str(out), "--seeds", "0", "1"]
    assert main(printed) == 0, capsys.readouterr().err
    for seed in (0, 1):
        result = json.loads((out / f"seed{seed}" / "result.json").read_text())
        assert (result["seed"], result["mode"], result["batch"]) == (seed, "R", 4)


def test_flags_beside_resume_change_only_what_a_run_may_change(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["control", "cartpole", "--epochs", "1", "--train", "4", "--test", "4", "--batch",
            "4", "--dtype", "float64", "--no-progress"]
    assert main([*args, "--out", str(out)]) == 0
    # a key that cannot change: named, on one line, and the run stays as it was
    before = (out / "result.json").read_bytes()
    assert main(["control", "--resume", "--out", str(out), "--lr", "0.5"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "differs in lr" in err, err
    assert (out / "result.json").read_bytes() == before
    # the task of another run is a key like any other
    assert main(["control", "guidance", "--resume", "--out", str(out)]) == 2
    assert "differs in" in capsys.readouterr().err
    # a larger length continues the finished run, under its recorded configuration
    assert main(["control", "--resume", "--out", str(out), "--epochs", "2",
                 "--no-progress"]) == 0, capsys.readouterr().err
    result = json.loads((out / "result.json").read_text())
    assert (result["epochs"], result["batch"], result["dtype"]) == (2, 4, "float64")


def test_a_fit_is_returned_by_resume_and_out_alone(tmp_path, capsys):
    out = tmp_path / "fit"
    assert main(["fit", "--demo", "burgers-nu", "--maxiter", "2", "--no-plots", "--no-progress",
                 "--out", str(out)]) == 0
    before = (out / "result.json").read_bytes()
    assert main(["fit", "--resume", "--out", str(out)]) == 0, capsys.readouterr().err
    assert (out / "result.json").read_bytes() == before


def test_a_task_or_problem_is_needed_without_a_run_to_resume(tmp_path, capsys):
    assert main(["control", "--out", str(tmp_path / "a")]) == 2
    assert "the task is needed" in capsys.readouterr().err
    assert main(["hig", "--out", str(tmp_path / "b")]) == 2
    assert "config key 'problem' is needed" in capsys.readouterr().err
    assert main(["hig", "--resume", "--out", str(tmp_path / "c")]) == 2
    assert "config key 'problem' is needed" in capsys.readouterr().err


def test_a_run_stopped_by_its_iteration_cap_resumes_to_its_end(tiny, tmp_path, capsys):
    """--max-iterations caps one invocation, not the run: --resume --out DIR alone goes on to
    the end of the run instead of stopping at the recorded cap again."""
    out = tmp_path / "run"
    args = [a.format(tiny=tiny) for a in COMMANDS["train"]]
    assert main([*args, "--no-progress", "--out", str(out), "--max-iterations", "1"]) == 0
    assert not (out / "result.json").exists()
    assert main(["train", "--resume", "--out", str(out), "--no-progress"]) == 0, \
        capsys.readouterr().err
    result = json.loads((out / "result.json").read_text())
    assert result["iterations"] > 1 and result["max_iterations"] == 0


@pytest.mark.parametrize("command", ["train", "hig", "pinn", "fit"])
def test_resume_of_another_commands_run_is_refused_by_name(command, tmp_path, capsys):
    """The recorded configuration of another command is not taken for this one's (a train
    run would otherwise look for the default dataset, a hig run for its problem)."""
    out = tmp_path / "control-run"
    assert main(["control", "cartpole", "--epochs", "1", "--train", "4", "--test", "4",
                 "--batch", "4", "--no-progress", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main([command, "--resume", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "holds another command's run" in err, err


@pytest.mark.parametrize("command", ["control", "hig", "pinn", "train"])
def test_resume_of_a_run_whose_config_is_damaged_names_the_file(command, tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.json").write_text('{"task": "cartpole", "mode": "C", "cl')
    assert main([command, "--resume", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == (f"adjointsim {command}: --resume: {out / 'config.json'} is not a readable "
                   "config (damaged?); restore it, or choose another --out\n")


def test_a_wrong_value_in_a_runs_recorded_config_is_named_as_the_files(tmp_path, capsys):
    from adjointsim.train.control import ControlConfig

    out = tmp_path / "run"
    out.mkdir()
    recorded = {**ControlConfig(task="cartpole", out=str(out)).as_dict(), "lr": "0.001"}
    (out / "config.json").write_text(json.dumps(recorded))
    assert main(["control", "--resume", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("adjointsim control: config key 'lr' in the run's config.json: "
                          "'0.001' (str) is not"), err
    assert main(["control", "--resume", "--out", str(out), "--lr", "x"]) == 2
    assert "'x'" in capsys.readouterr().err  # the flag's own value is checked as the flag's
