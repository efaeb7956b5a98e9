"""The `pgs` commands end to end on a tiny synthetic scene: train (into HAC's adaptive phase),
eval, encode, info, decode, eval / render of the decoded file, export-ply, and the errors a user
sees for bad input."""
import json

import numpy as np
import pytest

from baseline.cli import main


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    scene = d / "scene"
    assert main(["make-scene", str(scene), "--views", "10", "--width", "48", "--height", "36",
                 "--seed", "4"]) == 0
    run = d / "run"
    # 150 iterations: HAC's phase milestones (3k / 10k of 30k) scale to 15 / 50
    assert main(["train", str(scene), "--out", str(run), "--patch", "demo",
                 "--set", "train.iterations=150", "--set", "train.threads=1",
                 "--set", "train.log_every=1000", "--no-progress"]) == 0
    return d, scene, run


def test_train_writes_a_run_folder(trained):
    _, _, run = trained
    res = json.loads((run / "results.json").read_text())
    assert res["iterations"] == 150 and res["anchors"] > 0
    assert np.isfinite(res["test"]["psnr"]) and res["test"]["lpips"] is None
    assert (run / "config.toml").exists() and (run / "checkpoint.pt").exists()
    last = json.loads((run / "train_log.jsonl").read_text().splitlines()[-1])
    assert last["it"] == 150 and last["train_time"] > 0 and last["anchors"] == res["anchors"]


def test_eval_encode_info_decode_render_export(trained, capsys):
    d, scene, run = trained
    assert main(["eval", str(run)]) == 0
    cap = capsys.readouterr()
    res = json.loads(cap.out)                            # stdout: the JSON alone
    assert np.isfinite(res["psnr"])
    assert res["lpips"] is not None or "LPIPS unavailable" in cap.err
    pgs = d / "m.pgs"
    assert main(["encode", str(run), "-o", str(pgs)]) == 0
    assert pgs.stat().st_size > 0
    capsys.readouterr()
    assert main(["info", str(pgs)]) == 0
    info = capsys.readouterr().out
    for section in ("positions", "feat", "scaling", "offsets"):
        assert section in info
    dec = d / "dec"
    assert main(["decode", str(pgs), "-o", str(dec)]) == 0       # no --render: the PLY
    res = json.loads((dec / "results.json").read_text())
    assert res["ply"]["gaussians"] > 0 and (dec / "point_cloud.ply").exists()
    assert not (dec / "renders").exists()
    capsys.readouterr()
    assert main(["eval", str(pgs)]) == 0
    ev = json.loads(capsys.readouterr().out)
    # the field's layout: OUT/test/ours_N/{renders,gt,per_view.json}, as 3DGS's test folders
    assert ev["views"] == str(d / "m" / "test" / "ours_150") and ev["ssim_convention"] == "3dgs"
    renders = d / "renders"
    assert main(["render", str(pgs), "-o", str(renders)]) == 0
    for out in (renders, d / "m" / "test" / "ours_150"):
        names = sorted(p.name for p in (out / "renders").glob("*.png"))
        assert names and names == sorted(p.name for p in (out / "gt").glob("*.png"))
        per = json.loads((out / "per_view.json").read_text())["ours_150"]
        assert sorted(per["PSNR"]) == sorted(per["SSIM"]) == sorted(per["SSIM_skimage"]) == names
        assert sum(per["PSNR"].values()) / len(names) == pytest.approx(ev["psnr"])
        assert sum(per["SSIM"].values()) / len(names) == pytest.approx(ev["ssim"])
    assert "per_view.json" in capsys.readouterr().out
    ply = d / "g.ply"
    assert main(["export-ply", str(run), "-o", str(ply)]) == 0
    head = ply.read_bytes().split(b"end_header")[0]
    assert head.startswith(b"ply") and b"element vertex" in head
    # the run's export (its coded state) and the decoded file's are the same Gaussians, from
    # the same recorded viewpoint, byte for byte
    # (the header's comments name the source)
    body = ply.read_bytes().split(b"end_header", 1)
    body_dec = (dec / "point_cloud.ply").read_bytes().split(b"end_header", 1)
    assert body[1] == body_dec[1]
    strip = lambda h: [x for x in h.splitlines() if not x.startswith(b"comment")]  # noqa: E731
    assert strip(body[0]) == strip(body_dec[0])


