"""What the tests of every layer share. The tests are laid out by layer: ``core/`` (the
solvers, their adjoints and checks, fitting, the study runner; no torch needed),
``training/`` (the torch layer and the networks) and ``commands/`` (the command line and the
package's structure)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# The NumPy references in benchmarks/numpy_ref are what several solvers are tested against.
sys.path.insert(0, str(ROOT / "benchmarks"))


@pytest.fixture(scope="session")
def tiny(tmp_path_factory) -> Path:
    """A tiny KS dataset (seconds to make), shared by every test that trains."""
    from adjointsim.train import data as datamod

    path = tmp_path_factory.mktemp("data") / "ks-tiny.h5"
    datamod.save(datamod.generate("ks", "tiny", seed=0, progress=False), path)
    return path
