"""The ``compile`` config key of train, control, hig and pinn: checked by name, and a run
compiled with ``aot_eager`` (torch's own kernels on the traced graph) trains to the eager
run's history and weights to the bit, alone and as an ensemble (train's, stopped compiled and
resumed eager, and inductor's, to round-off, in the slow tests)."""

from __future__ import annotations

import pytest
import torch

from adjointsim.cli import main as cli
from adjointsim.errors import UserError
from adjointsim.run import read_history
from adjointsim.train.checkpoint import load_checkpoint
from adjointsim.train.compiled import BACKENDS, compiled
from adjointsim.train.control import ControlConfig, train_controller
from adjointsim.train.hig_problems import HigConfig
from adjointsim.train.hig_problems import train_run as hig_run
from adjointsim.train.pinn import PinnConfig
from adjointsim.train.pinn import train_run as pinn_run
from adjointsim.train.trainer import TrainConfig, train

CONFIGS = [(TrainConfig, {}), (ControlConfig, {"mode": "R"}), (PinnConfig, {}),
           (HigConfig, {"problem": "chain", "optimizer": "adam"})]


@pytest.mark.parametrize(("cls", "base"), CONFIGS)
def test_the_key_is_checked_by_name(cls, base):
    assert cls.load(**base).compile == "off"  # the default: compiling did not pay measured
    for backend in BACKENDS:
        assert cls.load(**base, compile=backend).compile == backend
    for bad in ("jit", "true", True):
        with pytest.raises(UserError, match="config key 'compile'") as e:
            cls.load(**base, compile=bad)
        if bad != True:  # noqa: E712 (a bool is named as the wrong type)
            assert "off, aot_eager, inductor" in str(e.value)


def test_what_cannot_be_compiled_is_refused_with_the_way_out():
    with pytest.raises(UserError, match="'compile'.*doubled batch.*compile = off"):
        ControlConfig.load(mode="C", compile="aot_eager")
    with pytest.raises(UserError, match="'compile'.*doubled batch"):
        TrainConfig.load(mode="C", compile="aot_eager")
    with pytest.raises(UserError, match="'compile'.*optimizer adam"):
        HigConfig.load(problem="chain", optimizer="hig", compile="aot_eager")
    with pytest.raises(ValueError, match="not one of off, aot_eager, inductor"):
        compiled(len, "jit")


