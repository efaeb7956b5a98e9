"""Tests of the rasterizer (baseline.render): CPU backend vs the PyTorch reference.

Tolerances:
    forward  image and alpha: max |cpu - ref| <= 1e-4 (the reference runs in float64 on the
             same float32 inputs, so it is the exact answer up to float64 rounding).
    gradient of every input tensor X: max |g_cpu - g_ref| <= 1e-3 * max |g_ref| + 1e-6,
             i.e. 1e-3 relative to the tensor's largest gradient, plus a tiny absolute floor
             for tensors whose gradients are all ~0.
"""
from __future__ import annotations

import math

import pytest
import torch

from baseline.camera import Camera
from baseline.render import (RenderOutput, prefilter_anchors, rasterize, rasterize_cpu,
                             rasterize_reference, resolve_backend)
from baseline.render import cpu as cpu_backend

FWD_TOL = 1e-4
GRAD_REL = 1e-3
GRAD_ABS = 1e-6
NAMES = ("means", "quats", "scales", "opacities", "colors")


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    cpu_backend.set_num_threads(1)
    yield
    torch.set_num_threads(old)
    cpu_backend.set_num_threads(None)


def make_camera(width, height, fov_deg=60.0, viewmat=None, near=0.2, far=1e10):
    fx = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    vm = torch.eye(4) if viewmat is None else viewmat
    return Camera(viewmat=vm, fx=fx, fy=fx, cx=width / 2, cy=height / 2, width=width,
                  height=height, near=near, far=far)


def random_scene(n, width, height, seed, channels=3, sigma_px=(0.5, 6.0), depth=(1.5, 6.0),
                 opacity=(0.05, 0.95), margin=1.2):
    """n random Gaussians in front of a camera at the origin; float32 tensors."""
    g = torch.Generator().manual_seed(seed)
    cam = make_camera(width, height)
    r = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    z = r(n) * (depth[1] - depth[0]) + depth[0]
    x = (r(n) * 2 - 1) * z * margin * width / (2 * cam.fx)
    y = (r(n) * 2 - 1) * z * margin * height / (2 * cam.fy)
    means = torch.stack([x, y, z], -1)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    lo, hi = sigma_px
    scales = lo * torch.exp(r(n, 3) * math.log(hi / lo)) * z[:, None] / cam.fx
    opac = r(n) * (opacity[1] - opacity[0]) + opacity[0]
    colors = r(n, channels)
    return [t.float() for t in (means, quats, scales, opac, colors)], cam


def render(backend, tensors, cam, background=None, grad=False, weights=None, dtype=None,
           **kw):
    """Render; with grad=True backpropagate sum(image * wi) + sum(alpha * wa) and return the
    gradients of the inputs and of means2d."""
    ts = [t.detach().clone() for t in tensors]
    if dtype is not None:
        ts = [t.to(dtype) for t in ts]
        background = None if background is None else background.to(dtype)
    if grad:
        for t in ts:
            t.requires_grad_(True)
    if backend == "dense":
        out = rasterize_reference(*ts, cam, background, dense=True, **kw)
    else:
        out = rasterize(*ts, cam, background=background, backend=backend)
    if not grad:
        return out, None
    wi, wa = weights
    loss = (out.image * wi.to(out.image.dtype)).sum() + (out.alpha * wa.to(out.alpha.dtype)).sum()
    loss.backward()
    grads = {n: t.grad for n, t in zip(NAMES, ts)}
    grads["means2d"] = out.means2d.grad
    return out, grads


def loss_weights(cam, channels=3, seed=0):
    g = torch.Generator().manual_seed(1000 + seed)
    return (torch.randn(cam.height, cam.width, channels, generator=g, dtype=torch.float64),
            torch.randn(cam.height, cam.width, generator=g, dtype=torch.float64))


def assert_forward_close(out, ref, tol=FWD_TOL):
    assert out.image.shape == ref.image.shape
    d_img = (out.image.double() - ref.image.double()).abs().max().item()
    d_a = (out.alpha.double() - ref.alpha.double()).abs().max().item()
    assert d_img <= tol, f"image differs by {d_img:.3g}"
    assert d_a <= tol, f"alpha differs by {d_a:.3g}"


