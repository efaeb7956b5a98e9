"""HAC's rate term as its reference code trains it (docs/method.md section 3), and the near plane.

* the offsets' bits are weighted by the straight-through *float* Gaussian mask, so the rate's
  gradient reaches the mask logits (forward 0/1, backward the sigmoid's gradient);
* the sampled bits are multiplied by the share of valid anchors among the visible ones
  (``mask_anchor_rate``, detached);
* the context grid is normalised by the widened anchor bounds, so anchors grown after the
  adaptive phase starts still read context features;
* anchors and Gaussians at view-space z <= 0.2 are culled by the prefilter and every backend.
"""
from __future__ import annotations

import math
import types

import numpy as np
import pytest
import torch

from baseline.camera import Camera
from baseline.codec.rangecoder import anchor_bounds
from baseline.config import build_config
from baseline.contracts import CodedAttribute
from baseline.data.scene import load_scene
from baseline.hac.entropy import HACEntropyModel
from baseline.pipeline import render_view, visible_anchors
from baseline.render import gsplat_backend, prefilter_anchors, rasterize
from baseline.scaffold.model import AnchorModel
from baseline.train.losses import rate_term
from baseline.train.trainer import Trainer
from conftest import demo_cfg

K = 3
ATTRS = (CodedAttribute("feat", 4, 1.0), CodedAttribute("offsets", 3 * K, 0.2, masked=True))


def _mask_of(logits):
    """The model's training mask (AnchorModel.gaussian_mask) for logits [n, K]."""
    fake = types.SimpleNamespace(per_anchor={"mask": logits[..., None]}, mask_threshold=0.01)
    return AnchorModel.gaussian_mask(fake)


