"""No module reaches into another module's private names: the package (adjointsim/, train/,
nets/, cli/) and the benchmarks import no ``_name`` of a module of ours and use no
``module._name`` of a module (or of anything) they imported from one. What a module keeps
private can then change without breaking another; what others need is public and documented."""

from __future__ import annotations

import ast
from pathlib import Path

import adjointsim

ROOT = Path(adjointsim.__file__).resolve().parent.parent
#: folder -> the package it is installed as (the benchmarks are scripts, not installed)
PACKAGES = {"adjointsim": "adjointsim", "train": "adjointsim.train", "nets": "adjointsim.nets",
            "cli": "adjointsim.cli", "benchmarks": ""}
#: the benchmarks import one another by their bare names, and the tests' NumPy references
BENCHMARKS = {p.stem for p in (ROOT / "benchmarks").glob("*.py")}


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _ours(module: str) -> bool:
    top = module.split(".")[0]
    return top in ("adjointsim", "tests") or top in BENCHMARKS


def reach_ins(source: str, package: str) -> list[tuple[int, str]]:
    """``(line, what)`` for each private name of ours that ``source``, a module of ``package``
    ("" for a script), imports or uses through a name it imported."""
    tree = ast.parse(source)
    imported: set[str] = set()  # the local names bound to modules or objects of ours
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1])
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module or ""
            if not _ours(module):
                continue
            for alias in node.names:
                if _private(alias.name):
                    found.append((node.lineno, f"from {module} import {alias.name}"))
                imported.add(alias.asname or alias.name)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if _ours(alias.name):
                    imported.add(alias.asname or alias.name.split(".")[0])
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _private(node.attr):
            base = node.value
            while isinstance(base, ast.Attribute):
                base = base.value
            if isinstance(base, ast.Name) and base.id in imported:
                found.append((node.lineno, ast.unparse(node)))
    return sorted(found)


def _package_of(path: Path) -> str:
    """The package a file's relative imports resolve against."""
    folder, *inner = path.relative_to(ROOT).parent.parts
    return ".".join(p for p in (PACKAGES[folder], *inner) if p)


def test_no_module_uses_another_modules_private_names():
    found = [f"{path.relative_to(ROOT)}:{line}: {what}"
             for folder in PACKAGES for path in sorted((ROOT / folder).rglob("*.py"))
             for line, what in reach_ins(path.read_text(encoding="utf-8"), _package_of(path))]
    assert not found, "private names used across modules:\n" + "\n".join(found)


def test_the_scan_finds_imports_and_uses_of_private_names():
    source = (
        "import adjointsim.train.control as control\n"
        "from adjointsim import runner\n"
        "from adjointsim.train.trainer import _claim, TrainConfig\n"
        "from .ensemble import _update\n"
        "from numpy import _globals\n"
        "import threads\n"
        "control._finish(run)\n"
        "runner._STUDIES.clear()\n"
        "TrainConfig._fields\n"
        "threads._rows()\n"
        "self._state, run._x, control.__name__, control.public()\n"
    )
    assert reach_ins(source, "adjointsim.train") == [
        (3, "from adjointsim.train.trainer import _claim"),
        (4, "from adjointsim.train.ensemble import _update"),
        (7, "control._finish"), (8, "runner._STUDIES"), (9, "TrainConfig._fields"),
        (10, "threads._rows")]