def assert_grads_close(g_cpu, g_ref, names=NAMES + ("means2d",)):
    for name in names:
        a, b = g_cpu[name], g_ref[name]
        assert a is not None and b is not None, name
        assert torch.isfinite(a).all(), f"{name}: non-finite CPU gradient"
        a, b = a.double(), b.double()
        err = (a - b).abs().max().item() if a.numel() else 0.0
        scale = b.abs().max().item() if b.numel() else 0.0
        assert err <= GRAD_REL * scale + GRAD_ABS, \
            f"{name}: max err {err:.3g} vs max |ref| {scale:.3g}"


def assert_finite(out: RenderOutput, grads=None):
    assert torch.isfinite(out.image).all() and torch.isfinite(out.alpha).all()
    assert torch.isfinite(out.means2d).all()
    if grads:
        for name, g in grads.items():
            assert g is not None, name
            assert torch.isfinite(g).all(), f"non-finite gradient of {name}"


# ------------------------------------------------------------------------------------------
# forward
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed,n,size", [(0, 300, (37, 23)), (1, 500, (45, 31)),
                                         (2, 120, (16, 16)), (3, 400, (33, 50)),
                                         (4, 60, (17, 9))])
def test_forward_matches_reference(seed, n, size):
    ts, cam = random_scene(n, *size, seed=seed)
    bg = torch.tensor([0.2, 0.5, 0.9])
    out, _ = render("cpu", ts, cam, bg)
    ref, _ = render("reference", ts, cam, bg, dtype=torch.float64)
    assert out.image.dtype == torch.float32
    assert out.image.shape == (cam.height, cam.width, 3) and out.alpha.shape == (cam.height,
                                                                                cam.width)
    assert_forward_close(out, ref)
    assert torch.equal(out.radii, ref.radii)
    assert torch.equal(out.visible, ref.radii > 0)
    assert out.radii.dtype == torch.int32 and out.visible.dtype == torch.bool
    assert (out.means2d.double() - ref.means2d).abs().max() < 1e-3
    # the scene is dense enough to saturate pixels: the transmittance rule matters
    assert out.alpha.max() > 0.99


def test_tiled_reference_equals_dense_reference():
    """The opacity-aware boxes + tiles never drop a contribution."""
    ts, cam = random_scene(200, 41, 27, seed=5)
    tiled, _ = render("reference", ts, cam, dtype=torch.float64)
    dense, _ = render("dense", ts, cam, dtype=torch.float64, chunk_pixels=300)
    assert (tiled.image - dense.image).abs().max() < 1e-12
    assert (tiled.alpha - dense.alpha).abs().max() < 1e-12


@pytest.mark.parametrize("channels", [1, 3, 5])
def test_channels(channels):
    """Any colour channel count; C != 3 runs the generic (non-fused) kernel path."""
    ts, cam = random_scene(150, 29, 21, seed=10 + channels, channels=channels)
    bg = torch.linspace(0.1, 0.9, channels)
    wts = loss_weights(cam, channels, seed=channels)
    out, g1 = render("cpu", ts, cam, bg, grad=True, weights=wts)
    ref, g2 = render("reference", ts, cam, bg, grad=True, weights=wts, dtype=torch.float64)
    assert out.image.shape == (21, 29, channels)
    assert_forward_close(out, ref)
    assert_grads_close(g1, g2)


def test_background_and_alpha_composition():
    ts, cam = random_scene(80, 24, 20, seed=7, opacity=(0.05, 0.4))
    bg = torch.tensor([0.3, 0.6, 0.1])
    out0, _ = render("cpu", ts, cam, None)
    out1, _ = render("cpu", ts, cam, bg)
    expected = out0.image + (1 - out0.alpha)[..., None] * bg
    assert (out1.image - expected).abs().max() < 1e-6


# ------------------------------------------------------------------------------------------
# gradients
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gradients_match_reference(seed):
    ts, cam = random_scene(150, 31, 23, seed=20 + seed)
    bg = torch.tensor([0.1, 0.2, 0.3])
    wts = loss_weights(cam, seed=seed)
    _, g1 = render("cpu", ts, cam, bg, grad=True, weights=wts)
    _, g2 = render("reference", ts, cam, bg, grad=True, weights=wts, dtype=torch.float64)
    assert_grads_close(g1, g2)


