"""Reference trajectories: generation, atomic HDF5 files, validated loading, training windows.

A dataset file holds one group per split (``train``, ``interpolation``, ``extrapolation``) with
``trajectories`` (S, T, C, *coarse grid) float32, ``params`` (S,) and ``conditions`` (S,), and
the problem's configuration as attributes. Files are written to a temporary name and renamed, so
an interrupted run never leaves a half-written dataset behind.

Every dataset in the file carries HDF5's Fletcher-32 checksum, verified by HDF5 on every read: a
flipped bit is reported as a damaged file with the command that regenerates it. A file rewritten
through h5py passes its checksums (HDF5 recomputes them on write), so the file also holds the
SHA-256 digest of each attribute that defines the data and of each array, written with them and
compared on load (format version 3): an edited seed or trajectory is named. The metadata are
cross-checked too: the attributes against each other and this version's problems, and each
split's arrays against what the ``config`` attribute generates. Older files still load, with a
warning: format version 2 (no digests) and 1 (no checksums either).
"""

from __future__ import annotations

import hashlib
import json
import warnings
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
from tqdm.auto import tqdm

from adjointsim import validate
from adjointsim.errors import DamagedFileError, UserError
from adjointsim.files import atomic_path
from adjointsim.stepper import NonFiniteStateError

from .problems import PROBLEMS, Problem, get_problem

#: 3: SHA-256 digests of the defining attributes and the arrays (attribute ``digests``);
#: 2: Fletcher-32 checksums only; 1: neither (2 and 1 load with a warning)
FORMAT_VERSION = 3
#: the attributes that define a dataset's contents, each covered by a digest
DEFINING = ("problem", "size", "seed", "config")


@dataclass
class Split:
    trajectories: np.ndarray  # (S, T, C, *grid) float32
    params: np.ndarray  # (S,)
    conditions: np.ndarray  # (S,)


@dataclass
class Dataset:
    problem: Problem
    size: str
    seed: int
    splits: dict[str, Split]


def generate(
    problem: Problem | str, size: str = "quick", seed: int = 0, progress: bool = True
) -> Dataset:
    """Run the reference solver for every split and parameter; store the coarse-grid frames."""
    problem = get_problem(problem) if isinstance(problem, str) else problem
    if size not in problem.sizes:
        choices = sorted(problem.sizes)
        raise ValueError(f"unknown size {size!r} for {problem.name}; choose from {choices}")
    cfg = problem.sizes[size]
    frames = cfg["frames"]
    jobs = [(split, p) for split, params in problem.splits.items() for p in params]
    total = sum(problem.warmup_frames + frames for _ in jobs)
    bar = tqdm(total=total, desc=f"data {problem.name}/{size}", unit="frame", disable=not progress)
    out: dict[str, list] = {s: [] for s in problem.splits}
    for j, (split, param) in enumerate(jobs):
        rng = np.random.default_rng([seed, j])
        count = cfg["train_per_param"] if split == "train" else cfg["test_per_param"]
        solver = problem.reference(param)
        u = problem.initial_states(rng, param, count, split).astype(np.float64)
        try:
            for _ in range(problem.warmup_frames):
                u = solver.rollout(u, problem.substeps)
                bar.update()
            traj = np.empty((frames, *problem.to_coarse(u).shape), dtype=np.float32)
            for t in range(frames):
                traj[t] = problem.to_coarse(u)
                u = solver.rollout(u, problem.substeps)
                bar.update()
        except NonFiniteStateError as e:
            # A rare initial state the reference scheme cannot carry at this step size: the
            # data of a seed are all or nothing, so say which seed and let the user pick one.
            bar.close()
            raise UserError(f"seed {seed}: the {problem.name} reference solver blew up on "
                            f"{split} trajectory {j} (parameter {param}): {e}; generate the "
                            "data with another --seed") from None
        out[split].append((np.swapaxes(traj, 0, 1), param, problem.condition(param)))
    bar.close()
    splits = {
        s: Split(
            np.concatenate([t for t, _, _ in items]),
            np.concatenate([np.full(len(t), p) for t, p, _ in items]),
            np.concatenate([np.full(len(t), c) for t, _, c in items]),
        )
        for s, items in out.items()
    }
    return Dataset(problem, size, seed, splits)


