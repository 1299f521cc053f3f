"""The run engine's claim rule, cadence and resume, on a toy problem without torch."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import pytest

from adjointsim import engine
from adjointsim.errors import RunExists, UserError
from adjointsim.files import atomic_path
from adjointsim.run import Config, Interval


class JsonStore:
    @staticmethod
    def save(payload: dict, path: Path) -> None:
        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps(payload))

    @staticmethod
    def load(path: Path, keys, recover: str) -> dict:
        return json.loads(path.read_text())


@dataclass
class CountConfig(Config):
    epochs: int = 5
    rate: float = 0.5
    threads: int = 1
    ACCEPTED: ClassVar = {"epochs": Interval(1), "rate": Interval(0), "threads": Interval(1)}


# --8<-- [start:problem]
class Count(engine.Problem):
    """x ← x + rate · (1 − x), one epoch an update; stops on KeyboardInterrupt when asked."""

    RESUMABLE = ("threads",)
    EXTENDABLE = ("epochs",)
    HISTORIES = {"history.csv": ("epoch", "x")}
    RUN_FILES = ("x.txt",)
    RESULT_KEYS = {"x": float}
    STORE = JsonStore()
    UNIT = "epoch"
    stop_at: int | None = None

    def build(self):
        self.x, self.epoch, self.rows = 0.0, 0, []

    def total(self):
        return self.config.epochs

    def position(self):
        return self.epoch

    def update(self):
        if self.epoch == self.stop_at:
            raise KeyboardInterrupt
        self.x += self.config.rate * (1 - self.x)
        self.epoch += 1
        self.rows.append({"epoch": self.epoch, "x": self.x})
        return True

    def finish(self):
        return {"x": self.x}

    def plot(self):
        (self.out / "x.txt").write_text(str(self.x))

    def state_dict(self):
        return {"x": self.x, "epoch": self.epoch}

    def load_state_dict(self, state):
        self.x, self.epoch = state["x"], state["epoch"]

    def histories(self):
        return {"history.csv": self.rows}

    def load_histories(self, histories):
        self.rows = list(histories["history.csv"])
# --8<-- [end:problem]


def count(out, stop_at=None, **cfg):
    p = Count(CountConfig(**cfg), out)
    p.stop_at = stop_at
    return p


def test_fresh_run_writes_config_history_result(tmp_path):
    result = engine.run(count(tmp_path / "r"), progress=False)
    assert result["x"] == pytest.approx(1 - 0.5**5)
    for name in ("config.json", "checkpoint.pt", "history.csv", "result.json", "x.txt"):
        assert (tmp_path / "r" / name).exists()
    assert len((tmp_path / "r" / "history.csv").read_text().splitlines()) == 6


def test_interrupted_run_resumes_bit_identically(tmp_path):
    whole = engine.run(count(tmp_path / "a"), progress=False)
    with pytest.raises(engine.Saved, match="--resume") as stopped:
        engine.run(count(tmp_path / "b", stop_at=3), progress=False)
    assert stopped.value.out == tmp_path / "b"  # what the command line's resume command names
    assert not (tmp_path / "b" / "result.json").exists()
    assert len((tmp_path / "b" / "history.csv").read_text().splitlines()) == 1 + 3  # epochs 1-3
    with pytest.raises(RunExists, match="unfinished run; continue it with --resume"):
        engine.run(count(tmp_path / "b"), progress=False)
    resumed = engine.run(count(tmp_path / "b", threads=2), resume=True, progress=False)
    assert resumed["x"] == whole["x"]
    assert (tmp_path / "a" / "history.csv").read_text() == \
        (tmp_path / "b" / "history.csv").read_text()


def test_finished_run_returned_refused_or_extended(tmp_path):
    out = tmp_path / "r"
    first = engine.run(count(out, epochs=2), progress=False)
    assert engine.run(count(out, epochs=2), resume=True, progress=False) == first
    with pytest.raises(RunExists, match="finished run; choose another --out"):
        engine.run(count(out, epochs=2), progress=False)
    with pytest.raises(RunExists, match="continue it to more with --resume"):
        engine.run(count(out, epochs=4), progress=False)
    with pytest.raises(RunExists, match="epochs = 2"):
        engine.run(count(out, epochs=1), resume=True, progress=False)
    longer = engine.run(count(out, epochs=4), resume=True, progress=False)
    assert longer["x"] == engine.run(count(tmp_path / "s", epochs=4), progress=False)["x"]


def test_a_limit_below_no_limit_is_shorter(tmp_path):
    """An extendable length recorded as None (no limit) is longer than any number."""
    out = tmp_path / "r"
    out.mkdir()
    (out / "config.json").write_text(json.dumps({"epochs": None, "rate": 0.5, "threads": 1}))
    (out / "result.json").write_text(json.dumps({"epochs": None, "rate": 0.5, "threads": 1,
                                                 "x": 1.0}))
    with pytest.raises(RunExists, match="epochs = None; pass as much or more"):
        engine.RunDir(count(out, epochs=3)).claim(True, False)


def test_foreign_and_other_configuration_refused(tmp_path):
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with pytest.raises(RunExists, match="other files"):
        engine.run(count(other), progress=False)
    with pytest.raises(RunExists, match="other files"):
        engine.run(count(other), overwrite=True, progress=False)
    assert (other / "notes.txt").read_text() == "mine"
    out = tmp_path / "r"
    engine.run(count(out), progress=False)
    with pytest.raises(RunExists, match="differs in rate"):
        engine.run(count(out, rate=0.25), resume=True, progress=False)
    result = engine.run(count(out, rate=0.25), overwrite=True, progress=False)
    assert result["rate"] == 0.25
    with pytest.raises(UserError, match="pass one"):
        engine.run(count(out), resume=True, overwrite=True, progress=False)


def test_resume_without_a_run_says_so(tmp_path):
    with pytest.raises(UserError, match="holds no run to continue"):
        engine.run(count(tmp_path / "none"), resume=True, progress=False)


def test_a_study_cell_resumes_where_a_run_was_started(tmp_path):
    """``resume=started(out)`` starts a cell's run where none is and returns or continues it
    where one is."""
    out = tmp_path / "cell"
    assert not engine.started(out)
    first = engine.run(count(out), resume=engine.started(out), progress=False)
    assert engine.started(out)
    assert engine.run(count(out), resume=engine.started(out), progress=False) == first
    (out / "result.json").unlink()
    (out / "checkpoint.pt").unlink()
    assert engine.started(out)  # its config.json alone: stopped before its first checkpoint


def test_an_out_that_is_a_file_is_named(tmp_path):
    (tmp_path / "afile").write_text("")
    with pytest.raises(OSError, match="cannot write the run to --out .*afile"):
        engine.run(count(tmp_path / "afile"), progress=False)


def test_zero_length_ensemble_refused(tmp_path):
    with pytest.raises(UserError, match="at least one member"):
        engine.run([], progress=False)


def test_ensemble_members_keep_their_own_directories(tmp_path):
    class Together:
        def __init__(self, group):
            self.group = group

        def done(self):
            return all(p.done() for p in self.group)

        def update(self):
            return all([p.update() for p in self.group])

        def sync(self):
            pass

    members = [count(tmp_path / f"seed{k}", rate=r) for k, r in enumerate((0.5, 0.25))]
    results = engine.run(members, progress=False, ensemble=Together)
    assert [r["rate"] for r in results] == [0.5, 0.25]
    assert results[1]["x"] == pytest.approx(1 - 0.75**5)


def test_a_paused_run_is_saved_unfinished_and_resumes(tmp_path):
    whole = engine.run(count(tmp_path / "a"), progress=False)
    capped = count(tmp_path / "b")
    capped.update = lambda: Count.update(capped) and False  # no boundary: saved at the pause
    assert engine.run(capped, progress=False, until=2) is None
    assert not (tmp_path / "b" / "result.json").exists()
    assert len((tmp_path / "b" / "history.csv").read_text().splitlines()) == 3
    with pytest.raises(RunExists, match="unfinished run; continue it with --resume"):
        engine.run(count(tmp_path / "b"), progress=False)
    # a turn at a time: the recorded length stays 5 whatever the stop
    assert engine.run(count(tmp_path / "b"), resume=True, progress=False, until=4) is None
    assert len((tmp_path / "b" / "history.csv").read_text().splitlines()) == 5
    assert engine.run(count(tmp_path / "b"), resume=True, progress=False)["x"] == whole["x"]
    assert (tmp_path / "a" / "history.csv").read_text() == \
        (tmp_path / "b" / "history.csv").read_text()


def test_resumed_ensemble_starts_an_added_member_fresh(tmp_path):
    """--resume continues the members that hold a run and starts one without (a seed added,
    its directory deleted) beside them, so neither spelling of the command refuses it; an
    ensemble with nothing to continue is refused."""
    engine.run([count(tmp_path / "seed0", epochs=2)], progress=False)
    members = [count(tmp_path / f"seed{k}", epochs=3) for k in (0, 1)]
    results = engine.run(members, resume=True, progress=False)
    assert [r["x"] for r in results] == [pytest.approx(1 - 0.5**3)] * 2
    assert len((tmp_path / "seed0" / "history.csv").read_text().splitlines()) == 4
    with pytest.raises(UserError, match="holds no run to continue"):
        engine.run([count(tmp_path / f"new{k}") for k in (0, 1)], resume=True, progress=False)


def test_a_run_of_an_earlier_version_is_this_commands_not_foreign(tmp_path):
    class Renamed(Count):
        ADDED = ("rate",)
        RETIRED = ("speed",)

    out = tmp_path / "old"
    out.mkdir()
    (out / "config.json").write_text(json.dumps({"epochs": 5, "threads": 1, "speed": 0.5}))
    (out / "checkpoint.pt").write_text("{}")
    with pytest.raises(RunExists, match=r"another configuration \(differs in rate, speed\)"):
        engine.run(Renamed(CountConfig(), out), resume=True, progress=False)
    with pytest.raises(RunExists, match="another command's run"):
        engine.run(count(out), overwrite=True, progress=False)
    result = engine.run(Renamed(CountConfig(), out), overwrite=True, progress=False)
    assert result["rate"] == 0.5 and "speed" not in json.loads((out / "config.json").read_text())


class Busy(Count):
    """Many quick updates, each with a figure beside the bar's count."""

    def update(self):
        super().update()
        return False  # no boundary: saved on the engine's clock only

    def postfix(self):
        return {"x": self.x}


