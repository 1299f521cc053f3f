"""Built-in solvers. Importing this package imports every module in it, and each module
registers its steppers with :func:`adjointsim.registry.register`: adding a solver means adding a
module here, nothing else."""

import importlib
import pkgutil

for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")