def test_gradients_opacity_clamp_and_transmittance_cutoff():
    """Opacities at/near the 0.999 clamp and stacks that end pixels (T (1 - a) <= 1e-4)."""
    ts, cam = random_scene(120, 27, 19, seed=31, opacity=(0.9, 1.0), sigma_px=(1.5, 6.0))
    means, quats, scales, opac, colors = ts
    opac[:40] = torch.tensor([0.999, 0.9995, 1.0, 0.9985]).repeat(10)
    # a stack of opaque Gaussians on one spot: the second one ends the centre pixels
    means[40:50] = torch.tensor([0.05, -0.03, 2.0]) + 0.01 * torch.arange(10.0)[:, None] * \
        torch.tensor([0.0, 0.0, 1.0])
    scales[40:50] = 0.05
    opac[40:50] = 0.99
    ts = [means, quats, scales, opac, colors]
    wts = loss_weights(cam, seed=31)
    out, g1 = render("cpu", ts, cam, None, grad=True, weights=wts)
    ref, g2 = render("reference", ts, cam, None, grad=True, weights=wts, dtype=torch.float64)
    assert_forward_close(out, ref)
    assert_grads_close(g1, g2)
    # the pixel under the stack stopped: its transmittance stayed above 1e-4
    cx, cy = out.means2d[40].detach().long().tolist()
    assert 1e-4 < 1 - out.alpha[cy, cx] < 1.1e-2
    # Gaussians at/behind the cut-off in the stack receive no gradient there except via
    # pixels they do reach; the clamped ones get no opacity gradient at their centre
    assert torch.isfinite(g1["opacities"]).all()


def test_medium_scene_many_tiles():
    """Thousands of Gaussians over 30 tiles (binning chunks, early tile stops, row masks)."""
    ts, cam = random_scene(3000, 96, 72, seed=40, sigma_px=(0.5, 10.0))
    wts = loss_weights(cam, seed=40)
    out, g1 = render("cpu", ts, cam, None, grad=True, weights=wts)
    ref, g2 = render("reference", ts, cam, None, grad=True, weights=wts, dtype=torch.float64)
    assert_forward_close(out, ref)
    assert_grads_close(g1, g2)


def test_depth_order_radix_sort_is_stable():
    import numpy as np

    K = cpu_backend.kernels()
    rng = np.random.default_rng(0)
    d = np.concatenate([rng.random(3000) * 5, -rng.random(100), [0.0, -0.0, 1e300, 2.0, 2.0]])
    d[::7] = d[3]  # many ties
    ids = np.arange(d.size, dtype=np.int64)
    assert np.array_equal(K.depth_order(d, ids), np.argsort(d, kind="stable"))
    sub = np.sort(rng.choice(d.size, 500, replace=False)).astype(np.int64)
    assert np.array_equal(K.depth_order(d, sub), sub[np.argsort(d[sub], kind="stable")])
    assert K.depth_order(d, np.zeros(0, np.int64)).shape == (0,)


def test_background_gradient():
    ts, cam = random_scene(60, 20, 14, seed=3, opacity=(0.05, 0.5))
    wts = loss_weights(cam, seed=3)
    grads = []
    for backend, dt in (("cpu", torch.float32), ("reference", torch.float64)):
        bg = torch.tensor([0.2, 0.4, 0.6], dtype=dt, requires_grad=True)
        out = rasterize(*[t.to(dt) for t in ts], cam, background=bg, backend=backend)
        ((out.image * wts[0].to(dt)).sum()).backward()
        grads.append(bg.grad.double())
    assert (grads[0] - grads[1]).abs().max() <= 1e-3 * grads[1].abs().max() + 1e-6


def test_float64_inputs_keep_dtype():
    ts, cam = random_scene(50, 16, 12, seed=4)
    ts64 = [t.double().requires_grad_(True) for t in ts]
    out = rasterize(*ts64, cam, backend="cpu")
    assert out.image.dtype == torch.float64 and out.means2d.dtype == torch.float64
    out.image.sum().backward()
    assert all(t.grad.dtype == torch.float64 for t in ts64)


