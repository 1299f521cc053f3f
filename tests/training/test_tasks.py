"""Controller tasks: every registered task is complete (level, scene, net, loss terms, plot),
and the heat task, added as one file, trains."""

import dataclasses

import numpy as np
import pytest
import torch

from adjointsim.train import control
from adjointsim.train.tasks import TASKS, get_task


def test_the_registry_holds_the_papers_tasks_and_heat():
    assert {"cartpole", "guidance", "quantum", "heat"} <= set(TASKS.names())
    fields = {f.name for f in dataclasses.fields(control.ControlConfig)}
    keys = [cls.key for _, cls in TASKS.items()]
    assert len(set(keys)) == len(keys) and not set(keys) & fields  # each its own flag


@pytest.mark.parametrize("name", TASKS.names())
def test_every_task_is_complete(name, tmp_path):
    cls = TASKS.get(name)
    assert cls.level_of(None) == cls.levels[0]
    with pytest.raises(ValueError, match=rf"not one of .* \(the {name} task's"):
        cls.level_of(-7)
    task = get_task(name, cls.levels[-1])
    assert task.scene == cls.SCENE and task.level == cls.levels[-1]
    task.steps = 3  # a short rollout: the checks below are about shapes and names
    net = task.net().double()
    x0 = torch.from_numpy(task.initial_states(np.random.default_rng(0), 2))
    assert tuple(x0.shape) == task.solver.state_shape(2)
    c = task.control(net(x0))
    assert c.shape == (2, *task.solver.control_shape) and float(c.detach().abs().max()) == 0.0
    with torch.no_grad():
        terms = control.closed_loop(task, net, x0, terms=True)[0]
        loss = control.closed_loop(task, net, x0)[0]
    assert set(terms) == set(task.terms)
    assert float(loss) == pytest.approx(float(sum(terms.values())), rel=1e-12)
    # each row's loss is its episode's alone: the batch's rows one at a time give the same
    rng = np.random.default_rng(1)
    x = torch.from_numpy(rng.standard_normal(task.solver.state_shape(3)))
    u = torch.from_numpy(rng.standard_normal((3, *task.solver.control_shape)))
    for t in range(task.steps):
        rows = task.row_loss(x, u, t)
        if rows is None:
            assert task.step_loss(x, u, t) is None
            continue
        assert rows.shape == (3,)
        alone = torch.stack([task.step_loss(x[i:i + 1], u[i:i + 1], t) for i in range(3)])
        torch.testing.assert_close(rows, alone, rtol=1e-14, atol=0)
        torch.testing.assert_close(task.step_loss(x, u, t), rows.mean(), rtol=1e-14, atol=0)
    control.plot_rollout(task, net, x0[:1], tmp_path / "rollout.png", title=name)
    assert (tmp_path / "rollout.png").stat().st_size > 0


def test_a_task_takes_its_scene_from_the_config_checked_by_the_solver():
    task = get_task("heat", 2, {"nu": 0.05, "n": 16})
    assert task.solver.param_values[0] == 0.05 and task.solver.grid_shape == (16,)
    assert task.net()(torch.zeros(1, 1, 16)).shape == (1, 16)
    with pytest.raises(ValueError, match="nu must be a finite number"):
        get_task("heat", 1, {"nu": float("nan")})
    with pytest.raises(ValueError, match="scene key 'k': diffusion1d-crank-nicolson takes n, "):
        get_task("heat", 1, {"k": 2})
    with pytest.raises(ValueError, match="scene key 'poles' is the cartpole task's level"):
        get_task("cartpole", 1, {"poles": 2})
    q = get_task("quantum", 5, {"n": 20})  # the eigenstates and the net follow the grid
    x0 = torch.from_numpy(q.initial_states(np.random.default_rng(0), 3))
    assert q.net().double()(x0).shape == (3, 1)
    np.testing.assert_allclose(q.solver.h * (x0.numpy() ** 2).sum(axis=(1, 2)), 1.0)


def test_tasks_of_one_scene_share_their_solver():
    """One solver object per scene in a process (what a compiled loop is traced for); another
    scene or level, another solver."""
    a, b = get_task("quantum", 5, None), get_task("quantum", 5, {"n": 32})
    assert a.solver is b.solver and a is not b
    assert get_task("quantum", 5, {"n": 20}).solver is not a.solver
    assert get_task("cartpole", 2, None).solver is not get_task("cartpole", 3, None).solver
    assert get_task("cartpole", 2, None).solver.poles == 2


def test_heat_reaches_its_target_and_a_trained_controller_gets_closer(tmp_path):
    task = get_task("heat", 2)
    target = torch.from_numpy(task.target[None])
    last = task.step_terms(target, torch.zeros(1, 1, 32, dtype=target.dtype), task.steps - 1)
    assert float(last["tracking"]) == 0.0 and float(last["control"]) == 0.0
    cfg = control.ControlConfig(task="heat", level=2, mode="R", epochs=3, train=16, test=8,
                                batch=8, lr=1e-2, dtype="float64", out=str(tmp_path / "run"))
    result = control.train_controller(cfg, progress=False)
    untrained = control.evaluate(task, control.build_net(cfg, task),
                                 control.initial_states(cfg, task)[1])
    assert result["test_loss"] < 0.5 * untrained and result["wavenumber"] == 2
    assert (tmp_path / "run" / "rollout.png").exists()