def test_decoded_ply_is_byte_identical_across_thread_counts(trained, tmp_path):
    import os
    import subprocess
    import sys

    d, _, run = trained
    pgs = tmp_path / "t.pgs"
    assert main(["encode", str(run), "-o", str(pgs)]) == 0
    plys = []
    for n in ("1", "2"):
        out = tmp_path / f"dec{n}"
        env = dict(os.environ, OMP_NUM_THREADS=n, NUMBA_NUM_THREADS=n)
        r = subprocess.run([sys.executable, "-m", "baseline.cli", "decode", str(pgs), "-o",
                            str(out)], env=env, capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        plys.append((out / "point_cloud.ply").read_bytes())
    assert plys[0] == plys[1]


def test_a_failed_decode_leaves_nothing(trained, tmp_path, capsys):
    d, _, run = trained
    bad = tmp_path / "bad.pgs"
    good = d / "m.pgs"
    if not good.exists():
        assert main(["encode", str(run), "-o", str(good)]) == 0
    raw = bytearray(good.read_bytes())
    raw[-10] ^= 0xFF                                       # a payload byte: its CRC fails
    bad.write_bytes(bytes(raw))
    out = tmp_path / "never"
    assert main(["decode", str(bad), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "bad.pgs" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_bad_input_gives_a_named_error(trained, tmp_path, capsys):
    d, scene, run = trained
    assert main(["eval", str(tmp_path / "missing")]) == 2
    assert "missing" in capsys.readouterr().err
    junk = tmp_path / "junk.pgs"
    junk.write_bytes(b"not a pgs file at all")
    assert main(["info", str(junk)]) != 0
    err = capsys.readouterr().err
    assert "junk.pgs" in err or "magic" in err.lower()
    assert main(["train", str(scene), "--out", str(tmp_path / "r"), "--set", "train.nope=1"]) == 2
    assert "nope" in capsys.readouterr().err


def test_encode_with_float16_weights(trained, capsys):
    from baseline.modelfile import decode_model, file_info

    d, _, run = trained
    f32, f16 = d / "w32.pgs", d / "w16.pgs"
    assert main(["encode", str(run), "-o", str(f32)]) == 0
    before = json.loads((run / "results.json").read_text()).get("encode")
    assert main(["encode", str(run), "-o", str(f16), "--weights", "float16", "--rate-check"]) == 0
    assert "rate check" in capsys.readouterr().out
    # the run's record keeps its own configuration's encoding
    assert json.loads((run / "results.json").read_text()).get("encode") == before
    i32, i16 = file_info(f32), file_info(f16)
    assert i16["total_bytes"] < i32["total_bytes"]
    assert decode_model(f16).header["weight_dtype"] == "float16"
    assert main(["eval", str(f16)]) == 0
    # exact decoding at float16: the values the encoder coded are the decoded ones, bit for bit
    import dataclasses

    import torch

    from baseline.modelfile import encode_model
    from baseline.run import load_run
    t, _ = load_run(run, device="cpu")
    cfg = dataclasses.replace(t.cfg, codec=dataclasses.replace(t.cfg.codec, weight_dtype="float16"))
    st = encode_model(cfg, t.model, t.entropy, d / "w16b.pgs")
    dec = decode_model(d / "w16b.pgs")
    for k, v in st["values"].items():
        assert torch.equal(v, dec.model.fixed_values[k]), k
    for name, p in t.model.decoder.state_dict().items():
        assert torch.equal(p, dec.model.decoder.state_dict()[name]), name


def test_bench_codec_with_a_trained_run(trained, capsys):
    _, _, run = trained
    assert main(["bench", "codec", "--anchors", "2000", "--threads", "1", "--run", str(run)]) == 0
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if ln.startswith(("reference", "fast", "run"))]
    assert [ln.split()[:2] for ln in lines] == [["reference", "hac"], ["fast", "hac"],
                                                  ["reference", "hacpp"], ["fast", "hacpp"],
                                                  ["run", "run"]]
    assert all(ln.rstrip().endswith("True") for ln in lines)     # every decode exact
    assert str(run) in out


def test_demo_trains_three_rate_points_in_parallel_with_the_reference(tmp_path, monkeypatch):
    """The main job: HAC and Predict-GS at three lambdas plus the uncompressed Scaffold-GS
    reference, as parallel jobs (the longer Predict-GS trainings first), then the report with
    the paired FPS bench and the synthetic-scene caveat; '--reference none' leaves it out."""
    import baseline.data.synthetic as synthetic
    import baseline.experiment as compare
    import baseline.experiment.executors as executors

    calls, batches = [], []
    monkeypatch.setattr(synthetic, "make_scene", lambda path: None)
    monkeypatch.setattr(compare, "run_compare", lambda *a, **kw: calls.append(kw))
    monkeypatch.setattr(executors.LocalExecutor, "execute",
                        lambda self, jobs: batches.append((self.jobs, jobs)) or {"done": [], "failed": []})
    assert main(["demo", "--out", str(tmp_path / "d")]) == 0
    assert main(["demo", "--out", str(tmp_path / "d"), "--reference", "none"]) == 0
    assert [c["reference"] for c in calls] == ["scaffold", None]
    assert calls[0]["vs"] == ["predict-gs"] and calls[0]["common_patches"] == ["demo"]
    assert calls[0]["lambdas"] == [0.004, 0.002, 0.001] and calls[0]["paired_fps"]
    assert "synthetic scene" in calls[0]["scope"]
    _, jobs = batches[0]
    assert [(j.method, j.lmbda, j.reference) for j in jobs] == [
        ("predict-gs", 0.004, False), ("predict-gs", 0.002, False), ("predict-gs", 0.001, False),
        ("baseline", 0.004, False), ("baseline", 0.002, False), ("baseline", 0.001, False),
        ("scaffold", None, True)]
    assert len(batches[1][1]) == 6


@pytest.mark.slow
def test_demo_end_to_end_ends_with_a_verdict(tmp_path, monkeypatch, scene_maker, capsys):
    """A short demo for real (tiny scene, 200 iterations, parallel workers): six runs, the
    verdict at the top of report.md and printed last."""
    import shutil

    import baseline.data.synthetic as synthetic

    small = scene_maker()
    monkeypatch.setattr(synthetic, "make_scene",
                        lambda path: shutil.copytree(small, path, dirs_exist_ok=True))
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--reference", "none",
                 "--set", "train.iterations=200", "--set", "train.threads=1"]) == 0
    printed = capsys.readouterr().out
    md = (out / "report.md").read_text()
    assert "### Verdict" in md and md.index("### Verdict") < md.index("Quality and size")
    verdict = md.split("### Verdict", 1)[1].split("###", 1)[0]
    assert "Predict-GS" in verdict and "HAC" in verdict
    assert ("at equal quality (BD-rate" in verdict) or ("no BD-rate" in verdict)
    assert "renders at" in verdict and "x HAC's FPS" in verdict
    assert "synthetic scene" in verdict
    assert "Verdict" in printed and "demo wall time" in printed
    res = json.loads((out / "results.json").read_text())
    assert len(res["runs"]) == 6 and set(res["fps_pair"]) == {"predict-gs"}


