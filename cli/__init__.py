"""The ``adjointsim`` command line: one module per command, each with ``arguments(parser)``
and ``run(args) -> int``, under one error boundary (:func:`main`).

It sits above both layers: the solvers (``adjointsim``) and the torch layer
(``adjointsim.train``). A command's module is imported only when that command runs, so
``adjointsim gradcheck`` never loads torch.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence

from adjointsim import __version__, registry
from adjointsim.compiling import announce_compiles
from adjointsim.engine import Saved
from adjointsim.errors import UserError
from adjointsim.files import stop_on_sigterm

from .options import resume_command

#: every command, its module under ``adjointsim.cli`` and its one line of help
COMMANDS: dict[str, tuple[str, str]] = {
    "gradcheck": ("gradcheck", "verify the discrete adjoints (dot-product, Taylor and "
                  "finite-difference tests)"),
    "fit": ("fit", "fit initial state, controls and coefficients to observations (HDF5) with "
            "the adjoints"),
    "data": ("data", "generate reference trajectories (HDF5) for training"),
    "train": ("train", "train a neural time-stepper through a solver (ONE/NOG/WIG or "
              "R/M/S/N/C, prediction/correction)"),
    "eval": ("evaluate", "evaluate a trained run: errors, correlation time, stability, plots, "
             "metrics.json"),
    "control": ("control", "train a controller through a simulator (cartpole, guidance, "
                "heat, quantum; R/M/S/N/C)"),
    "hig": ("hig", "train through a solver with half-inverse gradients, Gauss-Newton or Adam"),
    "pinn": ("pinn", "physics-informed training with loss balancing (inverse-Dirichlet, "
             "GradNorm, ReLoBRaLo, PCGrad, ConFIG, ...)"),
    "study": ("study", "a grid of runs on Dask: every study, the stability sweep included"),
    "bench": ("bench", "benchmarks: work-precision sweeps (error against run time)"),
}

#: one line and exit 2 for these; anything else (a bare KeyError too) is a bug and keeps its
#: traceback (``ADJOINTSIM_TRACEBACK=1`` shows it for these too)
USER_ERRORS = (UserError, ValueError, registry.UnknownSolverError, OSError)


class _Parser(argparse.ArgumentParser):
    """A parser whose mistakes are user errors: one line through :func:`main`, exit 2."""

    def error(self, message: str):  # type: ignore[override]
        raise UserError(f"{message} (see {self.prog} --help)")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The whole parser; only ``command``'s module is imported to fill in its options."""
    parser = _Parser(
        prog="adjointsim", description="Solvers with hand-written discrete adjoints, and "
        "training of neural networks through them.",
        epilog="adjointsim COMMAND --help shows a command's options.")
    parser.add_argument("--version", action="version", version=f"adjointsim {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == command:  # the others' modules stay unimported
            mod = importlib.import_module(f"{__name__}.{module}")
            mod.arguments(p)
            p.set_defaults(_command=mod.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """The one error boundary of every command: user errors print ``adjointsim CMD: message``
    and exit 2, Ctrl-C (or SIGTERM) exits 130 with how to continue, a closed pipe exits
    quietly, genuine bugs raise."""
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    if command is None and not {"-h", "--help", "--version"} & set(argv):
        build_parser().print_help(sys.stderr)
        return 2
    args = None
    try:
        try:
            args = build_parser(command).parse_args(argv)
        except UserError as e:  # the root parser reports a command's unknown options
            if command in COMMANDS:
                raise UserError(str(e).replace("(see adjointsim --help)",
                                               f"(see adjointsim {command} --help)")) from None
            raise
        if getattr(args, "progress", True) and not os.environ.get("TQDM_DISABLE"):
            announce_compiles()  # silenced with the progress bars whose stall it explains
        with stop_on_sigterm():  # `kill` or a scheduler's stop: a checkpoint, as Ctrl-C
            status = args._command(args)
        sys.stdout.flush()
        return status
    except BrokenPipeError:  # `adjointsim ... | head`: the reader has all it wants
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    except KeyboardInterrupt as e:
        hint = e.args[0] if e.args else "files are written atomically, so run the command again"
        if isinstance(e, Saved):  # the whole command, which needs none of the run's flags
            hint += f", or just: {resume_command(command, e.out, args)}"
        print(f"adjointsim {command}: interrupted; {hint}", file=sys.stderr)
        return 130
    except (*USER_ERRORS, MemoryError) as e:
        if os.environ.get("ADJOINTSIM_TRACEBACK"):
            raise
        message = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
        if isinstance(e, MemoryError):  # a grid, batch or ensemble too large for this machine
            message = (f"not enough memory ({message}); choose a smaller grid (--scene n=...), "
                       "batch or ensemble")
        print(f"adjointsim {command}: {' '.join(str(message).split())}", file=sys.stderr)
        return 2