def _scene_config(problem: Problem, size: str) -> dict:
    """What the trajectories depend on beyond the seed, stored with them as metadata (the
    scene's keys where they differ from the problem's defaults)."""
    scene = {k: v for k, v in problem.scene.items() if v != problem.SCENE[k]}
    return {
        "splits": {k: list(v) for k, v in problem.splits.items()},
        "warmup_frames": problem.warmup_frames,
        "substeps": problem.substeps,
        "sizes": problem.sizes[size],
        **({"scene": scene} if scene else {}),
    }


def save(dataset: Dataset, path: str | Path) -> Path:
    """Write atomically: to a temporary file beside ``path``, then rename over it."""
    path = Path(path)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["problem"] = dataset.problem.name
        f.attrs["size"] = dataset.size
        f.attrs["seed"] = dataset.seed
        f.attrs["config"] = json.dumps(_scene_config(dataset.problem, dataset.size))
        digests = {key: _attribute_digest(f.attrs[key]) for key in DEFINING}
        for name, split in dataset.splits.items():
            g = f.create_group(name)
            for key in ARRAYS:
                a = getattr(split, key)
                # One chunk (and checksum) per trajectory: HDF5's automatic chunks split the
                # grid and read about 2x slower.
                chunks = (1, *a.shape[1:]) if a.ndim > 1 else a.shape
                d = g.create_dataset(key, data=a, fletcher32=True, chunks=chunks)
                digests[f"{name}/{key}"] = _array_digest(d[...])
        f.attrs["digests"] = json.dumps(digests)
    return path


def _attribute_digest(value: object) -> str:
    """SHA-256 of an attribute's value as h5py reads it back (a NumPy scalar as its number)."""
    value = value.item() if isinstance(value, np.generic) else value
    return hashlib.sha256(json.dumps(value).encode()).hexdigest()


def _array_digest(a: np.ndarray) -> str:
    """SHA-256 of an array's type, shape and values."""
    digest = hashlib.sha256(f"{a.dtype.str} {a.shape}".encode())
    digest.update(np.ascontiguousarray(a).data)
    return digest.hexdigest()


ARRAYS = ("trajectories", "params", "conditions")


