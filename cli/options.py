"""The options every command spells the same way, and typed flags made from a config dataclass.

``--out DIR`` the run directory, ``--resume`` / ``--overwrite`` what to do with a run already
there, ``--config FILE.toml`` a file of config keys (flags override it), ``--seed N``,
``--json PATH`` rows as JSON, ``--no-progress`` no progress bar, ``--threads N`` the threads
of the solvers (and of torch, in a command that trains).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any

from adjointsim.errors import DamagedFileError
from adjointsim.run import unwrap


def at_least(lo: int, hi: int | None = None) -> Callable[[str], int]:
    """An argparse type: an integer lo ≤ n (≤ hi)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < lo or (hi is not None and value > hi):
            bound = f"≥ {lo}" if hi is None else f"in [{lo}, {hi}]"
            raise argparse.ArgumentTypeError(f"must be {bound}, not {value}")
        return value

    return parse


def out_option(p: argparse.ArgumentParser, default: str) -> None:
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help=f"the run directory (default {default})")


def scene_option(p: argparse.ArgumentParser) -> None:
    """``--scene KEY=VALUE`` (repeatable): a scene parameter of the solver the command builds,
    over the ``[scene]`` table of ``--config``; the solver checks it."""
    p.add_argument("--scene", action="append", default=None, metavar="KEY=VALUE",
                   help="a scene parameter of the solver (dt, n, nu, ...), over the [scene] "
                   "table of --config; repeatable")


def scene_of(args: argparse.Namespace) -> dict | None:
    """The ``--scene`` flags as a table (None: none given)."""
    from adjointsim.run import scene_pairs

    return None if not args.scene else scene_pairs(args.scene)


def seed_option(p: argparse.ArgumentParser, default: int | None = 0) -> None:
    p.add_argument("--seed", type=at_least(0, 2**63 - 1), default=default,
                   help=f"random seed, ≥ 0 (default {default})")


def seeds_option(p: argparse.ArgumentParser) -> None:
    """``--seeds N [N ...]``: one run per seed, trained together as an ensemble."""
    p.add_argument("--seeds", type=at_least(0, 2**63 - 1), nargs="+", default=None,
                   metavar="N", help="train one run per seed, together as one ensemble, each "
                   "in --out/seedN (replaces --seed)")


def train_seeds(args: argparse.Namespace, cfg: Any, out: Path, what: str,
                train_members: Callable[..., list]) -> tuple[list, list]:
    """``--seeds``: ``cfg`` once per seed, each run in ``out/seedN``, trained as one ensemble
    (announced as ``what``) by ``train_members(cfgs, resume=, progress=, overwrite=)``;
    returns the members' configs and what each run returns."""
    from adjointsim.engine import run_errors, started
    from adjointsim.errors import UserError
    if args.seed is not None:
        raise UserError("--seed and --seeds: pass one")
    if len(set(args.seeds)) < len(args.seeds):
        raise UserError(f"--seeds {' '.join(map(str, args.seeds))} repeats a seed")
    cfgs = [dataclasses.replace(cfg, seed=s, out=str(out / f"seed{s}")) for s in args.seeds]
    # --resume continues the seeds that hold a run; one without (added, or its directory
    # deleted) starts fresh beside them
    if args.resume and not any(started(c.out) for c in cfgs):
        raise UserError(f"--resume: no seed in {out} holds a run to continue; run the command "
                        "without --resume to start them")
    print(f"{what}: an ensemble of {len(cfgs)} seeds", flush=True)
    with run_errors([Path(c.out) for c in cfgs]):
        results = train_members(cfgs, resume=args.resume, progress=args.progress,
                                 overwrite=args.overwrite)
    return cfgs, results


def resumed(args: argparse.Namespace, default_out: Callable[[], Path], problem: type,
            cls: type) -> dict | None:
    """With ``--resume``: the configuration the run to continue recorded (its ``config.json``
    in ``--out``, else in ``default_out()``; with ``--seeds``, the first member's there), for
    :meth:`~adjointsim.run.Config.load` to lay the flags given over. So ``--resume --out DIR``
    alone continues a run as it was started, and a flag beside it changes only its own key
    (the engine names a key that a run cannot change when continued). None without
    ``--resume``, or where no run is recorded (the engine then says so); a run of another
    command than ``problem`` (an engine Problem with configs ``cls``) is refused."""
    from adjointsim.engine import another_commands, same_command

    if not args.resume:
        return None
    out = args.out if args.out is not None else default_out()
    seeds = getattr(args, "seeds", None)
    for folder in [out / f"seed{s}" for s in seeds] if seeds else [out]:
        path = folder / "config.json"
        try:
            theirs = json.loads(path.read_text())
        except FileNotFoundError:
            continue
        except (OSError, ValueError, UnicodeDecodeError):
            theirs = None
        if not isinstance(theirs, dict):
            raise DamagedFileError(f"--resume: {path} is not a readable config (damaged?); "
                                   "restore it, or choose another --out")
        if not same_command(problem, (f.name for f in dataclasses.fields(cls)), theirs):
            raise another_commands(folder)
        return theirs
    return None


