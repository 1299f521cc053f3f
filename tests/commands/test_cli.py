"""The CLI's contract with its user: bad configs and arguments name the key, the value and what
is accepted, on one line (exit 2) and without a traceback; Ctrl-C says how to continue; a run
is never overwritten silently; JSON output never holds NaN or Infinity. Entry points run
in-process through ``adjointsim.cli.main`` (the one error boundary)."""

import json
import math
import os
import subprocess
import sys
from dataclasses import fields

import pytest

from adjointsim.cli import main
from adjointsim.train import data as datamod
from adjointsim.train.trainer import ACCEPTED, Interval, TrainConfig

#: the cheapest run: the prediction setup calls no solver
TINY = ["--setup", "prediction", "--width", "2", "--blocks", "1", "--unroll", "2",
        "--batch", "4", "--stride", "8", "--epochs", "1"]


def _run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _one_line_error(capsys, *argv, command):
    code, _, err = _run(capsys, *argv)
    assert code == 2, err
    assert err.startswith(f"adjointsim {command}: ") and err.count("\n") == 1, err
    return err


def test_train_refuses_an_existing_run_unless_resume_or_overwrite(tiny, tmp_path, capsys):
    """a second `train` into the same --out used to overwrite the finished run."""
    out = tmp_path / "run"
    args = ["train", "--data", tiny, "--out", out, *TINY]
    assert _run(capsys, *args)[0] == 0
    ckpt = out / "checkpoint.pt"
    stamp, before = ckpt.stat().st_mtime_ns, ckpt.read_bytes()
    err = _one_line_error(capsys, *args, command="train")
    assert "finished run" in err and "--out" in err and "--overwrite" in err
    assert ckpt.stat().st_mtime_ns == stamp and ckpt.read_bytes() == before
    # An unfinished run gets the same refusal.
    cut = tmp_path / "cut"
    assert _run(capsys, "train", "--data", tiny, "--out", cut, *TINY, "--max-iterations", 1)[0] == 0
    err = _one_line_error(capsys, "train", "--data", tiny, "--out", cut, *TINY, command="train")
    assert "unfinished run; continue it with --resume" in err
    # --overwrite starts again; --resume with --overwrite is refused in one line.
    assert _run(capsys, *args, "--overwrite")[0] == 0
    assert ckpt.read_bytes() != before or ckpt.stat().st_mtime_ns != stamp
    err = _one_line_error(capsys, *args, "--overwrite", "--resume", command="train")
    assert "not allowed with argument --overwrite" in err


@pytest.mark.parametrize("toml, key, shown, expected", [
    ('unroll = "3"', "unroll", "'3' (str)", "an integer"),
    ("batch = 2.5", "batch", "2.5 (float)", "an integer"),
    ("width = 4.5", "width", "4.5 (float)", "an integer"),
    ("blocks = true", "blocks", "True (bool)", "an integer"),
    ("lr = [1e-3]", "lr", "[0.001] (list)", "a finite number"),
    ("mode = 3", "mode", "3 (int)", "a string"),
])
def test_wrong_toml_types_name_key_value_and_type(tmp_path, capsys, toml, key, shown, expected):
    """`unroll = "3"` failed deep inside training without naming the key."""
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(toml + "\n")
    err = _one_line_error(capsys, "train", "--config", cfg, "--out", tmp_path / "r",
                          command="train")
    assert f"config key '{key}' in {cfg}: {shown} is not {expected}; accepted:" in err


def test_unknown_keys_and_broken_toml(tmp_path, capsys):
    cfg = tmp_path / "cfg.toml"
    cfg.write_text("unrol = 3\n")
    err = _one_line_error(capsys, "train", "--config", cfg, command="train")
    assert "unknown config option 'unrol' (did you mean 'unroll'?); valid options:" in err
    assert "spike_factor" in err
    cfg.write_text("unroll = \n")
    assert "is not valid TOML" in _one_line_error(capsys, "train", "--config", cfg,
                                                  command="train")
    err = _one_line_error(capsys, "train", "--config", tmp_path / "none.toml", command="train")
    assert "no config file at" in err


@pytest.mark.parametrize("toml, message", [
    ("lr_decay = -1", "config key 'lr_decay' in {cfg}: -1.0 is not a finite number in (0, 1]"),
    ("spike_factor = -1", "'spike_factor' in {cfg}: -1.0 is not a finite number > 1"),
    ("max_iterations = -5", "'max_iterations' in {cfg}: -5 is not an integer ≥ 0"),
    ("lr = 0", "'lr' in {cfg}: 0.0 is not a finite number in (0, 1]"),
    ("lr = nan", "'lr' in {cfg}: nan is not a finite number in (0, 1]"),
    ("epochs = inf", "'epochs' in {cfg}: inf is not a finite number > 0"),
    ("curriculum = [[2, -1e-3]]", "stage [2, -0.001] is not an [m, lr] pair"),
])
def test_nonsensical_values_are_rejected_with_the_range(tmp_path, capsys, toml, message):
    """`lr_decay = -1` (gradient ascent every other step) used to exit 0."""
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(toml + "\n")
    err = _one_line_error(capsys, "train", "--config", cfg, command="train")
    assert message.format(cfg=cfg) in err


