"""MkDocs hooks: the pages that are generated from the code, and the source tree the API
reference reads.

- ``solvers.md`` and ``cli.md`` hold a marker that is replaced, at build time, by the solver
  catalogue (from the registry) and by the ``--help`` of every command (from the parsers), so
  neither can fall behind the code.
- mkdocstrings reads the sources statically (griffe), and griffe finds packages by their
  folders: ``adjointsim.train``, ``adjointsim.nets`` and ``adjointsim.cli`` live in ``train/``,
  ``nets/`` and ``cli/`` (setuptools' ``package-dir``), which no folder layout on disk shows.
  So the build reads a temporary tree of symbolic links that has the installed layout.
"""

from __future__ import annotations

import argparse
import atexit
import functools
import inspect
import re
import shutil
import sys
import tempfile
from pathlib import Path

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parent.parent
#: fixed width of the CLI reference, whatever terminal runs the build
HELP_WIDTH = 80
CATALOGUE_MARKER = "<!-- solver-catalogue -->"
COMMANDS_MARKER = "<!-- cli-reference -->"
#: the theme's text column fits about 75 characters of code at a laptop's width; the examples
#: and the help texts are up to 100 wide, and solver names must not break at their hyphens
STYLESHEET = "assets/stylesheets/adjointsim.css"
CSS = """\
.md-grid { max-width: 1600px; }
.md-typeset table:not([class]) td:first-child code,
.md-typeset table:not([class]) td:last-child code { white-space: nowrap; }
.md-typeset code .nobreak { white-space: nowrap; }
"""

#: test files that run over every registered solver, and what they verify there
REGISTRY_WIDE_TESTS = (
    ("tests/core/test_properties.py",
     "dot-product, Taylor and finite-difference checks of state, controls and every parameter "
     "on drawn scenes"),
    ("tests/core/test_contract.py", "the contract's edges and binomial checkpointing"),
    ("tests/core/test_scene_validation.py", "validation of every constructor argument"),
    ("tests/core/test_reverse_inputs.py", "non-finite inputs refused by the reverse sweep"),
    ("tests/training/test_bridge.py", "torch's gradcheck through the bridge"),
)


# ----------------------------------------------------------------------- the API source tree
def _installed_layout() -> Path:
    """A temporary folder ``adjointsim/`` whose entries link to the core's files and to the
    three folders installed inside it."""
    tmp = Path(tempfile.mkdtemp(prefix="adjointsim-docs-"))
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)
    pkg = tmp / "adjointsim"
    pkg.mkdir()
    for entry in (ROOT / "adjointsim").iterdir():
        if entry.name != "__pycache__":
            (pkg / entry.name).symlink_to(entry)
    for folder in ("train", "nets", "cli"):
        (pkg / folder).symlink_to(ROOT / folder)
    return tmp


# Before mkdocstrings' own on_config, which creates the Python handler with its paths.
@event_priority(100)
def on_config(config, **kwargs):
    handlers = config.plugins["mkdocstrings"].config.handlers
    python = handlers.setdefault("python", {})
    python["paths"] = [str(_installed_layout())]
    config.extra_css.append(STYLESHEET)
    _every_result_in_the_nav(config.nav)
    return config


def _every_result_in_the_nav(nav: list) -> None:
    """Each page under ``docs/results/`` that the Results section of ``mkdocs.yml`` does not
    name joins it, titled by its first heading (else its file name): a study's page committed
    without a nav entry is still reachable from the menu."""
    section = next(item["Results"] for item in nav if isinstance(item, dict) and "Results" in item)
    named = {next(iter(entry.values())) for entry in section if isinstance(entry, dict)}
    for page in sorted((ROOT / "docs" / "results").rglob("*.md")):
        path = page.relative_to(ROOT / "docs").as_posix()
        if path not in named:
            heading = re.search(r"^# (.+)$", page.read_text(encoding="utf-8"), re.M)
            title = heading[1].strip() if heading else page.stem.replace("-", " ").capitalize()
            section.append({title: path})


def on_files(files, config, **kwargs):
    files.append(File.generated(config, STYLESHEET, content=CSS))
    return files


# ----------------------------------------------------------------------- solver catalogue
def _first_paragraph(text: str | None) -> str:
    return inspect.cleandoc(text or "").split("\n\n")[0].replace("\n", " ").strip()


def _summary(cls) -> str:
    """The class's own docstring, else its module's (where one module holds a family)."""
    own = cls.__dict__.get("__doc__")
    return _first_paragraph(own or sys.modules[cls.__module__].__doc__)


def _tests_naming(cls, tests: dict[str, str]) -> list[str]:
    """Test files that name the solver or its class, plus the one named after its module."""
    stem = cls.__module__.rsplit(".", 1)[-1]
    by_class = re.compile(rf"\b{re.escape(cls.__name__)}\b")
    wide = {path for path, _ in REGISTRY_WIDE_TESTS}
    return sorted(
        path for path, text in tests.items()
        if path not in wide and (f'"{cls.name}"' in text or f"'{cls.name}'" in text
                                 or by_class.search(text) or Path(path).stem == f"test_{stem}"))


