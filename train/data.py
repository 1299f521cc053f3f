"""Reference trajectories: generation, atomic HDF5 files, validated loading, training windows.

A dataset file holds one group per split (``train``, ``interpolation``, ``extrapolation``) with
``trajectories`` (S, T, C, *coarse grid) float32, ``params`` (S,) and ``conditions`` (S,), and
the problem's configuration as attributes. Files are written to a temporary name and renamed, so
an interrupted run never leaves a half-written dataset behind.

Every dataset in the file carries HDF5's Fletcher-32 checksum (format version 2), verified by
HDF5 on every read: a flipped bit is reported as a damaged file with the command that
regenerates it. Files of format version 1 (no checksums) still load, with a warning.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
from tqdm.auto import tqdm

from adjointsim.errors import DamagedFileError, UserError
from adjointsim.files import atomic_path

from .problems import Problem, get_problem

#: 2: every dataset has a Fletcher-32 checksum; 1: none (loaded with a warning)
FORMAT_VERSION = 2


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
        for _ in range(problem.warmup_frames):
            u = solver.rollout(u, problem.substeps)
            bar.update()
        traj = np.empty((frames, *problem.to_coarse(u).shape), dtype=np.float32)
        for t in range(frames):
            traj[t] = problem.to_coarse(u)
            u = solver.rollout(u, problem.substeps)
            bar.update()
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
    """What the trajectories depend on beyond the seed, stored with them as metadata."""
    return {
        "splits": {k: list(v) for k, v in problem.splits.items()},
        "warmup_frames": problem.warmup_frames,
        "substeps": problem.substeps,
        "sizes": problem.sizes[size],
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
        for name, split in dataset.splits.items():
            g = f.create_group(name)
            for key in ARRAYS:
                a = getattr(split, key)
                # One chunk (and checksum) per trajectory: HDF5's automatic chunks split the
                # grid and read about 2x slower.
                chunks = (1, *a.shape[1:]) if a.ndim > 1 else a.shape
                g.create_dataset(key, data=a, fletcher32=True, chunks=chunks)
    return path


ARRAYS = ("trajectories", "params", "conditions")


def load(path: str | Path) -> Dataset:
    """Read and validate a dataset file; a damaged file gets an error that says what to do."""
    path = Path(path)
    fix = f"delete it and regenerate it with `adjointsim data PROBLEM --out {path}`"
    if not path.exists():
        raise FileNotFoundError(f"no dataset at {path}; create it with `adjointsim data PROBLEM`")
    try:
        with h5py.File(path, "r") as f:
            version = f.attrs.get("format_version")
            if version not in (1, FORMAT_VERSION):
                raise UserError(
                    f"{path} has format version {version}, expected {FORMAT_VERSION}; {fix}"
                )
            problem = get_problem(str(f.attrs["problem"]))
            size = str(f.attrs["size"])
            seed = int(f.attrs["seed"])
            seed_flag = f" --seed {seed}" if seed else ""
            fix = (f"delete it and regenerate it with `adjointsim data {problem.name} --size "
                   f"{size}{seed_flag} --out {path}`")
            if json.loads(f.attrs["config"]) != _scene_config(problem, size):
                raise UserError(
                    f"{path} was made with another configuration of the {problem.name!r} "
                    f"problem than this version's; {fix}"
                )
            if version == 1:
                warnings.warn(f"{path} predates checksums (format version 1), so damage to it "
                              f"cannot be detected; to get them, {fix}", stacklevel=2)
            splits = {}
            for name in problem.splits:
                arrays = []
                for key in ARRAYS:
                    d = f[name][key]
                    if version == FORMAT_VERSION and not d.fletcher32:
                        raise DamagedFileError(f"{path}: {name}/{key} has no checksum; {fix}")
                    try:
                        arrays.append(d[...])
                    except OSError:  # HDF5's checksum failed (or the chunk is unreadable)
                        raise DamagedFileError(
                            f"{path} is damaged: the checksum of {name}/{key} does not match "
                            f"its contents (a flipped bit on disk or an edited file); {fix}"
                        ) from None
                split = Split(*arrays)
                s = split.trajectories.shape[0]
                if split.params.shape != (s,) or split.conditions.shape != (s,):
                    raise DamagedFileError(f"{path}: split {name!r} has inconsistent shapes; {fix}")
                if not np.all(np.isfinite(split.trajectories)):
                    raise DamagedFileError(f"{path}: split {name!r} holds non-finite values; {fix}")
                splits[name] = split
            return Dataset(problem, size, seed, splits)
    except (OSError, KeyError) as e:
        raise DamagedFileError(
            f"{path} is not a readable adjointsim dataset ({e}); {fix}"
        ) from None


def windows(split: Split, length: int, stride: int = 1) -> np.ndarray:
    """(trajectory, start frame) pairs of every window of ``length`` frames."""
    s, t = split.trajectories.shape[:2]
    if length > t:
        raise UserError(f"windows of {length} frames (unroll + warmup + 1) do not fit the "
                        f"dataset's {t}-frame trajectories: unroll + warmup can be at most {t - 1}")
    starts = np.arange(0, t - length + 1, stride)
    return np.stack(np.meshgrid(np.arange(s), starts, indexing="ij"), -1).reshape(-1, 2)
