"""What the tests of every layer share. The tests are laid out by layer: ``core/`` (the
solvers, their adjoints and checks, fitting, the study runner; no torch needed),
``training/`` (the torch layer and the networks) and ``commands/`` (the command line and the
package's structure)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# Some tests run the benchmark scripts (benchmarks/threads.py, benchmarks/torch_spectral.py),
# which import one another by their bare names.
sys.path.insert(0, str(ROOT / "benchmarks"))
# Two test workers share the machine's cores: one solver thread each unless a test says more.
os.environ.setdefault("ADJOINTSIM_THREADS", "1")


@pytest.fixture(scope="session")
def tiny(tmp_path_factory) -> Path:
    """A tiny KS dataset (seconds to make), shared by every test that trains."""
    from adjointsim.train import data as datamod

    path = tmp_path_factory.mktemp("data") / "ks-tiny.h5"
    datamod.save(datamod.generate("ks", "tiny", seed=0, progress=False), path)
    return path


@pytest.fixture
def figures(monkeypatch) -> list:
    """The figures the package saves while a test runs, laid out and drawn as they are saved
    (every module that took ``save_figure`` from ``adjointsim.files`` is patched)."""
    from adjointsim import files

    plt = files.pyplot()
    saved: list = []
    real = files.save_figure

    def capture(fig, path, dpi=110):
        real(fig, path, dpi)  # lays out, writes and closes: the objects stay readable
        fig.canvas.draw()
        saved.append(fig)

    for module in list(sys.modules.values()):
        if getattr(module, "save_figure", None) is real:
            monkeypatch.setattr(module, "save_figure", capture)
    yield saved
    for fig in saved:
        plt.close(fig)