def test_backward_is_deterministic_across_thread_counts():
    ts, cam = random_scene(300, 40, 36, seed=8)
    wts = loss_weights(cam, seed=8)
    results = []
    try:
        for n in (1, 2, 1):
            cpu_backend.set_num_threads(n)
            if cpu_backend.get_num_threads() != n:
                pytest.skip(f"needs {n} numba threads (NUMBA_NUM_THREADS caps the pool at "
                            f"{cpu_backend.get_num_threads()})")
            _, g = render("cpu", ts, cam, None, grad=True, weights=wts)
            results.append(g)
    finally:
        cpu_backend.set_num_threads(1)
    for g in results[1:]:
        for name in results[0]:
            assert torch.equal(g[name], results[0][name]), name


# ------------------------------------------------------------------------------------------
# hard cases: finite outputs and gradients (and agreement with the reference)
# ------------------------------------------------------------------------------------------

def _check_both(ts, cam, bg=None, compare=True, tol=FWD_TOL):
    wts = loss_weights(cam, seed=99)
    out, g1 = render("cpu", ts, cam, bg, grad=True, weights=wts)
    ref, g2 = render("reference", ts, cam, bg, grad=True, weights=wts, dtype=torch.float64)
    assert_finite(out, g1)
    assert_finite(ref, g2)
    if compare:
        assert_forward_close(out, ref, tol)
        assert_grads_close(g1, g2)
    return out, g1


def test_behind_camera_and_on_near_plane():
    cam = make_camera(32, 24, near=0.5)
    means = torch.tensor([[0.0, 0.0, -1.0],   # behind
                          [0.1, 0.0, 0.5],    # exactly on the near plane: culled
                          [0.0, 0.1, 0.0],    # in the camera centre
                          [0.0, 0.0, 0.5001],  # just in front, very large on screen
                          [0.2, -0.1, 3.0]])  # ordinary
    n = means.shape[0]
    ts = [means, torch.randn(n, 4, generator=torch.Generator().manual_seed(0)),
          torch.full((n, 3), 0.05), torch.full((n,), 0.8), torch.rand(n, 3)]
    out, g = _check_both(ts, cam)
    assert out.radii[:3].eq(0).all() and out.radii[3:].gt(0).all()
    for name in ("means", "quats", "scales", "opacities", "colors"):
        assert g[name][:3].eq(0).all(), name


@pytest.mark.parametrize("scale", [1e-8, 1e4])
def test_tiny_and_huge_scales(scale):
    ts, cam = random_scene(40, 23, 17, seed=11)
    ts[2][:20] = scale
    out, _ = _check_both(ts, cam)
    if scale > 1:
        assert out.alpha.min() > 0.5  # huge Gaussians cover everything


def test_degenerate_covariances():
    """Needles along the view ray, edge-on sheets and zero scales: singular 3D covariances
    whose 2D covariance only the 0.3 px^2 dilation keeps invertible."""
    cam = make_camera(30, 20)
    n = 6
    means = torch.tensor([[0.0, 0.0, 2.0], [0.2, 0.1, 3.0], [-0.3, 0.0, 2.5],
                          [0.1, -0.2, 4.0], [0.0, 0.2, 2.0], [-0.1, -0.1, 3.5]])
    quats = torch.tensor([[1.0, 0, 0, 0]] * n)
    scales = torch.tensor([[0.0, 0.0, 1.0],     # needle along z (the view ray): a point
                           [1.0, 1.0, 0.0],     # sheet facing the camera
                           [0.0, 1.0, 1.0],     # sheet edge-on
                           [0.0, 0.0, 0.0],     # a point
                           [1e-30, 1e-30, 1e-30],
                           [0.5, 0.0, 0.0]])   # a line
    ts = [means, quats, scales, torch.full((n,), 0.9), torch.rand(n, 3)]
    out, _ = _check_both(ts, cam)
    assert out.visible.all()


