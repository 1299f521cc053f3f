"""Reference trajectories: generation, atomic HDF5 files, validated loading, training windows.

A dataset file holds one group per split (``train``, ``interpolation``, ``extrapolation``) with
``trajectories`` (S, T, C, *coarse grid) float32, ``params`` (S,) and ``conditions`` (S,), and
the problem's configuration as attributes. Files are written to a temporary name and renamed, so
an interrupted run never leaves a half-written dataset behind.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
from tqdm.auto import tqdm

from .atomic import atomic_path
from .problems import Problem, get_problem

FORMAT_VERSION = 1


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
            g.create_dataset("trajectories", data=split.trajectories)
            g.create_dataset("params", data=split.params)
            g.create_dataset("conditions", data=split.conditions)
    return path


def load(path: str | Path) -> Dataset:
    """Read and validate a dataset file; a damaged file gets an error that says what to do."""
    path = Path(path)
    fix = f"delete it and regenerate it with `adjointsim data PROBLEM --out {path}`"
    if not path.exists():
        raise FileNotFoundError(f"no dataset at {path}; create it with `adjointsim data PROBLEM`")
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format_version") != FORMAT_VERSION:
                raise ValueError(
                    f"{path} has format version {f.attrs.get('format_version')}, expected "
                    f"{FORMAT_VERSION}; {fix}"
                )
            problem = get_problem(str(f.attrs["problem"]))
            size = str(f.attrs["size"])
            if json.loads(f.attrs["config"]) != _scene_config(problem, size):
                raise ValueError(
                    f"{path} was made with another configuration of the {problem.name!r} "
                    f"problem than this version's; {fix}"
                )
            splits = {}
            for name in problem.splits:
                g = f[name]
                split = Split(g["trajectories"][...], g["params"][...], g["conditions"][...])
                s = split.trajectories.shape[0]
                if split.params.shape != (s,) or split.conditions.shape != (s,):
                    raise ValueError(f"{path}: split {name!r} has inconsistent shapes; {fix}")
                if not np.all(np.isfinite(split.trajectories)):
                    raise ValueError(f"{path}: split {name!r} holds non-finite values; {fix}")
                splits[name] = split
            return Dataset(problem, size, int(f.attrs["seed"]), splits)
    except (OSError, KeyError) as e:
        raise ValueError(f"{path} is not a readable adjointsim dataset ({e}); {fix}") from None


def windows(split: Split, length: int, stride: int = 1) -> np.ndarray:
    """(trajectory, start frame) pairs of every window of ``length`` frames."""
    s, t = split.trajectories.shape[:2]
    if length > t:
        raise ValueError(f"windows of {length} frames do not fit trajectories of {t} frames")
    starts = np.arange(0, t - length + 1, stride)
    return np.stack(np.meshgrid(np.arange(s), starts, indexing="ij"), -1).reshape(-1, 2)
