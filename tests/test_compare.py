"""`pgs compare` end to end on a tiny scene: an interrupted comparison resumes without redoing
finished work, the entropy-model swap gives two comparable rows, the report lists them."""
import json
import shutil
from pathlib import Path

import pytest
import torch

import baseline.run as run_mod
from baseline import registry
from baseline.modelfile import MODEL_FILE, file_info
from baseline.config import ConfigError
from baseline.data.synthetic import make_scene
from baseline.experiment import (BASELINE, RECORD, RECORD_FILES, archive_records,
                                   is_finished, parse_methods, plan_runs, run_compare,
                                   with_own_lambdas)
from baseline.train.trainer import CHECKPOINT_NAME, Trainer

ITERS = 24
SETS = [f"train.iterations={ITERS}", "train.threads=1", "train.log_every=1000",
        "train.save_test_renders=false"]
VS = ["entropy-factorized", "predict-gs"]


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    torch.set_num_threads(1)
    registry.ensure_loaded()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("cmp_scene")
    return make_scene(d / "scene", n_views=10, width=48, height=36, n_points=600, seed=3)


def test_methods_and_plan(tmp_path):
    ms = parse_methods(["predict-gs", "predict-gs+entropy-factorized"])
    assert [m.name for m in ms] == [BASELINE, "predict-gs", "predict-gs+entropy-factorized"]
    assert ms[2].patches == ("predict-gs", "entropy-factorized")
    with pytest.raises(ValueError, match="twice"):
        parse_methods(["predict-gs", "predict-gs"])
    with pytest.raises(ValueError, match="joined by"):
        parse_methods(["+"])
    specs = plan_runs(tmp_path, ms, [0.004, 0.0005], ["demo"], SETS)
    assert len(specs) == 6 and len({s.dir for s in specs}) == 6
    assert {s.cfg.entropy.lmbda for s in specs} == {0.004, 0.0005}
    assert specs[0].dir.name.startswith("baseline-l0.004-")
    assert specs[5].cfg.model.feature_provider == "sfp" and specs[5].cfg.entropy.model == "factorized"
    # no --lambda: each method at its own configured lambda
    own = plan_runs(tmp_path, parse_methods(["predict-gs-high-rate"]), None, ["demo"], SETS)
    assert [s.lmbda for s in own] == [0.004, 0.0005]
    with pytest.raises(ConfigError, match="unknown patch"):
        plan_runs(tmp_path, parse_methods(["no-such-patch"]), None, [], SETS)


def test_lambda_for_gives_one_method_its_own_rate_points(scene, tmp_path, capsys):
    ms = with_own_lambdas(parse_methods(["predict-gs"]),
                          [["HAC", "0.008", "0.004"], ["predict-gs", "0.004", "0.0005"]], ["demo"])
    specs = plan_runs(tmp_path, ms, [0.002], ["demo"], SETS)
    assert [(s.method.name, s.lmbda) for s in specs] == \
        [(BASELINE, 0.008), (BASELINE, 0.004), ("predict-gs", 0.004), ("predict-gs", 0.0005)]
    assert [s.cfg.entropy.lmbda for s in specs] == [0.008, 0.004, 0.004, 0.0005]
    # a run at a lambda both methods share is the same run (same folder) with or without it
    plain = plan_runs(tmp_path, parse_methods(["predict-gs"]), [0.004], ["demo"], SETS)
    assert {s.dir for s in plain} <= {s.dir for s in specs}
    # a method not named keeps --lambda
    ms = with_own_lambdas(parse_methods(["predict-gs"]), [["Predict-GS", "0.0005"]], ["demo"])
    assert [(s.method.name, s.lmbda) for s in plan_runs(tmp_path, ms, [0.002, 0.001], ["demo"],
                                                        SETS)] == \
        [(BASELINE, 0.002), (BASELINE, 0.001), ("predict-gs", 0.0005)]
    for bad, msg in (([["HACK", "0.1"]], "not a method of this comparison"),
                     ([["HAC", "0.1"], ["baseline", "0.2"]], "twice"),
                     ([["HAC", "x"]], "must be numbers"),
                     ([["HAC", "0.1", "0.1"]], "lists a value twice"),
                     ([["HAC"]], "one or more lambdas")):
        with pytest.raises(ValueError, match=msg):
            with_own_lambdas(parse_methods(["predict-gs"]), bad, ["demo"])
    # out of the config's range: refused when the runs are planned, as for --lambda
    with pytest.raises(ConfigError, match="out of range"):
        plan_runs(tmp_path, with_own_lambdas(parse_methods([]), [["HAC", "-0.1"]], ["demo"]),
                  None, ["demo"], SETS)
    # through the CLI: --report-only lists exactly the planned runs as not run yet
    from baseline.cli import main

    out = tmp_path / "cmp"
    assert main(["compare", str(scene), "--patch", "demo", "--out", str(out), "--no-progress",
                 "--no-plots", "--vs", "predict-gs", "--lambda", "0.002", "--report-only",
                 "--lambda-for", "HAC", "0.008", "0.004",
                 *[a for s in SETS for a in ("--set", s)]]) == 0
    res = json.loads((out / "results.json").read_text())
    assert len(res["missing"]) == 3 and res["runs"] == []
    assert sum("lambda=0.008" in m for m in res["missing"]) == 1
    assert sum("lambda=0.002" in m for m in res["missing"]) == 1       # Predict-GS's
    assert res["methods"][0] == {"name": BASELINE, "patches": [], "lambdas": [0.008, 0.004]}
    assert "lambdas" not in res["methods"][1]
    assert "1/2 rate point(s)" in capsys.readouterr().out


