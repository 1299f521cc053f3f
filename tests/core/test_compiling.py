"""The word while kernels compile: said once on stderr when kernels are not in numba's
on-disk cache, not at all when they are (which commands say it: tests/commands/
test_compiling_notice.py)."""

from __future__ import annotations

import os
import subprocess
import sys

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


