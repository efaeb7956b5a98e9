"""Scaffold-GS pieces: voxelization, decoder, growing on a hand-made case, pruning."""
import math
from types import SimpleNamespace

import pytest
import torch

from baseline.config import build_config
from baseline.scaffold.anchors import init_log_scaling, knn_mean_sq_dist, voxelize
from baseline.scaffold.densify import ScaffoldDensify, _unique_rows, grow_anchors
from baseline.scaffold.build import build_model
from baseline.scaffold.model import decode_all_then_select


def test_voxelize_matches_bruteforce():
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(500, 3, generator=g) * 2 - 1
    v = 0.13
    got = voxelize(pts, v)
    # brute force, one point at a time (torch's round-half-even semantics)
    cells = {tuple(torch.round(torch.tensor(p, dtype=torch.float64) / v).long().tolist()) for p in pts.tolist()}
    want = sorted(cells)
    assert got.shape == (len(want), 3)
    assert torch.allclose(got, torch.tensor(want, dtype=torch.float64).mul(v).float())


def test_knn_and_scaling_init():
    pts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3], [10, 10, 10]])
    d = knn_mean_sq_dist(pts)
    assert d[0].item() == pytest.approx((1 + 4 + 9) / 3)
    ls = init_log_scaling(pts)
    assert ls.shape == (5, 6)
    assert ls[0, 0].item() == pytest.approx(math.log(math.sqrt(14 / 3)), rel=1e-5)
    same = init_log_scaling(torch.zeros(4, 3))   # coincident points: clamped, finite
    assert torch.isfinite(same).all()


def _model(cfg, xyz):
    model, v = build_model(cfg, xyz)
    return model


def _cfg(**sets):
    s = [f"{k}={v}" for k, v in sets.items()]
    return build_config([], s)