def test_small_things_a_new_user_meets(tmp_path, capsys):
    """--version; pgs info on a file that is not a .pgs names it; a wrong scene path leaves no
    output folder; make-scene refuses sizes below 1 with a message, not a traceback."""
    import subprocess
    from pathlib import Path

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith("pgs ")
    txt = tmp_path / "notes.txt"
    txt.write_text("hello")
    assert main(["info", str(txt)]) == 2
    err = capsys.readouterr().err
    assert f"{txt}: wrong magic" in err and "<bytes>" not in err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["train", str(empty), "--out", str(tmp_path / "r"), "--patch", "demo"]) == 2
    assert main(["compare", str(empty), "--out", str(tmp_path / "c"), "--patch", "demo"]) == 2
    assert not (tmp_path / "r").exists() and not (tmp_path / "c").exists()
    for bad in (["--width", "-5"], ["--views", "0"]):
        with pytest.raises(SystemExit) as e:
            main(["make-scene", str(tmp_path / "s"), *bad])
        assert e.value.code == 2 and "must be at least 1" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["compare", str(empty), "--out", str(tmp_path / "c"), "--jobs", "0"])
    assert e.value.code == 2 and "--jobs: 0 must be at least 1" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()
    run_sh = Path(__file__).parent.parent / "run.sh"
    p = subprocess.run(["bash", str(run_sh)], capture_output=True, text=True)
    assert p.returncode == 2 and "usage: ./run.sh demo" in p.stderr