class Bar:
    """A stand-in for tqdm's bar that records what the engine asks of it."""

    bars: ClassVar[list] = []

    def __init__(self, total, initial=0, **_):
        self.n, self.postfix, self.forced, self.drawn = initial, {}, 0, []
        Bar.bars.append(self)

    def set_postfix(self, postfix=None, refresh=True, **more):
        self.postfix = {**(postfix or {}), **more}
        self.forced += refresh

    def update(self, n=1):  # tqdm draws here, when its interval has passed
        self.n += n
        self.drawn.append((self.n, dict(self.postfix)))

    def refresh(self):
        self.forced += 1

    def close(self):
        pass


def test_the_bar_is_drawn_at_tqdms_pace_with_the_figure_of_the_update_it_counts(
        tmp_path, monkeypatch):
    """A bar redrawn on every update (``set_postfix``'s refresh) wrote a line per update to a
    study's log; tqdm paces the draws of ``update``, which must show that update's figure."""
    import tqdm.auto

    monkeypatch.setattr(tqdm.auto, "tqdm", Bar)
    Bar.bars.clear()
    engine.run(Busy(CountConfig(epochs=3), tmp_path / "r"), progress=True)
    (bar,) = Bar.bars
    assert bar.forced == 0
    assert bar.drawn == [(1, {"x": 0.5}), (2, {"x": 0.75}), (3, {"x": 0.875})]


