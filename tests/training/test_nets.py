"""Networks: shapes, periodicity (circular padding) and the List et al. parameter counts."""

import pytest
import torch

from adjointsim.nets import MLP, DilatedResNet, ResNet, UNet, parameter_count


def test_resnet_presets_match_list_et_al():
    assert abs(parameter_count(ResNet.preset("small", 2, 1)) - 33_000) < 500
    assert abs(parameter_count(ResNet.preset("large", 2, 1)) - 196_000) < 1_000


@pytest.mark.parametrize("dims", [1, 2])
@pytest.mark.parametrize("make", [
    lambda d: ResNet(2, 1, d, width=8, blocks=2),
    lambda d: DilatedResNet(2, 1, d, width=8, dilations=(1, 2, 1)),
    lambda d: UNet(2, 1, d, width=4, levels=2),
])
def test_conv_nets_are_translation_equivariant_on_periodic_grids(make, dims):
    torch.manual_seed(0)
    net = make(dims).double()
    shape = (3, 2, 16) if dims == 1 else (3, 2, 16, 16)
    x = torch.randn(shape, dtype=torch.float64)
    y = net(x)
    assert y.shape == (shape[0], 1, *shape[2:])
    shifted = net(torch.roll(x, 4, dims=-1))
    torch.testing.assert_close(shifted, torch.roll(y, 4, dims=-1))


def test_mlp_activations():
    # a shape alone would pass with any activation (or none) between the layers
    torch.manual_seed(0)
    x = torch.randn(5, 3)
    for act, fn in (("sin", torch.sin), ("tanh", torch.tanh), ("relu", torch.relu)):
        mlp = MLP(3, 2, width=8, depth=2, activation=act)
        *hidden, last = [m for m in mlp.modules() if isinstance(m, torch.nn.Linear)]
        assert len(hidden) == 2
        h = x
        for layer in hidden:
            h = fn(layer(h))
        torch.testing.assert_close(mlp(x), last(h), rtol=0, atol=0)
    with pytest.raises(ValueError, match="unknown activation"):
        MLP(3, 2, activation="swish2")


def test_unet_rejects_indivisible_grids():
    with pytest.raises(ValueError, match="divisible by 4"):
        UNet(1, 1, 1, levels=2)(torch.randn(1, 1, 18))
