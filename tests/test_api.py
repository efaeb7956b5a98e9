"""The Python API (baseline/api.py): train, encode, decode, render, evaluate in five calls, with
the command line's guards; TensorBoard logging of a training, outside the run's identity."""
from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from baseline import api
from baseline.config import build_config, config_hash
from baseline.data.images import read_png_u8
from baseline.guard import OutputError

ITERS = 60
SETS = [f"train.iterations={ITERS}", "train.threads=1", "train.log_every=10"]


@pytest.fixture(scope="module")
def trained(scene_maker, tmp_path_factory):
    pytest.importorskip("tensorboard", reason="tensorboard is not installed (pip install -e .[tensorboard])")
    d = tmp_path_factory.mktemp("api")
    scene = scene_maker(seed=6)
    run = api.train(scene, d / "run", patches=["demo"], sets=SETS + ["train.tensorboard=true"])
    return d, scene, run


def test_five_calls_train_encode_decode_render_evaluate(trained):
    d, _, run = trained
    res = json.loads((run / "results.json").read_text())
    assert res["iterations"] == ITERS and res["test"]["ssim_convention"] == "3dgs"
    assert (run / "test" / f"ours_{ITERS}" / "per_view.json").is_file()
    pgs = api.encode(run, d / "model.pgs")
    assert pgs.stat().st_size == json.loads((run / "results.json").read_text())["encode"]["bytes"]
    model = api.decode(pgs)
    assert model.phase == "decoded" and model.iterations == ITERS
    images = api.render(model, out=d / "views")
    cams = model.cameras("test")
    assert len(images) == len(cams) and all(i.dtype == np.uint8 for i in images)
    ev = api.evaluate(model, out=d / "eval")
    assert ev["n_views"] == len(cams) and np.isfinite(ev["psnr"]) and 0 < ev["ssim"] <= 1
    per = json.loads((d / "eval" / "per_view.json").read_text())[f"ours_{ITERS}"]
    assert set(per) >= {"PSNR", "SSIM", "SSIM_skimage"}
    assert np.mean(list(per["PSNR"].values())) == pytest.approx(ev["psnr"])
    for name in per["PSNR"]:              # what render returned is what evaluate measured
        a = read_png_u8(d / "views" / "renders" / name)
        assert np.array_equal(a, read_png_u8(d / "eval" / "renders" / name))
    # a path works as well as a decoded model, and a run folder renders its coded state
    assert api.evaluate(pgs)["psnr"] == pytest.approx(ev["psnr"])
    assert np.isfinite(api.evaluate(run)["psnr"])


def test_the_api_has_the_command_lines_guards(trained):
    d, scene, run = trained
    with pytest.raises(OutputError, match="holds a run"):
        api.train(scene, run, patches=["demo"], sets=SETS)            # neither resume nor overwrite
    with pytest.raises(ValueError, match="no run to resume"):
        api.train(scene, d / "empty", patches=["demo"], sets=SETS, resume=True)
    with pytest.raises(OutputError, match="results.json of the run"):
        api.encode(run, run / "results.json")
    with pytest.raises(OutputError, match="inside the scene folder"):
        api.encode(run, scene / "m.pgs")
    with pytest.raises(OutputError, match="holds a run"):
        api.render(run, out=run)
    with pytest.raises(OutputError, match="inside the scene folder"):
        api.evaluate(run, out=scene / "eval")
    with pytest.raises(FileNotFoundError):
        api.decode(d / "missing.pgs")


def test_tensorboard_logs_the_training_curves_outside_the_runs_identity(trained):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    _, _, run = trained
    ea = EventAccumulator(str(run / "tb"))
    ea.Reload()
    tags = set(ea.Tags()["scalars"])
    assert {"train/loss", "train/l1", "train/psnr", "model/anchors", "model/gaussians",
            "rate/bits_per_anchor", "lr/offsets", "lr/mlp_opacity"} <= tags
    log = [json.loads(x) for x in (run / "train_log.jsonl").read_text().splitlines()]
    psnr = {e.step: e.value for e in ea.Scalars("train/psnr")}
    assert sorted(psnr) == [e["it"] for e in log]
    for e in log:
        assert psnr[e["it"]] == pytest.approx(e["psnr"], rel=1e-6)
    anchors = {e.step: e.value for e in ea.Scalars("model/anchors")}
    assert anchors[ITERS] == json.loads((run / "results.json").read_text())["anchors"]
    bits = {e.step: e.value for e in ea.Scalars("rate/bits_per_anchor")}
    assert bits and all(v > 0 for v in bits.values())
    # logging is no training setting: the same run, the same folder hash
    on = build_config(["demo"], SETS + ["train.tensorboard=true"])
    off = build_config(["demo"], SETS)
    assert on.train.tensorboard and config_hash(on) == config_hash(off)
    from baseline.guard import config_difference
    assert config_difference(on, off) == []
    from baseline.cli import _config_sets
    ns = argparse.Namespace(set=[], tensorboard=True)
    assert _config_sets(ns) == ["train.tensorboard=true"]