def _payload(n=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    m = HACEntropyModel(ATTRS, K, grid_options=dict(resolutions_3d=(4, 8), log2_table_3d=8,
                                                    resolutions_2d=(8,), log2_table_2d=8)).double()
    xyz = torch.rand(n, 3, generator=g, dtype=torch.float64)
    m.set_bounds(torch.zeros(3), torch.ones(3))
    vals = {"feat": torch.randn(n, 4, generator=g, dtype=torch.float64) * 3,
            "offsets": torch.randn(n, 3 * K, generator=g, dtype=torch.float64)}
    logits = torch.randn(n, K, generator=g, dtype=torch.float64) * 3
    logits[0] = torch.tensor([2.0, -1.0, -8.0])   # anchor 0: two masks on, one off
    return m, xyz, vals, logits


def _offset_bits(m, xyz, vals, weights):
    """Total training bits with the given float mask weights (noise fixed by the seed)."""
    torch.manual_seed(123)
    _, bits = m(xyz, vals, weights, training=True)
    return bits["offsets"].sum() + bits["feat"].sum()


def test_offsets_rate_trains_the_masks():
    m, xyz, vals, logits0 = _payload()
    logits = logits0.clone().requires_grad_(True)
    gmask = _mask_of(logits)
    hard = gmask.detach().round()
    assert torch.allclose(gmask.detach(), hard, atol=1e-12)       # forward: 0/1 (to an ulp)
    _offset_bits(m, xyz, vals, gmask).backward()
    grad = logits.grad
    on = torch.sigmoid(logits0) > 0.01
    assert on[0, 0] and grad[0, 0] > 0            # a Gaussian whose mask is on is pushed off
    assert (grad[on] > 0).all()
    # the gradient is the straight-through one: d/dl of sum(bits * (hard + sigmoid(l) - const))
    assert torch.equal(hard, on.double())
    for a, k in [(0, 0), (0, 1), (5, 2), (17, 1)]:
        eps = 1e-6

        def f(delta):
            lg = logits0.clone()
            lg[a, k] += delta
            w = hard + torch.sigmoid(lg) - torch.sigmoid(logits0)   # forward = hard at delta 0
            with torch.no_grad():
                return float(_offset_bits(m, xyz, vals, w))
        fd = (f(eps) - f(-eps)) / (2 * eps)
        assert grad[a, k].item() == pytest.approx(fd, rel=1e-5, abs=1e-9)
    # and it is what the offsets' own bits times sigmoid' give
    torch.manual_seed(123)
    b = _value_bits(m, xyz, vals)["offsets"].reshape(-1, K, 3).sum(-1)
    s = torch.sigmoid(logits0)
    assert torch.allclose(grad, b * s * (1 - s), rtol=1e-9, atol=1e-12)


def _value_bits(m, xyz, vals):
    """Per-value bits [n, d] of the training forward (no masks)."""
    from baseline.hac.entropy import gaussian_bits
    from baseline.hac.quant import noise_quantize
    P = m.params(xyz)
    out = {}
    for a in m.attrs:
        mean, scale, q = P[a.name]
        out[a.name] = gaussian_bits(noise_quantize(vals[a.name], q), mean, scale, q)
    return out


def test_codec_keeps_boolean_masks():
    """Evaluation (and the codec) count the masked-off values as not coded, whatever the float
    mask's value; training weighs by the float mask as it is."""
    m, xyz, vals, logits = _payload()
    gmask = _mask_of(logits).detach()
    _, bits = m(xyz, vals, gmask * 0.7, training=False)         # boolean: > 0.5 -> coded
    _, ref = m(xyz, vals, gmask, training=False)
    assert torch.allclose(bits["offsets"], ref["offsets"])
    torch.manual_seed(1)
    _, tb = m(xyz, vals, gmask * 0.5, training=True)
    torch.manual_seed(1)
    _, tr = m(xyz, vals, gmask, training=True)
    assert torch.allclose(tb["offsets"], 0.5 * tr["offsets"])


def test_rate_term_by_hand():
    bits = {"feat": torch.tensor([10.0, 20.0]), "offsets": torch.tensor([3.0, 5.0])}
    rate, bpv = rate_term(bits, 2, 0.75, torch.tensor(860.0), 100, 86)
    assert bpv == pytest.approx(38 / (2 * 86))
    assert float(rate) == pytest.approx(38 / (2 * 86) * 0.75 + 860 / (100 * 86))
    rate, bpv = rate_term({}, 0, 0.5, None, 10, 86)
    assert rate == 0.0 and bpv is None
    # the hash bits' own denominator H: the sampled part keeps V
    rate, bpv = rate_term(bits, 2, 0.75, torch.tensor(860.0), 100, 61, 86)
    assert bpv == pytest.approx(38 / (2 * 61))
    assert float(rate) == pytest.approx(38 / (2 * 61) * 0.75 + 860 / (100 * 86))


@pytest.fixture(scope="module")
def scene(scene_maker):
    return load_scene(scene_maker(n_views=8, width=48, height=36, seed=3))


def _trainer(scene, tmp_path, *sets):
    torch.set_num_threads(1)
    cfg = demo_cfg(300, *sets)
    return Trainer(cfg, scene, tmp_path / "run", progress=False)


def test_mask_anchor_rate_is_the_valid_share_of_visible_anchors(scene, tmp_path):
    t = _trainer(scene, tmp_path, "entropy.noise_from=0", "entropy.context_from=0",
                 "entropy.rate_sample=1.0")
    t.hooks[1].before_step(1)
    assert t.phase == "adaptive"
    cam = scene.train_cameras[0]
    vis = visible_anchors(t.model, cam)
    assert len(vis) > 20
    with torch.no_grad():                      # a third of the visible anchors: every mask off
        t.model.per_anchor["mask"][vis[::3]] = -10.0
        t.model.per_anchor["mask"][vis[1::3], :2] = -10.0     # some: a few masks off
    valid = (torch.sigmoid(t.model.per_anchor["mask"][vis, :, 0]) > 0.01).any(1)
    want = int(valid.sum()) / len(vis)
    assert 0.5 < want < 0.8
    res = render_view(t.model, cam, t.background, phase="adaptive", training=True,
                      entropy=t.entropy, rate_sample=1.0, generator=t.step_generator)
    assert res.valid_share == pytest.approx(want)
    assert res.n_rate_anchors == int(valid.sum())           # all valid visible anchors sampled
    # the trainer's rate uses it: its logged share and the loss with lambda set
    terms = t.step(1)
    assert 0 < terms["valid_share"] < 1


def test_hash_bits_denominator_is_its_own_option(scene, tmp_path):
    """entropy.hash_values_per_anchor = H divides the hash bits (context grid and a provider's
    grid) by N * H in the mask trainings' rate, the sampled bits still by N * V; 0 = V. The
    option keeps the hash of configs without it, and the Predict-GS patch hash-rate-hac sets
    HAC's 86 where Predict-GS codes 61 values per anchor."""
    from baseline.config import config_hash

    sets = ("entropy.noise_from=0", "entropy.context_from=0", "entropy.rate_sample=1.0")
    res = types.SimpleNamespace(bits={"feat": torch.tensor([10.0, 20.0])}, n_rate_anchors=2,
                                valid_share=0.5)
    for h in (0, 43):
        t = _trainer(scene, tmp_path / str(h), *sets, f"entropy.hash_values_per_anchor={h}")
        assert t.rate_values_per_anchor == 86
        assert t.hash_values_per_anchor == (h or 86)
        hb = float(t.entropy.hash_bits().detach())
        assert hb > 0
        (lam_rate, _), _ = t.mask_training.loss(res)
        rate = float(lam_rate.detach()) / t.cfg.entropy.lmbda
        sampled = 30.0 / (2 * 86) * 0.5
        assert rate == pytest.approx(sampled + hb / (t.model.n_anchors * (h or 86)), rel=1e-5)
    # HAC++'s mask training (its own rate sample, the same draw in both): only the hash part moves
    hacpp = {}
    for h in (0, 43):
        t = _trainer(scene, tmp_path / f"pp{h}", *sets, "entropy.mask_training=hacpp",
                     f"entropy.hash_values_per_anchor={h}")
        hb = float(t.entropy.hash_bits().detach())
        (lam_rate,), _ = t.mask_training.loss(None)
        hacpp[h] = (float(lam_rate.detach()) / t.cfg.entropy.lmbda, hb, t.model.n_anchors)
    (r0, hb, n), (r43, _, _) = hacpp[0], hacpp[43]
    assert r43 - r0 == pytest.approx(hb / (n * 43) - hb / (n * 86), rel=1e-4)
    assert config_hash(demo_cfg(300)) == config_hash(demo_cfg(300, "entropy.hash_values_per_anchor=0"))
    assert config_hash(demo_cfg(300)) != config_hash(demo_cfg(300, "entropy.hash_values_per_anchor=86"))
    pgs = build_config(["predict-gs", "hash-rate-hac"], [])
    assert pgs.entropy.hash_values_per_anchor == 86
    assert config_hash(pgs) != config_hash(build_config(["predict-gs"], []))


def test_grown_anchor_reads_context_features(scene, tmp_path):
    """The context grid's box is HAC's widened anchor bounds, set at the start of iteration
    context_from: an anchor grown afterwards outside the raw min/max box (inside the widened
    one) reads non-zero features; with the raw box it would read zeros."""
    t = _trainer(scene, tmp_path, "entropy.noise_from=1000", "entropy.context_from=2000")
    phases = t.hooks[1]
    ctx = phases.context_from
    assert ctx == 20
    for it in range(1, ctx):
        phases.before_step(it)
    grid = t.entropy.grid
    assert torch.equal(grid.xyz_min, torch.zeros(3))          # not set before context_from
    phases.before_step(ctx)
    xyz = t.model.xyz.detach()
    lo, hi = anchor_bounds(xyz.numpy())
    assert np.array_equal(grid.xyz_min.numpy(), lo) and np.array_equal(grid.xyz_max.numpy(), hi)
    raw_hi = xyz.max(0).values
    assert (raw_hi > 0).all()
    new = (raw_hi * 1.1)[None]                                # beyond every anchor
    n0 = t.model.n_anchors
    t.model.append_anchors(new, torch.zeros(1, 6), torch.zeros(1, dtype=torch.long),
                           torch.zeros(1, dtype=torch.long), t.optimizer)
    with torch.no_grad():
        f = grid(t.model.xyz[n0:])
        assert f.abs().sum() > 0
        grid.set_bounds(xyz.min(0).values, raw_hi)            # the raw box: outside, zeros
        assert float(grid(t.model.xyz[n0:]).abs().sum()) == 0.0
    phases.before_step(ctx + 1)                                # not moved again
    assert np.array_equal(grid.xyz_max.numpy(), raw_hi.numpy())


# ------------------------------------------------------------------------------- near plane
def _cam(near=None):
    fx = 0.5 * 32 / math.tan(math.radians(30))
    kw = {} if near is None else {"near": near}
    return Camera(viewmat=torch.eye(4), fx=fx, fy=fx, cx=16, cy=12, width=32, height=24, **kw)


def _one_gaussian(z):
    return [torch.tensor([[0.0, 0.0, z]]), torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
            torch.full((1, 3), 0.05 * z), torch.tensor([0.9]), torch.tensor([[1.0, 0.5, 0.2]])]


@pytest.mark.parametrize("backend", ["cpu", "reference", "gsplat"])
def test_gaussian_at_z_015_is_culled_by_every_backend(backend):
    cam = _cam()
    assert cam.near == 0.2
    if backend == "gsplat":
        if not (torch.cuda.is_available() and gsplat_backend.gsplat_available()):
            calls = []                              # without CUDA: what gsplat is told

            def rasterization(*a, **kw):
                calls.append(kw)
                raise RuntimeError("stop")
            with pytest.raises(RuntimeError, match="stop"):
                gsplat_backend.rasterize_with_module(
                    types.SimpleNamespace(rasterization=rasterization), *_one_gaussian(0.15),
                    cam, torch.zeros(3))
            assert calls[0]["near_plane"] == 0.2
            return
        dev = "cuda"
    else:
        dev = "cpu"
    for z, drawn in ((0.15, False), (0.25, True)):
        ts = [x.to(dev) for x in _one_gaussian(z)]
        out = rasterize(*ts, cam, background=torch.zeros(3, device=dev), backend=backend)
        assert (float(out.alpha.max()) > 0.01) == drawn, (backend, z)


def test_prefilter_culls_anchors_nearer_than_the_near_plane():
    xyz = torch.tensor([[0.0, 0.0, 0.15], [0.0, 0.0, 0.25]])
    vis = prefilter_anchors(xyz, torch.full((2, 3), 0.01), _cam())
    assert vis.tolist() == [False, True]
    assert prefilter_anchors(xyz, torch.full((2, 3), 0.01), _cam(near=0.1)).tolist() == [True, True]


def test_scene_cameras_take_the_configured_near(scene, tmp_path):
    assert all(c.near == 0.2 for c in scene.train_cameras + scene.test_cameras)
    assert scene.protocol["near"] == 0.2
    s = load_scene(scene.source_path, near=0.05)
    assert all(c.near == 0.05 for c in s.train_cameras)
    assert build_config([]).data.near == 0.2