def test_nothing_a_user_runs_replaces_their_work(trained, tmp_path, capsys):
    """Outputs never land on a run's records or inside a scene; training into a run needs
    --resume (checked: same scene, same training config) or --overwrite; --resume needs a run."""
    import shutil

    d, scene, run = trained
    ck = (run / "checkpoint.pt").read_bytes()
    res = (run / "results.json").read_bytes()
    assert main(["encode", str(run), "-o", str(run / "checkpoint.pt")]) == 2
    assert "is the checkpoint.pt of the run" in capsys.readouterr().err
    assert main(["export-ply", str(run), "-o", str(run / "checkpoint.pt")]) == 2
    assert main(["encode", str(run), "-o", str(scene / "model.pgs")]) == 2
    assert "inside the scene folder" in capsys.readouterr().err
    f = tmp_path / "m.pgs"
    assert main(["encode", str(run), "-o", str(f)]) == 0        # (records its encode in results)
    res = (run / "results.json").read_bytes()
    assert main(["decode", str(f), "-o", str(run)]) == 2
    assert "holds a run" in capsys.readouterr().err
    assert main(["decode", str(f), "-o", str(scene / "images" / "x")]) == 2
    assert main(["train", str(scene), "--out", str(run), "--patch", "demo",
                 "--set", "train.iterations=150", "--set", "train.threads=1"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["train", str(scene), "--out", str(scene / "out"), "--patch", "demo"]) == 2
    assert (run / "checkpoint.pt").read_bytes() == ck and (run / "results.json").read_bytes() == res
    # --resume: needs a run, the same scene and the same training configuration
    assert main(["train", str(scene), "--out", str(tmp_path / "none"), "--resume",
                 "--patch", "demo"]) == 2
    assert "holds no run to resume" in capsys.readouterr().err
    other = tmp_path / "other"
    assert main(["make-scene", str(other), "--views", "10", "--width", "48", "--height", "36",
                 "--seed", "9"]) == 0
    copy = tmp_path / "copy"
    shutil.copytree(run, copy)
    base = ["--patch", "demo", "--set", "train.iterations=150", "--set", "train.threads=1",
            "--set", "train.log_every=1000", "--no-progress", "--resume"]
    assert main(["train", str(other), "--out", str(copy), *base]) == 2
    err = capsys.readouterr().err
    assert "cannot resume on this scene" in err and str(other.resolve()) in err
    assert main(["train", str(scene), "--out", str(copy), *base,
                 "--set", "model.voxel_size=0.1"]) == 2
    err = capsys.readouterr().err
    assert "cannot resume with another training configuration" in err
    assert "model.voxel_size: 0.03 -> 0.1" in err
    assert main(["train", str(scene), "--out", str(copy), *base]) == 0      # the same: resumes
    # --overwrite starts over
    assert main(["train", str(scene), "--out", str(copy), "--patch", "demo", "--overwrite",
                 "--set", "train.iterations=60", "--set", "train.threads=1", "--no-progress"]) == 0
    assert json.loads((copy / "results.json").read_text())["iterations"] == 60


def test_a_run_folder_is_owned_by_one_process(tmp_path):
    """A second process cannot take a run folder while the first holds it; the lock is
    re-entrant in its process and goes with the process, however it ends."""
    import subprocess
    import sys

    from baseline.guard import OutputError, RunLock

    run = tmp_path / "run"
    code = ("import sys, time; from baseline.guard import RunLock; "
            f"RunLock({str(run)!r}).acquire(); print('held', flush=True); time.sleep(60)")
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "held"
        with pytest.raises(OutputError, match=f"in use by another pgs process \\(pid {p.pid}\\)"):
            RunLock(run).acquire()
    finally:
        p.kill()                                   # a crash: nothing is cleaned up
        p.wait()
    with RunLock(run):                             # free again
        with RunLock(run):                         # re-entrant
            pass
        out = subprocess.run([sys.executable, "-c", code.replace("time.sleep(60)", "pass")],
                             capture_output=True, text=True)
        assert out.returncode != 0 and "in use by another pgs process" in out.stderr
    for _ in range(3):
        with RunLock(run):
            pass
    # an executor's worker waits for the holder instead (a retried job whose first attempt
    # still runs): it gets the run once the holder ends
    done = tmp_path / "holder-done"
    p = subprocess.Popen([sys.executable, "-c", code.replace(
        "time.sleep(60)", f"time.sleep(2); open({str(done)!r}, 'w').close()")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "held"
        assert not done.exists()
        with RunLock(run, wait=True):
            assert done.exists()                      # only after the holder's last step
    finally:
        p.kill()
        p.wait()


def test_warmup_fills_the_grid_kernel_cache(tmp_path, capsys):
    """``warm_kernels`` compiles every grid kernel a training and a decode call (index files in
    a fresh numba cache); ``pgs warmup`` runs both parts and reports success."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    subprocess.run([sys.executable, "-c", "from baseline.hac.hashgrid import warm_kernels; "
                    "warm_kernels()"], env=env, check=True)
    names = {p.name.split(".")[1].rsplit("-", 1)[0] for p in tmp_path.rglob("*.nbi")}
    assert {"grid_fwd", "grid_bwd", "_bwd_range", "grid_fwd_exact"} <= names, names
    assert main(["warmup"]) == 0                   # the project's own cache: loads, no compile
    assert "warmup: CPU kernels compiled or loaded" in capsys.readouterr().out


def _digests(*paths):
    import hashlib
    from pathlib import Path

    return {str(f): hashlib.sha256(f.read_bytes()).hexdigest()
            for p in paths for f in ([Path(p)] if Path(p).is_file() else
                                     sorted(x for x in Path(p).rglob("*") if x.is_file()))}


def test_existing_files_are_replaced_only_when_asked(trained, tmp_path, capsys):
    """The one output rule: a path that exists is refused (exit 2, one line naming it and the
    flag, every byte as it was) unless it is the command's own earlier output for the same
    input or --overwrite is given; a folder of the user's files is never written into."""
    _, scene, run = trained
    user = tmp_path / "user"
    user.mkdir()
    (user / "results.json").write_text('{"mine": 1}')
    dec = tmp_path / "dec"
    dec.mkdir()
    (dec / "point_cloud.ply").write_text("my cloud")
    (dec / "results.json").write_text("{}")
    ply, notes = tmp_path / "mine.ply", tmp_path / "notes.txt"
    ply.write_text("my ply")
    notes.write_text("my notes")
    before = _digests(user, dec, ply, notes)
    f = tmp_path / "m.pgs"
    assert main(["encode", str(run), "-o", str(f)]) == 0
    for cmd, path in ((["train", str(scene), "--out", str(user), "--patch", "demo"], user),
                      (["decode", str(f), "-o", str(dec)], dec),
                      (["decode", str(f), "-o", str(dec), "--overwrite"], dec),
                      (["export-ply", str(run), "-o", str(ply)], ply),
                      (["encode", str(run), "-o", str(notes)], notes)):
        capsys.readouterr()
        assert main(cmd) == 2, cmd
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and str(path) in err and "--overwrite" in err, err
    assert _digests(user, dec, ply, notes) == before
    # the command's own earlier output for the same input is rebuilt in place
    assert main(["encode", str(run), "-o", str(f)]) == 0
    out = tmp_path / "out"
    assert main(["decode", str(f), "-o", str(out)]) == 0
    assert main(["decode", str(f), "-o", str(out)]) == 0
    assert json.loads((out / ".pgs-output").read_text()) == {"command": "decode",
                                                            "input": str(f.resolve())}
    g = tmp_path / "g.pgs"
    assert main(["encode", str(run), "-o", str(g), "--weights", "float16"]) == 0
    capsys.readouterr()
    assert main(["decode", str(g), "-o", str(out)]) == 2      # another file's output folder
    assert "holds pgs decode's output for" in capsys.readouterr().err
    assert main(["export-ply", str(run), "-o", str(tmp_path / "e.ply")]) == 0
    assert main(["export-ply", str(run), "-o", str(tmp_path / "e.ply")]) == 0
    # asked: --overwrite replaces a file
    assert main(["export-ply", str(run), "-o", str(ply), "--overwrite"]) == 0
    assert ply.read_bytes().startswith(b"ply\n")


def test_make_scene_ranges_and_replacing_a_scene(tmp_path, capsys):
    """make-scene refuses NaN / infinite detail and views, sizes beyond their ranges; onto a
    scene of other arguments it is refused (every file kept), with --overwrite the scene is
    replaced whole (no stale images); its own scene for the same arguments is rebuilt."""
    s = tmp_path / "s"
    small = ["--width", "24", "--height", "18"]
    for bad, msg in ((["--detail", "nan"], "--detail (texture_detail) must be finite"),
                     (["--detail", "inf"], "must be finite"),
                     (["--detail", "-1"], "out of range"),
                     (["--views", "1000000"], "--views (n_views) = 1000000 is out of range"),
                     (["--width", "100000"], "out of range"),
                     (["--views", "2000", "--width", "4096", "--height", "4096"], "pixels")):
        assert main(["make-scene", str(s), *bad]) == 2, bad
        assert msg in capsys.readouterr().err, bad
    assert not s.exists() and not list(tmp_path.iterdir())
    assert main(["make-scene", str(s), "--views", "6", *small]) == 0
    before = _digests(s)
    assert len(list((s / "images").iterdir())) == 6
    assert main(["make-scene", str(s), "--views", "2", *small]) == 2
    err = capsys.readouterr().err
    assert "other arguments (n_views: 6 -> 2)" in err and "--overwrite" in err
    assert _digests(s) == before
    assert main(["make-scene", str(s), "--views", "6", *small]) == 0     # the same: rebuilt
    assert _digests(s) == before
    assert main(["make-scene", str(s), "--views", "2", *small, "--overwrite"]) == 0
    assert sorted(p.name for p in (s / "images").iterdir()) == ["view_000.png", "view_001.png"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]          # no temporary left
    user = tmp_path / "u"
    user.mkdir()
    (user / "a.txt").write_text("x")
    assert main(["make-scene", str(user), "--overwrite"]) == 2
    assert "holds files pgs did not write (a.txt)" in capsys.readouterr().err


def test_an_interrupted_make_scene_leaves_no_half_scene(tmp_path):
    """SIGTERM during a long generation: exit 130, no scene folder and no temporary left; a
    scene being replaced (--overwrite) stays as it was."""
    import os
    import signal
    import subprocess
    import sys
    import time

    def interrupted(out, *extra):
        p = subprocess.Popen([sys.executable, "-m", "baseline.cli", "make-scene", str(out),
                              "--views", "400", "--width", "64", "--height", "48", *extra],
                             stderr=subprocess.PIPE, text=True, env=dict(os.environ))
        t0 = time.time()
        while not list(tmp_path.glob(f".{out.name}.partial-*/images/view_002.png")):
            assert p.poll() is None and time.time() - t0 < 300
            time.sleep(0.1)
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=120)
        return p.returncode, err

    rc, err = interrupted(tmp_path / "s")
    assert rc == 130 and "interrupted" in err
    assert sorted(tmp_path.iterdir()) == []
    old = tmp_path / "old"
    assert main(["make-scene", str(old), "--views", "3", "--width", "24", "--height", "18"]) == 0
    before = _digests(old)
    rc, _ = interrupted(old, "--overwrite")
    assert rc == 130 and _digests(old) == before
    assert [p.name for p in tmp_path.iterdir()] == ["old"]


def test_demo_contenders_come_from_the_method_specs(tmp_path, monkeypatch, capsys):
    """pgs demo's default contenders are the registered methods whose spec is marked for the
    demo; with none marked, one line and exit 2, nothing written."""
    from baseline import registry
    from baseline.cli.experiments import demo_contenders

    assert demo_contenders() == ["predict-gs"]
    assert registry.methods()["predict-gs"].demo
    monkeypatch.setattr(registry, "methods", lambda: {})
    out = tmp_path / "d"
    assert main(["demo", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--vs" in err[0] and not out.exists()


def test_the_demo_report_names_the_iterations_it_trained():
    from baseline.cli.experiments import demo_scope

    assert "(1k iterations, one seed)" in demo_scope(1000)
    assert "(30 iterations, one seed)" in demo_scope(30)
    assert "(1,500 iterations, one seed)" in demo_scope(1500)