def solver_catalogue() -> str:
    import adjointsim

    tests = {str(p.relative_to(ROOT)): p.read_text(encoding="utf-8")
             for p in sorted((ROOT / "tests").rglob("test_*.py"))}
    wide = [(path, what) for path, what in REGISTRY_WIDE_TESTS if path in tests]
    names = adjointsim.names()
    rows, sections = [], []
    for name in names:
        cls = adjointsim.get(name)
        scene = cls.default()
        summary = _summary(cls)
        params = ", ".join(f"`{k}` = {v:g}" for k, v in scene.params.items()) or "none"
        controls = ("none" if scene.control_shape is None
                    else f"`(n, B, {', '.join(map(str, scene.control_shape))})`")
        own = _tests_naming(cls, tests)
        rows.append(f"| [`{name}`](#{name}) | {_escape(summary)} | {controls} |")
        sections += [
            f"### {name}", "",
            summary, "",
            f"- class: `{cls.__module__}.{cls.__name__}`",
            f"- state of the default scene: `(B, {', '.join(map(str, scene.state_shape(1)[1:]))})`",
            f"- parameters of the default scene: {params}",
            f"- controls per rollout: {controls}",
            "- tests of this solver: " + (", ".join(f"`{p}`" for p in own) or "none besides the "
                                          "registry-wide ones above"),
            "",
        ]
    out = [f"{len(names)} registered solvers (`adjointsim.names()`).", "",
           "| solver | what | controls |", "|---|---|---|", *rows, "",
           "## Verification", "",
           "No check runs while this page is built. These test files run every registered "
           "solver in the test suite (`python3 -m pytest`), and `adjointsim gradcheck --all` "
           "runs the same three adjoint checks from the command line:", ""]
    out += [f"- `{path}`: {what}" for path, what in wide]
    out += ["", "Each solver below also names the test files written for it.", "",
            "## Solvers", "", *sections]
    return "\n".join(out)


def _escape(text: str) -> str:
    # Table cells: a bare | would end the cell.
    return text.replace("|", "\\|")


# ----------------------------------------------------------------------- CLI reference
def command_help(name: str) -> str:
    """``adjointsim NAME --help`` as printed at a fixed width."""
    from adjointsim.cli import build_parser

    parser = build_parser(name)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    p = sub.choices[name]
    p.formatter_class = functools.partial(p.formatter_class, width=HELP_WIDTH)
    return p.format_help()


def cli_reference() -> str:
    from adjointsim.cli import COMMANDS, build_parser

    top = build_parser()
    top.formatter_class = functools.partial(top.formatter_class, width=HELP_WIDTH)
    out = ["## adjointsim", "", "```text", top.format_help().rstrip(), "```", ""]
    for name, (_, help_text) in COMMANDS.items():
        out += [f"## {name}", "", help_text[0].upper() + help_text[1:] + ".", "",
                "```text", command_help(name).rstrip(), "```", ""]
    return "\n".join(out)


# ----------------------------------------------------------------------- page hooks
def on_page_markdown(markdown: str, page, **kwargs):
    if CATALOGUE_MARKER in markdown:
        markdown = markdown.replace(CATALOGUE_MARKER, solver_catalogue())
    if COMMANDS_MARKER in markdown:
        markdown = markdown.replace(COMMANDS_MARKER, cli_reference())
    return markdown


#: Sphinx roles (:class:`X`) in the docstrings; Markdown shows them as text before the code
_ROLE = re.compile(r":(?:class|meth|func|attr|mod|data|exc|obj):(?=<code)")


#: a reST literal-block marker ("the fast path::") ending a paragraph of a docstring: Markdown
#: shows the code block below it as it is and the second colon as text
_LITERAL_MARKER = re.compile(r"(?<=\w)::(?=</p>)")
#: inline code (not a code block's); browsers break a line after a hyphen, also inside code,
#: which splits an option such as --threads into "-" and "-threads"
_INLINE_CODE = re.compile(r"(?<!<pre>)(?<!</span>)<code>([^<]*)</code>")
_HYPHENATED = re.compile(r"[^\s]*-[^\s]*")


def _unbroken(match: re.Match) -> str:
    """Inline code whose hyphenated words (options, paths, solver names) never break."""
    inner = _HYPHENATED.sub(lambda m: f'<span class="nobreak">{m.group()}</span>', match[1])
    return f"<code>{inner}</code>"


def on_page_content(content: str, page, **kwargs):
    content = _LITERAL_MARKER.sub(":", _ROLE.sub("", content))
    return _INLINE_CODE.sub(_unbroken, content)

