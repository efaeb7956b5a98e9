"""Training never loses a good checkpoint: non-finite states are refused (on save and on
resume), killed writers' temp files are cleaned up, SIGTERM stops after writing a checkpoint,
and a run interrupted that way and resumed with `pgs train --resume` ends bit for bit where the
uninterrupted run ends (across growing, HAC's phase switches and Predict-GS's stage switch)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from baseline.data.scene import load_scene
from baseline.train.trainer import NonFiniteError, Trainer
from conftest import demo_cfg

PY = sys.executable


def _trainer(scene_dir, out, iters=40, *sets):
    cfg = demo_cfg(iters, *sets)
    return Trainer(cfg, load_scene(scene_dir), out, progress=False)


def test_a_nan_optimizer_state_is_refused_on_resume_and_the_file_kept(small_scene, tmp_path,
                                                                       capsys):
    from baseline.cli import main

    run = tmp_path / "run"
    args = ["train", str(small_scene), "--out", str(run), "--patch", "demo", "--set",
            "train.iterations=30", "--set", "train.threads=1", "--set", "train.log_every=1000",
            "--no-progress"]
    assert main(args) == 0
    ck = run / "checkpoint.pt"
    s = torch.load(ck, weights_only=False)
    st = next(iter(s["optimizer"]["state"].values()))
    st["exp_avg"].view(-1)[0] = float("nan")
    torch.save(s, ck)
    before = ck.read_bytes()
    capsys.readouterr()
    assert main(args + ["--resume"]) == 2
    err = capsys.readouterr().err
    assert "optimizer state" in err and "NaN" in err and "Traceback" not in err
    assert ck.read_bytes() == before


def test_a_non_finite_model_is_never_checkpointed(small_scene, tmp_path):
    t = _trainer(small_scene, tmp_path / "r")
    t.train(until=10)
    ck = tmp_path / "r" / "checkpoint.pt"
    before = ck.read_bytes()
    with torch.no_grad():
        t.model.decoder.mlp_color[0].weight[0, 0] = float("inf")
    with pytest.raises(NonFiniteError, match="mlp_color"):
        t.save_checkpoint()
    with pytest.raises(NonFiniteError):              # training: the loss goes non-finite
        t.train(until=20)
    assert ck.read_bytes() == before
    assert not list((tmp_path / "r").glob(".*tmp*"))


def test_stale_temp_files_are_removed(small_scene, tmp_path):
    run = tmp_path / "r"
    run.mkdir()
    stale = run / ".checkpoint.0badcafe.tmp.pt"
    stale.write_bytes(b"half a checkpoint")
    keep = run / ".notes.txt"
    keep.write_text("a user's file")
    _trainer(small_scene, run, iters=5).train()
    assert not stale.exists() and keep.exists()


def _cli(*args, env=None):
    return [PY, "-m", "baseline.cli", *args]


def test_sigterm_then_resume_equals_the_uninterrupted_run(small_scene, tmp_path):
    """Predict-GS, 300 iterations of the demo schedule: growing until 150, HAC's noise phase
    from 30 and context from 100, the residual stage from 50. The run is stopped by SIGTERM
    wherever it is, resumed with `pgs train --resume`, and must end bit for bit where an
    uninterrupted run ends: final model and encoded file."""
    common = ["--patch", "demo", "--patch", "predict-gs", "--set", "train.iterations=300",
              "--set", "train.threads=1", "--set", "train.log_every=5", "--no-progress"]
    env = dict(os.environ, OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    a, b = tmp_path / "a", tmp_path / "b"
    p = subprocess.Popen(_cli("train", str(small_scene), "--out", str(a), *common), env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    log = a / "train_log.jsonl"
    deadline = time.time() + 600
    while time.time() < deadline:            # stop it once it is past the stage switch
        if log.exists():
            lines = log.read_text().splitlines()
            if lines and json.loads(lines[-1])["it"] >= 60:
                break
        if p.poll() is not None:
            break
        time.sleep(0.05)
    p.send_signal(signal.SIGTERM)
    out, err = p.communicate(timeout=600)
    assert p.returncode == 130, (out, err)
    assert "Traceback" not in err and "stopped at iteration" in err, err
    stopped = torch.load(a / "checkpoint.pt", weights_only=False)["iteration"]
    assert 60 <= stopped < 300
    r = subprocess.run(_cli("train", str(small_scene), "--out", str(a), "--resume", *common),
                       env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    r = subprocess.run(_cli("train", str(small_scene), "--out", str(b), *common), env=env,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    sa = torch.load(a / "checkpoint.pt", weights_only=False)
    sb = torch.load(b / "checkpoint.pt", weights_only=False)
    assert sa["iteration"] == sb["iteration"] == 300
    assert sa["model"].keys() == sb["model"].keys()
    for k in sa["model"]:
        assert torch.equal(sa["model"][k], sb["model"][k]), k
    timings = ("train_time", "stall_time")     # the machine's, not the training's
    la = [{k: v for k, v in json.loads(x).items() if k not in timings}
          for x in (a / "train_log.jsonl").read_text().splitlines()]
    lb = [{k: v for k, v in json.loads(x).items() if k not in timings}
          for x in (b / "train_log.jsonl").read_text().splitlines()]
    assert la == lb and all("stall_time" in json.loads(x) for x in
                            (a / "train_log.jsonl").read_text().splitlines())
    for run in (a, b):
        r = subprocess.run(_cli("encode", str(run), "-o", str(tmp_path / f"{run.name}.pgs")), env=env,
                           capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
    assert (tmp_path / "a.pgs").read_bytes() == (tmp_path / "b.pgs").read_bytes()


@pytest.mark.parametrize("patches", [[], ["predict-gs"]], ids=["hac", "predict-gs"])
def test_a_view_that_sees_no_anchor_trains_on_the_background(small_scene, tmp_path, monkeypatch,
                                                             patches):
    """A training view whose prefilter keeps no anchor (a camera looking away from the scene)
    renders the background and takes a finite step, in every phase."""
    import baseline.pipeline as pipeline

    cfg = demo_cfg(40, patches=patches)
    t = Trainer(cfg, load_scene(small_scene), tmp_path / "run", progress=False)
    monkeypatch.setattr(pipeline, "visible_anchors",
                        lambda model, cam: torch.zeros(0, dtype=torch.long))
    for phase in ("none", "noise", "adaptive"):
        t.phase = phase
        terms = t.step(1)
        assert terms["gaussians"] == 0 and torch.isfinite(torch.tensor(terms["loss"])), phase


def test_training_whose_every_anchor_is_pruned_stops_with_a_clear_error(small_scene, tmp_path):
    """No Gaussian above zero opacity anywhere is an absorbing state (no gradient reaches
    anything again): the first pruning that would empty the model raises TrainingCollapsed,
    naming the iteration, and writes no checkpoint over the last one."""
    from baseline.train.trainer import TrainingCollapsed

    t = _trainer(small_scene, tmp_path / "run", 300)
    with torch.no_grad():
        last = t.model.decoder.mlp_opacity[-1]
        last.weight.zero_()
        last.bias.fill_(-100.0)                      # tanh(-100) < 0: every Gaussian dropped
    with pytest.raises(TrainingCollapsed, match=r"collapsed at iteration \d+: every anchor"):
        t.train()
    assert not (tmp_path / "run" / "checkpoint.pt").exists()
