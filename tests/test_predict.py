"""Predict-GS plugin: schedule values (eq. 6), stage switching, SFP, zero-correction identity."""
import math
from types import SimpleNamespace

import pytest
import torch

from baseline.config import build_config
from baseline.scaffold.build import build_model
from predict_plugin.schedule import downsample_scale


def test_cosine_schedule_eq6_values():
    T = 9000
    assert downsample_scale(0, "cosine", 0.7, 1.0, T) == pytest.approx(0.7)
    assert downsample_scale(T // 2, "cosine", 0.7, 1.0, T) == pytest.approx(0.85)
    assert downsample_scale(T, "cosine", 0.7, 1.0, T) == pytest.approx(1.0)
    assert downsample_scale(T + 100, "cosine", 0.7, 1.0, T) == 1.0
    t = 2000
    want = 1.0 + 0.5 * (0.7 - 1.0) * (1 + math.cos(math.pi * t / T))
    assert downsample_scale(t, "cosine", 0.7, 1.0, T) == pytest.approx(want)


def test_linear_and_none_schedules():
    assert downsample_scale(4500, "linear", 0.7, 1.0, 9000) == pytest.approx(0.85)
    assert downsample_scale(10, "none", 0.7, 1.0, 9000, stage2_from=5000) == 0.7
    assert downsample_scale(5000, "none", 0.7, 1.0, 9000, stage2_from=5000) == 1.0
    with pytest.raises(ValueError, match="unknown progressive schedule"):
        downsample_scale(0, "cubic", 0.7, 1.0, 9000)


def _pgs_cfg(*sets):
    return build_config(["predict-gs"], list(sets))


def _pgs_model(cfg, n=300, seed=0):
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(n, 3, generator=g) * 2 - 1
    model, _ = build_model(cfg, pts)
    return model


def test_sfp_declares_residual_instead_of_feat():
    cfg = _pgs_cfg("model.voxel_size=0.2")
    model = _pgs_model(cfg)
    names = [(a.name, a.dims, a.q0, a.masked) for a in model.coded_attributes()]
    assert names == [("residual", 25, 1.0, False), ("scaling", 6, 0.001, False),
                     ("offsets", 30, 0.2, True)]
    assert "feat" not in model.per_anchor and model.per_anchor["residual"].shape[1] == 25
    cfg2 = _pgs_cfg("model.voxel_size=0.2", "predict.residual_dim=10")
    assert _pgs_model(cfg2).per_anchor["residual"].shape[1] == 10


def test_sfp_output_shape_and_gradient_reaches_hash_params():
    # PyTorch's init of the fusion: a zero last layer passes no gradient to the grid at start
    cfg = _pgs_cfg("model.voxel_size=0.2", "predict.fusion_init=default")
    model = _pgs_model(cfg)
    sfp = model.provider
    idx = torch.arange(model.n_anchors)
    f = sfp.decoder_features(idx, {}, model.xyz[idx])
    assert f.shape == (model.n_anchors, 50)
    f.square().sum().backward()
    grads = [p.grad for p in sfp.grid.parameters()]
    assert all(g is not None for g in grads)
    assert sum(float(g.abs().sum()) for g in grads) > 0, "no gradient through the binarization STE"


def test_zero_correction_leaves_prediction_unchanged():
    cfg = _pgs_cfg("model.voxel_size=0.2")
    model = _pgs_model(cfg)
    with torch.no_grad():
        model.per_anchor["residual"].normal_()
    idx = torch.arange(model.n_anchors)
    cam = torch.tensor([0.0, 0.0, -4.0])
    model.refiner.active = False
    g0 = model.decode(cam, idx)
    model.refiner.active = True          # zero-initialised last layers: corrections are zero
    g1 = model.decode(cam, idx)
    for a in ("means", "quats", "scales", "opacities", "colors"):
        assert torch.equal(getattr(g0, a), getattr(g1, a)), a
    with torch.no_grad():                 # a non-zero correction changes the Gaussians
        model.refiner.appearance_head[2].bias.fill_(0.5)
    g2 = model.decode(cam, idx)
    assert not torch.allclose(g0.opacity_all, g2.opacity_all)


def test_refined_gaussians_are_kept_before_they_are_activated():
    """With the MGRD on (non-zero corrections), decode() keeps the Gaussians first and
    activates only those: the same Gaussians as activating all candidates, then selecting."""
    from baseline.scaffold.model import decode_all_then_select

    torch.manual_seed(1)
    cfg = _pgs_cfg("model.voxel_size=0.2")
    model = _pgs_model(cfg)
    with torch.no_grad():
        model.per_anchor["residual"].normal_()
        model.per_anchor["mask"].normal_(std=4.0)
        for head in (model.refiner.shape_head, model.refiner.appearance_head):
            head[2].weight.normal_(std=0.5)
    model.refiner.active = True
    idx = torch.arange(0, model.n_anchors, 2)
    cam = torch.tensor([0.3, 0.1, -4.0])
    got = model.decode(cam, idx)
    want = decode_all_then_select(model, cam, idx)
    assert 0 < len(want["means"]) < len(idx) * model.n_offsets
    for k, v in want.items():
        assert torch.allclose(getattr(got, k), v, rtol=1e-6, atol=1e-7), k


def test_post_activation_corrections_add_to_the_attributes():
    """predict.corrections = "post": opacity = tanh(raw) + d_o and colour = sigmoid(raw) + d_c
    (eq. 5 on the coarse heads' outputs), cov corrections before its activations; a zero
    correction changes nothing; decode() keeps the same Gaussians as activating all candidates
    first; such a model is not baked."""
    from baseline.scaffold.baked import BakedDecoder
    from baseline.scaffold.model import decode_all_then_select, view_inputs

    torch.manual_seed(2)
    cfg = _pgs_cfg("model.voxel_size=0.2", "predict.corrections=post")
    model = _pgs_model(cfg)
    assert model.refiner.post_activation == ("opacity", "color")
    idx = torch.arange(0, model.n_anchors, 2)
    cam = torch.tensor([0.3, 0.1, -4.0])
    with torch.no_grad():
        model.per_anchor["residual"].normal_()
        model.per_anchor["mask"].normal_(std=4.0)
    model.refiner.active = False
    g0 = model.decode(cam, idx)
    model.refiner.active = True          # zero last layers: nothing changes
    g1 = model.decode(cam, idx)
    for a in ("means", "quats", "scales", "opacities", "colors"):
        assert torch.equal(getattr(g0, a), getattr(g1, a)), a
    with torch.no_grad():
        for head in (model.refiner.shape_head, model.refiner.appearance_head):
            head[2].weight.normal_(std=0.5)
        h = model.raw_heads(cam, idx)
        model.refiner.active = False
        h0 = model.raw_heads(cam, idx)
        model.refiner.active = True
        view_dir, dist = view_inputs(model.xyz[idx], cam)
        d = model.refiner(idx, model.coded_values(idx), view_dir, dist)
    assert torch.equal(h.raw_op, h0.raw_op) and torch.equal(h.raw_col, h0.raw_col)
    assert torch.allclose(h.opacity(), torch.tanh(h0.raw_op) + d["opacity"])
    every = torch.arange(h.raw_col.numel() // 3)
    assert torch.allclose(h.colors(every), torch.sigmoid(h0.raw_col).reshape(-1, 3)
                          + d["color"].reshape(-1, 3))
    assert torch.allclose(h.raw_cov, h0.raw_cov + d["cov"])
    assert (h.opacity() > 1).any() or (h.colors(every) > 1).any() or (h.colors(every) < 0).any()
    got = model.decode(cam, idx)
    want = decode_all_then_select(model, cam, idx)
    assert 0 < len(want["means"]) < len(idx) * model.n_offsets
    for k, v in want.items():
        assert torch.allclose(getattr(got, k), v, rtol=1e-6, atol=1e-7), k
    model.fixed_values = model.coded_values(torch.arange(model.n_anchors))
    assert BakedDecoder.from_model(model) is None
    pre = _pgs_model(_pgs_cfg("model.voxel_size=0.2"))
    assert pre.refiner.post_activation == ()
    with pytest.raises(ValueError, match="predict.corrections"):
        _pgs_model(_pgs_cfg("model.voxel_size=0.2", "predict.corrections=after"))


def test_corrections_option_keeps_the_hash_of_configs_without_it():
    from baseline.config import config_hash

    base = _pgs_cfg()
    assert config_hash(base) == config_hash(_pgs_cfg("predict.corrections=pre"))
    assert config_hash(base) != config_hash(_pgs_cfg("predict.corrections=post"))
    assert config_hash(build_config(["predict-gs", "mgrd-post"], [])) == config_hash(
        _pgs_cfg("predict.corrections=post"))


def test_mgrd_init_option_starts_the_output_layers_at_zero_or_at_pytorch_init():
    """predict.mgrd_init: "zero" (default) gives a zero correction for any input, so stage 2's
    first step leaves the prediction unchanged; "default" (patch mgrd-init-default) PyTorch's
    random init, a correction that varies with the view; the default keeps the config hash; a
    bad value is refused."""
    from baseline.config import config_hash

    x = {"residual": torch.zeros(5, 25)}
    view, dist = torch.nn.functional.normalize(torch.randn(5, 3), dim=-1), torch.rand(5, 1)
    zero = _pgs_model(_pgs_cfg("model.voxel_size=0.2")).refiner
    with torch.no_grad():
        out = zero(None, x, view, dist)
    assert all(torch.count_nonzero(v) == 0 for v in out.values())
    torch.manual_seed(0)
    cfg = build_config(["predict-gs", "mgrd-init-default"], ["model.voxel_size=0.2"])
    default = _pgs_model(cfg).refiner
    with torch.no_grad():
        out = default(None, x, view, dist)
    assert all(float(v.abs().min()) > 0 for v in out.values())
    assert not torch.allclose(out["cov"][0], out["cov"][1])       # depends on the view
    assert config_hash(_pgs_cfg()) == config_hash(_pgs_cfg("predict.mgrd_init=zero"))
    assert config_hash(cfg) != config_hash(build_config(["predict-gs"], ["model.voxel_size=0.2"]))
    with pytest.raises(ValueError, match="predict.mgrd_init"):
        _pgs_model(_pgs_cfg("model.voxel_size=0.2", "predict.mgrd_init=uniform"))


def test_mgrd_lr_heads_gives_each_head_the_rate_of_the_head_it_corrects():
    """predict.mgrd_lr = "heads" (patch mgrd-lr-heads): the shape head at the cov head's
    schedule, the appearance head at the colour head's; "own" (default): one group at
    lr_mgrd_*; the default keeps the config hash; a bad value is refused."""
    from baseline.config import config_hash

    own = _pgs_model(_pgs_cfg("model.voxel_size=0.2"))
    cfg = build_config(["predict-gs", "mgrd-lr-heads"], ["model.voxel_size=0.2"])
    heads = _pgs_model(cfg)
    g_own = own.refiner.param_groups(own_cfg := _pgs_cfg("model.voxel_size=0.2"))
    assert [g["name"] for g in g_own] == ["mgrd"]
    assert (g_own[0]["lr_init"], g_own[0]["lr_final"]) == (own_cfg.ext["predict"].lr_mgrd_init,
                                                           own_cfg.ext["predict"].lr_mgrd_final)
    g = {x["name"]: x for x in heads.refiner.param_groups(cfg)}
    assert set(g) == {"mgrd_shape", "mgrd_appearance"}
    assert (g["mgrd_shape"]["lr_init"], g["mgrd_shape"]["lr_final"]) == (cfg.lr.mlp_cov,) * 2
    assert (g["mgrd_appearance"]["lr_init"], g["mgrd_appearance"]["lr_final"]) == (
        cfg.lr.mlp_color_init, cfg.lr.mlp_color_final)
    ids = lambda ps: {id(p) for p in ps}                                       # noqa: E731
    assert ids(g["mgrd_shape"]["params"]) == ids(heads.refiner.shape_head.parameters())
    assert ids(g["mgrd_appearance"]["params"]) == ids(heads.refiner.appearance_head.parameters())
    assert config_hash(_pgs_cfg()) == config_hash(_pgs_cfg("predict.mgrd_lr=own"))
    assert config_hash(_pgs_cfg()) != config_hash(_pgs_cfg("predict.mgrd_lr=heads"))
    with pytest.raises(ValueError, match="predict.mgrd_lr"):
        _pgs_model(_pgs_cfg("model.voxel_size=0.2", "predict.mgrd_lr=decoder"))


def test_residual_noise_rate_leaves_the_residual_exact_in_the_noise_phase(monkeypatch):
    """predict.residual_noise = "rate" (patch residual-noise-rate): training's noise phase adds
    U(-0.5, 0.5) x Q0 to scaling and offsets but not to the residual; "always" (default) to
    all; the default keeps the config hash; a bad value is refused."""
    from baseline.camera import Camera
    from baseline.config import config_hash
    from baseline.pipeline import render_view

    vm = torch.eye(4)
    vm[2, 3] = 4.0                       # the anchors in [-1, 1]^3 lie 3-5 units in front
    cam = Camera(viewmat=vm, fx=40.0, fy=40.0, cx=32.0, cy=24.0, width=64, height=48,
                 near=0.2, far=100.0)
    for mode, residual_noised in (("always", True), ("rate", False)):
        model = _pgs_model(_pgs_cfg("model.voxel_size=0.2", f"predict.residual_noise={mode}"))
        with torch.no_grad():
            model.per_anchor["residual"].normal_()
        seen = {}
        decode = model.decode

        def spy(cam_center, idx, values=None, **kw):
            seen.update(idx=idx, values={k: v.detach().clone() for k, v in values.items()})
            return decode(cam_center, idx, values, **kw)

        monkeypatch.setattr(model, "decode", spy)
        render_view(model, cam, torch.zeros(3), phase="noise", training=True,
                    generator=torch.Generator().manual_seed(0))
        raw = model.coded_values(seen["idx"])
        assert len(seen["idx"]) > 0
        for k in ("scaling", "offsets"):
            assert not torch.equal(seen["values"][k], raw[k].detach()), k
        assert torch.equal(seen["values"]["residual"], raw["residual"].detach()) != \
            residual_noised
    assert config_hash(_pgs_cfg()) == config_hash(_pgs_cfg("predict.residual_noise=always"))
    assert config_hash(_pgs_cfg()) != config_hash(_pgs_cfg("predict.residual_noise=rate"))
    assert config_hash(build_config(["predict-gs", "residual-noise-rate"], [])) == config_hash(
        _pgs_cfg("predict.residual_noise=rate"))
    with pytest.raises(ValueError, match="predict.residual_noise"):
        _pgs_model(_pgs_cfg("model.voxel_size=0.2", "predict.residual_noise=never"))


def test_stage_switch_and_resolution_hook():
    from predict_plugin.hooks import PredictStages

    cfg = _pgs_cfg("model.voxel_size=0.2", "train.iterations=300")
    model = _pgs_model(cfg)
    t = SimpleNamespace(cfg=cfg, model=model, render_scale=1.0)
    hook = PredictStages(t)
    assert hook.residual_from == 50 and hook.T == 90     # 5k and 9k of 30k, scaled to 300
    hook.before_step(50)
    assert model.refiner.active is False and t.render_scale == pytest.approx(
        downsample_scale(50, "cosine", 0.7, 1.0, 90))
    hook.before_step(51)
    assert model.refiner.active is True
    hook.before_step(0)
    assert t.render_scale == pytest.approx(0.7)
    hook.before_step(90)
    assert t.render_scale == pytest.approx(1.0)


def test_loaded_run_renders_with_its_refiner(tmp_path, scene_maker):
    """A stage-2 run loaded from its checkpoint renders like the trainer that wrote it (the
    MGRD switched on by the hooks' restore, not left off until a training step)."""
    from baseline.run import evaluate_trainer, load_run, train_run
    from conftest import demo_cfg

    scene = scene_maker(n_views=9, width=48, height=36, seed=4)
    res = train_run(str(scene), tmp_path / "run", demo_cfg(40, patches=["predict-gs"]),
                    progress=False)
    t, scene = load_run(tmp_path / "run")
    assert t.model.refiner.active is True
    ev = evaluate_trainer(t, scene)
    assert ev["psnr"] == pytest.approx(res["test"]["psnr"], abs=1e-6)


def test_baseline_config_unchanged_by_plugin():
    cfg = build_config()
    assert cfg.model.feature_provider == "explicit" and cfg.model.refiner == "none"
    assert "predict_stages" not in cfg.train.hooks


def test_auto_sized_sfp_decodes_after_the_anchor_count_changed(tmp_path):
    """With predict.grid_auto the SFP grid is sized from the anchors at the start of training;
    the file keeps that layout (codec_state), so a model whose anchor count changed since (growing)
    decodes to the same grid and the same predicted features."""
    from baseline.modelfile import decode_model, encode_model, file_info
    from baseline.scaffold.build import build_entropy

    torch.set_num_threads(1)
    cfg = _pgs_cfg("model.voxel_size=0.05", "predict.grid_auto=true")
    model = _pgs_model(cfg, n=200)
    layout0 = dict(model.provider.grid_layout)
    g = torch.Generator().manual_seed(1)
    n_new = 3000
    model.append_anchors(torch.rand(n_new, 3, generator=g) * 2 - 1, torch.full((n_new, 6), -3.0),
                         parent=torch.zeros(n_new, dtype=torch.long), inverse=torch.arange(n_new))
    from predict_plugin.sfp import SpatialFeaturePool
    rebuilt = SpatialFeaturePool(model, cfg)            # what sizing from the new count gives
    assert rebuilt.grid_layout != layout0, "the test must change the auto layout"
    entropy = build_entropy(cfg, model)
    st = encode_model(cfg, model, entropy, tmp_path / "m.pgs")
    dec = decode_model(tmp_path / "m.pgs")
    assert dec.model.provider.grid_layout == layout0
    assert file_info(tmp_path / "m.pgs")["n_anchors"] == model.n_anchors == dec.model.n_anchors
    with torch.no_grad():
        assert torch.equal(dec.model.provider.predict(st["xyz_q"]), model.provider.predict(st["xyz_q"]))
    # a damaged state in the header is a clear bitstream error, not a crash
    # (the header re-signed as an encoder would: only its content is wrong)
    from baseline.codec.container import BitstreamError, read_container
    from baseline.testing.hostile import _resign
    header, sections = read_container(tmp_path / "m.pgs")
    header["module_state"]["provider"] = {"grid": "junk"}
    (tmp_path / "bad.pgs").write_bytes(_resign(header, list(sections.items())))
    with pytest.raises(BitstreamError, match="module_state"):
        decode_model(tmp_path / "bad.pgs")


def test_sfp_starts_with_one_feature_for_every_anchor_and_each_cell_learns_from_step_one():
    """The default start (predict.grid_init = "shared", fusion_init = "default"): every table
    entry at +init_range, so every anchor reads one binarized code and gets one feature (as
    Scaffold-GS's anchors all start at feature 0); the first gradient reaches the grid's
    entries, and one Adam step gives the cells different codes and the anchors different
    features. "random" starts from HAC's random code per cell."""
    cfg = _pgs_cfg("model.voxel_size=0.2")
    p = cfg.ext["predict"]
    assert (p.grid_init, p.fusion_init) == ("shared", "default")
    model = _pgs_model(cfg)
    sfp = model.provider
    start = sfp.grid.config["init_range"]
    assert start > 0 and all(bool((t == start).all()) for t in sfp.grid.parameters())
    f = sfp.predict(model.xyz)
    assert f.abs().max() > 1e-2
    assert torch.equal(f, f[:1].expand_as(f))                   # one feature for all anchors
    opt = torch.optim.Adam(sfp.parameters(), lr=0.005)
    target = torch.randn_like(f)
    (f * target).sum().backward()
    assert sum(float(t.grad.abs().sum()) for t in sfp.grid.parameters()) > 0
    opt.step()
    f1 = sfp.predict(model.xyz)
    assert f1.std(dim=0).mean() > 1e-3                          # the anchors have diverged
    rnd = _pgs_model(_pgs_cfg("model.voxel_size=0.2", "predict.grid_init=random"))
    f2 = rnd.provider.predict(rnd.xyz)
    assert f2.std(dim=0).mean() > 1e-3                          # a random code per anchor
    with pytest.raises(ValueError, match="grid_init"):
        _pgs_model(_pgs_cfg("model.voxel_size=0.2", "predict.grid_init=ones"))


def test_fusion_zero_option_starts_at_zero_and_learns_away_from_it():
    """predict.fusion_init = "zero" (the SFP's semantics 2 and 3) gives f_c = 0 for every
    anchor at start, and the first step moves the fusion's last layer (the grid's gradient then
    flows); "default" starts from PyTorch's init."""
    cfg = _pgs_cfg("model.voxel_size=0.2", "predict.fusion_init=zero", "predict.grid_init=random")
    model = _pgs_model(cfg)
    idx = torch.arange(model.n_anchors)
    f = model.provider.predict(model.xyz[idx])
    assert torch.count_nonzero(f) == 0
    f.retain_grad()
    (f * torch.randn_like(f)).sum().backward()
    last = model.provider.fusion[2]
    assert last.weight.grad is not None and last.weight.grad.abs().sum() > 0
    rnd = _pgs_model(_pgs_cfg("model.voxel_size=0.2", "predict.fusion_init=default",
                              "predict.grid_init=random"))
    f2 = rnd.provider.predict(rnd.xyz)
    assert f2.abs().mean() > 1e-2 and f2.std(dim=0).mean() > 1e-3   # differs between anchors
    with pytest.raises(ValueError, match="fusion_init"):
        _pgs_model(_pgs_cfg("model.voxel_size=0.2", "predict.fusion_init=ones"))


@pytest.mark.parametrize("rule", ["zero", "parent"])
def test_grown_anchor_residual_rule(rule):
    """predict.residual_grow: a grown anchor's residual is zero (default) or the element-wise
    max of its parents' residuals (HAC's feature rule); the parents' rows are unchanged, and a
    rule that does not exist is refused by name."""
    cfg = _pgs_cfg("model.voxel_size=0.2", f"predict.residual_grow={rule}")
    model = _pgs_model(cfg, n=20)
    N = model.n_anchors
    with torch.no_grad():
        r = model.per_anchor["residual"]
        r.copy_(torch.randn(r.shape, generator=torch.Generator().manual_seed(1)))
    before = model.per_anchor["residual"].detach().clone()
    # three candidates: parents 0 and 1 make new anchor 0, parent 2 makes new anchor 1
    parent, inverse = torch.tensor([0, 1, 2]), torch.tensor([0, 0, 1])
    model.append_anchors(torch.tensor([[3.0, 3.0, 3.0], [4.0, 4.0, 4.0]]), torch.zeros(2, 6),
                         parent, inverse)
    got = model.per_anchor["residual"].detach()
    assert got.shape == (N + 2, 25) and torch.equal(got[:N], before)
    if rule == "zero":
        assert torch.equal(got[N:], torch.zeros(2, 25))
    else:
        assert torch.equal(got[N], torch.maximum(before[0], before[1]))
        assert torch.equal(got[N + 1], before[2])
    with pytest.raises(ValueError, match="residual_grow"):
        _pgs_model(_pgs_cfg("model.voxel_size=0.2", "predict.residual_grow=mean"))


def test_predict_gs_hash_of_the_archived_truck_record_survives_new_options():
    """Options added to Predict-GS after its semantics-4 truck records were archived stay out of
    the hash at their default: the current code reuses those records (same training), and the
    option turned on trains a new run."""
    from pathlib import Path

    from baseline.config import config_hash

    root = Path(__file__).parent.parent / "docs/examples/truck-r4-cpu-s4/runs"
    runs = {d.name.rsplit("-", 1)[0]: d.name.rsplit("-", 1)[1] for d in root.iterdir()}
    for name, h in runs.items():
        method, lam, seed = name.rsplit("-", 2)
        patches = ["cpu"] + (["predict-gs"] if method == "predict-gs" else [])
        sets = ["data.resolution=4", f"entropy.lmbda={float(lam[1:])!r}",
                f"train.seed={int(seed[1:])}", "train.positions=float"]    # semantics 2
        assert config_hash(build_config(patches, sets), semantics=2) == h, name
        assert config_hash(build_config(patches, sets[:-1])) != h, name
        on = build_config(patches + ["residual-grow-parent"], sets)
        assert (config_hash(on, semantics=2) == h) == (method == "baseline"), name
    assert "predict-gs-l0.004-s0" in runs


def test_sfp_training_semantics_changes_only_predict_gs_hashes():
    """The SFP's component semantics (4: one shared code at the start) enters the hash of the configs that
    use it: the archived semantics-2 truck records of HAC keep their folder hashes, those of
    Predict-GS trained with the old init do not. (Those records predate the cpu preset's scaled
    mask learning rate: they are built here with it off, and under the current preset no hash
    matches.)"""
    from pathlib import Path

    from baseline.config import component_semantics, config_hash

    root = Path(__file__).parent.parent / "tests/data/archived/truck-r4-cpu-s2/runs"
    assert component_semantics(build_config(["cpu"])) == {}
    assert component_semantics(build_config(["cpu", "predict-gs"])) == {"feature_provider.sfp": 4}
    for d in root.iterdir():
        method, lam, seed, h = d.name.rsplit("-", 3)
        cfg = build_config(["cpu"] + (["predict-gs"] if method == "predict-gs" else []),
                           ["data.resolution=4", f"entropy.lmbda={float(lam[1:])!r}",
                            f"train.seed={int(seed[1:])}", "train.positions=float"])
        assert config_hash(cfg, semantics=2) != h, d.name
        cfg.lr.mask_schedule_scaled = False
        assert (config_hash(cfg, semantics=2) == h) == (method == "baseline"), d.name


def test_hac_and_predict_gs_start_from_the_same_decoder_with_one_seed(small_scene, tmp_path):
    """The provider draws its initial values from a stream of its own: with one seed, HAC and
    Predict-GS start from the same decoder weights and the same anchors; HAC's is the draw that
    follows the seed."""
    from baseline.data.scene import load_scene
    from baseline.train.trainer import Trainer

    scene = load_scene(small_scene, progress=False)
    models = {}
    for patches in (["demo"], ["demo", "predict-gs"]):
        cfg = build_config(patches, ["train.seed=3", "train.threads=1"])
        models[len(patches)] = Trainer(cfg, scene, tmp_path / str(len(patches)),
                                       progress=False).model
    hac, pgs = models[1], models[2]
    for (n, a), (_, b) in zip(hac.decoder.state_dict().items(), pgs.decoder.state_dict().items()):
        assert torch.equal(a, b), n
    assert torch.equal(hac.xyz, pgs.xyz)
    # and it is the draw that follows the seed, as before the provider had its own stream
    from baseline.scaffold.model import DecoderMLPs
    torch.manual_seed(3)
    ref = DecoderMLPs(hac.provider.feature_dim, hac.n_offsets, cfg.model.hidden,
                      cfg.model.use_distance)
    for (n, a), (_, b) in zip(ref.state_dict().items(), hac.decoder.state_dict().items()):
        assert torch.equal(a, b), n


def test_contracted_sfp_box_is_the_inner_quantiles_and_decodes_the_same(tmp_path):
    """predict.box = "contract": the grid bounds are the anchors' inner-quantile box (+10%),
    positions inside map linearly onto the middle half of the grid, far ones into the outer
    shell (never outside [0, 1)), continuously at the box face; a decoded model reads the same
    f_c (the flag comes from the config, the bounds from the file)."""
    from baseline.modelfile import decode_model, encode_model
    from baseline.hac.hashgrid import contract_unit
    from baseline.scaffold.build import build_entropy

    u = torch.tensor([[0.5, 0.5, 0.5], [0.0, 1.0, 0.25], [3.0, 0.5, 0.5], [-1e6, 0.5, 2.0]],
                     dtype=torch.float64)
    c = contract_unit(u)
    assert torch.allclose(c[0], torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64))
    assert torch.allclose(c[1], torch.tensor([0.25, 0.75, 0.375], dtype=torch.float64))
    assert bool(((c >= 0) & (c < 1)).all())
    assert float(c[2, 0]) == pytest.approx((2 - 1 / 5) / 4 + 0.5)      # v = 5 -> 1.8 -> 0.95
    edge = contract_unit(torch.tensor([[1.0 + 1e-12, 0.5, 0.5]], dtype=torch.float64))
    assert float(edge[0, 0]) == pytest.approx(0.75)

    cfg = _pgs_cfg("model.voxel_size=0.05", "predict.box=contract", "predict.fusion_init=default")
    g = torch.Generator().manual_seed(1)
    pts = torch.cat([torch.rand(400, 3, generator=g) * 2 - 1, torch.tensor([[50.0, -40.0, 30.0]])])
    model, _ = build_model(cfg, pts)
    grid = model.provider.grid
    assert grid.contract and float(grid.xyz_max[0]) < 5.0       # the outlier is outside the box
    un = grid.normalize(model.xyz)
    assert bool(((un >= 0) & (un < 1)).all())
    f = model.provider.predict(model.xyz)
    ent = build_entropy(cfg, model)
    encode_model(cfg, model, ent, tmp_path / "m.pgs")
    dec = decode_model(tmp_path / "m.pgs")
    sfp = dec.model.provider
    assert sfp.grid.contract
    valid = model.anchor_valid()
    f_dec = sfp.predict(dec.model.xyz)
    assert f_dec.shape[0] == int(valid.sum())
    # decoded positions are 16-bit quantized: compare f_c at the decoded positions
    assert torch.allclose(f_dec, model.provider.predict(dec.model.xyz), atol=1e-6)
    assert not torch.allclose(f, torch.zeros_like(f))
    # only the grid entries decoded anchors read (codec.grids = used): read through the contraction
    from dataclasses import replace
    cfg_used = replace(cfg, codec=replace(cfg.codec, grids="used"))
    encode_model(cfg_used, model, ent, tmp_path / "used.pgs")
    dec2 = decode_model(tmp_path / "used.pgs")
    assert (tmp_path / "used.pgs").stat().st_size < (tmp_path / "m.pgs").stat().st_size
    assert torch.equal(dec2.model.provider.predict(dec2.model.xyz), f_dec)


def test_scene_facts_tool(decoded_files, capsys):
    """tools/probes/scene_facts.py: the camera layout and point boxes of a scene, and per run the
    anchors and (Predict-GS only) the SFP's box over the anchors' inner box."""
    import importlib.util
    import json
    import pathlib

    spec = importlib.util.spec_from_file_location(
        "scene_facts", pathlib.Path(__file__).parents[1] / "tools" / "probes" / "scene_facts.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    runs = [str(decoded_files["baseline"]), str(decoded_files["predict-gs"])]
    assert tool.main([str(decoded_files["scene"]), "--runs", *runs]) == 0
    scene, hac, pgs = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert scene["views"] == 10 and scene["points"] > 0
    assert 0 <= scene["view_dir_resultant"] <= 1 and 0 <= scene["camera_side_resultant"] <= 1
    assert len(scene["sfm_box_over_inner"]) == 3 and min(scene["sfm_box_over_inner"]) >= 1
    assert hac["anchors"] > 0 and "sfp_box_over_anchors_inner" not in hac
    # the SFP box is the initial anchors' full box plus 10% per side: wider than their inner 90%
    assert min(pgs["sfp_box_over_anchors_inner"]) > 1
    with pytest.raises(SystemExit, match="checkpoint"):
        tool.main([str(decoded_files["scene"]), "--runs", str(decoded_files["scene"])])


def test_grid_point_order_probe(decoded_files):
    """tools/probes/grid_point_order.py: each grid of a run (HAC: the entropy context; Predict-GS:
    that and the SFP's grid) timed in the model's, Morton and a random point order, whose forward
    values it checks to be the model order's, permuted; the Morton order sorts by Z-code."""
    import importlib.util
    import pathlib

    spec = importlib.util.spec_from_file_location(
        "grid_point_order", pathlib.Path(__file__).parents[1] / "tools" / "probes" / "grid_point_order.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    u = torch.tensor([[0.9, 0.9, 0.9], [0.0, 0.0, 0.0], [0.6, 0.0, 0.0], [0.0, 0.6, 0.0]])
    assert tool.morton_order(u).tolist() == [1, 2, 3, 0]
    hac = tool.probe_run(str(decoded_files["baseline"]), views=2, repeats=1)
    pgs = tool.probe_run(str(decoded_files["predict-gs"]), views=2, repeats=1)
    assert [r["grid"] for r in hac] == ["entropy context"] * 2
    assert [r["grid"] for r in pgs] == ["entropy context"] * 2 + ["feature provider"] * 2
    for r in hac + pgs:
        assert r["points"] > 0 and r["levels"] > 0
        assert all(t > 0 for o in ("model", "Morton", "random") for t in r[o]) and r["corners only"] > 0
    assert "feature provider" in tool.format_rows(pgs)


def test_kept_share_probe_tool(small_scene, capsys):
    """tools/probes/kept_share_probe.py: with one seed it measures HAC's and Predict-GS's start (one row
    each; with the SFP's earlier zero fusion layer, f_c = 0 as HAC's features, the two starts are
    the same decoder on the same input); a short training reports each asked step."""
    import importlib.util
    import json
    import pathlib

    spec = importlib.util.spec_from_file_location(
        "kept_share_probe", pathlib.Path(__file__).parents[1] / "tools" / "probes" / "kept_share_probe.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    assert tool.main([str(small_scene), "--patch", "demo", "--init-seeds", "1"]) == 0
    rows = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [(r["seed"], r["patches"]) for r in rows] == [(0, ["demo"]), (0, ["demo", "predict-gs"])]
    assert tool.main([str(small_scene), "--patch", "demo", "--patch", "sfp-zero-fusion",
                      "--init-seeds", "1"]) == 0
    zero = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert zero[0]["kept_share"] == zero[1]["kept_share"] == rows[0]["kept_share"]
    assert 0 < rows[0]["kept_share"] <= 1 and abs(sum(rows[0]["per_anchor"]) - 1) < 1e-2
    assert tool.main([str(small_scene), "--patch", "demo", "--patch", "predict-gs",
                      "--steps", "0", "3"]) == 0
    rows = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [r["it"] for r in rows] == [0, 3]
    assert all(0 < r["kept_share"] <= 1 and r["gaussians"] > 0 for r in rows)


def test_a_grid_pass_is_shared_only_for_the_same_positions_and_tables():
    """``BinaryHashGrid.shared_query``: the same position tensor under the same tables gives
    the very same output (one pass for the SFP and an entropy context reading its grid); new
    positions, an in-place change of the positions or a table update give a fresh pass, equal
    to a direct query; a pass without gradients is neither reused nor kept."""
    from baseline.hac.hashgrid import BinaryHashGrid

    torch.manual_seed(0)
    grid = BinaryHashGrid(resolutions_3d=(4, 8), log2_table_3d=6, resolutions_2d=(8,),
                          log2_table_2d=6)
    xyz = torch.rand(50, 3)
    a = grid.shared_query(xyz)
    assert grid.shared_query(xyz) is a and torch.equal(a, grid(xyz))
    b = grid.shared_query(xyz.clone())
    assert b is not a and torch.equal(b, a)
    a = grid.shared_query(xyz)
    with torch.no_grad():                  # without gradients: neither reused nor kept
        c = grid.shared_query(xyz)
        assert grid.shared_query(xyz) is not c
    assert c is not a and torch.equal(c, a) and grid.shared_query(xyz) is a
    with torch.no_grad():
        for g in grid.grids.values():
            g.params.mul_(-1.0)            # as an optimizer step would move the tables
    d = grid.shared_query(xyz)
    assert d is not a and torch.equal(d, grid(xyz)) and not torch.equal(d, a)
    xyz.add_(0.01)
    assert torch.equal(grid.shared_query(xyz), grid(xyz))


@pytest.mark.parametrize("coding", [[], ["hacpp"]], ids=["HAC", "HAC++"])
def test_entropy_context_from_the_sfp_grid_trains_codes_and_decodes(tmp_path, scene_maker, coding):
    """``entropy.context = "provider"`` (patch ``sfp-context``): HAC's entropy model reads the
    SFP's grid as its context. It owns no grid (no parameters, state, hash bits or file section
    of one), the rate's gradient does not reach the SFP's tables, the SFP keeps its box at the
    rate's start, the optimizer holds each table once, and the file decodes to exactly the
    values the encoder quantized, from the decoded SFP grid."""
    from baseline.config import config_hash
    from baseline.codec.container import read_container
    from baseline.modelfile import decode_model, encode_model
    from baseline.pipeline import coded_state
    from baseline.run import load_run, train_run
    from conftest import demo_cfg

    cfg = demo_cfg(40, patches=["predict-gs", *coding, "sfp-context"])
    assert cfg.entropy.context == "provider"
    assert config_hash(cfg) != config_hash(demo_cfg(40, patches=["predict-gs", *coding]))
    scene = scene_maker(n_views=9, width=48, height=36, seed=4)
    train_run(str(scene), tmp_path / "run", cfg, progress=False)
    t, _ = load_run(tmp_path / "run")
    ent, sfp = t.entropy, t.model.provider
    assert ent.ctx_grid is sfp.grid
    assert not any(n.startswith("grid.") for n, _ in ent.named_parameters())
    assert not any(k.startswith("grid.") for k in ent.state_dict())
    assert t.phase == "adaptive"           # the rate (and the context) ran
    assert float(ent.hash_bits()) == 0.0 and float(sfp.rate_bits().detach()) > 0
    # one grid pass per training step serves the SFP and the context of the visible anchors
    # (HAC++'s rate, sampled over all anchors, reads its sample's positions in a pass of its own)
    calls = []
    plain = sfp.grid.forward
    sfp.grid.forward = lambda *a, **k: calls.append(len(a[0])) or plain(*a, **k)
    t.step(t.iteration + 1)
    del sfp.grid.forward
    if coding:
        assert len(calls) == 2 and calls[1] < calls[0]
    else:
        assert len(calls) == 1
    opt_params = [p for g in t.optimizer.param_groups for p in g["params"]]
    for p in sfp.grid.parameters():
        assert sum(q is p for q in opt_params) == 1
    box = (sfp.grid.xyz_min.clone(), sfp.grid.xyz_max.clone())
    ent.set_bounds(box[0] - 5.0, box[1] + 5.0)          # HAC's box at the rate's start
    assert torch.equal(sfp.grid.xyz_min, box[0]) and torch.equal(sfp.grid.xyz_max, box[1])
    # the rate trains the context MLP, not the SFP's tables
    t.optimizer.zero_grad(set_to_none=True)
    idx = torch.arange(t.model.n_anchors)
    xyz = t.model.xyz[idx]
    _, bits = ent(xyz, t.model.coded_values(idx), t.model.gaussian_mask(idx), training=True)
    sum(b.sum() for b in bits.values()).backward()
    assert all(p.grad is None for p in sfp.grid.parameters())
    assert ent.mlp[0].weight.grad is not None and ent.mlp[0].weight.grad.abs().sum() > 0
    # coded and decoded
    f = tmp_path / "m.pgs"
    encode_model(t.cfg, t.model, ent, f)
    dec = decode_model(f)
    assert dec.entropy.ctx_grid is dec.model.provider.grid
    names = set(read_container(f)[1])
    assert "em.mlp" in names and "em.grid" not in names
    cs = coded_state(t.model, ent, t.cfg.codec.positions)    # what the encoder quantized
    assert cs.index.numel() == dec.model.n_anchors > 0
    at = {p: i for i, p in enumerate(map(tuple, cs.xyz.tolist()))}   # the file's anchor order
    order = torch.tensor([at[p] for p in map(tuple, dec.model.xyz.tolist())])
    for name, v in cs.values.items():
        assert torch.equal(dec.model.fixed_values[name], v[order]), name


def test_entropy_context_from_a_provider_needs_a_grid_and_the_hac_model():
    from baseline.config import ConfigError

    with pytest.raises(ValueError, match="has no grid to read"):
        build_model_and_entropy(["sfp-context"])
    with pytest.raises(ValueError, match="no grid context"):
        build_model_and_entropy(["predict-gs", "entropy-factorized", "sfp-context"])
    with pytest.raises(ConfigError, match="entropy.context must be"):
        build_config(["predict-gs"], ["entropy.context=shared"])


def build_model_and_entropy(patches):
    from baseline.scaffold.build import build_entropy

    cfg = build_config(patches, ["model.voxel_size=0.2"])
    return build_entropy(cfg, _pgs_model(cfg))


def test_a_header_naming_the_providers_grid_where_there_is_none_is_refused(tmp_path):
    """A file whose entropy entry says its context is the provider's grid decodes only when
    the provider has one and no grid of the entropy model's own is described; otherwise one
    BitstreamError naming the field."""
    from baseline.codec.container import BitstreamError, build_container, read_container
    from baseline.codec.header import BINDING_FIELDS, digest_sections
    from baseline.modelfile import decode_model, encode_model
    from baseline.scaffold.build import build_entropy

    def encoded(patches):
        cfg = build_config(patches, ["model.voxel_size=0.2"])
        model = _pgs_model(cfg)
        f = tmp_path / ("+".join(patches) + ".pgs")
        encode_model(cfg, model, build_entropy(cfg, model), f)
        return read_container(f)

    def decode_with(header, sections, name):
        """``header`` edited, then bound to the sections again (as a writer of such a file
        would: the checks under test are the entropy entry's, not the file's binding)."""
        rest = {k: v for k, v in header.items() if k not in BINDING_FIELDS}
        items = list(sections.items())
        f = tmp_path / name
        f.write_bytes(build_container({**rest, **digest_sections(rest, items)}, items))
        return decode_model(f)

    header, sections = encoded(["tandt"])                  # HAC: the explicit feature table
    e = dict(header["entropy"])
    e.pop("grid")
    e["context"] = "provider"
    with pytest.raises(BitstreamError, match="this file's provider has none"):
        decode_with({**header, "entropy": e}, sections, "a.pgs")
    with pytest.raises(BitstreamError, match="entropy.context"):
        decode_with({**header, "entropy": {**e, "context": "neighbours"}}, sections, "b.pgs")

    header, sections = encoded(["predict-gs", "sfp-context"])
    assert decode_with(header, sections, "c.pgs").entropy.context == "provider"
    grid = encoded(["predict-gs"])[0]["entropy"]["grid"]
    with pytest.raises(BitstreamError, match="entropy"):      # a grid described as well
        decode_with({**header, "entropy": {**header["entropy"], "grid": grid}}, sections, "d.pgs")
    e = dict(header["entropy"])
    e.pop("context")                                         # its own grid, not described
    with pytest.raises(BitstreamError, match="grid"):
        decode_with({**header, "entropy": e}, sections, "e.pgs")