def _outside(rule):
    """A value of the right type that the rule rejects."""
    if isinstance(rule, tuple):
        return "no-such-choice"
    if isinstance(rule, Interval):
        return rule.lo - 1 if not rule.lo_open else rule.lo
    return ""


@pytest.mark.parametrize("f", [f for f in fields(TrainConfig)], ids=lambda f: f.name)
def test_every_config_field_has_an_accepted_range(f):
    assert f.name in ACCEPTED, f"add {f.name!r} to adjointsim.train.trainer.ACCEPTED"
    default = TrainConfig()
    default.validate()
    value = _outside(ACCEPTED[f.name])
    if f.name == "curriculum":
        value = [[0, 1e-3]]
    elif isinstance(getattr(default, f.name), float):
        value = float(value)
    with pytest.raises(ValueError, match=f"config key '{f.name}'"):
        TrainConfig.load(**{f.name: value})


@pytest.mark.parametrize("flag", ["--seeds", "--jobs"])
def test_study_counts_must_be_positive(capsys, flag):
    err = _one_line_error(capsys, "study", "ks", "--size", "tiny", flag, "0", command="study")
    assert f"argument {flag}: must be ≥ 1, not 0" in err


def test_user_errors_print_one_line_without_a_traceback(tmp_path):
    """the torch commands printed a Python traceback for a bad config."""
    cfg = tmp_path / "cfg.toml"
    cfg.write_text('unroll = "3"\n')
    proc = subprocess.run([sys.executable, "-m", "adjointsim.cli", "train", "--config", str(cfg)],
                          capture_output=True, text=True, env={**os.environ, "TQDM_DISABLE": "1"})
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines() == [
        f"adjointsim train: config key 'unroll' in {cfg}: '3' (str) is not an integer; "
        "accepted: an integer ≥ 1"
    ]


def test_bugs_keep_their_traceback_and_ctrl_c_says_how_to_resume(tiny, tmp_path, capsys,
                                                                 monkeypatch):
    import adjointsim.train.trainer

    def bug(*args, **kwargs):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(adjointsim.train.trainer, "train", bug)
    with pytest.raises(ZeroDivisionError, match="a bug"):
        main(["train", "--data", str(tiny), "--out", str(tmp_path / "r"), *TINY])

    def lookup_bug(*args, **kwargs):
        return {}["a missing key"]

    monkeypatch.setattr(adjointsim.train.trainer, "train", lookup_bug)
    with pytest.raises(KeyError, match="a missing key"):
        main(["train", "--data", str(tiny), "--out", str(tmp_path / "r"), *TINY])
    # An unknown solver name is the user's KeyError: one line.
    assert "unknown solver 'no-such-solver'" in _one_line_error(
        capsys, "gradcheck", "no-such-solver", command="gradcheck")

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.undo()
    monkeypatch.setattr(adjointsim.train.trainer.StepperRun, "update", interrupted)
    code, _, err = _run(capsys, "train", "--data", tiny, "--out", tmp_path / "r", *TINY)
    assert code == 130
    # Ctrl-C at the first update: the engine saves the checkpoint first
    assert err.splitlines()[-1].endswith("adjointsim train: interrupted; the checkpoint is saved; "
                                         f"continue with the same command and --resume (--out "
                                         f"{tmp_path / 'r'}), or just: adjointsim train "
                                         f"--resume --out {tmp_path / 'r'}")


def test_eval_missing_directory_and_bad_horizons(tiny, tmp_path, capsys):
    """a missing run was 'not a readable checkpoint'; --horizon 0 became 12 and a
    horizon beyond the data was cut silently, writing Infinity into the JSON."""
    err = _one_line_error(capsys, "eval", tmp_path / "nowhere", command="eval")
    assert "does not exist" in err and "readable" not in err
    run = tmp_path / "run"
    assert _run(capsys, "train", "--data", tiny, "--out", run, *TINY)[0] == 0
    err = _one_line_error(capsys, "eval", run, "--horizon", "0", command="eval")
    assert "argument --horizon: must be ≥ 1, not 0" in err
    frames = datamod.load(tiny).splits["interpolation"].trajectories.shape[1]
    err = _one_line_error(capsys, "eval", run, "--horizon", frames, command="eval")
    assert f"between 1 and {frames - 1} steps" in err
    code, out, _ = _run(capsys, "eval", run, "--horizon", frames - 1, "--long-steps", frames - 1)
    assert code == 0

    def strict(name):
        raise AssertionError(f"{name} in JSON output")

    metrics = json.loads(out, parse_constant=strict)
    assert metrics["coarse_rel_error"] is None and "stable_fraction" in metrics


