"""Mask training strategies: HAC's (the default) and HAC++'s (`masks-hacpp`)."""
from __future__ import annotations

import pytest
import torch

from baseline.data.scene import load_scene
from baseline.pipeline import visible_anchors
from baseline.train.trainer import Trainer
from baseline.config import to_toml
from conftest import demo_cfg


@pytest.fixture(scope="module")
def scene(scene_maker):
    return load_scene(scene_maker(n_views=8, width=48, height=36, seed=3))


def _trainer(scene, tmp_path, patches=(), *sets):
    torch.set_num_threads(1)
    return Trainer(demo_cfg(300, "entropy.noise_from=0", "entropy.context_from=0", *sets,
                            patches=patches), scene, tmp_path / "run", progress=False)


def test_default_is_hacs_strategy(scene, tmp_path):
    t = _trainer(scene, tmp_path)
    assert t.mask_training.name == "hac" and not t.model.mask_after_selection
    assert t.mask_training.render_rate_sample == t.cfg.entropy.rate_sample


def test_masks_after_selection_in_training_only(scene, tmp_path):
    """HAC++: a masked Gaussian with opacity > 0 is kept in training with opacity 0 and scale 0,
    and its unmasked opacity counts in the growing and pruning statistics; evaluation drops it,
    as HAC does. (Its alpha is 0, below the rasterizer's 1/255 threshold, as in the reference
    rasterizer: the reconstruction does not reach an off mask in either code.)"""
    t = _trainer(scene, tmp_path, ["masks-hacpp"])
    m = t.model
    assert m.mask_after_selection
    cam = scene.train_cameras[0]
    idx = visible_anchors(m, cam)
    with torch.no_grad():
        m.per_anchor["mask"][idx[::2]] = -10.0                     # half the anchors off
    g = m.decode(cam.center, idx)
    off = torch.sigmoid(m.per_anchor["mask"][g.anchor_index, :, 0]).max(1).values < 0.01
    assert off.any() and (g.opacities[off] == 0).all() and (g.scales[off] == 0).all()
    assert (g.opacity_all[::2] > 0).any()                          # statistics: unmasked
    with torch.no_grad():
        ge = m.decode(cam.center, idx)
    off_e = torch.sigmoid(m.per_anchor["mask"][ge.anchor_index, :, 0]).max(1).values < 0.01
    assert not off_e.any() and len(ge.opacities) < len(g.opacities)
    # HAC's default: the masked ones are not drawn in training either
    m.mask_after_selection = False
    assert len(m.decode(cam.center, idx).opacities) == len(ge.opacities)


def test_hacpp_rate_over_all_anchors_with_anchor_masks(scene, tmp_path):
    t = _trainer(scene, tmp_path, ["masks-hacpp"], "entropy.rate_sample=1.0")
    t.hooks[1].before_step(1)
    t.phase = "adaptive"
    m = t.model
    with torch.no_grad():
        m.per_anchor["mask"][:40] = -10.0                          # 40 anchors fully off
    assert t.mask_training.render_rate_sample == 0.0
    parts, terms = t.mask_training.loss(None)                      # needs no render result
    assert len(parts) == 1                                         # no mask loss
    assert terms["valid_share"] == pytest.approx(1 - 40 / m.n_anchors)
    parts[0].backward()
    g = m.per_anchor["mask"].grad[..., 0]
    # an anchor that is off still receives the anchor mask's gradient (through the mean of its
    # K masks), and every on anchor's masks are pushed down by its bits
    assert (g[40:] > 0).float().mean() > 0.9 and g[:40].abs().sum() > 0
    # the mask learning rate decays to 1e-4 x lambda / 1e-3 x extent (Tanks&Temples' rule)
    grp = next(x for x in t.optimizer.param_groups if x["name"] == "mask")
    want = 1e-4 * t.cfg.entropy.lmbda / 1e-3 * t.extent * t._mask_lr_scale()
    assert grp["lr_final"] == pytest.approx(want)


@pytest.mark.parametrize("patches", [["masks-hacpp", "entropy-hacpp"],
                                     ["predict-gs", "masks-hacpp", "entropy-hacpp"],
                                     ["predict-gs", "masks-hacpp"]])
def test_training_and_exact_coding_with_hacpps_masks(small_scene, tmp_path, patches):
    from baseline.modelfile import decode_model, encode_model
    torch.set_num_threads(1)
    t = Trainer(demo_cfg(150, patches=patches), load_scene(small_scene), tmp_path / "r",
                progress=False)
    last = t.train()
    assert t.phase == "adaptive" and "bpp" in last
    st = encode_model(t.cfg, t.model, t.entropy, tmp_path / "m.pgs")
    dec = decode_model(tmp_path / "m.pgs")
    for k, v in st["values"].items():
        assert torch.equal(v, dec.model.fixed_values[k]), k


def test_mask_state_tool_reads_logits_and_adam_steps(tmp_path):
    """tools/probes/mask_state.py: masks off below logit(0.01); Adam's mean step over the learning rate
    is ~1 under a steady gradient and far below 1 when the same push comes in rare kicks."""
    import importlib.util
    import pathlib
    spec = importlib.util.spec_from_file_location(
        "mask_state", pathlib.Path(__file__).parents[1] / "tools" / "probes" / "mask_state.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)

    logits = torch.nn.Parameter(torch.tensor([[-5.0], [-4.0], [0.5], [-6.0]]))
    opt = torch.optim.Adam([{"params": [logits], "lr": 1e-3, "name": "mask"}], eps=1e-15)
    for it in range(200):
        # rows 0-1: a steady push down (positive gradient); rows 2-3: the same mean push
        # up/down delivered as one kick every 20 steps
        kick = 20.0 if it % 20 == 0 else 0.0
        logits.grad = torch.tensor([[1.0], [1.0], [-kick], [kick]])
        opt.step()
    ck = {"iteration": 200, "model": {"per_anchor.mask": logits.detach().clone()},
          "optimizer": opt.state_dict()}
    torch.save(ck, tmp_path / "checkpoint.pt")
    after = logits.detach().flatten()
    # no config.toml beside it: the default threshold 0.01 (logit -4.595)
    s = tool.mask_state(str(tmp_path / "checkpoint.pt"))
    assert s["off_share"] == pytest.approx(float((after < -4.595).float().mean()))
    # the run's own threshold: sigmoid(-4.0) = 0.018 < 0.05 switches one more Gaussian off
    (tmp_path / "config.toml").write_text(to_toml(demo_cfg(10, "entropy.mask_threshold=0.05")))
    s5 = tool.mask_state(str(tmp_path / "checkpoint.pt"))
    assert s5["off_share"] == pytest.approx(float((after < -2.944).float().mean()))
    assert s5["off_share"] > s["off_share"]
    m = opt.state[logits]["exp_avg"].flatten()
    v = opt.state[logits]["exp_avg_sq"].flatten()
    step = float(opt.state[logits]["step"])
    ratio = (m / (1 - 0.9 ** step)).abs() / (v / (1 - 0.999 ** step)).sqrt()
    assert ratio[:2].min() > 0.99                      # steady gradient: full steps
    assert ratio[2:].max() < 0.5                       # rare kicks: small mean steps
    assert s["step_over_lr_median"] == pytest.approx(float(ratio.median()), rel=1e-5)
    assert s["down_share"] == 0.75 and s["lr"] == 1e-3
