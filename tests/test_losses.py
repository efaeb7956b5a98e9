"""The training SSIM: separable blur vs the 2D-window definition, values and gradients."""
import torch
import torch.nn.functional as F

from baseline.train.losses import gaussian_blur, reconstruction_loss, ssim


def window_2d(size=11, sigma=1.5):
    """[size,size] float64: the 2D Gaussian window, written out independently of the module."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x ** 2) / (2 * sigma ** 2))
    g = g / g.sum()
    return g[:, None] * g[None, :]


def ssim_2d(img, gt, size=11, sigma=1.5):
    """The definition: 2D Gaussian window, depthwise conv, zero padding."""
    C = img.shape[-1]
    w = window_2d(size, sigma).expand(C, 1, size, size).to(img)
    a, b = img.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None]
    blur = lambda t: F.conv2d(t, w, padding=size // 2, groups=C)  # noqa: E731
    mx, my = blur(a), blur(b)
    sxx, syy, sxy = blur(a * a) - mx ** 2, blur(b * b) - my ** 2, blur(a * b) - mx * my
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return ((2 * mx * my + c1) * (2 * sxy + c2) / ((mx ** 2 + my ** 2 + c1) * (sxx + syy + c2))).mean()


def test_blur_matches_the_2d_window_at_the_borders():
    t = torch.zeros(1, 9, 13, dtype=torch.float64)
    t[0, 0, 0] = 1.0                          # a corner impulse: the border is where padding shows
    t[0, 4, 12] = 2.0
    got = gaussian_blur(t)
    ref = F.conv2d(t[None], window_2d()[None, None], padding=5)[0]
    assert torch.allclose(got, ref, atol=1e-15)


def test_ssim_and_its_gradient_match_the_definition():
    gen = torch.Generator().manual_seed(0)
    for H, W in ((17, 23), (136, 245)):
        a = torch.rand(H, W, 3, generator=gen, dtype=torch.float64, requires_grad=True)
        b = torch.rand(H, W, 3, generator=gen, dtype=torch.float64)
        v = ssim(a, b)
        (ga,) = torch.autograd.grad(v, a)
        v2 = ssim_2d(a, b)
        (ga2,) = torch.autograd.grad(v2, a)
        assert abs(float((v - v2).detach())) < 1e-12
        assert torch.allclose(ga, ga2, rtol=1e-9, atol=1e-15)
    # float32, as in training: agreement to rounding
    a32, b32 = a.detach().float(), b.float()
    assert abs(float(ssim(a32, b32)) - float(ssim_2d(a32, b32))) < 1e-6


def test_ssim_of_an_image_with_itself_is_one():
    img = torch.rand(20, 30, 3, generator=torch.Generator().manual_seed(1))
    assert abs(float(ssim(img, img)) - 1.0) < 1e-6
    loss, l1 = reconstruction_loss(img, img)
    assert float(l1) == 0.0 and abs(float(loss)) < 1e-6
