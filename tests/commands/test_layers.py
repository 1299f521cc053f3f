"""The house's structure: one installed name, layers that only point down, one command line."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

import adjointsim
from adjointsim.cli import COMMANDS, main

ROOT = Path(adjointsim.__file__).resolve().parent.parent
CORE = ROOT / "adjointsim"


def _imports(path: Path) -> set[str]:
    """Every module a file imports (relative imports resolved against its package)."""
    tree = ast.parse(path.read_text())
    parts = path.relative_to(ROOT).with_suffix("").parts[:-1]
    if parts and parts[0] in ("train", "nets", "cli"):  # installed inside adjointsim
        parts = ("adjointsim", *parts)
    package = ".".join(parts)
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                found.add(".".join([*base, node.module] if node.module else base))
            else:
                found.add(node.module)
    return found


def test_the_core_imports_neither_torch_nor_the_layers_above_it():
    offenders = {
        str(path.relative_to(ROOT)): sorted(m for m in _imports(path)
                                            if m.split(".")[0] == "torch"
                                            or m.startswith(("adjointsim.train", "adjointsim.cli",
                                                             "adjointsim.nets")))
        for path in CORE.rglob("*.py")
    }
    assert not {k: v for k, v in offenders.items() if v}


def test_importing_every_core_module_loads_no_torch():
    code = ("import importlib, pkgutil, sys, adjointsim\n"
            "for m in pkgutil.walk_packages(adjointsim.__path__, 'adjointsim.'):\n"
            "    if m.name.split('.')[1] not in ('train', 'nets', 'cli'):\n"
            "        importlib.import_module(m.name)\n"
            "assert 'torch' not in sys.modules, 'torch was imported'\n")
    subprocess.run([sys.executable, "-c", code], check=True, cwd="/")


def test_nothing_imports_the_bare_folder_names():
    for folder in ("adjointsim", "train", "nets", "cli", "tests", "benchmarks"):
        for path in (ROOT / folder).rglob("*.py"):
            bare = {m for m in _imports(path) if m.split(".")[0] in ("train", "nets", "cli")}
            assert not bare, f"{path.relative_to(ROOT)} imports {bare}"


def test_a_users_own_train_py_and_nets_folder_break_nothing(tmp_path):
    """A script of one's own named train.py beside a folder nets/ (the most common names in
    deep learning) still finds the torch layer."""
    (tmp_path / "nets").mkdir()
    (tmp_path / "nets" / "__init__.py").write_text("MINE = True\n")
    (tmp_path / "train.py").write_text(
        "from adjointsim.train.bridge import rollout\n"
        "from adjointsim.nets import ResNet\n"
        "import nets\n"
        "assert nets.MINE and callable(rollout) and ResNet\n"
        "print('ok')\n")
    proc = subprocess.run([sys.executable, "train.py"], cwd=tmp_path, capture_output=True,
                          text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "ok"


def test_help_lists_every_command_with_one_line(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "250")
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    out = " ".join(capsys.readouterr().out.split())
    for name, (_, text) in COMMANDS.items():
        assert f"{name} {' '.join(text.split())}" in out, name


@pytest.mark.parametrize("argv", [[], ["no-such-command"]])
def test_no_command_or_a_typo_lists_every_command(capsys, argv):
    try:
        code = main(argv)
    except SystemExit as e:
        code = e.code
    assert code == 2
    err = capsys.readouterr().err
    assert all(name in err for name in COMMANDS)


def test_version(capsys):
    with pytest.raises(SystemExit):
        main(["--version"])
    assert capsys.readouterr().out.strip() == f"adjointsim {adjointsim.__version__}"


def test_every_command_is_a_module_with_arguments_and_run(capsys):
    import importlib

    for name, (module, _) in COMMANDS.items():
        mod = importlib.import_module(f"adjointsim.cli.{module}")
        assert callable(mod.arguments) and callable(mod.run), name
        with pytest.raises(SystemExit) as e:
            main([name, "--help"])
        assert e.value.code == 0, name
    capsys.readouterr()


def test_a_closed_pipe_exits_quietly():
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.run(f"{sys.executable} -m adjointsim.cli gradcheck --list | head -1",
                          shell=True, capture_output=True, text=True, env=env)
    assert proc.stdout.strip() and proc.stderr == ""
