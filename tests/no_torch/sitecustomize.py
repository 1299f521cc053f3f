"""Torch made unimportable, for the run of the core tests that shows the core needs no torch:

    PYTHONPATH="$PWD/tests/no_torch" python3 -m pytest tests/core

Python imports ``sitecustomize`` at start-up from the first folder of its path that holds one,
and ``PYTHONPATH`` passes this folder to every process the run starts (test workers, Dask
workers, the commands tests run), so none of them can import torch. This file takes the place
of an installation's own ``sitecustomize`` for that run.
"""

import sys

# None in sys.modules is the import system's own "not there": `import torch` (and of any
# torch.* module) raises ModuleNotFoundError, importlib.util.find_spec("torch") answers None.
sys.modules["torch"] = None
