"""Dataset files: damaged or edited metadata or arrays are refused with the file, the attribute
or array and a command that regenerates the file (one the command line accepts)."""

import argparse
import json
import re
import shlex
import shutil

import h5py
import numpy as np
import pytest

from adjointsim.cli import data as data_command
from adjointsim.errors import DamagedFileError
from adjointsim.train import data as datamod
from adjointsim.train.problems import get_problem

#: what the messages write in place of what they cannot know
PLACEHOLDERS = {"PROBLEM": "ks", "SIZE": "tiny", "N": "3"}


def _suggested_commands(message: str) -> list[argparse.Namespace]:
    """Each `adjointsim data ...` command a message suggests, parsed by the command's own parser
    (placeholders filled in), after checking that it can make the problem at that size."""
    commands = re.findall(r"`adjointsim data ([^`]*)`", message)
    assert commands, f"no command suggested in: {message}"
    parsed = []
    for command in commands:
        parser = argparse.ArgumentParser(exit_on_error=False)
        data_command.arguments(parser)
        words = [PLACEHOLDERS.get(w, w) for w in shlex.split(command)]
        args = parser.parse_args(words)
        assert args.size in get_problem(args.problem).sizes, command
        parsed.append(args)
    return parsed


def _damaged(tiny, tmp_path, edit) -> str:
    """The message loading a copy of the tiny dataset raises once ``edit(file)`` has run."""
    path = tmp_path / "damaged.h5"
    shutil.copy(tiny, path)
    with h5py.File(path, "a") as f:
        edit(f)
    with pytest.raises(DamagedFileError) as info:
        datamod.load(path)
    message = str(info.value)
    assert message.startswith(f"{path}"), message
    for args in _suggested_commands(message):
        assert args.out == path
    return message


def _set(key, value):
    def edit(f):
        f.attrs[key] = value

    return edit


def test_a_config_attribute_that_is_not_json_is_named(tiny, tmp_path):
    message = _damaged(tiny, tmp_path, _set("config", '{"splits": {"train": [0.9,'))
    assert "its `config` attribute is not JSON" in message
    (args,) = _suggested_commands(message)
    assert (args.problem, args.size, args.seed) == ("ks", "tiny", 0)


@pytest.mark.parametrize("problem", ["kolmogorov", "heat"])
def test_a_problem_attribute_changed_to_another_problem_is_named(tiny, tmp_path, problem):
    message = _damaged(tiny, tmp_path, _set("problem", problem))
    assert (f"its `problem` attribute is {problem!r} but its `config` attribute is that of the "
            "'ks' problem at size 'tiny'") in message
    (args,) = _suggested_commands(message)
    assert (args.problem, args.size) == ("ks", "tiny")


def test_a_size_attribute_changed_is_named(tiny, tmp_path):
    message = _damaged(tiny, tmp_path, _set("size", "huge"))
    assert ("its `size` attribute is 'huge' but its `config` attribute is that of the 'ks' "
            "problem at size 'tiny'") in message


def test_unknown_problem_and_size_with_an_unknown_config_get_placeholders(tiny, tmp_path):
    def edit(f):
        f.attrs["problem"] = "heat"
        f.attrs["config"] = "{}"

    message = _damaged(tiny, tmp_path, edit)
    assert "its `problem` attribute is 'heat', not one of ['karman', 'kolmogorov', 'ks']" in message
    assert "`adjointsim data PROBLEM --size SIZE --out" in message

    def edit(f):
        f.attrs["size"] = "huge"
        f.attrs["config"] = "{}"

    message = _damaged(tiny, tmp_path, edit)
    assert ("its `size` attribute is 'huge', not a size of the 'ks' problem "
            "(full, quick, tiny)") in message