def load(path: str | Path) -> Dataset:
    """Read and validate a dataset file; a damaged file gets an error that says what to do.

    Beyond the checksums, which catch damage on disk but not a file rewritten through h5py, the
    attributes are checked against each other and the arrays against the ``config`` attribute:
    every split must hold the trajectories, parameters and conditions that config generates."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no dataset at {path}; create it with {_command(path)}")
    fix = _regenerate(path)
    try:
        with h5py.File(path, "r") as f:
            version, problem, size, seed, config = _metadata(f, path)
            fix = _regenerate(path, problem.name, size, seed)
            if version == 1:
                warnings.warn(f"{path} predates checksums (format version 1), so damage to it "
                              f"cannot be detected; to get them, {fix}", stacklevel=2)
            elif version == 2:
                warnings.warn(f"{path} predates content digests (format version 2), so an edit "
                              f"of its seed or trajectories cannot be detected; to get them, "
                              f"{fix}", stacklevel=2)
            digests = _digests(f, path, version, fix, _regenerate(path, problem.name, size, "N"))
            splits = {}
            for name in problem.splits:
                if name not in f:
                    raise DamagedFileError(f"{path} has no split {name!r}; {fix}")
                arrays = []
                for key in ARRAYS:
                    if key not in f[name]:
                        raise DamagedFileError(f"{path} has no {name}/{key}; {fix}")
                    d = f[name][key]
                    if version >= 2 and not d.fletcher32:
                        raise DamagedFileError(f"{path}: {name}/{key} has no checksum; {fix}")
                    try:
                        arrays.append(d[...])
                    except OSError:  # HDF5's checksum failed (or the chunk is unreadable)
                        raise DamagedFileError(
                            f"{path} is damaged: the checksum of {name}/{key} does not match "
                            f"its contents (a flipped bit on disk or an edited file); {fix}"
                        ) from None
                split = Split(*arrays)
                _check_split(path, name, split, problem, config, fix)
                if not np.all(np.isfinite(split.trajectories)):
                    raise DamagedFileError(f"{path}: split {name!r} holds non-finite values; {fix}")
                for key, a in zip(ARRAYS, arrays):
                    if digests is not None and _array_digest(a) != digests.get(f"{name}/{key}"):
                        raise DamagedFileError(
                            f"{path}: {name}/{key} is not what the file was written with (its "
                            f"digest differs: edited after writing); {fix}")
                splits[name] = split
            return Dataset(problem, size, seed, splits)
    except (OSError, KeyError) as e:
        raise DamagedFileError(
            f"{path} is not a readable adjointsim dataset ({e}); {fix}"
        ) from None


def _digests(f: h5py.File, path: Path, version: int, fix: str, seed_fix: str) -> dict | None:
    """The digests a file of format version 3 was written with (None for an older file), once
    its defining attributes are checked against them. ``seed_fix`` says how to regenerate the
    file when its seed was edited (the one thing the command cannot know then)."""
    if version < 3:
        return None
    text = f.attrs.get("digests")
    try:
        digests = json.loads(text) if isinstance(text, str) else None
    except ValueError:
        digests = None
    if not isinstance(digests, dict):
        raise DamagedFileError(f"{path} has no readable `digests` attribute; {fix}")
    for key in DEFINING:
        if _attribute_digest(f.attrs[key]) != digests.get(key):
            raise DamagedFileError(f"{path}: its `{key}` attribute is {_short(_show(f.attrs[key]))}"
                                   ", not what the file was written with (its digest differs: "
                                   f"edited after writing); {seed_fix if key == 'seed' else fix}")
    return digests


def _short(text: str) -> str:
    return text if len(text) <= 60 else text[:57] + "..."


def _command(path: Path, problem: str = "PROBLEM", size: str = "SIZE", seed: int | str = 0) -> str:
    """The command that writes the dataset ``path``; placeholders for what is not known."""
    seed_flag = f" --seed {seed}" if seed else ""
    return f"`adjointsim data {problem} --size {size}{seed_flag} --out {path}`"


def _regenerate(path: Path, problem: str = "PROBLEM", size: str = "SIZE",
                seed: int | str = 0) -> str:
    fix = f"delete it and regenerate it with {_command(path, problem, size, seed)}"
    return fix + (" (N: the seed it was made with)" if seed == "N" else "")


def _show(value: object) -> str:
    """An attribute's value as a user reads it (h5py gives NumPy scalars)."""
    return repr(value.item() if isinstance(value, np.generic) else value)


def _is_integer(value: object) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _attribute(f: h5py.File, key: str, path: Path, fix: str, kind: type) -> object:
    if key not in f.attrs:
        raise DamagedFileError(f"{path} has no `{key}` attribute; {fix}")
    value = f.attrs[key]
    if not isinstance(value, kind):
        raise DamagedFileError(
            f"{path}: its `{key}` attribute is {_show(value)}, not a {kind.__name__}; {fix}"
        )
    return value


def _made_with(config: object) -> tuple[str, str] | None:
    """The (problem, size) whose configuration ``config`` is in this version, if any."""
    if isinstance(config, dict):  # any scene: the problem checks it
        config = {k: v for k, v in config.items() if k != "scene"}
    for problem in PROBLEMS.values():
        for size in problem.sizes:
            if config == _scene_config(problem, size):
                return problem.name, size
    return None


