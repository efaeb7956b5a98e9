"""The Gaussian census (baseline/eval/census.py): counts against hand counts and the evaluation,
the corrections' split, neighbour patterns, births of grown anchors, the threshold sweep."""
import numpy as np
import pytest
import torch

from baseline.modelfile import decode_model
from baseline.data.scene import load_scene
from baseline.eval.census import _pattern_stats, census, psnr_at_gaussians
from baseline.eval.evaluate import evaluate
from baseline.train.trainer import Trainer

from conftest import demo_cfg


def test_pattern_stats_hand_count():
    # four anchors on a line: nearest neighbours 0<->1, 2<->3 (pairs at distance 1, 10 apart)
    xyz = np.array([[0, 0, 0], [1, 0, 0], [10, 0, 0], [11, 0, 0]], float)
    bits = np.array([[1, 0, 1], [1, 0, 1], [0, 0, 0], [0, 1, 0]], bool)
    s = _pattern_stats(xyz, bits, np.random.default_rng(0))
    assert s["pairs"] == 4
    assert s["equal_nn"] == 2                      # anchors 0 and 1 agree; 2 and 3 differ
    assert s["hamming_nn"] == 0 + 0 + 1 + 1
    assert 0 <= s["equal_random"] <= 4 and s["hamming_random"] <= 12


def test_psnr_at_gaussians_interpolates_inside_the_sweep_only():
    sweep = [{"threshold": 0.0, "gaussians": 1000.0, "psnr": 30.0},
             {"threshold": 0.1, "gaussians": 600.0, "psnr": 29.0},
             {"threshold": 0.2, "gaussians": 200.0, "psnr": 25.0}]
    assert psnr_at_gaussians(sweep, 800.0) == pytest.approx(29.5)
    assert psnr_at_gaussians(sweep, 400.0) == pytest.approx(27.0)
    assert psnr_at_gaussians(sweep, 1000.0) == pytest.approx(30.0)
    assert psnr_at_gaussians(sweep, 1500.0) is None and psnr_at_gaussians(sweep, 100.0) is None


@pytest.mark.parametrize("name", ["baseline", "predict-gs"])
def test_census_of_a_decoded_file_matches_the_evaluation(decoded_files, name):
    dec = decode_model(decoded_files[name] / "model.pgs")
    scene = load_scene(decoded_files["scene"])
    cams = scene.test_cameras or scene.train_cameras
    ev = evaluate(dec.model, scene, cams, phase="decoded", backend="cpu")
    c = census(dec.model, scene, cams, backend="cpu", thresholds=(0.0, 0.05, 0.3))
    assert c["gaussians"] == pytest.approx(ev["gaussians_mean"])
    assert c["sweep"][0]["gaussians"] == pytest.approx(ev["gaussians_mean"])
    assert c["sweep"][0]["psnr"] == pytest.approx(ev["psnr"])
    assert c["kept_share"] == pytest.approx(ev["opacity_kept_fraction"])
    g = [s["gaussians"] for s in c["sweep"]]
    assert g == sorted(g, reverse=True) and g[-1] < g[0]
    assert c["by_birth"] is None                    # a file does not carry births
    if name == "baseline":
        assert not c["refiner"] and c["kept_share_coarse"] == c["kept_share"]


def test_census_splits_what_the_corrections_add_and_remove(decoded_files):
    dec = decode_model(decoded_files["predict-gs"] / "model.pgs")
    scene = load_scene(decoded_files["scene"])
    cams = scene.test_cameras or scene.train_cameras
    model = dec.model
    model.unbake()
    assert model.refiner is not None and model.refiner.active
    head = model.refiner.appearance_head[2]
    K = model.n_offsets
    with torch.no_grad():                 # opacity correction of slot j: channel 4 j
        head.weight[0::4].zero_()
        head.bias[0::4] = -50.0           # every corrected opacity below 0: nothing is drawn
    c = census(model, scene, cams, backend="cpu", thresholds=(0.0,))
    assert c["gaussians"] == 0 and c["kept_share"] == 0
    assert c["kept_share_coarse"] > 0
    assert c["removed_share"] == pytest.approx(c["kept_share_coarse"]) and c["revived_share"] == 0
    with torch.no_grad():
        head.bias[0::4] = 50.0            # every mask-on candidate drawn
    c = census(model, scene, cams, backend="cpu", thresholds=(0.0,))
    assert c["kept_share"] == pytest.approx(1.0)
    assert c["revived_share"] == pytest.approx(1.0 - c["kept_share_coarse"])
    assert c["removed_share"] == 0
    assert K == 10


def test_grown_anchors_record_their_birth_and_the_census_splits_them(tmp_path, small_scene):
    cfg = demo_cfg(400)
    scene = load_scene(small_scene)
    t = Trainer(cfg, scene, tmp_path / "run", progress=False)
    n0 = t.model.n_anchors
    t.train()
    birth = t.model.per_anchor["birth"]
    assert birth.shape == (t.model.n_anchors,)
    initial = birth == 0
    assert int(initial.sum()) <= n0
    grown = birth[~initial]
    assert len(grown) > 0, "the demo schedule grows anchors in 400 iterations"
    assert bool((grown > 0).all()) and bool((grown <= 400).all())
    # every growth happens at an adjustment step of the densify hook
    interval = t.hooks[0].interval
    assert bool((torch.remainder(grown, interval) == 0).all())
    assert t.phase == "adaptive"
    from baseline.pipeline import coded_state

    cams = scene.test_cameras or scene.train_cameras
    c = census(t.model, scene, cams, coded=coded_state(t.model, t.entropy), cfg=t.cfg,
               backend="cpu", thresholds=(0.0,))
    assert set(c["by_birth"]) == {"initial", "grown"}
    on = sum(b["mask_on"] for b in c["by_birth"].values())
    kept = sum(b["kept"] for b in c["by_birth"].values())
    assert kept / on == pytest.approx(c["kept_share"])
    # a checkpoint written before births were kept loads with unknown births: no split
    ck = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    del ck["model"]["per_anchor.birth"]
    del ck["shapes"]["birth"]
    torch.save(ck, tmp_path / "old.pt")
    t2 = Trainer(cfg, scene, tmp_path / "run2", progress=False)
    t2.load_checkpoint(tmp_path / "old.pt")
    assert bool((t2.model.per_anchor["birth"] == -1).all())
    c2 = census(t2.model, scene, cams, coded=coded_state(t2.model, t2.entropy), cfg=t2.cfg,
                backend="cpu", thresholds=(0.0,))
    assert c2["by_birth"] is None and c2["gaussians"] == c["gaussians"]
