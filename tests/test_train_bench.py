"""`pgs bench train`: per-stage times of training steps, for run folders or a synthetic state."""
from __future__ import annotations


from baseline.cli import main
from baseline.timing import StageTimer, stage, timing
from baseline.bench.train import STAGE_ORDER, format_train_bench, run_train_bench


def test_stages_are_free_without_a_timer_and_nest_with_one():
    with stage("x"):                        # no timer: nothing recorded, nothing raised
        pass
    t = StageTimer()
    with timing(t):
        with stage("outer"):
            with stage("inner"):
                pass
    assert set(t.times) == {"outer", "inner"} and t.times["outer"] >= t.times["inner"] >= 0


def test_bench_train_on_a_run_folder(small_scene, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", str(small_scene), "--out", str(run), "--patch", "demo", "--patch",
                 "predict-gs", "--set", "train.iterations=60", "--set", "train.threads=1",
                 "--set", "train.log_every=1000", "--no-progress"]) == 0
    before = (run / "checkpoint.pt").read_bytes()
    res = run_train_bench([str(run)], steps=3, threads=1, warmup=1)
    r = res["runs"][0]
    assert len(r["wall"]) == 3 and r["anchors"] > 0
    st = r["stages"]
    for k in ("prefilter", "context + rate", "decode", "provider", "decoder MLPs", "refiner",
              "rasterize", "losses", "backward", "rasterize bwd", "optimizer"):
        assert k in st and len(st[k]) == 3 and all(v >= 0 for v in st[k]), k
    # the backward's parts add up to the backward
    parts = ["losses bwd", "rasterize bwd", "activations bwd", "decoder MLPs + refiner bwd",
             "rest bwd"]
    for i in range(3):
        assert abs(sum(st[p][i] for p in parts if p in st) - st["backward"][i]) < 1e-6
    assert (run / "checkpoint.pt").read_bytes() == before          # nothing written
    text = format_train_bench(res)
    assert "wall time" in text and "\nstep " in text and "context + rate" in text
    assert all(k in STAGE_ORDER for k in st)
    capsys.readouterr()
    assert main(["bench", "train", "--run", str(run), "--run", str(run), "--steps", "2",
                 "--threads", "1"]) == 0
    out = capsys.readouterr().out
    assert out.count("1.") > 0 and "/ run" in out               # the second run's ratio column


def test_bench_train_synthetic_states_of_two_methods_on_the_cpu_clock(capsys):
    """Without runs: HAC's synthetic state and Predict-GS's (every stage on from the first
    step: the provider and the refiner are timed) in one process, on the CPU-time clock."""
    res = run_train_bench([], steps=2, threads=1, warmup=1, anchors=3000,
                          methods=["predict-gs"], clock="cpu")
    hac, pgs = res["runs"]
    assert (hac["label"], pgs["label"]) == ("HAC", "Predict-GS") and res["clock"] == "cpu"
    assert "provider" not in hac["stages"] or max(hac["stages"]["provider"]) < 1e-3
    assert min(pgs["stages"]["refiner"]) > 0 and min(pgs["stages"]["provider"]) > 0
    text = format_train_bench(res)
    assert "process CPU time" in text and "Predict-GS / HAC" in text
    assert main(["bench", "train", "--anchors", "2000", "--steps", "1", "--threads", "1",
                 "--clock", "cpu"]) == 0
    assert "HAC: " in capsys.readouterr().out
