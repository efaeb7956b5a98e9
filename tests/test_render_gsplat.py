"""The gsplat (CUDA) backend wrapper.

Without a GPU the wrapper is exercised with a stand-in ``gsplat`` module whose
``rasterization()`` returns what gsplat's documented API returns (render_colors [1,H,W,C],
render_alphas [1,H,W,1], meta with "means2d" [1,N,2] inside the autograd graph, "radii"
[1,N,2], "depths" [1,N]), computed with the reference rasterizer. The real comparison against
the CPU backend runs only where CUDA and gsplat are available.
"""
from __future__ import annotations

import math
import sys
import types

import pytest
import torch

from baseline.camera import Camera
from baseline.render import gsplat_backend, rasterize
from baseline.render.reference import project_reference, render_projected


def _camera(width=28, height=20):
    fx = 0.5 * width / math.tan(math.radians(30))
    return Camera(viewmat=torch.eye(4), fx=fx, fy=fx, cx=width / 2, cy=height / 2,
                  width=width, height=height)


def _scene(n=60, seed=0):
    g = torch.Generator().manual_seed(seed)
    z = torch.rand(n, generator=g) * 3 + 2
    means = torch.stack([(torch.rand(n, generator=g) - 0.5) * z * 0.9,
                         (torch.rand(n, generator=g) - 0.5) * z * 0.7, z], -1)
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.1 + 0.02
    opac = torch.rand(n, generator=g) * 0.8 + 0.1
    colors = torch.rand(n, 3, generator=g)
    return [means, quats, scales, opac, colors]


def _fake_gsplat(calls):
    def rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                      **kw):
        calls.append(kw)
        K = Ks[0]
        cam = Camera(viewmat=viewmats[0].detach(), fx=float(K[0, 0]), fy=float(K[1, 1]),
                     cx=float(K[0, 2]), cy=float(K[1, 2]), width=width, height=height,
                     near=kw["near_plane"], far=kw["far_plane"])
        proj = project_reference(means, quats, scales, opacities, cam)
        m2d = proj.means2d[None]  # [1, N, 2], part of the graph like gsplat's
        image, alpha = render_projected(proj, m2d[0], opacities, colors, kw["backgrounds"][0],
                                        cam)
        meta = {"means2d": m2d, "radii": proj.radii_xy[None], "depths": proj.depths[None]}
        return image[None], alpha[None, ..., None], meta

    return types.SimpleNamespace(rasterization=rasterization)


def test_wrapper_with_stand_in_module():
    calls = []
    fake = _fake_gsplat(calls)
    cam = _camera()
    ts = [t.requires_grad_(True) for t in _scene()]
    bg = torch.tensor([0.1, 0.2, 0.3])
    out = gsplat_backend.rasterize_with_module(fake, *ts, cam, bg)
    kw = calls[0]
    assert kw["packed"] is False and kw["rasterize_mode"] == "classic"
    assert kw["eps2d"] == 0.3 and kw["tile_size"] == 16 and kw["sh_degree"] is None
    assert kw["backgrounds"].shape == (1, 3)
    assert out.backend == "gsplat"
    assert out.image.shape == (20, 28, 3) and out.alpha.shape == (20, 28)
    assert out.radii.shape == (60,) and out.radii.dtype == torch.int32
    assert torch.equal(out.visible, out.radii > 0)
    out.means2d.retain_grad()  # what the trainer does; a no-op on this leaf
    w = torch.randn(20, 28, 3, generator=torch.Generator().manual_seed(1))
    (out.image * w).sum().backward()
    got = out.means2d.grad.clone()

    ref_ts = [t.detach().clone().requires_grad_(True) for t in ts]
    ref = rasterize(*ref_ts, cam, background=bg, backend="reference")
    (ref.image * w).sum().backward()
    assert torch.allclose(out.image, ref.image)
    assert torch.equal(out.radii, ref.radii)
    assert torch.allclose(got, ref.means2d.grad)
    assert got.abs().sum() > 0
    assert torch.allclose(ts[0].grad, ref_ts[0].grad)


def test_wrapper_means2d_grad_accumulates():
    fake = _fake_gsplat([])
    cam = _camera()
    ts = [t.requires_grad_(True) for t in _scene(seed=2)]
    out = gsplat_backend.rasterize_with_module(fake, *ts, cam)
    out.image.sum().backward(retain_graph=True)
    first = out.means2d.grad.clone()
    out.image.sum().backward()
    assert torch.allclose(out.means2d.grad, 2 * first)


def test_missing_gsplat_message(monkeypatch):
    monkeypatch.setitem(sys.modules, "gsplat", None)  # makes `import gsplat` fail
    assert not gsplat_backend.gsplat_available()
    ts = _scene(5)
    with pytest.raises(ImportError, match="pip install gsplat"):
        rasterize(*ts, _camera(), backend="gsplat")


def test_gsplat_needs_cuda_tensors(monkeypatch):
    monkeypatch.setitem(sys.modules, "gsplat", _fake_gsplat([]))
    with pytest.raises(ValueError, match="CUDA"):
        rasterize(*_scene(5), _camera(), backend="gsplat")


@pytest.mark.skipif(not torch.cuda.is_available() or not gsplat_backend.gsplat_available(),
                    reason="needs CUDA and gsplat")
def test_gsplat_matches_cpu():  # pragma: no cover - GPU only
    cam = _camera(64, 48)
    ts = _scene(300, seed=5)
    w = torch.randn(48, 64, 3, generator=torch.Generator().manual_seed(2))
    outs, grads = [], []
    for backend, dev in (("cpu", "cpu"), ("gsplat", "cuda")):
        # fresh leaves on each device (t.to('cpu') would return t itself, and after that
        # t.to('cuda') would be a non-leaf copy whose .grad stays None)
        leaves = [t.detach().to(dev).clone().requires_grad_(True) for t in ts]
        out = rasterize(*leaves, cam, backend=backend)
        out.means2d.retain_grad()  # a no-op on gsplat's leaf; the CPU backend's is not a leaf
        (out.image * w.to(dev)).sum().backward()
        outs.append(out)
        grads.append([t.grad.cpu() for t in leaves] + [out.means2d.grad.cpu()])
    assert (outs[0].image - outs[1].image.cpu()).abs().max() < 2e-3
    assert (outs[0].alpha - outs[1].alpha.cpu()).abs().max() < 2e-3
    # same culling (gsplat < 1.5 sizes its boxes differently, so radii may differ)
    assert (outs[0].visible == outs[1].visible.cpu()).float().mean() > 0.99
    for a, b in zip(grads[0], grads[1]):
        assert (a - b).abs().max() <= 1e-2 * a.abs().max() + 1e-5