@pytest.mark.parametrize("seed", [2.5, 0.0, "zero", -1, True, np.array([0, 1])])
def test_a_seed_that_is_not_an_integer_is_named(tiny, tmp_path, seed):
    message = _damaged(tiny, tmp_path, _set("seed", seed))
    assert "its `seed` attribute is" in message and "not an integer ≥ 0" in message
    (args,) = _suggested_commands(message)
    assert (args.problem, args.size) == ("ks", "tiny")
    assert "--seed N" in message and "N: the seed it was made with" in message


@pytest.mark.parametrize("key", ["problem", "size", "seed", "config", "format_version"])
def test_a_missing_attribute_is_named(tiny, tmp_path, key):
    def edit(f):
        del f.attrs[key]

    path = tmp_path / "damaged.h5"
    shutil.copy(tiny, path)
    with h5py.File(path, "a") as f:
        edit(f)
    with pytest.raises(ValueError) as info:
        datamod.load(path)
    message = str(info.value)
    if key == "format_version":  # a file of another format: not damaged, just not ours
        assert "has format version None" in message
    else:
        assert isinstance(info.value, DamagedFileError)
        assert f"has no `{key}` attribute" in message
    _suggested_commands(message)


def _rewrite(f, name, key, values):
    """Replace a dataset as h5py would: with a checksum that matches the new contents."""
    old = f[name][key]
    chunks = (1, *values.shape[1:]) if values.ndim > 1 else values.shape
    del f[name][key]
    f[name].create_dataset(key, data=values.astype(old.dtype), fletcher32=True, chunks=chunks)


@pytest.mark.parametrize("split", ["train", "extrapolation"])
@pytest.mark.parametrize("key", ["params", "conditions"])
def test_split_parameters_that_the_config_does_not_generate_are_refused(tiny, tmp_path, split,
                                                                         key):
    def edit(f):
        values = f[split][key][...]
        values[0] = values[-1]  # a parameter of the same split: plausible, but not the config's
        _rewrite(f, split, key, values)

    message = _damaged(tiny, tmp_path, edit)
    assert f"{split}/{key} does not match its `config` attribute" in message
    assert "checksums" not in message


def test_a_split_with_trajectories_the_config_does_not_make_is_refused(tiny, tmp_path):
    def fewer(f):
        for key in datamod.ARRAYS:
            _rewrite(f, "interpolation", key, f["interpolation"][key][:-1])

    message = _damaged(tiny, tmp_path, fewer)
    assert "interpolation/trajectories has shape (1, 24, 1, 48)" in message
    assert "its `config` attribute makes (2, 24, ...)" in message

    def shorter(f):
        _rewrite(f, "train", "trajectories", f["train/trajectories"][:, :10])

    message = _damaged(tiny, tmp_path, shorter)
    assert "train/trajectories has shape (6, 10, 1, 48)" in message


def test_a_missing_split_is_named(tiny, tmp_path):
    def edit(f):
        del f["extrapolation"]

    assert "has no split 'extrapolation'" in _damaged(tiny, tmp_path, edit)

    def edit(f):
        del f["train/conditions"]

    assert "has no train/conditions" in _damaged(tiny, tmp_path, edit)


def test_an_edited_seed_is_named_and_the_seed_left_to_the_user(tiny, tmp_path):
    """A plausible seed (7 for 0) passes every check of the metadata: only its digest tells."""
    message = _damaged(tiny, tmp_path, _set("seed", 7))
    assert ("its `seed` attribute is 7, not what the file was written with (its digest "
            "differs: edited after writing)") in message
    (args,) = _suggested_commands(message)
    assert (args.problem, args.size) == ("ks", "tiny")
    assert "--seed N" in message and "N: the seed it was made with" in message


def test_a_config_attribute_rewritten_is_named(tiny, tmp_path):
    def edit(f):
        f.attrs["config"] = json.dumps(json.loads(f.attrs["config"]), indent=1)

    message = _damaged(tiny, tmp_path, edit)
    assert "its `config` attribute is '{\\n" in message and "edited after writing" in message
    (args,) = _suggested_commands(message)
    assert (args.problem, args.size, args.seed) == ("ks", "tiny", 0)