def test_unnormalized_and_zero_quaternions():
    ts, cam = random_scene(30, 21, 15, seed=12)
    q = ts[1] / ts[1].norm(dim=1, keepdim=True)
    ts_unit = [t.clone() for t in ts]
    ts_unit[1] = q
    ts_big = [t.clone() for t in ts]
    ts_big[1] = q * 1e3
    ts_small = [t.clone() for t in ts]
    ts_small[1] = q * 1e-3
    a, _ = render("cpu", ts_unit, cam)
    for other in (ts_big, ts_small):
        b, _ = render("cpu", other, cam)
        assert (a.image - b.image).abs().max() < 1e-5
    ts_zero = [t.clone() for t in ts]
    ts_zero[1][:10] = 0.0
    out, g = _check_both(ts_zero, cam)
    assert g["quats"][:10].eq(0).all()
    ident = [t.clone() for t in ts]
    ident[1][:10] = torch.tensor([1.0, 0, 0, 0])
    c, _ = render("cpu", ident, cam)
    assert (out.image - c.image).abs().max() < 1e-6


def test_opacity_zero_and_one():
    ts, cam = random_scene(40, 22, 18, seed=13)
    ts[3][:10] = 0.0
    ts[3][10:20] = 1.0
    out, g = _check_both(ts, cam)
    assert out.radii[:10].eq(0).all()
    assert g["opacities"][:10].eq(0).all()


@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_no_gaussians(backend):
    cam = make_camera(19, 11)
    ts = [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0),
          torch.zeros(0, 3)]
    ts = [t.requires_grad_(True) for t in ts]
    bg = torch.tensor([0.25, 0.5, 0.75])
    out = rasterize(*ts, cam, background=bg, backend=backend)
    assert torch.equal(out.image, bg.expand(11, 19, 3))
    assert out.alpha.eq(0).all()
    assert out.means2d.shape == (0, 2) and out.radii.shape == (0,) and out.visible.shape == (0,)
    out.image.sum().backward()
    assert ts[0].grad is not None and ts[0].grad.shape == (0, 3)


def test_single_gaussian_covering_the_image():
    cam = make_camera(40, 30)
    ts = [torch.tensor([[0.05, -0.02, 1.0]]), torch.tensor([[0.9, 0.1, 0.3, -0.2]]),
          torch.tensor([[3.0, 2.0, 0.5]]), torch.tensor([0.7]), torch.tensor([[0.2, 0.8, 0.4]])]
    out, _ = _check_both(ts, cam)
    assert out.radii[0] > 40
    assert (out.alpha - 0.7).abs().max() < 0.05


@pytest.mark.parametrize("size", [(1, 1), (17, 9), (1, 23), (33, 1)])
def test_tiny_and_odd_images(size):
    w, h = size
    ts, cam = random_scene(50, w, h, seed=14, sigma_px=(0.3, 3.0), margin=2.0)
    _check_both(ts, cam)


def test_far_from_origin_float32():
    """Camera and Gaussians 1e4 units from the origin, float32 inputs."""
    ts, cam0 = random_scene(80, 30, 20, seed=15)
    offset = torch.tensor([1e4, -1e4, 1e4])
    R = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # a rotated camera
    # world = R^T (cam-space) + centre; viewmat = [R | -R centre]
    means_w = ts[0] @ R + offset
    vm = torch.eye(4)
    vm[:3, :3] = R
    vm[:3, 3] = -(R @ offset)
    cam = make_camera(30, 20, viewmat=vm)
    ts_far = [means_w.float()] + ts[1:]
    out, _ = _check_both(ts_far, cam, compare=True)
    assert out.visible.sum() > 40


def test_offscreen_gaussians_clamped_jacobian():
    """Large Gaussians centred outside 1.3x the field of view (clamped Jacobian) that still
    reach into the image: exact gradients of the clamped projection."""
    cam = make_camera(32, 24)
    tan_x = cam.width / (2 * cam.fx)
    tan_y = cam.height / (2 * cam.fy)
    z = torch.tensor([2.0, 3.0, 2.5, 4.0])
    u = torch.tensor([1.6, -1.8, 0.0, 1.45]) * tan_x
    v = torch.tensor([0.0, 0.3, -1.7, 1.5]) * tan_y
    means = torch.stack([u * z, v * z, z], -1)
    n = means.shape[0]
    g = torch.Generator().manual_seed(3)
    ts = [means, torch.randn(n, 4, generator=g), torch.tensor([[0.8, 0.5, 0.6]] * n),
          torch.full((n,), 0.9), torch.rand(n, 3, generator=g)]
    out, _ = _check_both(ts, cam)
    assert out.visible.all()