def _metadata(f: h5py.File, path: Path) -> tuple[int, Problem, str, int, dict]:
    """The format version, problem, size, seed and configuration a dataset file's attributes
    name, after checking them against each other and against this version's problems."""
    fix = _regenerate(path)
    version = f.attrs.get("format_version")
    if not _is_integer(version) or version not in (1, 2, FORMAT_VERSION):
        raise UserError(
            f"{path} has format version {_show(version)}, expected {FORMAT_VERSION}; {fix}"
        )
    name = _attribute(f, "problem", path, fix, str)
    size = _attribute(f, "size", path, fix, str)
    # What the regenerating command can name: only a problem and size it accepts.
    which = (
        name if name in PROBLEMS else "PROBLEM",
        size if name in PROBLEMS and size in PROBLEMS[name].sizes else "SIZE",
    )
    fix = _regenerate(path, *which)
    if "seed" not in f.attrs:
        raise DamagedFileError(f"{path} has no `seed` attribute; {fix}")
    seed = f.attrs["seed"]
    if not _is_integer(seed) or seed < 0:
        raise DamagedFileError(
            f"{path}: its `seed` attribute is {_show(seed)}, not an integer ≥ 0; "
            f"{_regenerate(path, *which, 'N')}"
        )
    seed = int(seed)
    fix = _regenerate(path, *which, seed)
    text = _attribute(f, "config", path, fix, str)
    try:
        config = json.loads(text)
    except ValueError as e:
        raise DamagedFileError(f"{path}: its `config` attribute is not JSON ({e}); {fix}") from None
    made = _made_with(config)
    if made is not None and made != (name, size):
        edited = " and ".join(
            f"its `{key}` attribute is {value!r}"
            for key, value, original in (("problem", name, made[0]), ("size", size, made[1]))
            if value != original
        )
        raise DamagedFileError(
            f"{path}: {edited} but its `config` attribute is that of the {made[0]!r} problem at "
            f"size {made[1]!r}: the file was edited; {_regenerate(path, *made, seed)}"
        )
    if name not in PROBLEMS:
        raise DamagedFileError(
            f"{path}: its `problem` attribute is {name!r}, not one of {sorted(PROBLEMS)}; {fix}"
        )
    problem = PROBLEMS[name]
    if size not in problem.sizes:
        raise DamagedFileError(
            f"{path}: its `size` attribute is {size!r}, not a size of the {name!r} problem "
            f"({', '.join(sorted(problem.sizes))}); {fix}"
        )
    if made is None:
        raise UserError(
            f"{path} was made with another configuration of the {name!r} problem than this "
            f"version's; {fix}"
        )
    return int(version), get_problem(name, config.get("scene")), size, seed, config


def _check_split(
    path: Path, name: str, split: Split, problem: Problem, config: dict, fix: str
) -> None:
    """Refuse a split whose arrays are not what the ``config`` attribute generates."""
    params = config["splits"][name]
    sizes = config["sizes"]
    count = sizes["train_per_param"] if name == "train" else sizes["test_per_param"]
    rows = count * len(params)
    traj = split.trajectories
    if traj.ndim != problem.dims + 3 or traj.shape[:2] != (rows, sizes["frames"]):
        raise DamagedFileError(
            f"{path}: {name}/trajectories has shape {traj.shape}, but its `config` attribute "
            f"makes ({rows}, {sizes['frames']}, ...) (trajectories, frames, channels, *grid); "
            f"{fix}"
        )
    expected = {
        "params": np.repeat(np.asarray(params, dtype=np.float64), count),
        "conditions": np.repeat([problem.condition(p) for p in params], count),
    }
    for key, want in expected.items():
        got = getattr(split, key)
        if got.shape != want.shape or not np.array_equal(got, want):
            values = ", ".join(f"{v:g}" for v in np.unique(want))
            raise DamagedFileError(
                f"{path}: {name}/{key} does not match its `config` attribute, which makes "
                f"{count} trajectory(ies) for each of the {key} {values}; {fix}"
            )


def windows(split: Split, length: int, stride: int = 1) -> np.ndarray:
    """(trajectory, start frame) pairs of every window of ``length`` ≥ 1 frames, starting
    every ``stride`` ≥ 1 frames."""
    validate.integer("windows", "length", length, ge=1)
    validate.integer("windows", "stride", stride, ge=1)
    s, t = split.trajectories.shape[:2]
    if length > t:
        raise UserError(f"windows of {length} frames (unroll + warmup + 1) do not fit the "
                        f"dataset's {t}-frame trajectories: unroll + warmup can be at most {t - 1}")
    starts = np.arange(0, t - length + 1, stride)
    return np.stack(np.meshgrid(np.arange(s), starts, indexing="ij"), -1).reshape(-1, 2)
