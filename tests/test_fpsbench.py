"""pgs bench fps: decoded models timed on the same views, rounds in rotated order, ratios to the
first. Correctness only (the arithmetic, the order, the contenders, errors); never wall-clock."""
import math
import statistics

import pytest
import torch

from baseline.modelfile import decode_model
from baseline.data.scene import load_scene
from baseline.bench import fps as fpsbench
from baseline.eval.evaluate import evaluate
from baseline.bench.fps import Contender, bench_files, format_fps_bench, run_fps_bench


@pytest.fixture(scope="module")
def files(decoded_files):
    """A baseline and a Predict-GS file of one small scene (tests/conftest.py)."""
    return decoded_files


def test_evaluate_breaks_down_gaussians_per_view(files):
    """evaluate()'s visible anchors x K x mask-on share x opacity-kept share = Gaussians per view,
    each factor counted independently here; switching masks off moves the mask share only."""
    from baseline.pipeline import visible_anchors

    sc = load_scene(files["scene"])
    m = decode_model(files["predict-gs"] / "model.pgs").model
    K = m.n_offsets
    for step in ("as decoded", "half the masks off"):
        if step != "as decoded":
            with torch.no_grad():
                m.per_anchor["mask"][:, : K // 2] = -20.0
        ev = evaluate(m, sc, sc.test_cameras, phase="decoded", backend="cpu")
        vis = [visible_anchors(m, cam) for cam in sc.test_cameras]
        on = sum(int((m.gaussian_mask(i) > 0).sum()) for i in vis)
        n_vis = sum(len(i) for i in vis)
        assert ev["visible_anchors_mean"] == pytest.approx(n_vis / len(vis))
        assert ev["mask_on_fraction"] == pytest.approx(on / (n_vis * K))
        assert ev["opacity_kept_fraction"] == pytest.approx(ev["gaussians_mean"] * len(vis) / on)
        assert (ev["visible_anchors_mean"] * K * ev["mask_on_fraction"]
                * ev["opacity_kept_fraction"]) == pytest.approx(ev["gaussians_mean"])
        assert 0 < ev["opacity_kept_fraction"] <= 1
    assert ev["mask_on_fraction"] <= 0.5 + 1e-9


def test_bench_rows_contenders_and_counts(files):
    res = bench_files([str(files["baseline"]), str(files["predict-gs"] / "model.pgs")], rounds=2,
                      threads=1)
    labels = [r["label"] for r in res["rows"]]
    # each model plain and baked; Predict-GS also without its f_c cache
    assert labels == ["baseline", "baseline (baked)", "model", "model (baked)",
                      "model (no cache)"]
    assert [r["form"] for r in res["rows"]] == ["plain", "baked", "plain", "baked", "no cache"]
    ref = res["rows"][0]
    assert ref["ratio"] == ref["ratio_min"] == ref["ratio_max"] == 1.0
    # like-with-like ratios: baked against the baseline's baked form, the rest against plain
    assert [r["ref_form"] for r in res["rows"]] == ["baseline", "baseline (baked)", "baseline",
                                                    "baseline (baked)", "baseline"]
    rows = res["rows"]
    for r in (rows[1], rows[3]):
        same = [a / b for a, b in zip(rows[1]["seconds"], r["seconds"])]
        assert r["ratio_form"] == pytest.approx(statistics.median(same))
    assert rows[1]["ratio_form"] == 1.0 and rows[4]["ratio_form"] == rows[4]["ratio"]
    for r in res["rows"]:
        assert len(r["seconds"]) == 2 and all(s > 0 for s in r["seconds"])
        assert math.isfinite(r["fps"]) and r["fps_min"] <= r["fps"] <= r["fps_max"]
        assert r["ratio_min"] <= r["ratio"] <= r["ratio_max"]
    # Gaussians per view: what evaluate() renders on the same views
    sc = load_scene(files["scene"])
    for label, path in (("baseline", files["baseline"] / "model.pgs"),
                        ("model", files["predict-gs"] / "model.pgs")):
        dec = decode_model(path)
        ev = evaluate(dec.model, sc, sc.test_cameras, phase="decoded", backend="cpu")
        row = next(r for r in res["rows"] if r["label"] == label)
        assert row["gaussians_per_view"] == pytest.approx(ev["gaussians_mean"])
    assert res["views"] == len(sc.test_cameras) and res["split"] == "test"
    body = format_fps_bench(res).splitlines()[3:-1]              # one line per row, in order
    assert [ln.startswith(r["label"] + " ") for ln, r in zip(body, res["rows"])] == [True] * 5
    assert body[0].split()[-3:] == ["ref", "ref", "-"]              # the reference row
    assert body[1].split()[-2] == "ref"                 # the first model's baked form
    for ln, r in zip(body[1:], res["rows"][1:]):
        assert f"{r['ratio']:.3f} {r['ratio_min']:.3f}-{r['ratio_max']:.3f}" in " ".join(ln.split())
    for ln, r in zip(body[2:], res["rows"][2:]):
        assert ln.split()[-3:-1] == [f"{r['ratio_form']:.3f}",
                                     f"{r['ratio_form_min']:.3f}-{r['ratio_form_max']:.3f}"]
    # each form's images against its model's plain form: none for plain, small for the others
    # (baked: the first layers' sums in another order), exactly equal without the f_c cache
    diffs = [r["max_image_diff"] for r in rows]
    assert diffs[0] is None and diffs[2] is None
    assert 0 <= diffs[1] < 1e-4 and 0 <= diffs[3] < 1e-4 and diffs[4] == 0.0
    assert [ln.split()[-1] for ln in body] == ["-", f"{diffs[1]:.2g}", "-", f"{diffs[3]:.2g}", "0"]
    # decoded models are left as decoded: the f_c cache built again after the no-cache rounds
    dec = decode_model(files["predict-gs"] / "model.pgs")
    contenders = fpsbench.contenders_of("m", dec.model)
    run_fps_bench(contenders, sc.test_cameras[:1], sc.background.float(), rounds=1)
    assert dec.model.provider._cache is not None and dec.model.baked is None


def test_same_file_twice_gets_distinct_labels(files):
    res = bench_files([str(files["baseline"])] * 2, rounds=1, threads=1, max_views=1)
    assert [r["label"] for r in res["rows"]] == ["baseline", "baseline (baked)", "baseline'",
                                             "baseline' (baked)"]
    assert res["views"] == 1


class _Fake:
    def __init__(self):
        self.xyz = torch.zeros(1, 3)


def test_form_image_differences_over_chunks_and_nan(monkeypatch):
    """The largest |form - plain| per form over every view, across chunks of views (10 views in
    chunks of 4), each form rendered with its own set-up; NaN propagates; a model with no plain
    form and the plain forms themselves get None."""
    from types import SimpleNamespace

    m, lone = _Fake(), _Fake()
    baked_tag, other_tag = object(), object()
    plain = Contender("m", m, None, "plain", model_index=0)
    baked = Contender("m (baked)", m, None, "baked", baked_tag, 0)
    other = Contender("m (other)", m, None, "baked", other_tag, 0)
    orphan = Contender("x (baked)", lone, None, "baked", baked_tag, 1)
    views = list(range(10))

    def fake_render(model, cam, background, phase, backend):
        img = torch.zeros(3, 2, 2)
        if model.baked is baked_tag:
            img[0, 0, 0] = 1e-3 * (cam + 1)              # largest on the last view: 0.01
        elif model.baked is other_tag and cam == 9:
            img[1, 1, 1] = float("nan")
        return SimpleNamespace(render=SimpleNamespace(image=img))

    monkeypatch.setattr(fpsbench, "render_view", fake_render)
    got = fpsbench.form_image_differences([plain, baked, other, orphan], views, torch.zeros(3),
                                          chunk=4)
    assert got[0] is None and got[3] is None
    assert got[1] == pytest.approx(1e-2) and math.isnan(got[2])
    assert m.baked is None and lone.baked is None                  # left as decoded


def test_rotation_and_ratio_arithmetic(monkeypatch):
    """Round r times contender (j + r) % n at position j; FPS = 1 / median time; ratio per round."""
    a, b, c = (Contender(x, _Fake(), None) for x in "abc")
    per = {"a": [0.1, 0.2, 0.4], "b": [0.2, 0.2, 0.2], "c": [0.05, 0.5, 0.1]}
    calls = []

    def fake_time(cont, cameras, background, backend):
        r = sum(1 for x in calls if x == cont.label)
        calls.append(cont.label)
        return per[cont.label][r], 7.0

    monkeypatch.setattr(fpsbench, "_time_views", fake_time)
    rows = run_fps_bench([a, b, c], [object()], torch.zeros(3), rounds=3, warmup=False)
    assert calls == ["a", "b", "c", "b", "c", "a", "c", "a", "b"]
    ra, rb, rc = rows
    assert ra["fps"] == pytest.approx(1 / 0.2) and rb["fps"] == pytest.approx(5.0)
    assert rc["fps"] == pytest.approx(1 / 0.1)
    assert (rc["fps_min"], rc["fps_max"]) == (pytest.approx(2.0), pytest.approx(20.0))
    # per-round ratios a/b: 0.5, 1, 2 -> median 1; a/c: 2, 0.4, 4 -> median 2
    assert (rb["ratio"], rb["ratio_min"], rb["ratio_max"]) == (pytest.approx(1.0),
                                                                pytest.approx(0.5),
                                                                pytest.approx(2.0))
    assert rc["ratio"] == pytest.approx(2.0) and rc["ratio_min"] == pytest.approx(0.4)
    assert ra["gaussians_per_view"] == 7.0


def test_bad_inputs_are_named(files, tmp_path):
    with pytest.raises(FileNotFoundError, match="no such .pgs file"):
        bench_files([str(tmp_path / "nothing")])
    with pytest.raises(ValueError, match="at least one"):
        bench_files([])
    with pytest.raises(ValueError, match="rounds must be"):
        run_fps_bench([Contender("a", _Fake(), None)], [object()], torch.zeros(3), rounds=0)
    with pytest.raises(ValueError, match="does not name its scene"):
        bench_files([str(files["noscene"])])
    # another scene folder: not the same views, so no ratio
    with pytest.raises(ValueError, match="same views"):
        bench_files([str(files["baseline"]), str(files["elsewhere"])], rounds=1)


def test_cli_prints_the_table(files, capsys):
    from baseline.cli import main

    assert main(["bench", "fps", "--run", str(files["baseline"]), "--run",
                 str(files["predict-gs"]), "--rounds", "1", "--views", "1", "--threads", "1"]) == 0
    out = capsys.readouterr().out
    assert "1 test views" in out and "predict-gs (no cache)" in out


def test_frame_bench_times_each_stage_against_its_reference_form(files, capsys):
    """pgs bench frame: per stage, the current code and its reference form (checked equal on
    every view inside the bench) for each file, the cache as decoded; printed per model."""
    from baseline.cli import main
    from baseline.bench.fps import FRAME_STAGES, bench_frame_files, format_frame_bench

    res = bench_frame_files([str(files["baseline"]), str(files["predict-gs"])], rounds=2,
                            threads=1, max_views=2)
    assert [m["label"] for m in res["models"]] == ["baseline", "predict-gs"]
    assert res["views"] == 2 and res["rounds"] == 2 and res["threads"] == 1
    for m in res["models"]:
        st = m["stages"]
        assert st["gaussians"] > 0
        for k in FRAME_STAGES:
            assert len(st[k]["new"]) == 2 and all(t > 0 for t in st[k]["new"])
        assert all(t > 0 for t in st["prefilter"]["ref"] + st["decode"]["ref"])
        assert st["rasterize"]["ref"] is None
        # baked decoding, timed against decode (its reference) and checked to keep the same
        assert st["baked"]["ref"] == st["decode"]["new"] and all(t > 0 for t in st["baked"]["new"])
    # the refiner's heads (Predict-GS's MGRD) alone, a share of its decoding; none for HAC
    assert "refiner" not in res["models"][0]["stages"]
    pgs = res["models"][1]["stages"]
    assert pgs["refiner"]["ref"] is None
    # timed on its own (a count of samples, not a wall-clock comparison with decode)
    assert len(pgs["refiner"]["new"]) == 2 and all(math.isfinite(t) and t > 0
                                                   for t in pgs["refiner"]["new"])
    text = format_frame_bench(res)
    assert text.count("\nprefilter ") == 2 and text.count("\nframe ") == 2
    assert text.count("\nbaked dec ") == 2 and text.count("\nrefiner ") == 1
    with pytest.raises(ValueError, match="rounds must be"):
        bench_frame_files([str(files["baseline"])], rounds=0)
    assert main(["bench", "frame", "--run", str(files["predict-gs"]), "--rounds", "1",
                 "--views", "1", "--threads", "1"]) == 0
    assert "reference form" in capsys.readouterr().out


def test_gpu_fps_tool_exports_cameras_and_times_at_each_scale(files, tmp_path):
    """tools/gpu/gpu_fps.py (for machines without the scene): the exported cameras are the test
    views of the file's scene; the bench decodes once and times every model at each scale."""
    import importlib.util
    import json
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(
        "gpu_fps", Path(__file__).resolve().parents[1] / "tools" / "gpu" / "gpu_fps.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    cams_file = tmp_path / "cams.pt"
    tool.export(str(files["baseline"]), str(cams_file))
    blob = torch.load(cams_file, weights_only=True)
    test = load_scene(files["scene"]).test_cameras
    assert [c["name"] for c in blob["cameras"]] == [c.name for c in test]
    assert torch.equal(blob["cameras"][0]["viewmat"], test[0].viewmat)
    torch.set_num_threads(1)
    tool.bench(str(cams_file), [str(files["baseline"] / "model.pgs"),
                                str(files["predict-gs"] / "model.pgs")],
               "cpu", 1, [1, 2], str(tmp_path / "fps.json"))
    res = json.loads((tmp_path / "fps.json").read_text())
    assert [r["scale"] for r in res] == [1, 2]
    w, h = test[0].width, test[0].height
    assert f"{w}x{h} (scale 1)" in res[0]["protocol"]
    assert f"{2 * w}x{2 * h} (scale 2)" in res[1]["protocol"]
    for r in res:
        assert [row["label"] for row in r["rows"]] == ["baseline", "baseline (baked)",
                                                      "predict-gs", "predict-gs (baked)",
                                                      "predict-gs (no cache)"]
        assert r["rows"][3]["ref_form"] == "baseline (baked)"
    # frame: the stages of each file at each scale (pgs bench frame without the scene)
    st = tool.frame(str(cams_file), [str(files["predict-gs"] / "model.pgs")], "cpu", 1, [1, 2])
    assert set(st) == {1, 2} and list(st[2]) == ["predict-gs"]
    for k in (1, 2):
        s = st[k]["predict-gs"]
        assert s["gaussians"] > 0 and all(t > 0 for t in s["baked"]["new"] + s["decode"]["new"])
        assert r["rows"][0]["ratio"] == 1.0 and all(row["fps"] > 0 for row in r["rows"])


def test_bench_labels_tell_same_named_files_apart(tmp_path):
    """Two runs' model.pgs read as their run folders' names, not `model` and `model'`."""
    a, b = tmp_path / "hac" / "model.pgs", tmp_path / "pgs" / "model.pgs"
    deep = tmp_path / "x" / "same" / "model.pgs"
    run = tmp_path / "runs" / "baseline-l0.004"
    run.mkdir(parents=True)
    assert fpsbench.bench_labels([str(a), str(b)]) == ["hac/model", "pgs/model"]
    assert fpsbench.bench_labels([str(run), str(a)]) == ["baseline-l0.004", "model"]
    assert fpsbench.bench_labels([str(tmp_path / "same" / "model.pgs"), str(deep)]) == [
        f"{tmp_path.name}/same/model", "x/same/model"]
    assert fpsbench.bench_labels([str(a), str(a)]) == ["model", "model'"]
    assert fpsbench.bench_labels([str(a), str(b), str(a)]) == ["hac/model", "pgs/model",
                                                               "hac/model'"]