def test_far_plane_culls():
    cam = make_camera(16, 16, near=0.01, far=5.0)
    ts = [torch.tensor([[0.0, 0.0, 4.0], [0.0, 0.0, 5.0], [0.0, 0.0, 6.0]]),
          torch.tensor([[1.0, 0, 0, 0]] * 3), torch.full((3, 3), 0.1), torch.full((3,), 0.5),
          torch.rand(3, 3)]
    out, _ = render("cpu", ts, cam)
    assert out.visible.tolist() == [True, False, False]


# ------------------------------------------------------------------------------------------
# API, registry, prefilter
# ------------------------------------------------------------------------------------------

def test_registry_and_auto_backend():
    from baseline import registry

    assert {"cpu", "gsplat", "reference"} <= set(registry.names("rasterizer"))
    assert registry.get("rasterizer", "cpu") is rasterize_cpu
    assert resolve_backend("auto", torch.zeros(1, 3)) == "cpu"
    assert resolve_backend("reference", torch.zeros(1, 3)) == "reference"


def test_bad_shapes_are_rejected():
    cam = make_camera(8, 8)
    ok = [torch.zeros(2, 3), torch.zeros(2, 4), torch.ones(2, 3), torch.ones(2), torch.ones(2, 3)]
    with pytest.raises(ValueError, match="quats"):
        rasterize(ok[0], torch.zeros(2, 3), *ok[2:], cam, backend="cpu")
    with pytest.raises(ValueError, match="background"):
        rasterize(*ok, cam, background=torch.zeros(4), backend="cpu")


def test_means2d_grad_is_in_pixels():
    """Moving a Gaussian by d pixels changes the loss by <grad, d>."""
    ts, cam = random_scene(1, 24, 24, seed=16, sigma_px=(2.0, 3.0), depth=(2.0, 2.0),
                          margin=0.2)
    ts[3][:] = 0.6
    wts = loss_weights(cam, seed=16)
    out, g = render("cpu", ts, cam, grad=True, weights=wts, dtype=torch.float64)
    eps = 1e-3  # pixels
    means = ts[0].double()
    dz = means[0, 2].item()
    shifted = [t.double().clone() for t in ts]
    shifted[0][0, 0] += eps * dz / cam.fx  # moves the projection by eps px along x
    loss = lambda o: ((o.image * wts[0]).sum() + (o.alpha * wts[1]).sum()).item()  # noqa
    a, _ = render("cpu", shifted, cam, dtype=torch.float64)
    b, _ = render("cpu", [t.double() for t in ts], cam, dtype=torch.float64)
    fd = (loss(a) - loss(b)) / eps
    # means2d.grad only covers the path through the 2D centre, and a shift in x also moves
    # the Jacobian slightly; compare loosely
    assert abs(fd - g["means2d"][0, 0].item()) <= 0.05 * abs(fd) + 1e-3


def test_prefilter_anchors():
    cam = make_camera(64, 48)
    xyz = torch.tensor([[0.0, 0.0, 3.0],      # in front: visible
                        [0.0, 0.0, -3.0],     # behind: not
                        [0.0, 0.0, 0.1],      # in front but z < 0.2: not
                        [100.0, 0.0, 3.0],    # far outside the image: not
                        [2.05, 0.0, 3.0],     # just outside, but large: its box overlaps
                        [2.05, 0.0, 3.0]])    # just outside and small: not
    scales = torch.tensor([[0.1] * 3, [0.1] * 3, [0.1] * 3, [0.1] * 3, [0.5] * 3,
                           [0.001] * 3])
    vis = prefilter_anchors(xyz, scales, cam)
    assert vis.dtype == torch.bool
    assert vis.tolist() == [True, False, False, False, True, False]
    # random anchors: everything visible projects into (or near) the image
    g = torch.Generator().manual_seed(0)
    pts = (torch.rand(2000, 3, generator=g) * 2 - 1) * torch.tensor([6.0, 6.0, 6.0])
    sc = torch.full((2000, 3), 0.01)
    v = prefilter_anchors(pts, sc, cam)
    z = pts[:, 2]
    assert not v[z <= 0.2].any()
    u = cam.fx * pts[:, 0] / z + cam.cx
    v_ = cam.fy * pts[:, 1] / z + cam.cy
    inside = (z > 0.2) & (u > 1) & (u < cam.width - 1) & (v_ > 1) & (v_ < cam.height - 1)
    assert v[inside].all()


