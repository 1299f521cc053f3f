"""The documentation site: `mkdocs build --strict` passes, the generated pages name every
solver and every command, the results page links every committed result, and every Python
example written into the pages runs."""

from __future__ import annotations

import html
import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import adjointsim
from adjointsim.cli import COMMANDS

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
#: the pages written by hand (solvers.md and cli.md are completed at build time; the committed
#: results, with the pages that report them, are under docs/results/, one folder per study)
PAGES = ["index.md", "concepts.md", "solvers.md", "cli.md", "api.md", "results.md",
         *sorted(str(p.relative_to(DOCS)) for p in (DOCS / "howto").glob("*.md"))]


def _missing(*modules: str) -> list[str]:
    out = []
    for module in modules:
        try:
            found = importlib.util.find_spec(module) is not None
        except ModuleNotFoundError:  # its parent package is missing
            found = False
        if not found:
            out.append(module)
    return out


MISSING = _missing("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python")
needs_mkdocs = pytest.mark.skipif(
    bool(MISSING), reason=f"the site's build tools are not installed ({', '.join(MISSING)}); "
    'python3 -m pip install -e ".[docs]" installs them')


def text_of(page: Path) -> str:
    """A built page's text, without its markup."""
    return html.unescape(re.sub(r"<[^>]+>", "", page.read_text(encoding="utf-8")))


@needs_mkdocs
def test_the_site_builds_strictly_and_names_every_solver_and_command(tmp_path):
    # One build for every check: under xdist, separate tests could each build the site.
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir",
         str(tmp_path)],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert proc.returncode == 0, f"mkdocs build --strict failed:\n{proc.stdout}\n{proc.stderr}"

    solvers = text_of(tmp_path / "solvers" / "index.html")
    missing = [name for name in adjointsim.names() if name not in solvers]
    assert not missing, f"solvers missing from the catalogue: {missing}"
    assert f"{len(adjointsim.names())} registered solvers" in solvers

    cli = text_of(tmp_path / "cli" / "index.html")
    missing = [name for name in COMMANDS if f"usage: adjointsim {name}" not in cli]
    assert not missing, f"commands missing from the CLI reference: {missing}"

    api = (tmp_path / "api" / "index.html").read_text(encoding="utf-8")
    for anchor in ("adjointsim.stepper.Stepper.vjp", "adjointsim.registry.get",
                   "adjointsim.check.check_stepper", "adjointsim.fit.fit",
                   "adjointsim.engine.run", "adjointsim.run.Config", "adjointsim.runner.run",
                   "adjointsim.train.bridge.rollout",
                   "adjointsim.train.unroll.GradientFlow",
                   "adjointsim.train.hig.HalfInverseGradients",
                   "adjointsim.train.weighting.Weighting", "adjointsim.nets.ResNet"):
        assert f'id="{anchor}"' in api, f"the API reference lacks {anchor}"
    # a docstring's reST literal-block marker shows as text
    literal = re.findall(r".{40}\w::(?!\w).{20}", text_of(tmp_path / "api" / "index.html"))
    assert not literal, f"a literal '::' in the API reference: {literal}"

    # every page is in the navigation, and no option in inline code can break at its hyphen
    assert "not included in the \"nav\"" not in proc.stdout + proc.stderr, proc.stderr
    for page in sorted(tmp_path.rglob("*.html")):
        html_text = page.read_text(encoding="utf-8")
        for code in re.findall(r"(?<!<pre>)(?<!</span>)<code>(.*?)</code>", html_text, re.S):
            bare = re.sub(r'<span class="nobreak">[^<]*</span>', "", code)
            assert "--" not in re.sub(r"<[^>]+>", "", bare), (page, code)


RESULT_SUFFIXES = {".png", ".json", ".txt", ".csv", ".md"}


def test_the_results_page_links_every_committed_result():
    page = (DOCS / "results.md").read_text(encoding="utf-8")
    linked = set(re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", page))
    results = {p.relative_to(DOCS).as_posix() for p in (DOCS / "results").rglob("*")
               if p.is_file() and p.suffix in RESULT_SUFFIXES}
    missing = sorted(results - linked)
    assert not missing, f"docs/results.md does not link these committed results: {missing}"
    broken = sorted(link for link in linked if link.startswith("results/")
                    and not (DOCS / link).is_file())
    assert not broken, f"docs/results.md links files that do not exist: {broken}"
    # A result written straight into docs/ would sit among the pages, unlinked from its study.
    loose = sorted(p.name for p in DOCS.iterdir()
                   if p.is_file() and p.suffix in RESULT_SUFFIXES
                   and p.name not in {*PAGES, "results-notes.md"})
    assert not loose, f"these belong under docs/results/<study>/, not in docs/: {loose}"


def python_blocks() -> list:
    """Every ```python block of the hand-written pages, except the included example scripts
    (their own tests run them)."""
    cases = []
    for page in PAGES:
        source = (DOCS / page).read_text(encoding="utf-8")
        blocks = re.findall(r"^```python\n(.*?)^```", source, flags=re.S | re.M)
        for i, code in enumerate(blocks):
            if "--8<--" not in code:
                cases.append(pytest.param(code, id=f"{page}-{i}"))
    return cases


@pytest.mark.parametrize("code", python_blocks())
def test_the_python_in_the_pages_runs(code, capsys):
    # capsys keeps the blocks' prints out of the test output
    exec(compile(code, "<docs>", "exec"), {"__name__": "__docs__"})


def command_lines() -> list:
    """Every `adjointsim ...` line of the ```bash blocks of the hand-written pages."""
    cases = []
    for page in PAGES:
        source = (DOCS / page).read_text(encoding="utf-8")
        for block in re.findall(r"^```bash\n(.*?)^```", source, flags=re.S | re.M):
            for line in block.splitlines():
                line = line.split("#", 1)[0].strip()
                for command in line.split("&&"):
                    command = command.strip()
                    if command.startswith("adjointsim "):
                        cases.append(pytest.param(command, id=f"{page}: {command}"))
    return cases


@pytest.mark.parametrize("line", command_lines())
def test_the_commands_in_the_pages_parse(line):
    from adjointsim.cli import build_parser

    argv = line.split()[1:]
    build_parser(argv[0]).parse_args(argv)
