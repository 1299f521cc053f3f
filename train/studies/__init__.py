"""The studies run by ``adjointsim study NAME``. Each module here registers its studies with
:func:`adjointsim.runner.register_study` when imported; :func:`load_all` imports every one (and
the solver-only ``stability`` sweep of :mod:`adjointsim.stability`), so adding a study means
adding a module here, nothing else."""

import importlib
import pkgutil


def load_all() -> None:
    importlib.import_module("adjointsim.stability")
    for module in pkgutil.iter_modules(__path__):
        importlib.import_module(f"{__name__}.{module.name}")