def test_decoder_shapes_and_opacity_selection():
    cfg = _cfg(**{"model.voxel_size": 0.5})
    pts = torch.rand(200, 3) * 4
    model = _model(cfg, pts)
    N, K = model.n_anchors, model.n_offsets
    idx = torch.arange(N)
    with torch.no_grad():
        # make opacity of odd Gaussians negative, even positive
        lin = model.decoder.mlp_opacity[2]
        lin.weight.zero_()
        lin.bias.copy_(torch.tensor([1.0 if k % 2 == 0 else -1.0 for k in range(K)]))
    g = model.decode(torch.tensor([0.0, 0.0, -5.0]), idx)
    assert g.opacity_all.shape == (N, K)
    assert g.selection.shape == (N * K,)
    assert g.means.shape == (N * K // 2, 3) and g.quats.shape == (N * K // 2, 4)
    assert g.scales.shape == (N * K // 2, 3) and g.colors.shape == (N * K // 2, 3)
    assert (g.opacities > 0).all()
    assert torch.allclose(g.quats.norm(dim=1), torch.ones(len(g.quats)), atol=1e-5)
    # offsets are zero at init -> Gaussians at the anchor positions
    assert torch.allclose(g.means, model.xyz[g.anchor_index])
    # mask off -> no Gaussian of that anchor survives
    with torch.no_grad():
        model.per_anchor["mask"][0] = -10.0
    g2 = model.decode(torch.tensor([0.0, 0.0, -5.0]), idx)
    assert not (g2.anchor_index == 0).any()
    assert not model.anchor_valid()[0] and model.anchor_valid()[1:].all()


def test_selected_gaussians_equal_activating_all_then_selecting():
    """decode() activates only the kept Gaussians: the same values and gradients
    as activating all candidates and selecting after, with masks and opacities mixed."""
    torch.manual_seed(3)
    cfg = _cfg(**{"model.voxel_size": 0.3})
    model = _model(cfg, torch.rand(300, 3) * 4)
    N, K = model.n_anchors, model.n_offsets
    with torch.no_grad():
        for name in ("offsets", "scaling", "feat"):
            model.per_anchor[name].normal_()
        model.per_anchor["mask"].copy_(torch.randn(N, K, 1) * 4)       # about 1/3 off
        for mlp in (model.decoder.mlp_opacity, model.decoder.mlp_cov, model.decoder.mlp_color):
            mlp[2].weight.normal_(std=0.3)
    cam = torch.tensor([0.5, -1.0, -6.0])
    for idx in (torch.arange(N), torch.randperm(N)[: N // 3].sort().values):
        got = model.decode(cam, idx)
        want = decode_all_then_select(model, cam, idx)
        assert 0 < len(want["means"]) < len(idx) * K
        for k, v in want.items():     # equal up to the vectorised kernels' last-bit rounding
            assert getattr(got, k).shape == v.shape, k
            assert torch.allclose(getattr(got, k), v, rtol=1e-6, atol=1e-7), k
        # the same gradients reach every parameter
        w = {k: torch.randn_like(v) for k, v in want.items() if v.is_floating_point()}
        params = [p for p in model.parameters() if p.requires_grad]
        g_got = torch.autograd.grad(sum((getattr(got, k) * w[k]).sum() for k in w), params,
                                    allow_unused=True)
        g_want = torch.autograd.grad(sum((want[k] * w[k]).sum() for k in w), params,
                                     allow_unused=True)
        for a, b in zip(g_got, g_want):
            assert (a is None) == (b is None)
            if a is not None:
                assert torch.allclose(a, b, rtol=1e-5, atol=1e-6)


def _growth_setup(skip: bool):
    cfg = _cfg(**{"model.voxel_size": 0.1, "model.n_offsets": 2,
                  "densify.reference_level_skip": str(skip).lower()})
    model = _model(cfg, torch.tensor([[0.0, 0.0, 0.0], [5.0, 5.0, 5.0]]))
    with torch.no_grad():
        model.per_anchor["scaling"].zero_()            # exp = 1
        model.per_anchor["offsets"][0, 0] = torch.tensor([0.07, 0.0, 0.0])
        model.per_anchor["offsets"][0, 1] = torch.tensor([1.0, 1.0, 0.0])
        model.per_anchor["feat"][0] = torch.arange(50.0)
        model.per_anchor["feat"][1] = -1.0
    return cfg, model


def test_growing_hand_made_case():
    cfg, model = _growth_setup(skip=False)
    grads = torch.tensor([0.001, 0.0003, 0.0, 0.0])   # G0 reaches level 2, G1 only level 0
    eligible = torch.tensor([True, True, False, False])
    opt = torch.optim.Adam([model.per_anchor["feat"]], lr=0.1)
    model.per_anchor["feat"].grad = torch.ones_like(model.per_anchor["feat"])
    opt.step()
    added = grow_anchors(model, grads, eligible, cfg, 0.1, opt, rand=lambda n: torch.ones(n))
    assert added == 2
    new = model.xyz[2:]
    # level 0 (cell 1.6): G1 at (1,1,0) -> cell (1,1,0); G0 at (0.07,0,0) falls in anchor 0's cell
    # level 1 (cell 0.4): G0 needs grad >= 0.0004 -> cell (0,0,0) is occupied by anchor 0
    # level 2 (cell 0.1): G0 needs grad >= 0.0008 -> cell (1,0,0) -> (0.1, 0, 0)
    assert torch.allclose(new, torch.tensor([[1.6, 1.6, 0.0], [0.1, 0.0, 0.0]]), atol=1e-6)
    assert torch.allclose(model.per_anchor["scaling"][2], torch.full((6,), math.log(1.6)), atol=1e-6)
    assert torch.allclose(model.per_anchor["scaling"][3], torch.full((6,), math.log(0.1)), atol=1e-6)
    assert torch.equal(model.per_anchor["feat"][2], model.per_anchor["feat"][0].detach())
    assert torch.equal(model.per_anchor["offsets"][2:], torch.zeros(2, 2, 3))
    assert torch.equal(model.per_anchor["mask"][2:], torch.ones(2, 2, 1))
    # Adam moments: kept for old rows, zero for new rows, and aligned with the new parameter
    st = opt.state[model.per_anchor["feat"]]
    assert st["exp_avg"].shape == (4, 50)
    assert (st["exp_avg"][:2] != 0).all() and (st["exp_avg"][2:] == 0).all()


@pytest.mark.parametrize("shape,span", [((0, 3), 5), ((1, 3), 5), ((3000, 3), 4),
                                        ((5000, 3), 100000), ((2000, 2), 7), ((500, 3), 2 ** 40)])
def test_unique_rows_matches_torch(shape, span):
    """The packed-key unique used by growing gives torch.unique(dim=0)'s rows, order and inverse
    (negative cells included; spans too wide to pack take torch's own path)."""
    g = torch.Generator().manual_seed(shape[0])
    a = torch.randint(-span, span, shape, generator=g)
    if shape[0] > 10:
        a = torch.cat([a, a[: shape[0] // 3]])          # duplicates
    rows, inv = _unique_rows(a)
    ref_rows, ref_inv = torch.unique(a, dim=0, return_inverse=True)
    assert torch.equal(rows, ref_rows) and torch.equal(inv, ref_inv)


def test_reference_level_skip_quirk():
    for skip, expect in ((False, 1), (True, 0)):
        cfg, model = _growth_setup(skip)
        grads = torch.tensor([0.001, 0.0, 0.0, 0.0])      # level 0 adds nothing (cell occupied)
        eligible = torch.tensor([True, False, False, False])
        assert grow_anchors(model, grads, eligible, cfg, 0.1, rand=lambda n: torch.ones(n)) == expect


def test_random_keep_probability_applied():
    cfg, model = _growth_setup(skip=False)
    grads = torch.tensor([0.001, 0.0003, 0.0, 0.0])
    eligible = torch.tensor([True, True, False, False])
    # draws below every keep probability: nothing is kept
    assert grow_anchors(model, grads, eligible, cfg, 0.1, rand=lambda n: torch.zeros(n)) == 0


def test_pruning_and_scaling_clamp():
    cfg = _cfg(**{"model.voxel_size": 1.0, "model.n_offsets": 2})
    model = _model(cfg, torch.tensor([[0.0, 0, 0], [3, 0, 0], [6, 0, 0]]))
    with torch.no_grad():
        model.per_anchor["scaling"][:, 3:] = 1.0
    opt = torch.optim.Adam([p for p in model.per_anchor.values() if p.requires_grad], lr=0.1)
    for p in model.per_anchor.values():
        if p.requires_grad:
            p.grad = torch.ones_like(p)
    opt.step()
    trainer = SimpleNamespace(cfg=cfg, model=model, optimizer=opt, voxel_size=1.0,
                              generator=torch.Generator().manual_seed(0),
                              on_anchors_changed=lambda a, b: None)
    hook = ScaffoldDensify(trainer)
    interval = hook.interval
    hook.anchor_demon = torch.tensor([100.0, 100.0, 10.0])
    hook.opacity_accum = torch.tensor([0.1, 5.0, 0.0])   # anchor 0 below 0.005*100; 2 too few views
    marker = model.per_anchor["feat"][1].detach().clone()
    hook.adjust()
    assert model.n_anchors == 2
    assert torch.allclose(model.xyz, torch.tensor([[3.0, 0, 0], [6, 0, 0]]))
    assert torch.equal(model.per_anchor["feat"][0], marker)
    assert opt.state[model.per_anchor["feat"]]["exp_avg"].shape == (2, 50)
    assert hook.anchor_demon.tolist() == [0.0, 10.0]     # counted anchors reset, others kept
    assert hook.log_fields() == {"grown": 0, "pruned": 1}
    again = ScaffoldDensify(trainer)                      # the counts go with the checkpoint
    again.load_state_dict(hook.state_dict())
    assert again.log_fields() == {"grown": 0, "pruned": 1}
    old = {k: v for k, v in hook.state_dict().items() if k not in ("grown", "pruned")}
    again.load_state_dict(old)                            # a checkpoint without them: from 0
    assert again.log_fields() == {"grown": 0, "pruned": 0}
    assert (model.per_anchor["scaling"][:, 3:] <= 0.05 + 1e-7).all()
    assert interval == max(10, cfg.train.at(cfg.densify.update_interval))


def _three_anchor_hook(key: str, value: bool):
    """Three anchors, K = 2, and their densify hook, with config ``key`` set to ``value``."""
    cfg = _cfg(**{"model.voxel_size": 1.0, "model.n_offsets": 2, key: str(value).lower()})
    model = _model(cfg, torch.tensor([[0.0, 0, 0], [3, 0, 0], [6, 0, 0]]))
    trainer = SimpleNamespace(cfg=cfg, model=model, optimizer=None, voxel_size=1.0,
                              generator=torch.Generator().manual_seed(0),
                              on_anchors_changed=lambda a, b: None)
    return cfg, model, ScaffoldDensify(trainer)


@pytest.mark.parametrize("to_end", [False, True])
def test_scaling_clamp_after_the_adjustments_only_when_asked(to_end):
    """After update_until the reference stops clamping the scale multipliers (nothing adjusts
    anchors any more); ``densify.clamp_scaling_to_end`` keeps the clamp every update_interval to
    the end of training, without growing or pruning anything."""
    cfg, model, hook = _three_anchor_hook("densify.clamp_scaling_to_end", to_end)
    with torch.no_grad():
        model.per_anchor["scaling"][:, :3] = 2.0
        model.per_anchor["scaling"][:, 3:] = 3.0
    late = hook.update_until + hook.interval - hook.update_until % hook.interval
    hook.after_step(late + 1)                       # not a multiple of the interval: nothing
    assert (model.per_anchor["scaling"][:, 3:] == 3.0).all()
    hook.after_step(late)
    s = model.per_anchor["scaling"]
    assert model.n_anchors == 3 and (s[:, :3] == 2.0).all()      # positions' scales untouched
    expected = cfg.densify.prune_clamp_log_scaling if to_end else 3.0
    assert torch.allclose(s[:, 3:], torch.full_like(s[:, 3:], expected))


@pytest.mark.parametrize("quirk", [False, True])
def test_reference_skip_update_quirk(quirk):
    """With densify.reference_skip_update the per-anchor parameters get no update at the
    iterations that grow and prune (the reference replaces them before its optimizer step);
    the networks' gradients and every other iteration are untouched."""
    cfg, model, hook = _three_anchor_hook("densify.reference_skip_update", quirk)
    net = next(model.decoder.parameters())
    ctx = {"gaussians": SimpleNamespace(visible=torch.ones(3, dtype=torch.bool),
                                        opacity_all=torch.zeros(3, 2)),
           "render": SimpleNamespace(means2d=SimpleNamespace(grad=None)), "camera": None}
    adjusting = hook.update_from + hook.interval - hook.update_from % hook.interval
    assert hook.adjusts(adjusting) and not hook.adjusts(adjusting + 1)
    assert not hook.adjusts(hook.skip[0])
    for it in (adjusting, adjusting + 1, hook.skip[0]):
        trained = [p for p in model.per_anchor.values() if p.requires_grad]
        for p in trained + [net]:
            p.grad = torch.ones_like(p)
        hook.after_backward(it, ctx)
        dropped = quirk and it == adjusting
        assert all((p.grad is None) == dropped for p in trained), it
        assert net.grad is not None
