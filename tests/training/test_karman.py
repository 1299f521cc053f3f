"""The karman neural-stepper problem (train/steppers/karman.py): the cylinder wake's reference
and source solvers, the flux restriction between them, its dataset, the correction's gradient
through the bridge against central differences, the networks' non-periodic padding and the
``karman`` study end to end at its tiny size."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from adjointsim.errors import UserError
from adjointsim.nets import ResNet
from adjointsim.train import data as datamod
from adjointsim.train.model import NeuralStepper
from adjointsim.train.problems import PROBLEMS, get_problem
from adjointsim.train.unroll import unrolled_loss

#: the tiny study's scene: a 32 x 16 reference, a 16 x 8 source
SMALL = {"n": 16, "coarse_n": 8}


@pytest.fixture(scope="module")
def small():
    return get_problem("karman", SMALL)


@pytest.fixture(scope="module")
def dataset(small):
    return datamod.generate(small, "tiny", seed=0, progress=False)


def test_karman_is_registered_with_two_channels_and_replicate_padding():
    p = PROBLEMS["karman"]
    assert (p.dims, p.channels, p.padding) == (2, 2, "replicate")
    ref, coarse = p.reference(200.0), p.coarse(200.0)
    assert (ref.nx, ref.ny, coarse.nx, coarse.ny) == (128, 64, 32, 16)
    assert coarse.dt == pytest.approx(p.substeps * ref.dt)
    assert ref.params["nu"] == pytest.approx(0.25 / 200.0)


def test_a_model_state_beyond_the_source_solvers_limit_is_a_blow_up(small):
    from adjointsim.train.evaluate import BLOW_UPS

    source = small.coarse(200.0)
    u = np.zeros(source.state_shape(1))
    u[0, 0, 3, 2] = 1.01 * source.h / source.dt
    with pytest.raises(BLOW_UPS, match="the model's state moves at up to"):
        source.rollout(u, 1)
    u[0, 0, 3, 2] = 0.99 * source.h / source.dt
    assert np.isfinite(source.rollout(u, 1)).all()


def test_a_source_grid_that_does_not_divide_the_reference_is_refused():
    with pytest.raises(UserError, match="coarse_n .* must be a positive integer that divides n"):
        get_problem("karman", {"n": 16, "coarse_n": 5})


def test_the_flux_restriction_keeps_the_velocity_divergence_free(small):
    ref = small.reference(200.0)
    u = small.initial_states(np.random.default_rng(1), 200.0, 2, "train")
    u = ref.rollout(u, 3)  # projected: divergence-free on the reference grid
    coarse = small.to_coarse(u)
    assert coarse.shape == (2, 2, 17, 9)
    assert np.abs(small.coarse(200.0).divergence(coarse)).max() < 1e-10
    # a coarse face is the mean of the fine faces it covers
    assert coarse[1, 0, 3, 2] == pytest.approx(u[1, 0, 6, 4:6].mean())


def test_karman_dataset_round_trips_with_its_scene(dataset, tmp_path):
    train = dataset.splits["train"]
    assert train.trajectories.shape == (4, 24, 2, 17, 9)
    assert list(train.params) == [100.0, 200.0, 400.0, 800.0]
    assert np.allclose(train.conditions, train.params / 1000.0)
    path = datamod.save(dataset, tmp_path / "karman.h5")
    back = datamod.load(path)
    assert back.problem.scene == {**PROBLEMS["karman"].SCENE, **SMALL}
    assert np.array_equal(back.splits["interpolation"].trajectories,
                          dataset.splits["interpolation"].trajectories)


def _model(small) -> NeuralStepper:
    torch.manual_seed(0)
    net = ResNet(3, 2, 2, width=4, blocks=1, padding="replicate").double()
    return NeuralStepper(net, "correction", small.coarse, "sequential")


@pytest.mark.parametrize("mode", ["WIG", "NOG"])
def test_correction_gradient_through_the_bridge_matches_central_differences(small, dataset,
                                                                             mode):
    """Two unrolled correction steps S then f: the loss's derivative along a random direction
    of the weights, from the solver's adjoint (WIG) or without it (NOG), against central
    differences of the same loss (NOG's stops gradients, so it differs from WIG's)."""
    model = _model(small)
    split = dataset.splits["train"]
    frames = torch.from_numpy(split.trajectories[:2, :3]).double()
    params = torch.from_numpy(split.params[:2])
    cond = torch.from_numpy(split.conditions[:2])
    weights = list(model.parameters())
    loss = unrolled_loss(model, frames, params, cond, mode)
    grads = torch.autograd.grad(loss, weights)
    gen = torch.Generator().manual_seed(1)
    dirs = [torch.randn(w.shape, generator=gen, dtype=w.dtype) for w in weights]
    slope = sum(float((g * d).sum()) for g, d in zip(grads, dirs))

    def loss_at(eps: float) -> float:
        with torch.no_grad():
            for w, d in zip(weights, dirs):
                w.add_(eps * d)
            value = float(unrolled_loss(model, frames, params, cond, "WIG"))
            for w, d in zip(weights, dirs):
                w.sub_(eps * d)
        return value

    eps = 1e-6
    fd = (loss_at(eps) - loss_at(-eps)) / (2 * eps)
    if mode == "WIG":
        assert slope == pytest.approx(fd, rel=1e-6)
    else:  # the solver's derivative left out of the second step's chain
        assert abs(slope - fd) > 1e-4 * abs(fd)


def test_replicate_padding_does_not_wrap_around():
    torch.manual_seed(0)
    x = torch.randn(1, 3, 12, 8, dtype=torch.float64)
    bumped = x.clone()
    bumped[..., -1, :] += 1.0  # the last column along x
    for padding, wraps in (("circular", True), ("replicate", False), ("zeros", False)):
        net = ResNet(3, 2, 2, width=4, blocks=1, padding=padding).double()
        change = (net(bumped) - net(x))[..., 0, :].abs().max()
        assert bool(change > 0) == wraps, padding
    with pytest.raises(ValueError, match="padding must be one of circular, zeros, replicate"):
        ResNet(3, 2, 2, padding="reflect")


def test_karman_study_tiny(tmp_path):
    from adjointsim.runner import run
    from adjointsim.train.studies import load_all

    load_all()
    out = tmp_path / "karman"
    rows = run("karman", out, "tiny", None, cluster="none", progress=False)
    assert sorted(r["mode"] for r in rows) == ["NOG", "ONE", "WIG"]
    for r in rows:
        assert r["setup"] == "correction" and np.isfinite(r["coarse_rel_error"])
        assert r["rel_error"] is None or r["rel_error"] > 0
    table = (out / "table.txt").read_text()
    assert "correction  WIG" in table and "coarse solver alone" in table
    assert (out / "study.png").stat().st_size > 0