def run_config(args: argparse.Namespace, problem: type, cls: type, values: dict[str, Any],
               default_out: Callable[[Any], Path], fresh: tuple[str, ...] = ()) -> Any:
    """A command's config (``cls``, of the engine Problem ``problem``): the ``--config`` file,
    then the flags given (``values``, None for one not given), over the defaults, or with
    ``--resume`` over the run's recorded configuration (:func:`resumed`; ``default_out(config)``
    is where the run lives when ``--out`` is not given). The ``fresh`` keys hold for one
    invocation (a cap on its updates): they take their defaults, not the record's."""
    recorded = resumed(args, lambda: default_out(cls.load(args.config, **values)), problem, cls)
    if recorded is not None:
        recorded = {k: v for k, v in recorded.items() if k not in fresh}
    return cls.load(args.config, recorded=recorded, **values)


def resume_command(command: str, out: Path, args: argparse.Namespace | None) -> str:
    """The command line that continues the run in ``out`` (an ensemble's: with its seeds)."""
    seeds = getattr(args, "seeds", None)
    words = ["adjointsim", command, "--resume", "--out", str(out),
             *(["--seeds", *map(str, seeds)] if seeds else [])]
    return shlex.join(words)


def json_option(p: argparse.ArgumentParser, help_text: str = "also write the result rows "
                "here as JSON") -> None:
    p.add_argument("--json", type=_json_path, default=None, metavar="PATH", help=help_text)


def _json_path(text: str) -> Path:
    # checked before the run, not when its result is written at the end
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a directory; give a file, such as "
                                         f"{path / 'result.json'}")
    return path


def progress_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-progress", dest="progress", action="store_false",
                   help="no progress bar")


#: what ``--threads`` (or the config key ``threads``) sets in a command that runs torch
THREADS_HELP = ("threads of torch and of the solvers: the two take turns, each uses them all "
                "in its turn")
COMPILE_HELP = ("the update's loss eager (off) or through torch.compile with that backend: "
                "aot_eager gives the eager numbers to the bit, inductor generates code (faster "
                "updates, but a compile of seconds to minutes first; see the how-to on training "
                "through a solver)")


def threads_option(p: argparse.ArgumentParser, default: int | None = None) -> None:
    """``--threads N``: None for a command that runs only solvers (every core unless
    ``ADJOINTSIM_THREADS`` says otherwise), a count for one that runs torch."""
    text = (f"{THREADS_HELP} (default {default})" if default is not None else
            "solver threads (default: every core, or $ADJOINTSIM_THREADS when set)")
    p.add_argument("--threads", type=at_least(1), default=default, help=text)


def run_options(p: argparse.ArgumentParser, out_default: str, config: bool = True) -> None:
    """``--out``, ``--resume`` / ``--overwrite`` (one of them), ``--config``, ``--json`` and
    ``--no-progress``: what every training command takes (see :func:`write_result`)."""
    out_option(p, out_default)
    again = p.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true",
                       help="continue the run in --out from its checkpoint, with the "
                       "configuration it recorded: --resume --out DIR alone is enough, a flag "
                       "given beside it changes its key")
    again.add_argument("--overwrite", action="store_true",
                       help="discard the run already in --out and start again")
    if config:
        p.add_argument("--config", type=Path, default=None, metavar="FILE.toml",
                       help="config keys from a TOML file; flags override them")
    json_option(p, "also write the run's result here as JSON")
    progress_option(p)


def config_flags(p: argparse.ArgumentParser, cls: type, accepted: dict[str, Any],
                 skip: tuple[str, ...] = (), helps: dict[str, str] | None = None) -> None:
    """One ``--key`` flag per field of the config dataclass ``cls``: typed from its annotation,
    with the accepted choices or range from ``accepted`` and its default in the help. Unset
    flags are None, so a ``--config`` file's value stands unless a flag overrides it."""
    hints = typing.get_type_hints(cls)
    group = p.add_argument_group(f"{cls.__name__} keys (also accepted in --config)")
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        kind, _ = unwrap(hints[f.name])
        rule = accepted.get(f.name)
        default = (f.default if f.default is not dataclasses.MISSING
                   else f.default_factory())  # type: ignore[misc]
        text = (helps or {}).get(f.name, "")
        kwargs: dict[str, Any] = {"dest": f.name, "default": None}
        if isinstance(rule, tuple):
            kwargs["choices"] = rule
            kwargs["metavar"] = "{" + ",".join(map(str, rule)) + "}"
        elif rule is not None and not isinstance(rule, str):
            text = f"{text}; {rule}" if text else str(rule)
        if kind in (int, float, str):
            kwargs["type"] = _typed(kind)
        else:
            kwargs["type"] = str
        p_help = f"{text + '; ' if text else ''}default {default!r}"
        group.add_argument("--" + f.name.replace("_", "-"), help=p_help, **kwargs)


def _typed(kind: type) -> Callable[[str], Any]:
    def parse(text: str) -> Any:
        try:
            return kind(text)
        except ValueError:
            what = {int: "an integer", float: "a number"}.get(kind, kind.__name__)
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None

    parse.__name__ = kind.__name__
    return parse


def overrides(args: argparse.Namespace, cls: type) -> dict[str, Any]:
    """The config keys set on the command line (None: not given)."""
    return {f.name: getattr(args, f.name) for f in dataclasses.fields(cls)
            if getattr(args, f.name, None) is not None}


def write_result(args: argparse.Namespace, result: dict) -> None:
    """``--json PATH``: the run's result, as its ``result.json`` holds it."""
    if args.json is not None:
        from adjointsim.files import write_json

        write_json(args.json, result)
