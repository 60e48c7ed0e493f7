"""The SSIM used by the D-SSIM loss and the metrics against kornia's ssim (the reference it
replaces for speed), and its gradient against finite differences."""
import pytest
import torch
from kornia.metrics import ssim as kornia_ssim

from omnire.losses import ssim_map


@pytest.mark.parametrize("shape", [(37, 53, 3), (16, 16, 1)])
def test_ssim_map_matches_kornia(shape):
    g = torch.Generator().manual_seed(0)
    a = torch.rand(*shape, generator=g, dtype=torch.float64)
    b = (a + 0.2 * torch.randn(*shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    ref = kornia_ssim(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], 11)[0].mean(0)[..., None]
    torch.testing.assert_close(ssim_map(a, b), ref, rtol=0, atol=1e-6)
    torch.testing.assert_close(ssim_map(a, a), torch.ones_like(ref), rtol=0, atol=1e-6)


def test_ssim_gradient_matches_finite_differences():
    g = torch.Generator().manual_seed(1)
    a = torch.rand(12, 13, 3, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.rand(12, 13, 3, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: ssim_map(x, b).mean(), (a,), eps=1e-6, atol=1e-6)


def test_ssim_refuses_mismatched_images():
    with pytest.raises(ValueError, match="one shape"):
        ssim_map(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))
