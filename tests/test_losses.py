import math

import pytest
import torch

from gear.losses import composite, depth_log_l1, opacity_binarisation, photometric, ssim


def test_ssim_of_identical_images_is_one():
    img = torch.rand(20, 24, 3, generator=torch.Generator().manual_seed(0))
    assert float(ssim(img, img)) == pytest.approx(1.0, abs=1e-5)


def test_ssim_drops_with_noise_and_is_symmetric():
    g = torch.Generator().manual_seed(1)
    a = torch.rand(16, 16, 3, generator=g)
    b = (a + 0.3 * torch.randn(16, 16, 3, generator=g)).clamp(0, 1)
    assert float(ssim(a, b)) < 0.9
    assert float(ssim(a, b)) == pytest.approx(float(ssim(b, a)), abs=1e-6)


def test_ssim_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="ssim"):
        ssim(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))


def test_photometric_mixes_l1_and_dssim():
    a = torch.zeros(12, 12, 3)
    b = torch.full((12, 12, 3), 0.5)
    expected = 0.8 * 0.5 + 0.2 * (1 - float(ssim(a, b)))
    assert float(photometric(a, b, 0.2)) == pytest.approx(expected, rel=1e-6)
    assert float(photometric(b, b, 0.2)) == pytest.approx(0.0, abs=1e-6)


def test_depth_loss_uses_only_valid_pixels():
    rendered = torch.tensor([[1.0, 2.0], [3.0, 5.0]])
    target = torch.tensor([[1.5, 0.0], [3.0, 0.0]])  # 0 = missing
    expected = (math.log1p(0.5) + math.log1p(0.0)) / 2
    assert float(depth_log_l1(rendered, target)) == pytest.approx(expected, rel=1e-6)
    assert float(depth_log_l1(rendered, torch.zeros(2, 2))) == 0.0


def test_opacity_binarisation_matches_bce_and_pushes_to_the_nearer_end():
    logits = torch.tensor([2.0, -1.0, 0.1], requires_grad=True)
    o = torch.sigmoid(logits.detach())
    target = torch.tensor([1.0, 0.0, 1.0])
    expected = -(target * torch.log(o) + (1 - target) * torch.log(1 - o)).mean()
    loss = opacity_binarisation(logits)
    assert loss.item() == pytest.approx(float(expected), rel=1e-6)
    loss.backward()
    # descent direction (-grad) raises opacities above 0.5 and lowers those below
    assert logits.grad[0] < 0 and logits.grad[1] > 0 and logits.grad[2] < 0


def test_composite_over_background():
    rgb = torch.tensor([[[1.0, 0.0, 0.0]]])
    alpha = torch.tensor([[0.25]])
    out = composite(rgb, alpha, torch.tensor([0.0, 0.0, 1.0]))
    assert torch.allclose(out, torch.tensor([[[0.25, 0.0, 0.75]]]))


def test_separable_ssim_matches_a_direct_2d_window():
    import torch.nn.functional as F

    g = torch.Generator().manual_seed(2)
    a, b = torch.rand(20, 17, 3, generator=g), torch.rand(20, 17, 3, generator=g)
    x = torch.arange(11, dtype=torch.float32) - 5
    w1 = torch.exp(-(x**2) / (2 * 1.5**2))
    w1 = w1 / w1.sum()
    window = (w1[:, None] * w1[None, :]).expand(3, 1, 11, 11)

    def blur(t):
        return F.conv2d(t, window, padding=5, groups=3)

    xa, xb = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
    mx, my = blur(xa), blur(xb)
    vx, vy, cxy = blur(xa * xa) - mx**2, blur(xb * xb) - my**2, blur(xa * xb) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    expected = ((2 * mx * my + c1) * (2 * cxy + c2)
                / ((mx**2 + my**2 + c1) * (vx + vy + c2))).mean()
    assert float(ssim(a, b)) == pytest.approx(float(expected), abs=1e-5)
