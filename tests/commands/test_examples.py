"""The scripts under examples/ run as a user runs them: each with ``--tiny``, in a fresh process
whose working directory is empty, exits 0, prints its ``result:`` line and leaves the directory
empty (runs go to a temporary directory unless ``--out`` says otherwise)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
SCRIPTS = ("custom_solver", "correction_ks", "cartpole_controller", "pinn_poisson", "inverse_fit")


def test_every_example_is_tested():
    assert sorted(p.stem for p in EXAMPLES.glob("*.py")) == sorted(SCRIPTS)


@pytest.mark.parametrize("name", SCRIPTS)
def test_example_runs_tiny(name, tmp_path):
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / f"{name}.py"), "--tiny"], cwd=tmp_path,
        capture_output=True, text=True, timeout=300,
        env={**os.environ, "TQDM_DISABLE": "1", "MPLBACKEND": "Agg"},
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "\nresult: " in "\n" + proc.stdout, proc.stdout
    assert list(tmp_path.iterdir()) == [], "an example wrote into its working directory"
