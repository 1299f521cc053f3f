"""Networks: shapes, periodicity (circular padding) and the List et al. parameter counts."""

import numpy as np
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


@pytest.mark.parametrize(("make", "message"), [
    (lambda: ResNet(1, 1, kernel=4), "kernel must be odd to keep the grid size, not 4"),
    (lambda: ResNet(1, 1, width=-4), r"ResNet: width must be an integer ≥ 1, got -4"),
    (lambda: ResNet(0, 1), r"ResNet: in_channels must be an integer ≥ 1, got 0"),
    (lambda: UNet(1, 1, width=0), r"UNet: width must be an integer ≥ 1, got 0"),
    (lambda: UNet(1, 1, levels=-1), r"UNet: levels must be an integer ≥ 0, got -1"),
])
def test_a_network_that_cannot_keep_the_grid_is_refused_when_built(make, message):
    """an even kernel failed only in forward, a negative width or level in torch or indexing."""
    with pytest.raises(ValueError, match=message):
        make()


def test_sizes_of_another_type_are_a_type_error_and_numpy_integers_are_sizes():
    with pytest.raises(TypeError, match="ResNet: width must be an integer, got float 2.5"):
        ResNet(1, 1, width=2.5)
    unet = UNet(1, 1, levels=np.int64(1), width=np.int64(2))
    assert unet(torch.zeros(1, 1, 8)).shape == (1, 1, 8)
    # no blocks: the encoder and decoder alone, as before the sizes were checked
    assert ResNet(1, 1, blocks=0)(torch.zeros(1, 1, 4)).shape == (1, 1, 4)


@pytest.mark.parametrize(("net", "x", "message"), [
    (ResNet(1, 1, blocks=1), torch.zeros(2, 1, 16, 16),
     r"ResNet takes a tensor of shape \(batch, 1, N\), not \(2, 1, 16, 16\)"),
    (UNet(2, 1, 2), torch.zeros(2, 1, 16, 16),
     r"UNet takes a tensor of shape \(batch, 2, H, W\), not \(2, 1, 16, 16\)"),
    (DilatedResNet(1, 1), torch.zeros(1, 1, 4),
     r"DilatedResNet needs at least 8 grid point\(s\) per axis .*, not \(4,\)"),
])
def test_an_input_the_network_cannot_take_is_named_with_the_network(net, x, message):
    """torch's own errors named a padding size or 'wrapping around more than once'."""
    with pytest.raises(ValueError, match=message):
        net(x)
    # zero padding has no wrap-around limit
    assert DilatedResNet(1, 1, padding="zeros")(torch.zeros(1, 1, 4)).shape == (1, 1, 4)
