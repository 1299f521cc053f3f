"""Built-in solvers. Each module registers its steppers on import."""

from . import ftcs  # noqa: F401
