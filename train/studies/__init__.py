"""The studies run by ``adjointsim study NAME``. Each module here registers its studies with
:func:`adjointsim.runner.register_study` when imported; :func:`load_all` imports every one, and
the solver-only studies of the core (the ``stability`` sweep of :mod:`adjointsim.stability`,
the ``fit-params`` table of :mod:`adjointsim.fit_study`, the ``smoke`` optimisation of
:mod:`adjointsim.smoke_study`), so adding a study means adding a module here, nothing else.
:func:`load` registers one study with what it needs alone, so a study of the core starts
without importing torch."""

import importlib
import pkgutil

#: the core's studies: they need no torch, and register themselves like the modules here
CORE_STUDIES = ("adjointsim.stability", "adjointsim.fit_study", "adjointsim.smoke_study")


def load_all() -> None:
    for module in CORE_STUDIES:
        importlib.import_module(module)
    for module in pkgutil.iter_modules(__path__):
        importlib.import_module(f"{__name__}.{module.name}")


def load(name: str) -> None:
    """Register the study ``name`` with what it needs alone: a study of the core (or one
    registered already) without importing torch, any other (or an unknown name, whose error
    lists every study) by :func:`load_all`."""
    from adjointsim.runner import get_study

    for module in CORE_STUDIES:
        importlib.import_module(module)
    try:
        get_study(name)
    except ValueError:
        load_all()