def _at_the_near_plane(vm: torch.Tensor, n: int, g: torch.Generator) -> torch.Tensor:
    """[n,3] world points whose camera-space depth (``vm``: world-to-camera) is the default near
    plane 0.2, half of them moved by up to +-1e-6 across it."""
    cam_p = torch.cat([torch.randn(n, 2, generator=g), torch.full((n, 1), 0.2)], 1)
    cam_p[:n // 2, 2] += torch.linspace(-1e-6, 1e-6, n // 2)
    return ((cam_p.double() - vm[:3, 3].double()) @ vm[:3, :3].double()).float()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_prefilter_closed_form_matches_the_matrix_form(seed):
    """Rotated, off-centre cameras; anchors from tiny to huge, some near the image border,
    behind the camera, at z around the 0.2 threshold, and with inf / nan values."""
    g = torch.Generator().manual_seed(seed)
    q = torch.nn.functional.normalize(torch.randn(4, generator=g, dtype=torch.float64), dim=0)
    w, x, y, z = q.tolist()
    R = torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    vm = torch.eye(4)
    vm[:3, :3] = R.float()
    vm[:3, 3] = torch.randn(3, generator=g)
    cam = Camera(viewmat=vm, fx=70.0, fy=65.0, cx=40.0, cy=27.0, width=96, height=64,
                 near=0.01, far=1e10)
    n = 20000
    xyz = (torch.rand(n, 3, generator=g) * 2 - 1) * 8
    scales = torch.exp(torch.randn(n, 3, generator=g) * 2.5 - 3)
    xyz[:200] = _at_the_near_plane(vm, 200, g)
    xyz[200, 0], xyz[201, 1], scales[202, 2], scales[203, 0] = float("inf"), float("nan"), \
        float("inf"), float("nan")
    from baseline.render.prefilter import prefilter_anchors_matrix_form

    got = prefilter_anchors(xyz, scales, cam)
    want = prefilter_anchors_matrix_form(xyz, scales, cam)
    assert 0.05 < want.float().mean() < 0.95
    assert not got[200:204].any()
    assert torch.equal(got, want), int((got != want).sum())


@pytest.mark.parametrize("seed", [0, 1])
def test_prefilter_cpu_kernel_decides_as_the_torch_form(seed):
    """On the CPU the visibility test runs as one numba pass; it must decide exactly as the
    torch form that other devices run, on ordinary anchors and on hostile ones: NaN and inf in
    positions and scales, scales whose squares overflow, depths at the near plane and at
    +-0, centres far outside the image."""
    from baseline.render import prefilter as P

    g = torch.Generator().manual_seed(seed)
    vm = torch.eye(4)
    a = 0.4 + seed
    vm[:3, :3] = torch.tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0],
                               [-math.sin(a), 0.0, math.cos(a)]])
    vm[:3, 3] = torch.randn(3, generator=g)
    cam = Camera(viewmat=vm, fx=70.0, fy=65.0, cx=40.0, cy=27.0, width=96, height=64)
    n = 30000
    xyz = (torch.rand(n, 3, generator=g) * 2 - 1) * 10
    scales = torch.exp(torch.randn(n, 3, generator=g) * 3 - 3)
    bad = torch.tensor([float("nan"), float("inf"), -float("inf"), 3e38, -3e38, 1e-38, 0.0, -0.0])
    xyz.view(-1)[torch.randint(0, 3 * n, (600,), generator=g)] = bad[torch.arange(600) % 8]
    scales.view(-1)[torch.randint(0, 3 * n, (300,), generator=g)] = bad[torch.arange(300) % 8].abs()
    xyz[-300:] = _at_the_near_plane(vm, 300, g)

    p, cov, terms = P._camera_space(xyz, scales, cam, None)
    want = P._visible_torch(p, cov, *terms)
    got = P.prefilter_anchors(xyz, scales, cam)          # on the CPU: the numba pass
    assert 0.05 < want.float().mean() < 0.95
    assert torch.equal(got, want), int((got != want).sum())