@pytest.mark.parametrize("line, fields", [("3,0.5", 2), ("3,0.5,1,7", 4)])
def test_a_history_row_cut_short_or_too_long_is_a_damaged_file(tmp_path, line, fields):
    from adjointsim.errors import DamagedFileError
    from adjointsim.run import read_history, write_history

    path = tmp_path / "history.csv"
    write_history(path, [{"epoch": 1, "loss": 0.25, "ok": True}], ("epoch", "loss", "ok"))
    assert read_history(path) == [{"epoch": 1, "loss": 0.25, "ok": True}]
    path.write_text(path.read_text() + line + "\n")
    with pytest.raises(DamagedFileError, match=f"{path} is damaged: line 3 has {fields} fields, "
                       "its header 3; restore the file, or start the run again with --overwrite"):
        read_history(path)


@pytest.mark.parametrize("damage, says", [
    (lambda r: r.pop("x"), "it lacks 'x'"),
    (lambda r: r.update(x="0.97"), "it holds '0.97' under 'x', not a float"),
    (lambda r: r.pop("rate"), "it lacks 'rate'"),
])
def test_a_finished_result_of_the_wrong_keys_or_types_is_damaged(tmp_path, damage, says):
    out = tmp_path / "r"
    engine.run(count(out, epochs=2), progress=False)
    result = json.loads((out / "result.json").read_text())
    damage(result)
    (out / "result.json").write_text(json.dumps(result))
    with pytest.raises(RunExists, match=f"result.json is damaged \\({says}\\); delete it to "
                       "finish the run again from its checkpoint"):
        engine.run(count(out, epochs=2), resume=True, progress=False)
    (out / "result.json").unlink()
    assert engine.run(count(out, epochs=2), resume=True, progress=False)["x"] == 0.75


def test_a_config_that_cannot_be_read_is_named_and_its_run_left_alone(tmp_path):
    out = tmp_path / "r"
    engine.run(count(out, epochs=2), progress=False)
    (out / "config.json").write_text('{"epochs": 2, "ra')
    for overwrite in (False, True):
        with pytest.raises(RunExists, match="a config.json that cannot be read: if this is this "
                           "command's run, the file is damaged; restore it"):
            engine.run(count(out, epochs=2), resume=not overwrite, overwrite=overwrite,
                       progress=False)
    assert (out / "checkpoint.pt").exists() and (out / "result.json").exists()