def test_json_output_never_holds_nan_or_infinity():
    from adjointsim.files import json_text

    text = json_text([{"rel_error": math.inf, "split": {"x": math.nan}, "ok": 1.5}])
    assert "Infinity" not in text and "NaN" not in text
    (row,) = json.loads(text)
    assert row["rel_error"] is None and row["split"]["x"] is None and row["ok"] == 1.5
    assert row["non_finite"] == {"rel_error": "inf", "split.x": "nan"}


def test_every_training_command_takes_json_path(tiny, tmp_path, capsys):
    """--json PATH means the same everywhere: the run's result, also written there."""
    rows = tmp_path / "train.json"
    assert _run(capsys, "train", "--data", tiny, "--out", tmp_path / "t", *TINY, "--json",
                rows)[0] == 0
    result = json.loads(rows.read_text())
    assert result["iterations"] > 0 and result["setup"] == "prediction"
    for command in ("control", "hig", "pinn", "fit"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        assert "--json PATH" in capsys.readouterr().out, command


@pytest.mark.parametrize("command", ["train", "control", "hig", "pinn", "fit", "gradcheck",
                                     "study"])
def test_json_into_a_directory_is_refused_before_the_run(command, tmp_path, capsys):
    err = _one_line_error(capsys, command, "--json", tmp_path, command=command)
    assert f"argument --json: {tmp_path} is a directory; give a file, such as " in err
    assert not list(tmp_path.iterdir())


def test_a_run_too_large_for_memory_is_a_one_line_error(tmp_path, capsys, monkeypatch):
    import adjointsim.cli.control as control

    def huge(args):
        raise MemoryError("Unable to allocate 3.64 TiB for an array")

    monkeypatch.setattr(control, "run", huge)
    err = _one_line_error(capsys, "control", "quantum", "--out", tmp_path / "q",
                          command="control")
    assert err == ("adjointsim control: not enough memory (Unable to allocate 3.64 TiB for an "
                   "array); choose a smaller grid (--scene n=...), batch or ensemble\n")


def test_a_grid_beyond_numpys_largest_array_is_the_same_one_line_error(tmp_path, capsys):
    # numpy says "Maximum allowed size exceeded", naming no key, for a size it cannot index
    err = _one_line_error(capsys, "fit", "--demo", "ks-params", "--scene", f"n={10**30}",
                          "--out", tmp_path / "f", command="fit")
    assert err.startswith("adjointsim fit: not enough memory (ks1d-etdrk4 with {'n': 10000")
    assert "asks for arrays larger than numpy can index); choose a smaller grid" in err
    assert not (tmp_path / "f").exists()


@pytest.mark.parametrize("command", ["gradcheck", "bench", "fit", "data", "eval", "train",
                                     "control", "pinn", "hig"])
def test_every_command_that_runs_solvers_takes_threads(command, capsys):
    """A command that runs only solvers uses every core unless told; one that runs torch one
    thread, for torch and the solvers alike."""
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    solver_only = command in ("gradcheck", "bench", "fit", "data")
    expected = ("solver threads (default: every core" if solver_only
                else "threads of torch and of the solvers")
    assert "--threads THREADS" in text and expected in text, command


def test_threads_sets_the_solver_threads(capsys):
    from adjointsim import parallel

    try:
        assert main(["gradcheck", "cartpole", "--steps", "3", "--threads", "3"]) == 0
        assert parallel.threads() == 3
    finally:
        parallel.set_threads(None)
    assert main(["gradcheck", "cartpole", "--threads", "0"]) == 2
    assert "--threads: must be ≥ 1, not 0" in capsys.readouterr().err


def test_data_refuses_an_out_it_cannot_write_before_making_the_data(tmp_path, capsys,
                                                                  monkeypatch):
    from adjointsim.train import data

    def never(*args, **kwargs):
        raise AssertionError("the data were made before --out was checked")

    monkeypatch.setattr(data, "generate", never)
    blocker = tmp_path / "file"
    blocker.write_text("")
    err = _one_line_error(capsys, "data", "ks", "--size", "tiny", "--out", blocker / "ks.h5",
                          command="data")
    assert f"cannot make the folder {blocker} (" in err and "choose another --out" in err