@pytest.mark.parametrize("name", ["train", "extrapolation"])
def test_trajectories_rewritten_through_h5py_are_named(tiny, tmp_path, name):
    """HDF5 recomputes the checksums of a rewritten array; its digest is the file's own."""
    def edit(f):
        values = f[name]["trajectories"][...]
        values[0, 3] *= 1.001
        _rewrite(f, name, "trajectories", values)

    message = _damaged(tiny, tmp_path, edit)
    assert (f"{name}/trajectories is not what the file was written with (its digest differs: "
            "edited after writing)") in message
    (args,) = _suggested_commands(message)
    assert (args.problem, args.size, args.seed) == ("ks", "tiny", 0)


def test_digests_missing_from_a_current_file_are_named(tiny, tmp_path):
    def edit(f):
        del f.attrs["digests"]

    assert "has no readable `digests` attribute" in _damaged(tiny, tmp_path, edit)


def test_a_file_without_digests_loads_with_a_one_line_notice(tiny, tmp_path):
    old = tmp_path / "v2.h5"
    shutil.copy(tiny, old)
    with h5py.File(old, "a") as f:
        f.attrs["format_version"] = 2
        del f.attrs["digests"]
    with pytest.warns(UserWarning) as caught:
        ds = datamod.load(old)
    (warning,) = caught
    message = str(warning.message)
    assert "\n" not in message and "predates content digests (format version 2)" in message
    assert _suggested_commands(message)[0].out == old
    np.testing.assert_array_equal(ds.splits["train"].trajectories,
                                  datamod.load(tiny).splits["train"].trajectories)


def test_a_missing_file_suggests_a_command_that_writes_it(tmp_path):
    path = tmp_path / "absent.h5"
    with pytest.raises(FileNotFoundError) as info:
        datamod.load(path)
    (args,) = _suggested_commands(str(info.value))
    assert args.out == path


def test_an_intact_file_loads_as_it_was_written(tiny):
    ds = datamod.load(tiny)
    with h5py.File(tiny, "r") as f:
        config = json.loads(f.attrs["config"])
        for name, split in ds.splits.items():
            for key in datamod.ARRAYS:
                np.testing.assert_array_equal(getattr(split, key), f[name][key][...])
    assert config["splits"] == {k: list(v) for k, v in get_problem("ks").splits.items()}
    assert (ds.problem.name, ds.size, ds.seed) == ("ks", "tiny", 0)


def test_a_seed_whose_reference_blows_up_is_one_line(capsys):
    """Seed 1 of the tiny KS data draws an initial state the reference scheme cannot carry."""
    from adjointsim.cli import main

    assert main(["data", "ks", "--size", "tiny", "--seed", "1", "--out", "/nonexistent/x.h5",
                 "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "another --seed" in err


def test_data_never_replaces_a_file_silently(tmp_path, capsys):
    from adjointsim.cli import main

    target = tmp_path / "mine.h5"
    target.write_text("not yours")
    assert main(["data", "ks", "--size", "tiny", "--out", str(target), "--no-progress"]) == 2
    assert "pass --overwrite" in capsys.readouterr().err
    assert target.read_text() == "not yours"
    assert main(["data", "ks", "--size", "tiny", "--out", str(tmp_path), "--no-progress"]) == 2
    assert "is a directory" in capsys.readouterr().err


@pytest.mark.parametrize(("length", "stride", "error"), [
    (0, 1, ValueError), (-1, 1, ValueError), (3, 0, ValueError), (3, 1.5, TypeError)])
def test_windows_refuse_a_length_or_stride_below_one(tiny, length, stride, error):
    """length 0 or -1 gave windows starting past the trajectories' end; stride 0 divided by 0."""
    split = datamod.load(tiny).splits["train"]
    with pytest.raises(error, match=r"windows: (length|stride) must be an integer"):
        datamod.windows(split, length, stride)
