"""Which commands say the word while kernels compile: those that show progress, armed before
they refuse bad input, and not with --no-progress or TQDM_DISABLE; and a real command says it
once cold and not at all warm."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

import adjointsim.cli
from adjointsim.cli import main
from adjointsim.compiling import NOTICE


@pytest.mark.parametrize("argv, env, said", [
    (["gradcheck", "--list"], {}, True),
    (["fit"], {}, True),  # refused (no scene), after the word was armed
    (["fit", "--no-progress"], {}, False),
    (["gradcheck", "--list"], {"TQDM_DISABLE": "1"}, False),
])
def test_commands_that_show_progress_say_it(monkeypatch, capsys, tmp_path, argv, env, said):
    calls = []
    monkeypatch.setattr(adjointsim.cli, "announce_compiles", lambda: calls.append(1))
    monkeypatch.delenv("TQDM_DISABLE", raising=False)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    main([*argv, *(["--out", str(tmp_path / "fit")] if argv[0] == "fit" else [])])
    assert bool(calls) == said



@pytest.mark.slow
def test_a_command_says_it_once_cold_and_not_warm(tmp_path):
    """The real thing: a gradient check compiles a dozen kernels (about a minute cold)."""
    def gradcheck() -> str:
        proc = subprocess.run(
            [sys.executable, "-m", "adjointsim.cli", "gradcheck", "diffusion1d-ftcs", "--steps",
             "2"], capture_output=True, text=True,
            env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)})
        assert proc.returncode == 0, proc.stderr
        return proc.stderr

    assert gradcheck().count(NOTICE) == 1
    assert NOTICE not in gradcheck()

