"""Half-inverse gradients: the update against a dense NumPy computation, the Jacobian against
finite differences, error messages, the problems and their scenes, runs (history, resume,
extension, refusal) and the study."""

import json
import math
import signal
import time

import numpy as np
import pytest
import torch

from adjointsim.errors import RunExists
from adjointsim.run import read_history
from adjointsim.solvers.oscillators import Oscillators
from adjointsim.train import hig_problems
from adjointsim.train.checkpoint import load_checkpoint
from adjointsim.train.hig import HalfInverseGradients, SolverPhysics, TorchPhysics
from adjointsim.train.hig_problems import HigConfig, train_run
from adjointsim.train.higs import PROBLEMS, make_problem
from adjointsim.train.higs.poisson import five_point_laplacian, phiflow_noise

STEPS = 6


def small_problem(seed: int = 0):
    torch.manual_seed(seed)
    stepper = Oscillators(n=2, dt=0.25)
    physics = SolverPhysics(stepper, STEPS, lambda c: c.reshape(-1, 2, 2))
    model = torch.nn.Sequential(
        torch.nn.Linear(4, 5), torch.nn.Tanh(), torch.nn.Linear(5, STEPS)
    ).double()
    x = torch.rand(3, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    return stepper, physics, model, x


def flat_params(model):
    return torch.cat([p.detach().reshape(-1) for p in model.parameters()]).numpy().copy()


def outputs(stepper, model, theta, x):
    """y(θ) in NumPy: the model at flat parameters θ, then the stepper's own rollout."""
    params, offset = {}, 0
    for k, p in model.named_parameters():
        params[k] = torch.from_numpy(theta[offset : offset + p.numel()].reshape(p.shape))
        offset += p.numel()
    with torch.no_grad():
        f = torch.func.functional_call(model, params, (x,)).numpy()
    ctrl = np.ascontiguousarray(f.T[:, :, None])
    return stepper.rollout(x.numpy().reshape(-1, 2, 2), STEPS, ctrl).reshape(-1)


def fd_jacobian(stepper, model, theta: np.ndarray, x) -> np.ndarray:
    """d outputs / d theta by central differences."""
    eps = 1e-6
    columns = []
    for j in range(theta.size):
        e = np.zeros_like(theta)
        e[j] = eps
        columns.append((outputs(stepper, model, theta + e, x)
                        - outputs(stepper, model, theta - e, x)) / (2 * eps))
    return np.stack(columns, axis=1)


def test_jacobian_matches_central_finite_differences():
    stepper, physics, model, x = small_problem()
    opt = HalfInverseGradients(model, physics, lambda y, t: ((y - t) ** 2).sum(1))
    y, jac = opt.jacobian(x, x)
    theta = flat_params(model)
    np.testing.assert_allclose(y.reshape(-1).numpy(), outputs(stepper, model, theta, x),
                               rtol=1e-13)
    fd = fd_jacobian(stepper, model, theta, x)
    assert jac.shape == (3 * 4, theta.size)
    err = np.abs(jac.numpy() - fd).max() / np.abs(fd).max()
    assert err < 1e-8, err


@pytest.mark.parametrize("decomposition", ["svd", "gram"])
@pytest.mark.parametrize("kappa", [0.5, 1.0])
def test_hig_and_gn_steps_match_a_dense_numpy_svd(kappa, decomposition):
    stepper, physics, model, x = small_problem(1)
    target = torch.rand(3, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(7))

    def loss(y, t):
        return ((y - t) ** 2).sum(1)

    # The reference J: autograd through the bridge, one backward per row (not the batched
    # adjoint), then NumPy's SVD.
    names = [k for k, _ in model.named_parameters()]

    def y_of(*ps):
        f = torch.func.functional_call(model, dict(zip(names, ps)), (x,))
        return physics(f, x).reshape(-1)

    parts = torch.autograd.functional.jacobian(y_of, tuple(p.detach() for p in model.parameters()))
    jac = torch.cat([j.reshape(j.shape[0], -1) for j in parts], dim=1).numpy()
    with torch.no_grad():
        y = y_of(*model.parameters()).numpy()
    g = 2 * (y - target.numpy().reshape(-1)) / 3  # ∂(Σ L / b)/∂y
    u, s, vt = np.linalg.svd(jac, full_matrices=False)
    # τ between two singular values: the smallest ones must be dropped, not clamped
    tau = math.sqrt(s[-3] * s[-4]) / s[0]
    keep = s > tau * s[0]
    assert 0 < (~keep).sum() < len(s)
    lr = 0.3
    expected = -lr * vt[keep].T @ (s[keep] ** -kappa * (u[:, keep].T @ g))

    before = flat_params(model)
    opt = HalfInverseGradients(model, physics, loss, lr=lr, kappa=kappa, tau=tau,
                               decomposition=decomposition)
    value = opt.step(x, x, target)
    assert value == pytest.approx(np.mean(((y - target.numpy().reshape(-1)) ** 2)
                                          .reshape(3, 4).sum(1)), rel=1e-12)
    np.testing.assert_allclose(flat_params(model) - before, expected, rtol=1e-9,
                               atol=1e-12 * np.abs(expected).max())
    assert set(opt.timing) == {"network", "physics", "decomposition", "apply"}


def test_tall_jacobians_take_the_direct_svd():
    # More rows than parameters: J = U Σ Vᵀ directly; GN with τ = 0 is then least squares.
    model = torch.nn.Linear(2, 3, bias=False).double()
    physics = TorchPhysics(lambda f, c: torch.cat([f, f**2], dim=1))
    opt = HalfInverseGradients(model, physics, lambda y, t: ((y - t) ** 2).sum(1), kappa=1.0,
                               tau=0.0)
    x = torch.rand(4, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    _, jac = opt.jacobian(x, torch.zeros(4, 0))
    assert jac.shape == (24, 6)
    g = torch.rand(24, dtype=torch.float64)
    lstsq = np.linalg.lstsq(jac.numpy(), g.numpy(), rcond=None)[0]
    np.testing.assert_allclose(opt.direction(jac, g).numpy(), lstsq, rtol=1e-10)
    # the layer-factor route forms the same J from its factors, running the physics once
    calls = []
    physics.jacobian = lambda f, c, inner=physics.jacobian: calls.append(1) or inner(f, c)
    _, factors = opt.layer_factors(x, torch.zeros(4, 0))
    assert len(calls) == 1
    np.testing.assert_allclose(factors.dense().numpy(), jac.numpy(), rtol=1e-13)
    np.testing.assert_allclose(opt.direction(factors, g).numpy(), lstsq, rtol=1e-10)


@pytest.mark.parametrize(("decomposition", "what"),
                         [("svd", "Jacobian would be 12 × 61"),
                          ("gram", "Gram matrix J Jᵀ would be 12 × 12")])
def test_oversized_jacobian_is_refused_with_its_size_and_the_knob(decomposition, what):
    _, physics, model, x = small_problem()
    opt = HalfInverseGradients(model, physics, lambda y, t: y.sum(1), max_jacobian_mb=1e-4,
                               decomposition=decomposition)
    with pytest.raises(MemoryError, match=what + r" .*max_jacobian_mb.*batch size"):
        opt.step(x, x, x)


class _Scaled(torch.nn.Module):
    """Not a stack of Linear layers: a parameter outside them."""

    def __init__(self):
        super().__init__()
        self.lin = torch.nn.Linear(4, STEPS).double()
        self.scale = torch.nn.Parameter(torch.ones((), dtype=torch.float64))

    def forward(self, x):
        return self.scale * self.lin(x)


class _Twice(torch.nn.Module):
    """Not a stack of Linear layers: one layer applied twice."""

    def __init__(self):
        super().__init__()
        self.a, self.b = torch.nn.Linear(4, 4).double(), torch.nn.Linear(4, STEPS).double()

    def forward(self, x):
        return self.b(torch.tanh(self.a(torch.tanh(self.a(x)))))


class _Tied(torch.nn.Module):
    """Not a stack of Linear layers: two layers share a weight."""

    def __init__(self):
        super().__init__()
        self.a, self.b = torch.nn.Linear(4, 4).double(), torch.nn.Linear(4, 4).double()
        self.b.weight = self.a.weight
        self.c = torch.nn.Linear(4, STEPS).double()

    def forward(self, x):
        return self.c(torch.tanh(self.b(torch.tanh(self.a(x)))))


@pytest.mark.parametrize("bias", [True, False])
@pytest.mark.parametrize("act", [torch.nn.Tanh, torch.nn.ReLU, torch.nn.SiLU])
def test_layer_factors_give_the_gram_matrix_and_pullback_of_the_explicit_jacobian(bias, act):
    _, physics, _, x = small_problem()
    torch.manual_seed(3)
    model = torch.nn.Sequential(torch.nn.Linear(4, 7, bias=bias), act(),
                                torch.nn.Linear(7, 5), act(),
                                torch.nn.Linear(5, STEPS, bias=bias)).double()
    opt = HalfInverseGradients(model, physics, lambda y, t: y.sum(1))
    y, jac = opt.jacobian(x, x)
    y2, factors = opt.layer_factors(x, x)
    assert torch.equal(y, y2) and factors.shape == tuple(jac.shape)
    gram = jac @ jac.T
    assert float((factors.gram() - gram).abs().max()) <= 1e-13 * float(gram.abs().max())
    assert float((factors.dense() - jac).abs().max()) <= 1e-13 * float(jac.abs().max())
    w = torch.randn(jac.shape[0], dtype=jac.dtype, generator=torch.Generator().manual_seed(0))
    ref = jac.T @ w
    assert float((factors.rmatvec(w) - ref).abs().max()) <= 1e-13 * float(ref.abs().max())


@pytest.mark.parametrize("model", [_Scaled, _Twice, _Tied])
def test_other_models_form_the_jacobian(model):
    _, physics, _, x = small_problem()
    stepper = Oscillators(n=2, dt=0.25)
    net = model()
    opt = HalfInverseGradients(net, physics, lambda y, t: ((y - t) ** 2).sum(1), tau=1e-3)
    assert opt.layer_factors(x, x) is None
    # the explicit J against central differences: a shared weight or a layer used twice
    # must count every use
    _, jac = opt.jacobian(x, x)
    fd = fd_jacobian(stepper, net, flat_params(net), x)
    assert np.abs(jac.numpy() - fd).max() < 1e-8 * np.abs(fd).max()
    before = flat_params(net)
    opt.step(x, x, torch.zeros(3, 4, dtype=torch.float64))  # through the explicit J
    assert np.isfinite(flat_params(net)).all() and (flat_params(net) != before).any()


def test_non_finite_jacobian_is_a_clear_error():
    model = torch.nn.Linear(2, 2).double()
    physics = TorchPhysics(lambda f, c: torch.sqrt(f - f.detach()))  # d√z/dz at 0 is inf
    opt = HalfInverseGradients(model, physics, lambda y, t: y.sum(1))
    with pytest.raises(FloatingPointError, match="non-finite entries"):
        opt.step(torch.rand(2, 2, dtype=torch.float64), torch.zeros(2, 0), None)


@pytest.mark.parametrize("kwargs", [{"lr": -1.0}, {"tau": float("nan")}, {"kappa": "half"}])
def test_bad_settings_are_refused(kwargs):
    _, physics, model, _ = small_problem()
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        HalfInverseGradients(model, physics, lambda y, t: y.sum(1), **kwargs)


def test_problem_sizes_match_the_paper():
    counts = {name: sum(p.numel() for p in make_problem(name, 0, "tiny").model().parameters())
              for name in ("oscillators", "quantum", "poisson")}
    assert counts == {"oscillators": 2956, "quantum": 9484, "poisson": 24896}


def test_poisson_data_and_laplacian_agree_with_the_solver():
    from adjointsim.solvers.poisson import Poisson2D

    solver = Poisson2D(n=8, bc="dirichlet")
    f = np.random.default_rng(0).standard_normal((5, 1, 8, 8))
    u = solver.solve(f)  # (−Δ_h) u = f
    lap = five_point_laplacian(torch.from_numpy(u.reshape(5, 64)), solver.inv_h2, 8)
    np.testing.assert_allclose(lap.numpy(), -f.reshape(5, 64), atol=1e-11)
    p = make_problem("poisson", 0, "tiny")
    y, _, target = p.test
    assert torch.equal(y, target) and y.shape == (64, 64)


def test_poisson_fields_are_phiflow_noise_on_unit_cells():
    x = phiflow_noise(np.random.default_rng(0), 200, 8)
    np.testing.assert_allclose(x.std(axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(x.mean(axis=1), 0.0, atol=1e-12)
    # smooth: the 1/k² spectrum puts most of the energy in the lowest modes
    power = (np.abs(np.fft.fft2(x.reshape(-1, 8, 8))) ** 2).mean(axis=0)
    assert power[0, 1] > 20 * power[4, 4]
    # the problem's y is the unit-cell Laplacian of such fields: Δ⁻¹ y has unit std
    y = make_problem("poisson", 0, "tiny").test[0].numpy()
    from adjointsim.solvers.poisson import Poisson2D

    x_back = -Poisson2D(n=8, bc="dirichlet", length=9.0).solve(y.reshape(-1, 1, 8, 8))
    np.testing.assert_allclose(x_back.reshape(len(y), 64).std(axis=1), 1.0, rtol=1e-9)


def test_quantum_targets_are_normalised_and_the_loss_is_an_infidelity():
    p = make_problem("quantum", 0, "tiny")
    x, c, t = p.test
    np.testing.assert_allclose((t**2).sum(1).numpy(), 1.0, rtol=1e-12)
    # the initial ground state, through the physics with zero control, keeps unit norm
    y = p.physics(torch.zeros(2, 384, dtype=t.dtype), c[:2])
    np.testing.assert_allclose((y**2).sum(1).numpy(), 1.0, rtol=1e-10)
    assert torch.allclose(p.loss(t, t), torch.zeros(len(t), dtype=t.dtype), atol=1e-12)
    assert torch.allclose(p.loss(-t, t), torch.zeros(len(t), dtype=t.dtype), atol=1e-12)


def _interrupt_step(monkeypatch, after: int) -> None:
    """Ctrl-C (SIGINT) inside the update after ``after`` timed ones (the warm-up is the first
    call): as a user's, it stops the run once that update is done."""
    calls = {"n": 0}
    real_step = hig_problems.step

    def interrupted(*a):
        calls["n"] += 1
        if calls["n"] == after + 2:
            signal.raise_signal(signal.SIGINT)
        return real_step(*a)

    monkeypatch.setattr(hig_problems, "step", interrupted)


def _fake_clock(monkeypatch) -> None:
    """Every update takes 5 ms of CPU time: the evaluation marks, which follow the measured
    time, become the same from run to run."""
    clock = iter(range(1, 10**6))
    monkeypatch.setattr(time, "process_time", lambda: 0.0025 * next(clock))


def _model(out):
    return load_checkpoint(out / "checkpoint.pt", ("state",))["state"]["model"]


def _same_model(a, b) -> bool:
    ma, mb = _model(a), _model(b)
    return ma.keys() == mb.keys() and all(torch.equal(ma[k], mb[k]) for k in ma)


def test_run_writes_history_refuses_overwrite_and_resumes(tmp_path, monkeypatch):
    cfg = HigConfig("chain", "hig", seed=0, budget=1e6, size="tiny", max_updates=6)
    _interrupt_step(monkeypatch, after=2)
    with pytest.raises(KeyboardInterrupt):
        train_run(cfg, tmp_path, progress=False)
    assert (tmp_path / "checkpoint.pt").exists() and not (tmp_path / "result.json").exists()
    with pytest.raises(RunExists, match="--resume"):
        train_run(cfg, tmp_path, progress=False)
    result = train_run(cfg, tmp_path, resume=True, progress=False)
    assert result["updates"] == 6 and result["test_loss"] is not None
    history = (tmp_path / "history.csv").read_text().splitlines()
    assert history[0] == "update,wall_s,train_loss,test_loss"
    updates = [int(line.split(",")[0]) for line in history[1:]]
    assert updates[0] == 0 and updates[-1] == 6 and updates == sorted(updates)
    assert (tmp_path / "loss.png").stat().st_size > 1000
    with pytest.raises(RunExists, match="finished"):
        train_run(cfg, tmp_path, progress=False)
    assert train_run(cfg, tmp_path, resume=True, progress=False) == result
    other = HigConfig("chain", "hig", seed=0, budget=1e6, size="tiny", max_updates=5)
    with pytest.raises(RunExists, match="max_updates = 6; pass as much or more"):
        train_run(other, tmp_path, resume=True, progress=False)
    other = HigConfig("chain", "hig", seed=1, budget=1e6, size="tiny", max_updates=6)
    with pytest.raises(RunExists, match="differs in seed"):
        train_run(other, tmp_path, resume=True, progress=False)
    assert json.loads((tmp_path / "result.json").read_text())["optimizer"] == "hig"


@pytest.mark.parametrize(("problem", "optimizer"), [("chain", "hig"), ("poisson", "adam")])
def test_interrupted_run_resumes_to_the_same_model(tmp_path, monkeypatch, problem, optimizer):
    """The same model, result and history (the Poisson fields drawn ahead are part of the
    checkpoint)."""
    _fake_clock(monkeypatch)
    cfg = HigConfig(problem, optimizer, seed=0, budget=1e6, size="tiny", max_updates=5)
    whole = train_run(cfg, tmp_path / "a", progress=False, plot=False)
    with monkeypatch.context() as m:
        _interrupt_step(m, after=3)
        with pytest.raises(KeyboardInterrupt):
            train_run(cfg, tmp_path / "b", progress=False, plot=False)
    resumed = train_run(cfg, tmp_path / "b", resume=True, progress=False, plot=False)
    assert resumed["updates"] == whole["updates"] == 5
    assert resumed["test_loss"] == whole["test_loss"]
    assert _same_model(tmp_path / "a", tmp_path / "b")
    assert _history(tmp_path / "a") == _history(tmp_path / "b")


def _history(out) -> str:
    return (out / "history.csv").read_text()


def test_finished_run_continues_to_more_updates(tmp_path, monkeypatch):
    """A run finished at max_updates 3, continued to 6, is the run of 6: its final
    evaluation was no step of the training."""
    _fake_clock(monkeypatch)

    def cfg(n):
        return HigConfig("chain", "hig", seed=0, budget=1e6, size="tiny", max_updates=n)

    whole = train_run(cfg(6), tmp_path / "a", progress=False, plot=False)
    train_run(cfg(3), tmp_path / "b", progress=False, plot=False)
    with pytest.raises(RunExists, match="continue it to more with --resume"):
        train_run(cfg(6), tmp_path / "b", progress=False, plot=False)
    longer = train_run(cfg(6), tmp_path / "b", resume=True, progress=False, plot=False)
    assert longer["updates"] == 6 and longer["test_loss"] == whole["test_loss"]
    assert _same_model(tmp_path / "a", tmp_path / "b")
    assert _history(tmp_path / "a") == _history(tmp_path / "b")  # the final row at 3 is gone
    assert longer["wall_s"] == whole["wall_s"]


def test_corrupt_checkpoint_is_a_clear_error(tmp_path):
    cfg = HigConfig("chain", "hig", seed=0, budget=1e6, size="tiny", max_updates=2)
    train_run(cfg, tmp_path, progress=False, plot=False)
    (tmp_path / "result.json").unlink()
    (tmp_path / "checkpoint.pt").write_text("garbage\n")
    with pytest.raises(ValueError, match="checkpoint.pt is not a readable checkpoint"):
        train_run(cfg, tmp_path, resume=True, progress=False)
    (tmp_path / "config.json").unlink()  # not this run's files: refused before reading them
    with pytest.raises(RunExists, match="no readable config.json"):
        train_run(cfg, tmp_path, resume=True, progress=False)


def test_a_run_stopped_after_its_last_checkpoint_resumes_without_a_second_row(tmp_path):
    cfg = HigConfig("chain", "hig", seed=0, budget=1e6, size="tiny", max_updates=3)
    first = train_run(cfg, tmp_path, progress=False, plot=False)
    rows = read_history(tmp_path / "history.csv")
    (tmp_path / "result.json").unlink()  # Ctrl-C while plotting: no result yet
    again = train_run(cfg, tmp_path, resume=True, progress=False, plot=False)
    assert str(read_history(tmp_path / "history.csv")) == str(rows) and again == first
    with pytest.raises(ValueError, match=rf"'seed': -1 is not an integer in \[0, {2**63 - 1}\]"):
        HigConfig("chain", "hig", seed=-1, budget=1.0).validate()


def test_cli_runs_and_refuses_in_one_line(tmp_path, capsys):
    from adjointsim.cli import main

    out = tmp_path / "run"
    args = ["hig", "chain", "--optimizer", "gn", "--max-updates", "3", "--out", str(out)]
    assert main(args) == 0
    assert "3 updates" in capsys.readouterr().out
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "finished run" in err[0]


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_cli_resume_without_a_checkpoint_is_one_line(tmp_path, capsys):
    from adjointsim.cli import main

    out = tmp_path / "empty"
    out.mkdir()
    assert main(["hig", "chain", "--resume", "--out", str(out), "--no-progress"]) == 2
    assert "holds no run to continue" in _one_line(capsys)


def test_cli_overwrite_discards_the_run_and_starts_again(tmp_path, capsys):
    from adjointsim.cli import main

    out = tmp_path / "run"
    args = ["hig", "chain", "--size", "tiny", "--out", str(out), "--no-progress"]
    assert main([*args, "--max-updates", "3"]) == 0
    assert main([*args, "--max-updates", "2"]) == 2  # another run is there: refused
    assert "holds a run of max_updates = 3" in _one_line(capsys)
    assert main([*args, "--max-updates", "2", "--overwrite"]) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["updates"] == 2 and result["max_updates"] == 2
    assert read_history(out / "history.csv")[-1]["update"] == 2


def test_cli_config_file_sets_keys_and_names_a_wrong_typed_one(tmp_path, capsys):
    from adjointsim.cli import main

    good = tmp_path / "good.toml"
    good.write_text('optimizer = "adam"\nsize = "tiny"\nmax_updates = 2\nbudget = 50\n')
    out = tmp_path / "run"
    assert main(["hig", "chain", "--config", str(good), "--max-updates", "1", "--out", str(out),
                 "--no-progress"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config == {"problem": "chain", "optimizer": "adam", "seed": 0, "budget": 50.0,
                      "size": "tiny", "max_updates": 1, "threads": 1, "compile": "off",
                      # the flag overrides the file; the scene recorded
                      "scene": PROBLEMS.get("chain").SCENE}
    bad = tmp_path / "bad.toml"
    bad.write_text('max_updates = "three"\n')
    assert main(["hig", "chain", "--config", str(bad), "--out", str(tmp_path / "other")]) == 2
    assert "'max_updates'" in _one_line(capsys)
    assert HigConfig.load(problem="chain").budget == 100.0  # the problem's default


def test_cli_help_lists_the_choices(capsys):
    from adjointsim.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["hig", "--help"])
    assert stop.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert set(PROBLEMS.names()) == {"oscillators", "quantum", "poisson", "poisson64", "chain"}
    for part in ("{" + ",".join(PROBLEMS.names()) + "}", "{adam,gn,hig}", "{tiny,quick,full}",
                 "--time-budget", "--max-updates", "--resume", "--overwrite", "--config",
                 "--seed", "--threads", "--no-progress", "chain 100", "--scene KEY=VALUE"):
        assert part in text, part


def test_cli_ctrl_c_leaves_a_checkpoint_to_resume(tmp_path, capsys, monkeypatch):
    from adjointsim.cli import main

    _interrupt_step(monkeypatch, after=1)
    out = tmp_path / "run"
    args = ["hig", "chain", "--size", "tiny", "--max-updates", "3", "--out", str(out),
            "--no-progress"]
    assert main(args) == 130
    assert f"continue with the same command and --resume (--out {out})" in _one_line(capsys)
    assert (out / "checkpoint.pt").exists() and not (out / "result.json").exists()
    assert main([*args, "--resume"]) == 0
    assert json.loads((out / "result.json").read_text())["updates"] == 3


def test_tiny_study_end_to_end(tmp_path):
    import adjointsim.train.studies.hig as study
    from adjointsim.runner import run

    rows = run("hig", tmp_path, "tiny", None, cluster="none", progress=False)
    assert {(r["problem"], r["optimizer"]) for r in rows} == {
        (p, o) for p in ("chain", "oscillators") for o in ("adam", "gn", "hig")
    }
    for r in rows:
        assert {"problem", "optimizer", "seed", "wall_s", "test_loss"} <= set(r)
        assert r["wall_s"] >= r["budget"] or r["diverged"]
    text = (tmp_path / "table.txt").read_text()
    assert "chain" in text and "HIG below ADAM" in text
    assert (tmp_path / "hig.png").stat().st_size > 1000
    # a second run reuses every finished cell
    cell = study.cells("tiny", None)[0]
    assert study.run_cell(cell, tmp_path / cell["id"])["test_loss"] == rows[0]["test_loss"]


@pytest.mark.slow
def test_quick_study_reproduces_hig_below_adam_on_the_linear_chain(tmp_path):
    import adjointsim.train.studies.hig  # noqa: F401
    from adjointsim.runner import run

    rows = run("hig", tmp_path, "quick", 3, cluster="local", jobs=2, progress=False)
    chain = {(r["optimizer"], r["seed"]): r["test_loss"] for r in rows if r["problem"] == "chain"}
    for seed in range(3):
        assert chain[("hig", seed)] * 100 < chain[("adam", seed)]


def test_auto_takes_the_gram_route_only_where_tau_resolves_the_dropped_directions():
    _, physics, model, _ = small_problem()
    rng = np.random.default_rng(3)
    # a wide J with singular values from 1 down to 1e-9
    u = np.linalg.qr(rng.standard_normal((12, 12)))[0]
    v = np.linalg.qr(rng.standard_normal((40, 12)))[0]
    s = np.logspace(0, -9, 12)
    jac, g = torch.from_numpy(u * s @ v.T), torch.from_numpy(rng.standard_normal(12))

    def direction(tau, decomposition="auto", dtype=torch.float64):
        opt = HalfInverseGradients(model, physics, lambda y, t: y.sum(1), tau=tau,
                                   decomposition=decomposition)
        return opt, opt.direction(jac.to(dtype), g.to(dtype)).double().numpy()

    for tau in (1e-4, 1e-10):
        keep = s > tau
        exact = v[:, keep] @ (s[keep] ** -0.5 * (u[:, keep].T @ g.numpy()))
        opt, got = direction(tau)
        assert opt._gram(torch.float64) == (tau == 1e-4)
        # the SVD route resolves σ = 1e-9 to about ε·cond(J) = 1e-7 relative
        np.testing.assert_allclose(got, exact, rtol=1e-8 if tau == 1e-4 else 1e-5)
    assert not direction(1e-4)[0]._gram(torch.float32)  # 1e-8 is below float32's resolution
    # forced with τ = 0, the Gram route still drops what is round-off (σ < √(12 ε) ≈ 5e-8)
    # instead of dividing by it; the kept σ = 2.8e-7 is resolved to about ε/σ² = 3e-3
    keep = s > 1e-7
    exact = v[:, keep] @ (s[keep] ** -0.5 * (u[:, keep].T @ g.numpy()))
    np.testing.assert_allclose(direction(0.0, "gram")[1], exact, rtol=2e-2)
    zero = HalfInverseGradients(model, physics, lambda y, t: y.sum(1), decomposition="gram")
    assert not zero.direction(torch.zeros(3, 5, dtype=torch.float64),
                              torch.ones(3, dtype=torch.float64)).any()
    with pytest.raises(ValueError, match="unknown decomposition 'qr'; choose from auto, svd"):
        HalfInverseGradients(model, physics, lambda y, t: y.sum(1), decomposition="qr")


def test_a_checkpoint_of_another_layout_is_one_line(tmp_path, capsys):
    """An unfinished run saved with other layer names (an older version's network) is refused
    with what to do, not a traceback."""
    from adjointsim.cli import main
    from adjointsim.train.checkpoint import save_checkpoint

    out = tmp_path / "r"
    argv = ["hig", "poisson", "--max-updates", "2", "--out", str(out), "--no-progress"]
    assert main(argv) == 0
    (out / "result.json").unlink()
    ckpt = load_checkpoint(out / "checkpoint.pt", ("state",))
    ckpt["state"]["model"] = {f"old.{k}": v for k, v in ckpt["state"]["model"].items()}
    save_checkpoint(ckpt, out / "checkpoint.pt")
    capsys.readouterr()
    assert main([*argv, "--resume"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--overwrite" in err


def test_scene_keys_change_the_solver_and_are_recorded(tmp_path, capsys):
    """--scene over the problem's scene (the chain's Δt = 0.5): recorded whole in config.json,
    a different run; a key the solver does not take, or a value it refuses, is one line."""
    from adjointsim.cli import main

    args = ["hig", "chain", "--size", "tiny", "--max-updates", "2", "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "a")]) == 0
    assert main([*args, "--scene", "dt=0.25", "--out", str(tmp_path / "b")]) == 0
    config = json.loads((tmp_path / "b" / "config.json").read_text())
    assert config["scene"] == {**PROBLEMS.get("chain").SCENE, "dt": 0.25}
    results = [json.loads((tmp_path / d / "result.json").read_text()) for d in "ab"]
    assert results[0]["test_loss"] != results[1]["test_loss"]
    assert make_problem("chain", 0, "tiny", {"dt": 0.25}).solver.dt == 0.25
    capsys.readouterr()
    for scene, message in [("dt=-1", "'scene': oscillators-rk4: dt must be a finite number > 0"),
                           ("mass=2", "scene key 'mass': oscillators-rk4 takes n, dt,"),
                           ("n=2.5", "n must be an integer")]:
        assert main([*args, "--scene", scene, "--out", str(tmp_path / "c")]) == 2
        assert message in _one_line(capsys)
    assert not (tmp_path / "c").exists()
    with pytest.raises(ValueError, match="scene key 'bc' is fixed to 'dirichlet'"):
        HigConfig("poisson", scene={"bc": "periodic"}).validate()


def test_oscillators_scene_sizes_the_data_and_network():
    p = make_problem("oscillators", 0, "tiny", {"n": 3})
    x, _, _ = p.test
    assert x.shape == (256, 6) and p.model()(x).shape == (256, 96)
    assert p.test_loss(p.model()) > 0
