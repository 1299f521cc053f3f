"""Solver threads (adjointsim.parallel): every registered solver gives the same bits on one
thread and on two, split or not; the split itself; the knob and its errors; nested and
concurrent calls."""

from __future__ import annotations

import json
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

import adjointsim
from adjointsim import parallel, registry

#: rows enough to split, and over the spectral solvers' 12-row threshold
BATCH = 26
STEPS = 6


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal to the bit (a -0.0 for a 0.0 too), of the same shape and dtype."""
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def _everything(stepper: adjointsim.Stepper) -> dict[str, np.ndarray]:
    """Rollouts and sweeps of one drawn problem: states, cotangents and parameter sums."""
    rng = np.random.default_rng(7)
    u = stepper.random_state(rng, BATCH)
    ctrl = (None if stepper.control_shape is None
            else stepper.random_controls(rng, STEPS, BATCH))
    cot = {k: stepper.random_state(rng, BATCH) for k in (2, 5, STEPS)}
    out = {"all": stepper.rollout(u, STEPS, ctrl, keep="all"),
           "last": stepper.rollout(u, STEPS, ctrl)}
    sweeps = {"stored": {}, "checkpoint=3": {"checkpoint": 3},
              "trajectory": {"trajectory": out["all"]}}
    for name, extra in sweeps.items():
        g = stepper.vjp(u, STEPS, cot, ctrl, wrt_params=True, **extra)
        out[f"{name} state"] = g.state
        out[f"{name} controls"] = g.controls
        out[f"{name} params"] = np.array([g.params[k] for k in stepper.param_names])
    return out


def _with(threads: int, split: bool, stepper: adjointsim.Stepper, monkeypatch
          ) -> dict[str, np.ndarray]:
    with monkeypatch.context() as m:
        m.setattr(parallel, "MIN_CHUNK_WORK", 1 if split else 1 << 62)
        with parallel.using_threads(threads):
            return _everything(stepper)


@pytest.mark.parametrize("cls", registry.all_classes(), ids=registry.names())
def test_one_thread_and_two_give_the_same_bits(cls, monkeypatch):
    stepper = cls.default()
    one = _with(1, True, stepper, monkeypatch)
    two = _with(2, True, stepper, monkeypatch)
    unsplit = _with(1, False, stepper, monkeypatch)
    assert {k for k in one if not _same(one[k], two[k])} == set()
    # rows never interact: splitting them changes no state or cotangent of a state or control
    assert {k for k in one if "params" not in k and not _same(one[k], unsplit[k])} == set()


def test_a_split_forced_small_really_splits(monkeypatch):
    monkeypatch.setattr(parallel, "MIN_CHUNK_WORK", 1)
    seen = []
    real = parallel.map_chunks

    def spy(fn, items):
        seen.append((len(items), threading.current_thread().name))
        return real(fn, items)

    monkeypatch.setattr(parallel, "map_chunks", spy)
    stepper = adjointsim.get("ks1d-etdrk4").default()
    u = stepper.random_state(np.random.default_rng(0), BATCH)
    with parallel.using_threads(2):
        stepper.rollout(u, 3)
        stepper.vjp(u, 3, u)
    assert [n for n, _ in seen] == [2, 2]  # 26 rows, chunks of at least 12


def test_chunks_sizes_and_rules(monkeypatch):
    monkeypatch.setattr(parallel, "MIN_CHUNK_WORK", 10)
    with parallel.using_threads(4):
        parts = parallel.chunks(10, 100)
        assert [p.stop - p.start for p in parts] == [2, 3, 2, 3]
        assert parts[0].start == 0 and parts[-1].stop == 10
        assert all(a.stop == b.start for a, b in zip(parts, parts[1:]))
        assert parallel.chunks(10, 1) == [slice(0, 10)]  # 10 point-steps: one chunk's worth
        assert len(parallel.chunks(10, 2)) == 2  # work for two chunks only
        # at least min_rows per chunk once the batch reaches it; a smaller batch runs whole
        assert [p.stop - p.start for p in parallel.chunks(26, 100, min_rows=12)] == [13, 13]
        assert parallel.chunks(23, 100, min_rows=12) == [slice(0, 23)]
        # below it every chunk is too (the whole batch's arithmetic)
        assert [p.stop - p.start for p in parallel.chunks(11, 100, min_rows=12)] == [2, 3, 3, 3]
    with parallel.using_threads(1):
        assert parallel.chunks(10, 100) == [slice(0, 10)]


@pytest.mark.parametrize("batch", [3, 7, 16, 100])
def test_a_fixed_split_depends_on_the_call_alone(batch, monkeypatch):
    monkeypatch.setattr(parallel, "MIN_CHUNK_WORK", 1)
    splits = []
    for n in (1, 2, 3, 64):
        with parallel.using_threads(n):
            splits.append(parallel.chunks(batch, 1000, fixed=True))
    assert all(s == splits[0] for s in splits)
    count = len(splits[0])
    assert count == min(parallel.FIXED_CHUNKS, 1 << (batch.bit_length() - 1))
    assert count & (count - 1) == 0  # a power of two


@pytest.mark.parametrize("value", ["0", "x", "-2", "1.5"])
def test_a_bad_environment_variable_names_itself_and_the_fix(value, monkeypatch):
    monkeypatch.setenv(parallel.ENVIRONMENT, value)
    with parallel.using_threads(None), pytest.raises(ValueError) as e:
        parallel.threads()
    assert "ADJOINTSIM_THREADS" in str(e.value) and "unset it" in str(e.value)
    assert repr(value) in str(e.value)


def test_the_environment_variable_and_the_default(monkeypatch):
    with parallel.using_threads(None):
        monkeypatch.setenv(parallel.ENVIRONMENT, " 3 ")
        assert parallel.threads() == 3
        monkeypatch.delenv(parallel.ENVIRONMENT)
        assert parallel.threads() == parallel.available_cores()


@pytest.mark.parametrize("bad", [0, -1, True, np.True_, 2.0, np.float64(2.0), "2",
                                 np.int64(0)])
def test_set_threads_refuses_what_is_not_a_count(bad):
    before = parallel.threads()
    with pytest.raises(ValueError, match="whole number of threads of at least 1, not "):
        parallel.set_threads(bad)
    assert parallel.threads() == before


@pytest.mark.parametrize("count", [np.int64(2), np.uint8(2), np.int32(2), 2])
def test_set_threads_takes_any_integral_number(count):
    with parallel.using_threads(count):
        assert parallel.threads() == 2 and type(parallel.threads()) is int


def test_using_threads_restores_the_setting_after_an_error_too(monkeypatch):
    monkeypatch.setenv(parallel.ENVIRONMENT, "2")
    with parallel.using_threads(3):
        with pytest.raises(RuntimeError), parallel.using_threads(5):
            assert adjointsim.threads() == 5
            raise RuntimeError
        assert parallel.threads() == 3
        with parallel.using_threads(None):
            assert parallel.threads() == 2
        assert parallel.threads() == 3


def test_the_package_exports_the_knob():
    assert adjointsim.set_threads is parallel.set_threads
    assert adjointsim.using_threads is parallel.using_threads
    assert adjointsim.threads is parallel.threads


def test_a_solver_called_inside_a_chunk_runs_serially_and_finishes(monkeypatch):
    base = adjointsim.get("diffusion1d-ftcs")
    inner = base.default()
    seen = []

    class Nested(base):
        def _forward(self, states, n, ctrl, p):
            # another stepper's rollout, large enough to split were it called from outside
            seen.append((len(parallel.chunks(BATCH, 10**9)), len(parallel.chunks(
                BATCH, 10**9, fixed=True))))
            inner.rollout(np.ascontiguousarray(states[0]), n)
            super()._forward(states, n, ctrl, p)

    monkeypatch.setattr(parallel, "MIN_CHUNK_WORK", 1)
    outer = Nested()
    u = outer.random_state(np.random.default_rng(0), BATCH)
    result = []
    with parallel.using_threads(2):
        worker = threading.Thread(target=lambda: result.append(outer.rollout(u, 4)), daemon=True)
        worker.start()
        worker.join(timeout=120)
    assert not worker.is_alive(), "a nested call waited on the pool it runs in"
    assert _same(result[0], inner.rollout(u, 4))
    # inside a chunk: one chunk, except a fixed split, which stays (run serially there)
    assert seen == [(1, parallel.FIXED_CHUNKS)] * 2


def test_two_user_threads_on_one_stepper_get_the_one_thread_results(monkeypatch):
    monkeypatch.setattr(parallel, "MIN_CHUNK_WORK", 1)
    stepper = adjointsim.get("burgers1d-rusanov").default()
    rng = np.random.default_rng(4)
    inputs = [stepper.random_state(rng, BATCH) for _ in range(4)]

    def work(u):
        g = stepper.vjp(u, STEPS, u, wrt_params=True, checkpoint=3)
        return stepper.rollout(u, STEPS, keep="all"), g.state, g.params["nu"]

    with parallel.using_threads(1):
        alone = [work(u) for u in inputs]
    with parallel.using_threads(2), ThreadPoolExecutor(2) as users:
        together = list(users.map(work, inputs * 2))
    for (a, b), ref in zip(zip(together[:4], together[4:]), alone):
        for x, y, r in zip(a, b, ref):
            assert _same(x, r) and _same(y, r)


ROW_KEYS = {"solver", "batch", "threads", "forward_s", "gradient_s", "bitwise_equal", "steps",
            "n", "cores", "cpu_count", "cpu"}


def _bench(argv: list[str]) -> int:
    import threads as bench  # benchmarks/threads.py

    return bench.main(argv)


def test_the_threads_benchmark_writes_its_rows(tmp_path, capsys):
    path = tmp_path / "rows.json"
    assert _bench(["--quick", "--solvers", "diffusion1d-ftcs", "--batches", "8", "--repeats",
                   "1", "--json", str(path)]) == 0
    rows = json.loads(path.read_text())
    assert [r["threads"] for r in rows][:2] == [1, 2]
    assert all(set(r) == ROW_KEYS and r["bitwise_equal"] and r["forward_s"] > 0
               and r["gradient_s"] > r["forward_s"] for r in rows)
    assert "| diffusion1d-ftcs | 256 | 25 | 8 | 2 |" in capsys.readouterr().out


@pytest.mark.slow
def test_the_threads_benchmark_covers_every_family(tmp_path, capsys):
    assert _bench(["--quick", "--batches", "1", "8", "--repeats", "1", "--out",
                   str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "threads.json").read_text())
    assert all(set(r) == ROW_KEYS for r in rows)
    assert {r["solver"] for r in rows} == {
        "ks1d-etdrk4", "ns2d-etdrk2", "diffusion1d-ftcs", "diffusion2d-ftcs",
        "burgers1d-rusanov", "burgers1d-etdrk4", "diffusion2d-crank-nicolson", "poisson2d",
        "cartpole"}
    assert {(r["batch"], r["threads"]) for r in rows} >= {(1, 1), (1, 2), (8, 1), (8, 2)}
    assert all(r["bitwise_equal"] for r in rows)
    assert (tmp_path / "threads.md").read_text().count("\n| ") == len(rows)
    assert (tmp_path / "threads.png").stat().st_size > 0
