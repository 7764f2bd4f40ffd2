import pytest
import torch

from umi_aug.errors import PolicyError
from umi_aug.policy.unet import ConditionalUnet1D, SinusoidalPosEmb


@pytest.mark.parametrize("down_dims,horizon,scale", [([32, 64], 16, True), ([16, 32, 64], 16, False),
                                                      ([32], 10, True), ([16, 32, 64], 8, True)])
def test_unet_shapes(down_dims, horizon, scale):
    torch.manual_seed(0)
    net = ConditionalUnet1D(10, global_cond_dim=24, diffusion_step_embed_dim=16, down_dims=down_dims, kernel_size=5,
                            n_groups=8, cond_predict_scale=scale)
    x = torch.randn(3, horizon, 10)
    for t in (torch.tensor([0, 5, 9]), torch.tensor(7), 3):
        y = net(x, t, global_cond=torch.randn(3, 24))
        assert y.shape == x.shape and torch.isfinite(y).all()
    y.sum().backward()
    assert all(p.grad is not None for p in net.parameters())


def test_unet_umi_size_and_conditioning():
    """UMI's U-Net (down_dims 256/512/1024, kernel 5, FiLM scale) on a 1568-d condition; output depends on cond/t."""
    torch.manual_seed(0)
    net = ConditionalUnet1D(10, 1568, 128, [256, 512, 1024], 5, 8, True).eval()
    x, c = torch.randn(2, 16, 10), torch.randn(2, 1568)
    with torch.no_grad():
        y0 = net(x, torch.tensor([3, 3]), c)
        assert y0.shape == (2, 16, 10)
        assert not torch.allclose(y0, net(x, torch.tensor([3, 3]), c + 1.0))
        assert not torch.allclose(y0, net(x, torch.tensor([40, 40]), c))


def test_unet_rejects_bad_input():
    net = ConditionalUnet1D(10, 8, 16, [16, 32, 64], 3, 8)
    with pytest.raises(PolicyError, match="multiple of 4"):
        net(torch.randn(1, 10, 10), 0, torch.randn(1, 8))
    with pytest.raises(PolicyError, match="global_cond"):
        net(torch.randn(1, 16, 10), 0, None)
    with pytest.raises(PolicyError, match="sample"):
        net(torch.randn(1, 16, 7), 0, torch.randn(1, 8))
    with pytest.raises(PolicyError, match="divisible"):
        ConditionalUnet1D(10, 8, 16, [12, 32], 3, 8)


def test_sinusoidal_embedding():
    emb = SinusoidalPosEmb(8)(torch.tensor([0.0, 1.0]))
    assert emb.shape == (2, 8)
    assert torch.allclose(emb[0], torch.tensor([0, 0, 0, 0, 1, 1, 1, 1.0]))
    assert torch.allclose(emb[1, 0], torch.sin(torch.tensor(1.0)))
