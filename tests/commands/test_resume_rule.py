"""One claim rule for every command that writes a run: ``train``, ``control``, ``hig``,
``pinn`` and ``fit`` go through the same sequence on their tiniest settings and answer it the
same way (exit status and the words of the one-line error):

a fresh run finishes and writes config.json and result.json; the same command again is refused
(a finished run: another --out, or --overwrite); ``--resume`` returns the finished result as it
is; a changed key that cannot be resumed is refused with ``--resume``, named; ``--overwrite``
starts again under the changed key; ``--resume`` on an empty directory says there is no run to
continue; ``--resume --overwrite`` is refused."""

from __future__ import annotations

import json

import pytest

from adjointsim.cli import main

#: each command's tiniest run (everything but --out), and a key of it that --resume cannot
#: change: (flag, new value, config key)
COMMANDS = {
    "train": (["train", "--data", "{tiny}", "--setup", "prediction", "--width", "2", "--blocks",
               "1", "--unroll", "2", "--batch", "4", "--stride", "8", "--epochs", "1"],
              ("--lr", "0.002", "lr")),
    "control": (["control", "cartpole", "--epochs", "1", "--train", "4", "--test", "4",
                 "--batch", "4", "--dtype", "float64"],
                ("--lr", "0.002", "lr")),
    "hig": (["hig", "chain", "--size", "tiny", "--max-updates", "2"],
            ("--seed", "1", "seed")),
    "pinn": (["pinn", "poisson", "--width", "6", "--depth", "2", "--collocation", "40",
              "--edge-points", "6", "--log-every", "2", "--epochs", "2"],
             ("--width", "5", "width")),
    "fit": (["fit", "--demo", "burgers-nu", "--maxiter", "2", "--no-plots"],
            ("--tikhonov", "0.5", "tikhonov")),
}


def _call(capsys, argv: list) -> tuple[int, str]:
    """The exit status and what went to stderr."""
    code = main([str(a) for a in argv])
    return code, capsys.readouterr().err


def _refused(capsys, argv: list, command: str) -> str:
    """The one-line error of a refused call (exit 2, no traceback)."""
    code, err = _call(capsys, argv)
    assert code == 2, err
    assert err.startswith(f"adjointsim {command}: ") and err.count("\n") == 1, err
    return err


@pytest.mark.parametrize("command", list(COMMANDS))
def test_every_command_follows_the_one_resume_rule(command, tiny, tmp_path, capsys):
    argv, (flag, value, key) = COMMANDS[command]
    base = [a.format(tiny=tiny) for a in argv] + ["--no-progress"]
    out = tmp_path / "run"
    args = [*base, "--out", out]

    # (a) a fresh run finishes and writes its config and result
    code, err = _call(capsys, args)
    assert code == 0, err
    assert (out / "config.json").is_file() and (out / "result.json").is_file()
    result = (out / "result.json").read_bytes()
    stamp = (out / "result.json").stat().st_mtime_ns

    # (b) the same command again is refused, saying how to go on
    err = _refused(capsys, args, command)
    assert "finished run" in err and "--overwrite" in err, err

    # (c) --resume returns the finished result as it is
    code, err = _call(capsys, [*args, "--resume"])
    assert code == 0, err
    assert (out / "result.json").read_bytes() == result
    assert (out / "result.json").stat().st_mtime_ns == stamp

    # (d) a key --resume cannot change is refused, named, and the run stays as it was
    changed = [*args, flag, value]
    err = _refused(capsys, [*changed, "--resume"], command)
    assert f"differs in {key}" in err, err
    assert (out / "result.json").read_bytes() == result

    # (e) --overwrite starts again, under the changed key
    code, err = _call(capsys, [*changed, "--overwrite"])
    assert code == 0, err
    assert str(json.loads((out / "config.json").read_text())[key]) == value
    assert (out / "result.json").stat().st_mtime_ns != stamp

    # (f) --resume on an empty directory: nothing to continue
    empty = tmp_path / "empty"
    empty.mkdir()
    err = _refused(capsys, [*base, "--out", empty, "--resume"], command)
    assert "holds no run to continue" in err, err
    assert not any(empty.iterdir())

    # (g) --resume with --overwrite is refused
    err = _refused(capsys, [*args, "--resume", "--overwrite"], command)
    assert "--resume" in err and "--overwrite" in err, err
