"""The words a user reads agree with the code: ``study --help`` and the studies how-to list
every registered study, ``train --help`` says what each of its keys does, and a result of a
tiny size says that it only checks the pipeline."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from adjointsim.cli import main
from adjointsim.cli.study import STUDIES, TINY_NOTE

DOCS = Path(__file__).resolve().parents[2] / "docs"


def _registered() -> set[str]:
    """Every registered study, asked of a fresh process (tests register studies of their own in
    this one): an unknown name's error lists them."""
    code = ("from adjointsim import runner\n"
            "from adjointsim.train.studies import load_all\n"
            "load_all()\n"
            "try:\n"
            "    runner.get_study('no such study')\n"
            "except ValueError as e:\n"
            "    print(str(e).split('choose from', 1)[1])\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out, "an unknown study was found"
    return set(re.findall(r"'([^']+)'", out))


def test_study_help_and_the_howto_list_every_study(capsys):
    registered = _registered()
    assert set(STUDIES) == registered, sorted(registered ^ set(STUDIES))
    text = _help("study", capsys)
    howto = (DOCS / "howto" / "studies.md").read_text(encoding="utf-8")
    for name in registered:
        assert re.search(rf"^  {re.escape(name)} ", text, re.M), name
        assert f"| `{name}` |" in howto, name


def _help(command: str, capsys) -> str:
    try:
        main([command, "--help"])
    except SystemExit:
        pass
    return capsys.readouterr().out


def test_train_help_says_what_each_key_does(capsys):
    text = " ".join(_help("train", capsys).split())
    for flag in ("--correction", "--stride", "--warmup", "--truncate", "--rollback",
                 "--spike-factor", "--unroll", "--checkpoint-every"):
        described = re.search(rf"{flag} (?:\{{[^}}]*\}}|[A-Z_]+) (.*?)default", text)
        assert described and re.search(r"[a-z]{3}", described[1].split(";")[0]), flag


def test_a_tiny_result_says_it_only_checks_the_pipeline(tmp_path, capsys):
    assert main(["hig", "chain", "--size", "tiny", "--max-updates", "1", "--no-progress",
                 "--out", str(tmp_path / "run")]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == TINY_NOTE
