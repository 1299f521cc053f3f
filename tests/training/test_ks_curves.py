"""The test error along the way (``eval_every``) and the ``ks-curves`` study built on it."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from adjointsim.run import read_history
from adjointsim.train import data as datamod
from adjointsim.train.ensemble import train_ensemble
from adjointsim.train.evaluate import evaluate
from adjointsim.train.studies import ks_curves
from adjointsim.train.trainer import TrainConfig, TrainData, build_model, train

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> dict:
    """The tiny size's dataset, made as the study makes it."""
    return ks_curves.prepare("tiny", tmp_path_factory.mktemp("ks-curves"))


def _config(data: str, out, **keys) -> TrainConfig:
    return TrainConfig.load(problem="ks", data=data, out=str(out), setup="correction",
                            **{**ks_curves.SIZES["tiny"]["train"], **keys})


def test_the_test_error_is_the_study_tables_rel_error(tiny):
    dataset = datamod.load(tiny["data"])
    for setup in ("prediction", "correction"):
        model = build_model(TrainConfig(problem="ks", data=tiny["data"], setup=setup,
                                        width=4, blocks=1))
        assert TrainData.of(dataset, "float32").test_error(model, 12, "float32") == \
            evaluate(model, dataset, 12, torch.float32)["rel_error"]


def test_a_run_records_its_test_error_at_zero_every_eval_every_and_the_end(tiny, tmp_path):
    cfg = _config(tiny["data"], tmp_path / "run", mode="WIG", eval_every=4)
    train(cfg, progress=False)
    curve = read_history(tmp_path / "run" / "curve.csv")
    total = len(read_history(tmp_path / "run" / "history.csv"))
    assert total % 4  # the end is not a multiple of eval_every, and is measured too
    assert [r["updates"] for r in curve] == [*range(0, total, 4), total]
    assert all(r["horizon"] == 12 for r in curve)
    # without eval_every a run writes no curve
    train(_config(tiny["data"], tmp_path / "plain", mode="WIG", eval_every=0), progress=False)
    assert not (tmp_path / "plain" / "curve.csv").exists()


def test_a_stopped_ensemble_resumes_to_the_same_curve_and_weights(tiny, tmp_path):
    def cfgs(root, cap):
        return [_config(tiny["data"], root / f"s{s}", mode="NOG", seed=s, max_iterations=cap)
                for s in range(2)]

    whole = train_ensemble(cfgs(tmp_path / "whole", 0), progress=False)
    train_ensemble(cfgs(tmp_path / "parts", 5), progress=False)  # stopped between two points
    stopped = read_history(tmp_path / "parts" / "s0" / "curve.csv")
    assert [r["updates"] for r in stopped] == [0, 2, 4]
    parts = train_ensemble(cfgs(tmp_path / "parts", 0), resume=True, progress=False)
    for s, (a, b) in enumerate(zip(whole, parts)):
        assert read_history(tmp_path / "whole" / f"s{s}" / "curve.csv") == \
            read_history(tmp_path / "parts" / f"s{s}" / "curve.csv")
        for p, q in zip(a.parameters(), b.parameters()):
            assert torch.equal(p, q)


def test_the_study_rows_hold_every_evaluation_point(tiny, tmp_path):
    cells = [{**c, **tiny} for c in ks_curves.cells("tiny", 1)]
    dirs = [tmp_path / c["id"] for c in cells]
    (tmp_path / "ks-tiny.h5").symlink_to(tiny["data"])  # where collect finds the dataset
    # a stopped study: the modes' runs stopped at different points, one not started
    first = ks_curves.config(cells[0], dirs[0])
    train_ensemble([dataclasses.replace(first, max_iterations=3)], progress=False)
    assert [r["mode"] for r in ks_curves.collect(tmp_path, "tiny", 1)] == ["ONE"]
    rows = ks_curves.run_group(cells, dirs)
    split = datamod.load(tiny["data"]).splits["train"]
    for r in rows:
        assert r["curve"][0][0] == 0 and r["curve"][-1][0] == r["updates"] > 0
        assert r["rel_error"] == r["curve"][-1][1]
        # the paper's run: every window of m + 1 frames (ONE: 2, batch 48), 80 epochs
        m, batch, epochs = (1, 48, 240) if r["mode"] == "ONE" else (3, 16, 80)
        windows = sum(split.trajectories.shape[1] - m for _ in split.trajectories)
        assert r["paper_updates"] == windows // batch * epochs
    assert ks_curves.collect(tmp_path, "tiny", 1) == rows  # read back from the run directories
    text = ks_curves.report(rows, tmp_path / "report")
    points = json.loads((tmp_path / "report" / "ks-curves.json").read_text())
    assert len(points) == sum(len(r["curve"]) for r in rows)
    assert all(set(p) == {"mode", "seed", "updates", "paper_updates", "rel_error"}
               for p in points)
    assert "WIG<NOG<ONE" in text and (tmp_path / "report" / "ks-curves.png").exists()


def test_the_paper_size_counts_the_papers_updates():
    """36 trajectories of 5000 frames (what ``ks --size full`` generates)."""
    split = datamod.Split(trajectories=torch.zeros(36, 5000, 1, 1).numpy(), params=None,
                          conditions=None)
    assert ks_curves.paper_updates("WIG", split) == 36 * 4997 // 16 * 80 == 899_440
    assert ks_curves.paper_updates("ONE", split) == 36 * 4999 // 48 * 240 == 899_760


def test_the_table_ends_with_each_seeds_median_over_the_last_quarter():
    """Seed 0: WIG < NOG < ONE in every point but one spike of WIG's, which the median over the
    last quarter of the updates (9000-11000 of 11000) ignores; seed 1: NOG above ONE."""
    curves = {("ONE", 0): 3e-4, ("NOG", 0): 2e-4, ("WIG", 0): 1e-4,
              ("ONE", 1): 2e-4, ("NOG", 1): 4e-4, ("WIG", 1): 1e-4}
    rows = []
    for (mode, seed), level in curves.items():
        curve = [[1000 * k, level * (9.0 if (mode, seed, k) == ("WIG", 0, 11) else 1.0)]
                 for k in range(12)]
        rows.append({"mode": mode, "seed": seed, "paper_updates": 100_000, "curve": curve,
                     "updates": curve[-1][0], "rel_error": curve[-1][1]})
    last = ks_curves.table(rows).splitlines()[-3]
    assert last.startswith("each seed's median over its last 3 points (9000–11000 updates), "
                           "mean ± std over seeds:")
    assert "WIG 1.000e-04 ± 0.00e+00" in last and "ONE 2.500e-04 ± 5.00e-05" in last
    assert last.endswith("WIG<NOG<ONE 1/2")
    assert ks_curves.trailing([0, 1000, 2000, 3000, 4000], 4) == [3000, 4000]
