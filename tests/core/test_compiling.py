"""The word while kernels compile: said once on stderr when kernels are not in numba's
on-disk cache, not at all when they are, and only by commands that show progress."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

import adjointsim.cli
from adjointsim.cli import main
from adjointsim.compiling import NOTICE

# two small kernels: one word for both
TWO_KERNELS = """
import numpy as np
from numba import njit
from adjointsim.compiling import announce_compiles
from adjointsim.tridiagonal import transpose

@njit(cache=False)
def not_ours(x):
    return x + 1

announce_compiles()
announce_compiles()  # a second call adds no second listener
not_ours(1)  # numba compiling a function outside adjointsim: nothing said
transpose(np.zeros((3, 4)))
transpose(np.zeros((3, 4), dtype=np.float32))
"""


def _run(cache) -> str:
    proc = subprocess.run([sys.executable, "-c", TWO_KERNELS], capture_output=True, text=True,
                          env={**os.environ, "NUMBA_CACHE_DIR": str(cache)})
    assert proc.returncode == 0, proc.stderr
    return proc.stderr


def test_said_once_while_compiling_and_not_once_cached(tmp_path):
    assert _run(tmp_path).count(NOTICE) == 1
    assert any(tmp_path.rglob("*.nbi"))  # the kernels went to this cache
    assert NOTICE not in _run(tmp_path)


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