def test_help_lists_the_choices(capsys):
    for command in ("train", "control", "hig", "pinn"):
        with pytest.raises(SystemExit):
            cli([command, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert "--compile {off,aot_eager,inductor}" in text, command
        assert "torch.compile" in text, command


def _same_weights(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()  # a compiled run's checkpoint holds the same names
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0)


def _train(tiny, out, **kw):
    cfg = TrainConfig.load(data=str(tiny), out=str(out), width=4, blocks=1, unroll=2, epochs=1,
                           batch=2, checkpoint_every=2, mode="WIG", lr=1e-3, **kw)
    return train(cfg, progress=False)


@pytest.mark.slow  # ~20 s: each step's solver choice breaks the graph, tracing step by step
def test_train_compiled_then_resumed_eager_equals_eager_to_the_bit(tiny, tmp_path):
    """Stopped after 2 compiled updates, continued eager: the weights, history and checkpoint
    layout of the run that was eager all along."""
    eager = _train(tiny, tmp_path / "eager")
    _train(tiny, tmp_path / "cut", compile="aot_eager", max_iterations=2)
    cut = load_checkpoint(tmp_path / "cut" / "checkpoint.pt", ("config", "state"))
    assert cut["config"]["compile"] == "aot_eager"
    whole = load_checkpoint(tmp_path / "eager" / "checkpoint.pt", ("state",))["state"]
    assert cut["state"].keys() == whole.keys()
    resumed = train(TrainConfig.load(**{**cut["config"], "compile": "off",
                                        "max_iterations": 0}), resume=True, progress=False)
    _same_weights(eager.state_dict(), resumed.state_dict())
    assert read_history(tmp_path / "eager" / "history.csv") == \
        read_history(tmp_path / "cut" / "history.csv")


def _control(out, **kw):
    cfg = ControlConfig.load(task="cartpole", mode="R", epochs=2, train=8, test=4, batch=4,
                             dtype="float64", out=str(out), **kw)
    train_controller(cfg, progress=False)
    return _rows(out), load_checkpoint(out / "checkpoint.pt", ("state",))["state"]["net"]


def test_control_compiled_equals_eager_to_the_bit(tmp_path):
    rows, net = _control(tmp_path / "eager")
    rows_c, net_c = _control(tmp_path / "fast", compile="aot_eager")
    assert rows == rows_c and len(rows) == 2
    _same_weights(net, net_c)


def test_pinn_and_hig_compiled_equal_eager_to_the_bit(tmp_path):
    tiny = {"width": 6, "depth": 2, "collocation": 40, "edge_points": 6, "log_every": 2,
            "epochs": 4, "k": 2}
    runs = {c: pinn_run(PinnConfig(**tiny, compile=c), tmp_path / f"pinn-{c}", progress=False,
                        plot=False) for c in ("off", "aot_eager")}
    assert runs["off"]["rel_l2"] == runs["aot_eager"]["rel_l2"]
    # every logged row: the first alone is the untrained net's, the same whatever compiles
    assert _rows(tmp_path / "pinn-off") == _rows(tmp_path / "pinn-aot_eager")
    assert len(_rows(tmp_path / "pinn-off")) == 3
    for c in ("off", "aot_eager"):
        hig_run(HigConfig("chain", "adam", budget=1e6, size="tiny", max_updates=3, compile=c),
                tmp_path / f"hig-{c}", progress=False, plot=False)
    weights = [load_checkpoint(tmp_path / f"hig-{c}" / "checkpoint.pt", ("state",))["state"]
               ["model"] for c in ("off", "aot_eager")]
    _same_weights(*weights)


@pytest.mark.slow
def test_inductor_trains_the_controller_to_round_off(tmp_path):
    rows, net = _control(tmp_path / "eager")
    rows_c, net_c = _control(tmp_path / "fast", compile="inductor")
    for a, b in zip(rows, rows_c, strict=True):
        assert a["test_loss"] == pytest.approx(b["test_loss"], rel=1e-9)
    for k in net:
        torch.testing.assert_close(net[k], net_c[k], rtol=1e-9, atol=1e-12)


def _seeds(out, *flags):
    assert cli(["control", "cartpole", "--mode", "R", "--epochs", "2", "--train", "8", "--test",
                "4", "--batch", "4", "--dtype", "float64", "--seeds", "0", "1", "--out",
                str(out), "--no-progress", *flags]) == 0
    return [(_rows(out / f"seed{s}"), load_checkpoint(out / f"seed{s}" / "checkpoint.pt",
                                                      ("state",))["state"]["net"])
            for s in (0, 1)]


def _rows(out):
    return [{k: v for k, v in r.items() if k != "seconds"}
            for r in read_history(out / "history.csv")]


def test_an_ensemble_compiled_equals_it_eager_to_the_bit(tmp_path):
    """``--compile`` with ``--seeds``: the members' stacked loss compiled, the same training."""
    eager = _seeds(tmp_path / "eager")
    traced = _graphs()
    fast = _seeds(tmp_path / "fast", "--compile", "aot_eager")
    assert _graphs() > traced  # the key is not ignored
    for (rows, net), (rows_c, net_c) in zip(eager, fast, strict=True):
        assert rows == rows_c and len(rows) == 2
        _same_weights(net, net_c)
    assert any(not torch.equal(eager[0][1][k], eager[1][1][k]) for k in eager[0][1])


def _graphs() -> int:
    from torch._dynamo.utils import counters

    return counters["stats"]["unique_graphs"]


@pytest.mark.slow  # ~20 s: each step's solver choice breaks the graph, tracing step by step
def test_a_stepper_ensemble_compiled_equals_it_eager_to_the_bit(tiny, tmp_path):
    from adjointsim.train.ensemble import train_ensemble

    def run(where, backend):
        cfgs = [TrainConfig.load(data=str(tiny), out=str(tmp_path / where / f"s{s}"), width=4,
                                 blocks=1, unroll=2, epochs=1, batch=2, mode="WIG", seed=s,
                                 compile=backend) for s in (0, 1)]
        return [m.state_dict() for m in train_ensemble(cfgs, progress=False)]

    eager = run("eager", "off")
    traced = _graphs()
    fast = run("fast", "aot_eager")
    assert _graphs() > traced
    for a, b in zip(eager, fast, strict=True):
        _same_weights(a, b)
    for s in (0, 1):
        assert (read_history(tmp_path / "eager" / f"s{s}" / "history.csv")
                == read_history(tmp_path / "fast" / f"s{s}" / "history.csv"))


def test_the_controllers_loss_traces_without_a_graph_break():
    """What ``control --compile`` compiles is one graph (a break in the loop would make dynamo
    give up the loop and compile step by step, slower than eager)."""
    from adjointsim.train.control import build_net, closed_loop, initial_states
    from adjointsim.train.unroll import GradientFlow

    cfg = ControlConfig.load(task="cartpole", mode="R", train=8, test=4)
    task = cfg.make_task()
    task.steps = 3
    x0, _ = initial_states(cfg, task)
    explained = torch._dynamo.explain(closed_loop)(task, build_net(cfg, task), x0[:4],
                                                   GradientFlow("R"))
    assert (explained.graph_count, explained.graph_break_count) == (1, 0)