def _mtimes(d: Path) -> dict:
    return {n: (d / n).stat().st_mtime_ns for n in (CHECKPOINT_NAME, MODEL_FILE, RECORD, "results.json")}


def test_interrupted_compare_resumes(scene, tmp_path, monkeypatch, capsys):
    out = tmp_path / "cmp"
    real_train_run = run_mod.train_run
    calls = []

    def interrupted(scene_path, run_out, cfg, resume=False, progress=True, evaluate_after=True):
        calls.append(Path(run_out).name)
        if Path(run_out).name.startswith("entropy-factorized"):
            # killed halfway through training: a checkpoint at ITERS // 2, no results.json
            sc = run_mod.load_scene_for(cfg, scene_path)
            Trainer(cfg, sc, run_out, progress=False).train(until=ITERS // 2)
            raise KeyboardInterrupt
        return real_train_run(scene_path, run_out, cfg, resume=resume, progress=progress,
                              evaluate_after=evaluate_after)

    monkeypatch.setattr(run_mod, "train_run", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_compare(scene, out, vs=VS, common_patches=["demo"], sets=SETS, progress=False)
    specs = plan_runs(out, parse_methods(VS), None, ["demo"], SETS)
    base, fact, pgs = specs
    assert is_finished(base) and not is_finished(fact) and not is_finished(pgs)
    assert not (fact.dir / "results.json").exists()
    assert torch.load(fact.dir / CHECKPOINT_NAME, weights_only=False)["iteration"] == ITERS // 2
    partial = json.loads((out / "results.json").read_text())
    assert partial["complete"] is False and [r["method"] for r in partial["runs"]] == [BASELINE]
    base_before = _mtimes(base.dir)
    base_record = (base.dir / RECORD).read_text()

    calls.clear()

    def counting(scene_path, run_out, cfg, resume=False, progress=True, evaluate_after=True):
        calls.append(Path(run_out).name)
        return real_train_run(scene_path, run_out, cfg, resume=resume, progress=progress,
                              evaluate_after=evaluate_after)

    monkeypatch.setattr(run_mod, "train_run", counting)
    capsys.readouterr()
    res = run_compare(scene, out, vs=VS, common_patches=["demo"], sets=SETS, progress=False)
    printed = capsys.readouterr().out
    # the finished baseline was neither retrained nor re-encoded nor re-measured
    assert calls == [fact.dir.name, pgs.dir.name]
    assert _mtimes(base.dir) == base_before
    assert (base.dir / RECORD).read_text() == base_record
    # the interrupted run continued from its checkpoint
    assert f"resumed from {fact.dir / CHECKPOINT_NAME} at iteration {ITERS // 2}" in printed
    rows = {r["method"]: r for r in res["runs"]}
    assert rows[BASELINE]["stages_run"] == []
    assert rows["entropy-factorized"]["stages_run"] == ["train", "encode", "decode+eval", "census"]
    assert all(r["iterations"] == ITERS for r in rows.values())
    assert res["complete"] is True
    for name in ("results.json", "report.md", "rd.png", "bits.png", "speed.png", "results.csv"):
        assert (out / name).exists(), name
    import csv

    from baseline.eval.report import method_label
    with open(out / "results.csv", newline="") as fh:
        table = {(x["Method"], float(x["lambda"])): x for x in csv.DictReader(fh)}
    stored = json.loads((out / "results.json").read_text())["runs"]
    assert len(table) == len(stored)
    for r in stored:
        name = method_label(r["method"], ["demo"])
        x = table[(name, r["lmbda"])]
        assert float(x["PSNR"]) == pytest.approx(r["psnr"], abs=1e-6)
        assert int(x["Size [Bytes]"]) == r["bytes"] and int(x["#Gaussians"]) == r["masks_on"]["on"]
        # the field's SSIM and scikit-image's, both measured on the decoded file
        assert x["SSIM convention"] == r["ssim_convention"] == "3dgs"
        assert float(x["SSIM (skimage)"]) == pytest.approx(r["ssim_skimage"], abs=1e-6)
        # the survey's layout: one file per method and scene, one point named by the method
        with open(out / "survey" / name / scene.parent.name / f"{scene.name}.csv") as fh:
            (srow,) = list(csv.DictReader(fh))
        assert srow["Submethod"] == name and int(srow["Size [Bytes]"]) == r["bytes"]
        assert float(srow["SSIM"]) == pytest.approx(r["ssim"], abs=1e-6)
        # the decoded file's views as 3DGS lays them out: renders/, gt/, per_view.json
        views = Path(r["run_dir"]) / "decoded"
        per = json.loads((views / "per_view.json").read_text())
        assert list(per) == [f"ours_{ITERS}"]
        psnrs = per[f"ours_{ITERS}"]["PSNR"]
        assert sorted(psnrs) == sorted(p.name for p in (views / "renders").glob("*.png")) \
            == sorted(p.name for p in (views / "gt").glob("*.png"))
        assert len(psnrs) == r["n_views"]
        assert sum(psnrs.values()) / len(psnrs) == pytest.approx(r["psnr"])
    # first-run messages: a run trained now says so, a finished one is reused
    assert "trained now, then encode, decode+eval, census]" in printed
    assert "[reused (finished earlier)]" in printed

    # ---- the entropy-model swap: two comparable rows (same everything but the entropy model)
    b, f = rows[BASELINE], rows["entropy-factorized"]
    assert b["lmbda"] == f["lmbda"] and b["iterations"] == f["iterations"] == ITERS
    assert b["backend"] == f["backend"] == "cpu" and b["split"] == f["split"] == "test"
    secs_b = {s["section"] for s in b["sections"]}
    secs_f = {s["section"] for s in f["sections"]}
    assert "em.grid" in secs_b and "em.grid" not in secs_f and "em.factorized" in secs_f
    # named by the component that owns them
    labels = {s["section"]: s["label"] for r in rows.values() for s in r["sections"]}
    assert labels["em.grid"] == "hac.grid" and labels["em.factorized"] == "factorized"
    assert labels["provider.grid"] == "sfp.grid" and labels["provider.weights"] == "sfp.fusion"
    assert labels["refiner.weights"] == "mgrd" and labels["decoder.weights"] == "decoder"
    for r in rows.values():
        pgs_file = Path(r["run_dir"]) / MODEL_FILE
        info = file_info(pgs_file)
        assert r["bytes"] == pgs_file.stat().st_size == info["total_bytes"]
        assert r["mb"] == r["bytes"] / 2 ** 20
        assert sum(r["groups"].values()) == r["bytes"]
        assert r["groups"] == info["groups"]
        assert 0 < r["psnr"] < 100 and 0 < r["ssim"] <= 1 and r["lpips"] is None
        assert r["fps"] > 0 and r["encode_s"] > 0 and r["decode_s"] > 0 and r["train_time_s"] > 0
        assert 0 <= r["stall_s"] <= r["train_time_s"] and "stall_from" not in r
        assert r["anchors"] == info["n_anchors"]
        assert r["attributes"] == info["attributes"] and r["masks_on"] == info["masks_on"]
        # the Gaussians per view broken down (evaluate()); its product is the recorded mean
        k = info["header"]["n_offsets"]
        assert r["visible_anchors_mean"] * k * r["mask_on_fraction"] * r["opacity_kept_fraction"] \
            == pytest.approx(r["gaussians_mean"])
    # Predict-GS keeps a decoded-model cache: FPS with and without it, same image either way
    p = rows["predict-gs"]
    assert p["has_cache"] and p["fps_nocache"] > 0 and p["psnr_nocache"] == pytest.approx(p["psnr"])
    assert not b["has_cache"] and b["fps_nocache"] is None
    md = (out / "report.md").read_text()
    assert "| HAC+entropy-factorized | 0.004 |" in md and "| HAC | 0.004 |" in md
    assert "(no cache)" in printed and "Bjontegaard" in printed

    # ---- a third invocation through the CLI reuses everything
    from baseline.cli import main

    calls.clear()
    # a record written before the per-attribute counts were kept gets them from its model file,
    # with nothing re-encoded or remeasured
    rec = json.loads((base.dir / RECORD).read_text())
    del rec["encode"]["attributes"], rec["encode"]["masks_on"]
    (base.dir / RECORD).write_text(json.dumps(rec))
    assert main(["compare", str(scene), "--patch", "demo", "--out", str(out), "--no-progress",
                 *[a for v in VS for a in ("--vs", v)], *[a for s in SETS for a in ("--set", s)]]) == 0
    assert calls == []
    again = json.loads((out / "results.json").read_text())
    assert all(r["stages_run"] == [] for r in again["runs"])
    assert again["runs"][0]["attributes"] == rows[BASELINE]["attributes"]
    assert json.loads((base.dir / RECORD).read_text())["encode"]["encode_s"] == rec["encode"]["encode_s"]
    printed = capsys.readouterr().out
    assert "Coded values and bits per value" in printed
    assert [(r["method"], r["bytes"], r["psnr"]) for r in again["runs"]] == \
        [(r["method"], r["bytes"], r["psnr"]) for r in res["runs"]]
    assert "3 run(s)" in printed


def test_compare_refuses_other_scene(scene, tmp_path):
    other = make_scene(tmp_path / "other", n_views=10, width=48, height=36, n_points=100, seed=4)
    out = tmp_path / "cmp"
    spec = plan_runs(out, parse_methods([]), None, ["demo"], SETS)[0]
    spec.dir.mkdir(parents=True)
    (spec.dir / "scene.json").write_text(json.dumps({"path": str(Path(other).resolve())}))
    with pytest.raises(ValueError, match="another --out"):
        run_compare(scene, out, common_patches=["demo"], sets=SETS, progress=False, echo=False)


def test_lpips_weights_redo_only_the_decoded_stage(scene, tmp_path, monkeypatch):
    """Weights given on a rerun: only decode + evaluate run again, and LPIPS appears."""
    from baseline.eval.metrics import LPIPS

    out = tmp_path / "cmp"
    run_compare(scene, out, vs=["entropy-factorized"], common_patches=["demo"], sets=SETS,
                progress=False, plots=False, echo=False)
    spec = plan_runs(out, parse_methods(["entropy-factorized"]), None, ["demo"], SETS)[1]
    before = _mtimes(spec.dir)
    enc_before = json.loads((spec.dir / RECORD).read_text())["encode"]
    torch.manual_seed(0)
    net = LPIPS()        # random weights: this tests the plumbing, not the metric's values
    for lin in net.lins:
        lin.weight.data.abs_()                       # LPIPS heads are non-negative
    w = tmp_path / "lpips.pth"
    torch.save({k: v for k, v in net.state_dict().items() if k not in ("shift", "scale")}, w)
    calls = []
    monkeypatch.setattr(run_mod, "train_run", lambda *a, **k: calls.append(a) or {})
    res = run_compare(scene, out, vs=["entropy-factorized"], common_patches=["demo"], sets=SETS,
                      lpips_weights=str(w), progress=False, plots=False, echo=False)
    assert calls == []
    assert all(r["stages_run"] == ["decode+eval"] for r in res["runs"])
    assert all(r["lpips"] is not None and r["lpips"] >= 0 for r in res["runs"])
    assert json.loads((spec.dir / RECORD).read_text())["encode"] == enc_before
    after = _mtimes(spec.dir)
    assert after[MODEL_FILE] == before[MODEL_FILE] and after[CHECKPOINT_NAME] == before[CHECKPOINT_NAME]
    assert "VGG16 LPIPS with weights" in (out / "report.md").read_text()


def test_only_splits_a_comparison_and_remeasure_retakes_timings(scene, tmp_path):
    """--only trains and reports just the named method (the others untouched); a full run then
    reuses it; --remeasure redoes encode + decode/eval of every run, writing the same bytes."""
    out = tmp_path / "cmp"
    kw = dict(common_patches=["demo"], sets=SETS, progress=False, plots=False, echo=False)
    specs = plan_runs(out, parse_methods(["entropy-factorized"]), None, ["demo"], SETS)
    with pytest.raises(ValueError, match="not a method"):
        run_compare(scene, out, vs=["entropy-factorized"], only=["predict-gs"], **kw)
    res = run_compare(scene, out, vs=["entropy-factorized"], only=["entropy-factorized"], **kw)
    assert [r["method"] for r in res["runs"]] == ["entropy-factorized"]
    assert res["only"] == ["entropy-factorized"]
    assert not specs[0].dir.exists() and is_finished(specs[1])
    full = run_compare(scene, out, vs=["entropy-factorized"], **kw)
    rows = {r["method"]: r for r in full["runs"]}
    assert rows[BASELINE]["stages_run"] == ["train", "encode", "decode+eval", "census"]
    assert rows["entropy-factorized"]["stages_run"] == []
    # identical commands give identical reports: the paired FPS of a rebuilt report is the one
    # measured before, on the same files; --remeasure times it again
    import baseline.bench.fps as fpsbench
    timed = []
    real_bench = fpsbench.bench_files

    def counting_bench(*a, **k):
        timed.append(a)
        return real_bench(*a, **k)

    fpsbench.bench_files = counting_bench
    try:
        one = run_compare(scene, out, vs=["entropy-factorized"], paired_fps=True, **kw)
        md = (out / "report.md").read_text()
        two = run_compare(scene, out, vs=["entropy-factorized"], paired_fps=True, **kw)
        assert len(timed) == 1 and (out / "report.md").read_text() == md
        assert two["fps_pair"] == one["fps_pair"]
        fp = one["fps_pair"]["entropy-factorized"]
        assert fp["ratio"] == fp["fps"] / fp["fps_ref"]
        assert fp["runs"] == [specs[0].dir.name, specs[1].dir.name]
        assert f"{fp['ratio']:.2f}x ({fp['fps']:.1f} / {fp['fps_ref']:.1f} FPS)" in md
        again = run_compare(scene, out, vs=["entropy-factorized"], remeasure=True,
                            paired_fps=True, **kw)
        assert len(timed) == 2
    finally:
        fpsbench.bench_files = real_bench
    for r in again["runs"]:
        assert r["stages_run"] == ["encode", "decode+eval"]
        before = rows[r["method"]]
        assert (r["bytes"], r["psnr"], r["ssim"]) == (before["bytes"], before["psnr"], before["ssim"])
        assert r["train_time_s"] == before["train_time_s"]


def test_archived_records_are_reported_without_retraining(scene, tmp_path):
    """A run folder reduced to its records (no checkpoint, no model file) counts as finished: a
    comparison copied elsewhere reports it as recorded, trains only what is missing, and
    --remeasure leaves it alone; a run whose checkpoint is there but model file gone re-encodes."""
    from baseline.eval.report import format_report

    out = tmp_path / "cmp"
    kw = dict(common_patches=["demo"], sets=SETS, progress=False, plots=False, echo=False)
    first = run_compare(scene, out, vs=["entropy-factorized"], only=["baseline"], **kw)
    base = first["runs"][0]
    curve = base["train_curve"]         # the training log's summary, kept in the record
    assert curve["iterations"] == base["iterations"] and len(curve["l1"]) == 6
    # log_every 1000 > ITERS: only the last step is logged, so only the last span has a value
    assert curve["l1"][:-1] == [None] * 5 and curve["l1"][-1] > 0
    # archive: keep the records only, in a new comparison folder
    arch = tmp_path / "archive"
    # another comparison's finished run sharing the folder: kept only when nothing says which
    # runs this comparison reported
    other = out / "runs" / "other-comparison-l0.004-000000000000"
    shutil.copytree(base["run_dir"], other)
    assert other.name in [p.name for p in archive_records(out, tmp_path / "everything")]
    shutil.rmtree(tmp_path / "everything")
    kept = archive_records(out, arch, first)
    assert [p.name for p in kept] == [first["runs"][0]["run_dir"].split("/")[-1]]
    assert sorted(f.name for f in kept[0].iterdir()) == sorted(RECORD_FILES)
    assert (arch / "report.md").exists() and (arch / "results.json").exists()
    assert (arch / "results.csv").read_text() == (out / "results.csv").read_text()
    specs = plan_runs(arch, parse_methods(["entropy-factorized"]), None, ["demo"], SETS)
    assert is_finished(specs[0]) and not is_finished(specs[1])
    # --report-only: the archived run is reported, the missing one listed and not started
    with pytest.raises(ValueError, match="report-only"):
        run_compare(scene, arch, vs=["entropy-factorized"], report_only=True, remeasure=True, **kw)
    part = run_compare(scene, arch, vs=["entropy-factorized"], report_only=True, **kw)
    assert [r["method"] for r in part["runs"]] == [BASELINE] and part["runs"][0]["stages_run"] == []
    assert part["missing"] == [specs[1].label] and not part["complete"]
    assert not specs[1].dir.exists()
    assert f"1 run(s) not run yet ({specs[1].label})" in (arch / "report.md").read_text()
    assert format_report(part).startswith("Incomplete comparison: 1 run(s) not run yet")
    # --untimed marks a finished run's record (kept by the archive), an empty reason unmarks it
    name = Path(base["run_dir"]).name
    with pytest.raises(ValueError, match="'nope' is no run of this comparison"):
        run_compare(scene, arch, vs=["entropy-factorized"], report_only=True,
                    untimed=[["nope", "paused"]], **kw)
    with pytest.raises(ValueError, match="has not finished"):
        run_compare(scene, arch, vs=["entropy-factorized"], report_only=True,
                    untimed=[[specs[1].dir.name, "paused"]], **kw)
    assert not specs[1].dir.exists()
    marked = run_compare(scene, arch, vs=["entropy-factorized"], report_only=True,
                         untimed=[[name, " paused 14 min "]], **kw)
    assert marked["runs"][0]["untimed"] == "paused 14 min"
    assert json.loads((arch / "runs" / name / RECORD).read_text())["untimed"] == "paused 14 min"
    again = run_compare(scene, arch, vs=["entropy-factorized"], report_only=True, **kw)
    assert again["runs"][0]["untimed"] == "paused 14 min"
    assert "paused 14 min" in (arch / "report.md").read_text()
    unmarked = run_compare(scene, arch, vs=["entropy-factorized"], report_only=True,
                           untimed=[[name, ""]], **kw)
    assert unmarked["runs"][0]["untimed"] is None
    assert "untimed" not in json.loads((arch / "runs" / name / RECORD).read_text())
    full = run_compare(scene, arch, vs=["entropy-factorized"], **kw)
    rows = {r["method"]: r for r in full["runs"]}
    assert rows[BASELINE]["stages_run"] == [] and rows[BASELINE]["records_only"]
    assert (rows[BASELINE]["bytes"], rows[BASELINE]["psnr"]) == (base["bytes"], base["psnr"])
    assert rows[BASELINE]["train_curve"] == curve     # the archived records keep it, not the log
    assert rows["entropy-factorized"]["stages_run"] == ["train", "encode", "decode+eval", "census"]
    assert not rows["entropy-factorized"]["records_only"]
    assert "archived records" in format_report(full) and full["complete"] and full["missing"] == []
    assert "Incomplete" not in format_report(full)
    again = run_compare(scene, arch, vs=["entropy-factorized"], remeasure=True, **kw)
    rows2 = {r["method"]: r for r in again["runs"]}
    assert rows2[BASELINE]["stages_run"] == [] and rows2[BASELINE]["decode_s"] == base["decode_s"]
    assert rows2["entropy-factorized"]["stages_run"] == ["encode", "decode+eval"]
    # a model file missing beside its checkpoint is re-encoded, not taken from the record
    (specs[1].dir / MODEL_FILE).unlink()
    assert not is_finished(specs[1])


def test_reference_measures_every_run_against_the_uncompressed_model(scene, tmp_path):
    """--reference scaffold: the uncompressed run shares the protocol, is trained once (alone with
    --only reference), its float32 size counts every tensor the renderer reads (independent count
    below), each run's 'x smaller' and PSNR change come from it, and archived records keep it."""
    from baseline.experiment import REFERENCE, parse_reference, plan_reference
    from baseline.eval.report import format_report, reference_table
    from baseline.run import load_run

    with pytest.raises(ValueError, match="not an uncompressed reference"):
        plan_reference(tmp_path, parse_reference("predict-gs"), ["demo"], SETS)
    out = tmp_path / "cmp"
    kw = dict(common_patches=["demo"], sets=SETS, progress=False, plots=False, echo=False)
    alone = run_compare(scene, out, vs=["predict-gs"], reference="scaffold", only=[REFERENCE], **kw)
    ref = alone["reference"]
    assert alone["runs"] == [] and ref["stages_run"] == ["train", "float32 size"]
    spec = plan_reference(out, parse_reference("scaffold"), ["demo"], SETS)
    assert ref["run_dir"] == str(spec.dir) and spec.cfg.train.iterations == ITERS
    assert spec.cfg.train.hooks == ["scaffold_densify"]
    trainer, _ = load_run(spec.dir, device="cpu")
    m = trainer.model
    per_anchor = m.n_anchors * (3 + m.provider.feature_dim + m.n_offsets * 3 + 6)
    assert ref["float32_bytes"] == 4 * (per_anchor + sum(p.numel() for p in m.decoder.parameters()))
    assert ref["anchors"] == m.n_anchors
    assert ref["psnr"] == json.loads((spec.dir / "results.json").read_text())["test"]["psnr"]

    full = run_compare(scene, out, vs=["predict-gs"], reference="scaffold", **kw)
    assert full["reference"]["stages_run"] == []                     # trained once
    table = reference_table(full)
    assert len(table.rows) == 3 and table.rows[0][3] == "ref"
    for row, r in zip(table.rows[1:], full["runs"]):
        assert row[3] == f"{r['psnr'] - ref['psnr']:+.3f}"
        assert row[6] == f"{ref['float32_bytes'] / r['bytes']:.1f}x"
    text = format_report(full)
    assert "Against the uncompressed reference" in text and "scaffold = common patches" in text
    assert reference_table({**full, "reference": None}) is None

    arch = tmp_path / "archive"
    kept = archive_records(out, arch, full)
    assert spec.dir.name in [p.name for p in kept]
    part = run_compare(scene, arch, vs=["predict-gs"], reference="scaffold", report_only=True, **kw)
    assert part["reference"]["records_only"] and part["reference"]["psnr"] == ref["psnr"]
    assert part["complete"]
    # a comparison whose reference is not trained yet lists it as missing under --report-only
    empty = run_compare(scene, arch, vs=["predict-gs"], reference="scaffold+weights-fp16",
                        report_only=True, **kw)
    assert empty["reference"] is None and "reference (scaffold+weights-fp16)" in empty["missing"]


def test_codec_patch_reencodes_without_retraining(scene, tmp_path):
    """--codec compact-codec: every run is encoded, decoded and measured again with the codec
    settings (smaller files, the same decoded PSNR), its training reused; the settings are
    recorded and reported; back without --codec the default files are written again."""
    from baseline.experiment import codec_overrides

    out = tmp_path / "cmp"
    kw = dict(common_patches=["demo"], sets=SETS, progress=False, plots=False, echo=False)
    with pytest.raises(ValueError, match="only \\[codec\\] keys"):
        codec_overrides("predict-gs")
    assert codec_overrides("compact-codec") == {"positions": "sorted", "masks": "patterns",
                                                "grids": "used"}
    first = run_compare(scene, out, vs=["predict-gs"], **kw)
    comp = run_compare(scene, out, vs=["predict-gs"], codec="compact-codec", **kw)
    assert comp["codec"] == {"patch": "compact-codec", "settings": codec_overrides("compact-codec")}
    for a, b in zip(first["runs"], comp["runs"]):
        assert b["stages_run"] == ["encode", "decode+eval"] and b["run_dir"] == a["run_dir"]
        assert b["train_time_s"] == a["train_time_s"]
        assert b["codec"]["positions"] == "sorted" and a["codec"]["positions"] == "raw16"
        assert b["bytes"] < a["bytes"] and abs(b["psnr"] - a["psnr"]) < 0.01
    assert "--codec compact-codec (positions = sorted, masks = patterns, grids = used)" in \
        (out / "report.md").read_text()
    again = run_compare(scene, out, vs=["predict-gs"], codec="compact-codec", **kw)
    assert all(r["stages_run"] == [] for r in again["runs"])
    back = run_compare(scene, out, vs=["predict-gs"], **kw)
    for a, b in zip(first["runs"], back["runs"]):
        assert b["stages_run"] == ["encode", "decode+eval"] and b["bytes"] == a["bytes"]
    # archived records (no checkpoint) cannot be coded again: a clear error, nothing rewritten
    from baseline.experiment import archive_records

    arch = tmp_path / "arch"
    archive_records(out, arch, back)
    before = {p: p.read_bytes() for p in arch.rglob("compare.json")}
    with pytest.raises(ValueError, match="kept only as records"):
        run_compare(scene, arch, vs=["predict-gs"], codec="compact-codec", **kw)
    assert {p: p.read_bytes() for p in arch.rglob("compare.json")} == before


def test_jobs_trains_in_workers_and_reports_what_one_process_reports(scene, tmp_path, capsys):
    """--jobs 2: the runs to do train in two pinned worker processes (the codec patch goes
    with them), then the report is the one process's: every run finished once, the same bytes
    and PSNR as a comparison run in one process, nothing measured twice."""
    kw = dict(vs=["entropy-factorized"], common_patches=["demo"], sets=SETS, progress=False,
              plots=False, codec="compact-codec", seeds=[0])
    one = run_compare(scene, tmp_path / "one", echo=False, **kw)
    par = run_compare(scene, tmp_path / "par", jobs=2, **kw)
    said = capsys.readouterr().out
    from baseline.train.trainer import available_cores

    n = min(2, available_cores())                          # one worker per core at most
    assert f"2 run(s) to do on {n} worker(s)" in said and said.count("finished: ") == 2
    key = lambda r: (r["method"], r["lmbda"], r["seed"])            # noqa: E731
    a, b = sorted(one["runs"], key=key), sorted(par["runs"], key=key)
    assert [key(r) for r in a] == [key(r) for r in b] and len(b) == 2
    for x, y in zip(a, b):
        assert (y["bytes"], y["psnr"], y["ssim"]) == (x["bytes"], x["psnr"], x["ssim"])
        assert y["codec"]["positions"] == "sorted" and y["stages_run"] == []
        assert Path(y["run_dir"]).parent == tmp_path / "par" / "runs"
    again = run_compare(scene, tmp_path / "par", jobs=2, echo=False, **kw)
    assert all(r["stages_run"] == [] for r in again["runs"])   # nothing left to do: no workers
