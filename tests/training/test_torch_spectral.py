"""The PyTorch KS baseline of the spectral benchmarks (benchmarks/torch_spectral.py): its forward
and autograd gradient match ours, and one of its steps is one step of our rollout."""

import numpy as np
import pytest
import torch

import adjointsim.solvers.kuramoto_sivashinsky  # noqa: F401
from adjointsim import get
from adjointsim.bench.work_precision import relative_error


@pytest.mark.parametrize("dealias", [False, True])
def test_torch_ks_matches_ours_forward_and_gradient(dealias):
    from torch_spectral import TorchKS, forward_and_gradient

    stepper = get("ks1d-etdrk4")(n=128, length=64.0, dt=0.25, dealias=dealias)
    u0 = stepper.random_state(np.random.default_rng(1), 3)
    model = TorchKS(128, 64.0, 0.25, dealias=dealias)
    last, grad = forward_and_gradient(model, u0, 100)
    ours = stepper.rollout(u0, 100)
    assert relative_error(last, ours) < 1e-10
    ours_grad = stepper.vjp(u0, 100, ours).state
    assert relative_error(grad, ours_grad) < 1e-8


def test_torch_ks_step_is_one_rollout_step():
    from torch_spectral import TorchKS

    model = TorchKS(32, 22.0, 0.1, anti_diffusion=0.8, hyper_diffusion=1.2)
    stepper = get("ks1d-etdrk4")(n=32, length=22.0, dt=0.1, anti_diffusion=0.8,
                                 hyper_diffusion=1.2)
    u0 = stepper.random_state(np.random.default_rng(2), 2)
    u1 = model.step(torch.from_numpy(u0)).numpy()
    assert relative_error(u1, stepper.step(u0)) < 1e-12
