"""What CI runs (.ci/run): the README's install and test commands, then the core tests once
more where torch cannot be imported, which the core tests must pass: they import nothing of
torch, nor of the torch layer and the networks."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
NO_TORCH = ROOT / "tests" / "no_torch"
#: the core tests' files: the tests, the helpers they import and the NumPy references (the
#: fixtures of tests/conftest.py that train import the torch layer when a test asks for them)
CORE_TESTS = [*sorted((ROOT / "tests" / "core").glob("*.py")),
              *sorted((ROOT / "tests" / "references").glob("*.py"))]


def _run_without_torch(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(NO_TORCH)}
    return subprocess.run([sys.executable, *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout)


def test_ci_runs_the_readme_commands():
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text()
    commands = [line for line in ci.splitlines() if line.startswith("python3 -m")]
    assert commands, "no commands in .ci/run"
    for line in commands:
        assert line in readme, f".ci/run runs {line!r}, which the README does not show"


def test_ci_runs_the_core_tests_once_more_without_torch():
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert 'PYTHONPATH="$PWD/tests/no_torch" python3 -m pytest tests/core' in ci
    code = ("import importlib.util, subprocess, sys\n"
            "assert importlib.util.find_spec('torch') is None\n"
            "for name in ('torch', 'torch.nn', 'adjointsim.nets'):\n"
            "    try:\n"
            "        __import__(name)\n"
            "    except ModuleNotFoundError:\n"
            "        continue\n"
            "    raise AssertionError(f'{name} was imported')\n"
            # nor can the processes the tests start (test and Dask workers, commands)
            "child = subprocess.run([sys.executable, '-c', 'import torch'], capture_output=True,"
            " text=True)\n"
            "assert 'ModuleNotFoundError' in child.stderr, child.stderr\n")
    proc = _run_without_torch("-c", code)
    assert proc.returncode == 0, proc.stderr


def _torch_layer(module: str) -> bool:
    parts = module.split(".")
    return parts[0] == "torch" or parts[:2] in (["adjointsim", "train"], ["adjointsim", "nets"])


def test_no_core_test_imports_torch_or_the_layers_above_the_core():
    """Anywhere in the file, in a function too (collecting the core tests without torch, below,
    finds what they import through the package at import time, the CI run the rest)."""
    found = []
    for path in CORE_TESTS:
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                names = [node.module, *(f"{node.module}.{a.name}" for a in node.names)]
            else:
                continue
            found += [f"{path.relative_to(ROOT)}:{node.lineno}: {name}" for name in names
                      if _torch_layer(name)]
    assert not found, "the core tests import torch or its layers:\n" + "\n".join(found)


def test_the_core_tests_are_collected_without_torch():
    proc = _run_without_torch("-m", "pytest", "tests/core", "--collect-only", "-q", "-n", "0",
                              "-p", "no:cacheprovider")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