# ------------------------------------------------------------------------------------------
# benchmark (correctness of the harness only; no wall-clock assertions)
# ------------------------------------------------------------------------------------------

def test_bench_rows():
    from baseline.bench.raster import format_raster_bench, run_raster_bench

    rows = run_raster_bench(sizes=((300, 40, 30), (400, 48, 32)), backends=["cpu", "reference"],
                            threads=1, repeats=1, reference_max_pairs=50)
    assert len(rows) == 4
    keys = {"n", "width", "height", "backend", "threads", "torch_threads", "device", "repeats",
            "tile_pairs",
            "pairs", "forward_s", "forward_backward_s", "forward_median_s",
            "forward_backward_median_s", "pairs_per_s", "ratio_forward",
            "ratio_forward_backward", "skipped"}
    for r in rows:
        assert keys <= set(r)
        assert r["pairs"] == 256 * r["tile_pairs"]
        assert r["threads"] == 1
    # the reference was skipped on both sizes (more than 50 tile pairs)
    ref_rows = [r for r in rows if r["backend"] == "reference"]
    assert all(r["skipped"] and r["forward_s"] is None for r in ref_rows)
    cpu_rows = [r for r in rows if r["backend"] == "cpu"]
    assert all(r["forward_s"] > 0 and r["forward_backward_s"] > 0 for r in cpu_rows)
    assert all(r["ratio_forward"] is None for r in cpu_rows)
    text = format_raster_bench(rows)
    assert "skipped (" in text and "cpu" in text

    rows = run_raster_bench(sizes=((200, 32, 24),), backends=["cpu", "reference"], threads=1,
                            repeats=1)
    ref = [r for r in rows if r["backend"] == "reference"][0]
    cpu = [r for r in rows if r["backend"] == "cpu"][0]
    assert ref["ratio_forward_backward"] == pytest.approx(1.0)
    assert cpu["ratio_forward_backward"] == pytest.approx(
        ref["forward_backward_s"] / cpu["forward_backward_s"])
    from baseline.device import machine_name
    assert cpu["device"] == machine_name(torch.device("cpu"))
    if not torch.cuda.is_available():   # gsplat asked for without CUDA: skipped, not a crash
        g = run_raster_bench(sizes=((200, 32, 24),), backends=["gsplat"], threads=1,
                             repeats=1)[0]
        assert g["skipped"] == "no CUDA device" and g["device"] == "cuda (none here)"


def test_kernels_are_compiled_by_a_child_that_imports_this_checkout(monkeypatch, tmp_path):
    """The child that fills numba's cache runs ``python -c`` in the folder this package was
    imported from, so it compiles these kernels (not another checkout's found first on
    ``sys.path`` from the caller's working directory), and that folder imports this package."""
    import subprocess
    import sys
    from pathlib import Path

    import baseline

    seen = {}

    def fake_run(cmd, **kw):
        seen.update(kw)
        return subprocess.CompletedProcess(cmd, 0, "", "")

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(subprocess, "run", fake_run)
    assert cpu_backend._compile_in_child()
    root = Path(seen["cwd"])
    assert (root / "baseline" / "render" / "cpu.py").resolve() == Path(cpu_backend.__file__).resolve()
    monkeypatch.undo()
    out = subprocess.run([sys.executable, "-c", "import baseline; print(baseline.__file__)"],
                         cwd=root, capture_output=True, text=True, check=True).stdout.strip()
    assert Path(out).resolve() == Path(baseline.__file__).resolve()
