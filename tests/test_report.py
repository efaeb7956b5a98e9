"""Report generation from stored comparison results (no training): tables, report.md, plots."""
import json

import pytest

from baseline.eval.report import (verdict_lines, baseline_partner, compute_bd, format_report, rate_points,
                                  write_report)

MB = 2 ** 20
LAMBDAS = [0.0005, 0.002, 0.004]


def _row(method, lmbda, psnr, feat, others, cache=False, fps=100.0):
    total = feat + others
    groups = {"feature": feat, "anchor": others // 4, "scaling": others // 4, "offsets": others // 4,
              "mlps": others - 3 * (others // 4) - 100, "header+framing": 100}
    sections = [{"section": "feat" if not cache else "residual", "group": "feature", "bytes": feat},
                {"section": "positions", "group": "anchor", "bytes": groups["anchor"]},
                {"section": "scaling", "group": "scaling", "bytes": groups["scaling"]},
                {"section": "offsets", "group": "offsets", "bytes": groups["offsets"]},
                {"section": "decoder.weights", "group": "mlps", "bytes": groups["mlps"]}]
    return {"method": method, "method_patches": [] if method == "baseline" else method.split("+"),
            "patches": ["cpu"], "lmbda": lmbda, "run_dir": f"runs/{method}-l{lmbda:g}-x",
            "config_hash": "x", "psnr": psnr, "ssim": 0.9, "ssim_convention": "3dgs",
            "ssim_skimage": 0.88, "lpips": None, "bytes": total,
            "mb": total / MB, "sections": sections, "groups": groups, "iterations": 8000,
            "train_time_s": 1234.5, "s_per_it": 0.154, "threads": 2, "encode_s": 1.5,
            "decode_s": 0.75, "fps": fps, "fps_nocache": fps / 2 if cache else None,
            "has_cache": cache, "psnr_nocache": psnr if cache else None, "anchors": 5000,
            "anchors_trained": 5100, "gaussians_mean": 40000.0, "n_views": 25, "split": "test",
            "backend": "cpu", "phase_at_encode": "adaptive",
            "pre_encode": {"psnr": psnr, "ssim": 0.9, "fps": fps},
            "protocol": {"format": "colmap", "image_size": [980, 545], "downscale": 4.0,
                         "resolution": 4, "split": "every 8th view is a test view",
                         "background": [0.0, 0.0, 0.0], "n_train": 220, "n_test": 31},
            "train_versions": {"python": "3.11", "torch": "2.13.0"}}


def stored_results():
    base_psnr = [27.0, 26.2, 25.1]
    base_feat = [6 * MB, 4 * MB, 3 * MB]
    base_oth = [4 * MB, 3 * MB, 2 * MB]
    runs = []
    for lm, p, f, o in zip(LAMBDAS, base_psnr, base_feat, base_oth):
        runs.append(_row("baseline", lm, p, f, o))
        # contender: 0.8x the bytes of every group at the same PSNR -> BD-rate -20 % exactly
        runs.append(_row("predict-gs", lm, p, int(0.4 * f), int(0.8 * (f + o)) - int(0.4 * f),
                         cache=True, fps=80.0))
        runs.append(_row("entropy-factorized", lm, p - 0.5, f, o))       # same bytes, -0.5 dB
    # the factorized row's groups must sum to bytes; rows above do by construction
    return {"format": "pgs-compare/1", "scene": "/data/tandt_truck", "baseline": "baseline",
            "methods": [{"name": "baseline", "patches": []},
                        {"name": "predict-gs", "patches": ["predict-gs"]},
                        {"name": "entropy-factorized", "patches": ["entropy-factorized"]}],
            "common_patches": ["cpu"], "sets": [], "lambdas": LAMBDAS,
            "lpips": "LPIPS unavailable: pass --lpips-weights PATH",
            "versions": {"python": "3.11", "torch": "2.13.0"}, "complete": True, "runs": runs}


def test_bd_from_stored_results():
    res = stored_results()
    bd = {b["method"]: b for b in compute_bd(res)}
    # bytes were rounded to integers: -20 % up to that rounding
    assert bd["predict-gs"]["bd_rate"] == pytest.approx(-20.0, abs=1e-4)
    assert bd["entropy-factorized"]["bd_psnr"] == pytest.approx(-0.5, abs=1e-9)
    assert bd["entropy-factorized"]["bd_rate"] > 0


def test_bd_needs_three_points():
    res = stored_results()
    res["runs"] = [r for r in res["runs"] if r["lmbda"] != 0.004]
    bd = compute_bd(res)
    assert all(b["bd_rate"] is None and ">= 3" in b["note"] for b in bd)


def test_partner_and_points():
    res = stored_results()
    pts = rate_points(res)
    assert [len(p) for p in pts] == [3, 3, 3]
    r = [x for x in res["runs"] if x["method"] == "predict-gs" and x["lmbda"] == 0.002][0]
    assert baseline_partner(res, r)["lmbda"] == 0.002
    # one run per method at different lambdas (no --lambda): paired with the single baseline run
    res["runs"] = [res["runs"][0], res["runs"][4]]
    assert baseline_partner(res, res["runs"][1]) is res["runs"][0]
    assert [len(p) for p in rate_points(res)] == [2]



def test_points_group_by_lambda_when_a_run_is_missing():
    """A comparison under way (one method lacks a rate point) still pairs runs by lambda, never
    by rank: the section tables must not set lambda 0.001 beside lambda 0.002."""
    res = stored_results()
    res["runs"] = [r for r in res["runs"] if not (r["method"] == "predict-gs" and r["lmbda"] == 0.002)]
    pts = rate_points(res)
    assert all(len({r["lmbda"] for r in p}) == 1 for p in pts)
    assert sorted(len(p) for p in pts) == [2, 3, 3]
    text = format_report(res)
    assert "(lambda " not in text.split("Sections (bytes)")[1].split("\n")[0]


def test_report_text_and_markdown(tmp_path):
    res = stored_results()
    txt = format_report(res)
    for s in ("Quality and size", "Bit allocation by group", "Table 3", "Sections (bytes) at lambda 0.002",
              "Speed against error", "Bjontegaard", "Protocol", "980 x 545 px", "unavailable",
              "-20.00", "(no cache)", "threads"):
        assert s in txt, s
    # Table 3 savings are arithmetic on the stored bytes: predict-gs feature = 0.4 x baseline
    line = [ln for ln in txt.splitlines() if ln.startswith("Predict-GS") and "+60.0%" in ln]
    assert len(line) == 3
    paths = write_report(res, tmp_path)
    md = (tmp_path / "report.md").read_text()
    assert md.startswith("# Comparison report")
    assert "| method | lambda | PSNR (dB) |" in md
    assert "![rd](rd.png)" in md
    for k in ("rd", "bits", "speed"):
        p = paths[k]
        assert p.exists() and p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", k
        assert p.stat().st_size > 10_000
    json.dumps(res)               # still serializable after the report added its fields


def test_protocol_names_the_device():
    """Rows recorded before device support trained on the CPU; mixed devices are listed."""
    from baseline.eval.report import protocol_lines

    res = stored_results()
    assert dict(protocol_lines(res))["device"] == "cpu"
    for r in res["runs"]:
        if r["method"] == "predict-gs":
            r["device"] = "cuda:0 (NVIDIA H100 80GB HBM3)"
    dev = dict(protocol_lines(res))["device"]
    assert "cuda:0 (NVIDIA H100 80GB HBM3) (Predict-GS" in dev and "cpu (HAC" in dev


def test_report_with_single_points_and_lpips(tmp_path):
    res = stored_results()
    res["runs"] = [r for r in res["runs"] if r["lmbda"] == 0.004]
    for r in res["runs"]:
        r["lpips"] = 0.25
    txt = format_report(res)
    assert "0.2500" in txt and "needs >= 3 rate points" in txt
    write_report(res, tmp_path)
    assert (tmp_path / "bits.png").exists()


def test_bd_psnr_kept_when_only_bd_rate_is_impossible():
    res = stored_results()
    # contender PSNRs all above the baseline's (no PSNR overlap) but the same sizes (log-rate overlap)
    for r in res["runs"]:
        if r["method"] == "entropy-factorized":
            r["psnr"] += 5.0
    bd = {b["method"]: b for b in compute_bd(res)}["entropy-factorized"]
    assert bd["bd_rate"] is None and "BD-rate" in bd["note"] and "overlap" in bd["note"]
    assert bd["bd_psnr"] == pytest.approx(4.5, abs=1e-9)


def _with_counts(res):
    """Give every run per-attribute counts: the baseline codes feat (50 dims) on 5000 anchors and
    offsets for 20000 Gaussians; predict-gs codes a 25-dim residual and 26000 offsets whose
    bits each are 10% fewer."""
    for r in res["runs"]:
        pgs = r["method"] == "predict-gs"
        feat = {"section": "residual" if pgs else "feat", "dims": 25 if pgs else 50,
                "masked": False, "elements": 5000 * (25 if pgs else 50)}
        off = {"section": "offsets", "dims": 30, "masked": True,
               "elements": 3 * (26000 if pgs else 20000)}
        for a in (feat, off):
            bpe = (3.6 if pgs else 4.0) if a is off else 2.0
            a["bytes"] = int(a["elements"] * bpe / 8)
            a["bits_per_element"] = 8 * a["bytes"] / a["elements"]
        r["attributes"] = [feat, off]
        r["masks_on"] = {"on": 26000 if pgs else 20000, "total": 50000}
        r["gaussians_mean"] = 52000.0 if pgs else 40000.0
    return res


def _rows_of(txt, title):
    block = txt.split(title, 1)[1].split("\n\n", 1)[0].splitlines()
    return [ln.split() for ln in block[4:] if ln and not ln.startswith("  ")]


def test_elements_table_separates_count_from_bits_per_value():
    res = _with_counts(stored_results())
    txt = format_report(res)
    rows = _rows_of(txt, "Coded values and bits per value")
    assert len(rows) == 2 * len(res["runs"])
    off = {(r[0], r[1]): r for r in rows if r[2] == "offsets"}
    # baseline: 60000 values at 4 bits; predict-gs: +30% values at -10% bits per value
    assert off[("HAC", "0.004")][3:] == ["60000", "30000", "4.000", "ref", "ref", "40.0%"]
    assert off[("Predict-GS", "0.004")][3:] == ["78000", "35100", "3.600", "+30.0%", "-10.0%", "52.0%"]
    feat = [r for r in rows if r[0] == "Predict-GS" and r[2] == "residual"]
    assert len(feat) == 3 and all(r[6:8] == ["-", "-"] for r in feat)   # no residual in HAC
    # the speed table shows Gaussians per view and the change against the baseline
    speed = txt.split("Speed against error", 1)[1]
    assert "52000 (+30.0%)" in speed and "40000 " in speed


def test_elements_table_skips_archived_rows_without_counts():
    res = stored_results()
    assert "Coded values and bits per value" not in format_report(res)
    res = _with_counts(res)
    for r in res["runs"]:
        if r["method"] == "entropy-factorized":
            r.pop("attributes")
    txt = format_report(res)
    rows = _rows_of(txt, "Coded values and bits per value")
    assert {r[0] for r in rows} == {"HAC", "Predict-GS"}
    assert "not shown (records archived before these counts were kept): HAC+entropy-factorized" in txt


def test_alive_table_splits_gaussians_per_view():
    """Visible anchors, mask-on share and opacity-kept share beside the baseline's; rows without
    the breakdown (archived before it was kept) are named; no table when no row has it."""
    res = _with_counts(stored_results())
    assert "Where the Gaussians per view come from" not in format_report(res)
    for r in res["runs"]:
        if r["method"] == "entropy-factorized":
            continue
        pgs = r["method"] == "predict-gs"
        # 50000 visible x K = 10 x mask-on share x 0.2 kept = the stored 40000 / 52000 per view
        r["visible_anchors_mean"] = 50000.0
        r["mask_on_fraction"] = 0.52 if pgs else 0.40
        r["opacity_kept_fraction"] = 0.20
    txt = format_report(res)
    rows = _rows_of(txt, "Where the Gaussians per view come from")
    by = {(r[0], r[1]): r for r in rows}
    assert {r[0] for r in rows} == {"HAC", "Predict-GS"}
    assert by[("HAC", "0.004")][2:] == ["50000", "40.0%", "20.0%", "40000"]
    assert by[("Predict-GS", "0.004")][2:] == ["50000", "(+0.0%)", "52.0%", "(+30.0%)", "20.0%",
                                              "(+0.0%)", "52000", "(+30.0%)"]
    assert ("not shown (records archived before this breakdown was kept): HAC+entropy-factorized"
            in txt)


def test_rate_term_line_says_what_one_lambda_weighs_per_method():
    """HAC's rate term is bits per coded parameter: at one lambda a method coding fewer values
    per anchor weighs each bit more (here 80 vs 55 values: 1.45x); archived rows without counts
    leave their method out; with no counts at all the line says so."""
    from baseline.eval.report import protocol_lines, rate_elements

    res = stored_results()
    assert "E not in these records" in dict(protocol_lines(res))["rate term"]
    res = _with_counts(res)
    assert [rate_elements(r) for r in res["runs"][:2]] == [80, 55]
    for r in res["runs"]:
        if r["method"] == "entropy-factorized":
            r.pop("attributes")
    line = dict(protocol_lines(res))["rate term"]
    assert ": HAC 80, Predict-GS 55;" in line
    assert "against HAC's: Predict-GS 1.45x" in line and "entropy-factorized" not in line
    assert "rate term" in format_report(res) and "Predict-GS 1.45x" in format_report(res)


def seeded_results():
    """Two seeds per point. Seed 0: the contender is 0.8x the baseline's bytes at equal PSNR;
    seed 1: both curves 0.1 dB lower, the contender 0.9x. The seed-mean curves are then built
    from per-lambda means of size and PSNR."""
    res = stored_results()
    runs = []
    for r in res["runs"]:
        if r["method"] == "entropy-factorized":
            continue
        for seed, dp, scale in ((0, 0.0, 1.0), (1, -0.1, 1.125 if r["method"] != "baseline" else 1.0)):
            q = dict(r, seed=seed, psnr=r["psnr"] + dp, bytes=int(r["bytes"] * scale),
                     groups=dict(r["groups"]))
            q["mb"] = q["bytes"] / MB
            runs.append(q)
    res["runs"] = runs
    res["methods"] = res["methods"][:2]
    res["seeds"] = [0, 1]
    return res


def test_seeded_report_gives_bd_per_seed_and_on_the_seed_mean_curves(tmp_path):
    from baseline.eval.bdrate import bd_rate
    from baseline.eval.report import seed_mean_points

    res = seeded_results()
    bd = {b["seed"]: b for b in compute_bd(res)}
    assert set(bd) == {0, 1, "mean"}
    assert bd[0]["bd_rate"] == pytest.approx(-20.0, abs=1e-4)
    assert bd[1]["bd_rate"] == pytest.approx(-10.0, abs=1e-4)
    base = seed_mean_points(res, "baseline")
    pgs = seed_mean_points(res, "predict-gs")
    assert [p["lmbda"] for p in base] == LAMBDAS and all(p["n"] == 2 for p in base)
    # the mean curve from the hand means of the runs
    def hand(method):
        pts = []
        for lm in LAMBDAS:
            rs = [r for r in res["runs"] if r["method"] == method and r["lmbda"] == lm]
            pts.append((sum(r["mb"] for r in rs) / 2, sum(r["psnr"] for r in rs) / 2))
        return pts
    hb, hp = hand("baseline"), hand("predict-gs")
    assert [p["psnr"] for p in pgs] == pytest.approx([y for _, y in hp])
    assert bd["mean"]["bd_rate"] == pytest.approx(
        bd_rate([x for x, _ in hb], [y for _, y in hb], [x for x, _ in hp], [y for _, y in hp]))
    assert base[0]["psnr_max"] - base[0]["psnr_min"] == pytest.approx(0.1)
    # a row is paired with the baseline run of its own seed
    row = next(r for r in res["runs"] if r["method"] == "predict-gs" and r["seed"] == 1)
    assert baseline_partner(res, row)["seed"] == 1
    # one section table per (lambda, seed)
    assert len(rate_points(res)) == 6 and all(len(p) == 2 for p in rate_points(res))
    text = format_report(res)
    assert "Seed mean and spread" in text and "seed-mean curves" in text
    assert "0.004 s1" in text
    paths = write_report(res, tmp_path)
    assert (tmp_path / "rd.png").stat().st_size > 1000 and paths["report"].exists()


def test_a_lambda_missing_a_seed_stays_off_the_mean_curve():
    from baseline.eval.report import seed_mean_points

    res = seeded_results()
    res["runs"] = [r for r in res["runs"] if not (r["lmbda"] == 0.004 and r["seed"] == 1)]
    assert [p["lmbda"] for p in seed_mean_points(res, "baseline")] == LAMBDAS[:2]
    bd = {b["seed"]: b for b in compute_bd(res)}
    assert bd["mean"]["bd_rate"] is None and "needs >= 3" in bd["mean"]["note"]
    assert bd[0]["bd_rate"] == pytest.approx(-20.0, abs=1e-4)


def test_survey_csvs_one_per_method_and_scene_and_the_runs_table(tmp_path):
    """The survey's layout: one file per method and scene (``survey/<method>/<Dataset>/<scene>.csv``,
    a method's folder as the survey reads its ``results/``), its points highest rate first, the
    ends named <method>-highrate / -lowrate and the others unnamed (the survey shows at most two
    named submethods), seed means with seeds; SSIM only in the field's convention.
    results.csv holds every run, one row each, SSIM with its convention."""
    import csv

    from baseline.eval.report import method_label

    for res in (stored_results(), seeded_results()):
        for i, r in enumerate(res["runs"]):
            r["masks_on"] = {"on": 1000 + i, "total": 5000}
        out = tmp_path / str(len(res["runs"]))
        paths = write_report(res, out, plots=False)
        with open(paths["csv"], newline="") as f:
            rows = list(csv.DictReader(f))
        assert len(rows) == len(res["runs"])
        for r in res["runs"]:
            x = next(x for x in rows if x["Method"] == method_label(r["method"])
                     and float(x["lambda"]) == r["lmbda"]
                     and x["seed"] == ("" if r.get("seed") is None else str(r["seed"])))
            assert float(x["PSNR"]) == pytest.approx(r["psnr"], abs=1e-6)
            assert float(x["SSIM"]) == r["ssim"] and x["SSIM convention"] == "3dgs"
            assert int(x["Size [Bytes]"]) == r["bytes"] and x["LPIPS"] == ""
        seeded = bool(res.get("seeds"))
        for m in sorted({r["method"] for r in res["runs"]}):
            name = method_label(m)
            f = out / "survey" / name / "data" / "tandt_truck.csv"    # scene /data/tandt_truck
            assert f in paths.values()
            with open(f, newline="") as fh:
                srows = list(csv.DictReader(fh))
            assert list(srows[0]) == ["Submethod", "PSNR", "SSIM", "LPIPS", "Size [Bytes]",
                                      "#Gaussians"]
            assert [x["Submethod"] for x in srows] == [f"{name}-highrate", "", f"{name}-lowrate"]
            rs = sorted((r for r in res["runs"] if r["method"] == m), key=lambda r: r["lmbda"])
            for x, lm in zip(srows, sorted({r["lmbda"] for r in rs})):
                pts = [r for r in rs if r["lmbda"] == lm]
                assert float(x["PSNR"]) == pytest.approx(sum(r["psnr"] for r in pts) / len(pts),
                                                         abs=1e-6)
                assert float(x["Size [Bytes]"]) == pytest.approx(
                    sum(r["bytes"] for r in pts) / len(pts))
                assert float(x["#Gaussians"]) == pytest.approx(
                    sum(r["masks_on"]["on"] for r in pts) / len(pts))
                assert x["LPIPS"] == "" and float(x["SSIM"]) == 0.9
                assert ("." in x["Size [Bytes]"]) == seeded           # a mean of seeds
        assert "survey/<method>/data/tandt_truck.csv" in paths["report"].read_text()
    # a protocol patch names the survey's dataset folder; a record measured with
    # scikit-image's SSIM leaves the survey's SSIM empty
    res = stored_results()
    res["common_patches"] = ["tandt", "cpu"]
    for r in res["runs"]:
        r["ssim_convention"] = "skimage"
    write_report(res, tmp_path / "tandt", plots=False)
    with open(tmp_path / "tandt" / "survey" / "HAC" / "TanksAndTemples" / "tandt_truck.csv") as fh:
        assert {x["SSIM"] for x in csv.DictReader(fh)} == {""}


def test_report_names_the_ssim_convention_of_every_figure():
    """Records measured before the field's SSIM was kept hold scikit-image's: the report says
    which convention its SSIM is and marks the rows of the other, never mixing them unmarked,
    and a seed mean over two conventions is no number."""
    from baseline.eval.report import quality_table, seed_mean_points, ssim_note
    res = stored_results()
    assert "3DGS's (11x11 Gaussian window" in ssim_note(res)
    old = [r for r in res["runs"] if r["method"] == "baseline"]
    for r in old:
        r["ssim_convention"] = "skimage"
    t = quality_table(res)
    cells = {(row[0], row[1]): row[4] for row in t.rows}
    assert cells[("HAC", "0.002")] == "0.9000 (skimage)"
    assert cells[("Predict-GS", "0.002")] == "0.9000"
    note = next(n for n in t.notes if n.startswith("SSIM:"))
    assert "3DGS's" in note and "(skimage)" in note and "scikit-image's" in note
    seeded = seeded_results()
    seeded["runs"][0]["ssim_convention"] = "skimage"
    m, lm = seeded["runs"][0]["method"], seeded["runs"][0]["lmbda"]
    pt = next(p for p in seed_mean_points(seeded, m) if p["lmbda"] == lm)
    assert pt["ssim"] is None and pt["psnr"] is not None


def _census(gaussians, kept, coarse, refiner, sweep):
    return {"views": 25, "k": 10, "refiner": refiner, "visible_anchors": 50000.0,
            "mask_on_share": 1.0, "gaussians": gaussians, "kept_share": kept,
            "kept_share_coarse": coarse, "revived_share": 0.01 if refiner else 0.0,
            "removed_share": 0.02 if refiner else 0.0,
            "kept_per_anchor": [10, 0, 60, 20, 10, 0, 0, 0, 0, 0, 0],
            "pattern": {"anchors": 50000, "equal_nn": 0.5, "equal_random": 0.25,
                        "hamming_nn": 0.1, "hamming_random": 0.2},
            "pattern_coarse": None, "by_birth": {"initial": {"mask_on": 10, "kept": 3, "kept_share": 0.3},
                                                 "grown": {"mask_on": 10, "kept": 2, "kept_share": 0.2}},
            "psnr_coarse": None,
            "sweep": [{"threshold": t, "gaussians": g, "psnr": p} for t, g, p in sweep]}


def test_census_table_cuts_each_run_to_its_baselines_count():
    """The census table: kept shares, anchors by drawn count, patterns, births, and the PSNR a
    run keeps when cut to the baseline's Gaussians per view (interpolated in its sweep)."""
    res = stored_results()
    assert "Gaussian census" not in format_report(res)
    for r in res["runs"]:
        if r["method"] == "baseline":
            r["census"] = _census(40000.0, 0.2, 0.2, False, [(0.0, 40000.0, 27.0), (0.1, 30000.0, 26.0)])
        elif r["method"] == "predict-gs":
            r["census"] = _census(60000.0, 0.3, 0.32, True,
                                  [(0.0, 60000.0, 27.5), (0.05, 50000.0, 27.3), (0.1, 30000.0, 26.1)])
    txt = format_report(res)
    rows = _rows_of(txt, "Gaussian census")
    by = {(r[0], r[1]): r for r in rows}
    assert by[("HAC", "0.004")][2:7] == ["40000", "20.0%", "-", "-", "10.0%"]
    p = by[("Predict-GS", "0.004")]
    assert p[2:5] == ["60000", "30.0%", "32.0%"]
    # 40000 lies halfway between the sweep's 50000 (27.3 dB) and 30000 (26.1 dB): 26.7 dB
    assert p[-2:] == ["26.700", "(-0.800)"]
    assert "not shown (records archived before the census was kept)" in txt


def test_method_labels_are_the_names_users_know():
    """Tables, legends and CSVs name methods as users do; run ids stay as they are."""
    from baseline.eval.report import method_label

    assert method_label("baseline") == "HAC"
    assert method_label("predict-gs") == "Predict-GS"
    assert method_label("predict-gs+masks-lr-scaled") == "Predict-GS+masks-lr-scaled"
    assert method_label("masks-lr-scaled") == "HAC+masks-lr-scaled"
    assert method_label("baseline", ["cpu", "hacpp"]) == "HAC++"
    assert method_label("predict-gs", ["cpu", "hacpp"]) == "Predict-GS"
    assert method_label("scaffold") == "Scaffold-GS"
    res = stored_results()
    txt = format_report(res, markdown=True)
    assert "| HAC | 0.004 |" in txt and "| Predict-GS | 0.004 |" in txt
    assert "| baseline |" not in txt and "| predict-gs |" not in txt
    from baseline.eval.report import survey_rows
    assert {survey_rows(res, m)[0]["Submethod"] for m in
            ("baseline", "predict-gs", "entropy-factorized")} == {
        "HAC-highrate", "Predict-GS-highrate", "HAC+entropy-factorized-highrate"}


def test_verdict_spells_out_who_wins_by_how_much():
    res = stored_results()
    res["fps_pair"] = {"predict-gs": {"ratio": 0.8, "rounds": 3, "lmbda": 0.002, "fps": 40.0,
                                      "fps_ref": 50.0, "threads": 1}}
    res["scope"] = "the synthetic scene: not a claim about real scenes"
    v = verdict_lines(res)
    txt = "\n".join(v)
    # Predict-GS is 0.8x the bytes at the same PSNR at every lambda: BD-rate -20%
    assert "Predict-GS is 20.0% smaller than HAC at equal quality (BD-rate -20.00%, one seed)" in txt
    assert "lambda 0.004: 20.0% smaller, the same PSNR" in txt
    assert "lambda 0.002: the same size, 0.500 dB lower PSNR" in txt
    assert "HAC+entropy-factorized is 0.500 dB worse than HAC at equal size" in txt
    assert "Predict-GS renders at 0.80x HAC's FPS (slower" in txt
    assert "trains in 1.00x HAC's time" in txt and v[-1] == res["scope"]
    md = format_report(res, markdown=True)
    assert md.index("### Verdict") < md.index("Quality and size")


def test_verdict_opens_with_a_table_whose_ratios_are_their_values_ratios():
    """One row per contender and reference: BD-rate, BD-PSNR, size and PSNR change at each
    shared lambda, the FPS ratio and the training-time ratio, each beside the two values it is
    computed from (a recorded FPS 'ratio' that is the median of per-round ratios is not used:
    0.99x beside 28.2 vs 30.6 FPS contradicts itself); the caveats follow the table."""
    from baseline.eval.report import verdict_table
    res = stored_results()
    by = {(r["method"], r["lmbda"]): r for r in res["runs"]}
    for lm, t in zip(LAMBDAS, (1000.0, 2000.0, 4000.0)):
        by[("baseline", lm)]["train_time_s"] = t
        by[("predict-gs", lm)]["train_time_s"] = 1.5 * t
    res["fps_pair"] = {"predict-gs": {"ratio": 0.99, "rounds": 3, "lmbda": 0.002, "fps": 28.2,
                                      "fps_ref": 30.6, "threads": 1}}
    t = verdict_table(res)
    assert t.headers == ["contender", "against", "BD-rate", "BD-PSNR",
                         "lambda 0.0005: size / PSNR", "lambda 0.002: size / PSNR",
                         "lambda 0.004: size / PSNR", "FPS ratio", "training-time ratio"]
    rows = {r[0]: r for r in t.rows}
    assert rows["Predict-GS"][:4] == ["Predict-GS", "HAC", "-20.0%", rows["Predict-GS"][3]]
    assert rows["Predict-GS"][6] == "-20.0% / +0.000 dB"
    assert rows["Predict-GS"][7] == f"{28.2 / 30.6:.2f}x (28.2 / 30.6 FPS)" == "0.92x (28.2 / 30.6 FPS)"
    assert rows["Predict-GS"][8] == "1.50x (3500 / 2333 s)"      # means per run
    assert rows["HAC+entropy-factorized"][5] == "+0.0% / -0.500 dB"
    assert rows["HAC+entropy-factorized"][7] == "-"            # no paired FPS measured
    txt = "\n".join(verdict_lines(res))
    assert "renders at 0.92x HAC's FPS" in txt and "28.2 vs 30.6 FPS" in txt
    md = format_report(res, markdown=True)
    head = md.split("### Verdict", 1)[1].split("###", 1)[0]
    assert head.index("| contender |") < head.index("Caveats and readings:") \
        < head.index("Predict-GS is 20.0% smaller")
    assert format_report(res).rstrip().endswith(verdict_lines(res)[-1])   # terminal: last


def test_the_stall_rule_has_an_absolute_floor():
    """A short run on a quiet machine stalls a few seconds of its start-up (a 100 s demo run:
    6 s, 6%): flagged only past both 5% and 30 s."""
    from baseline.eval.report import STALL_FLOOR_S, stalled
    assert STALL_FLOOR_S == 30.0
    assert not stalled({"train_time_s": 100.0, "stall_s": 6.0})
    assert not stalled({"train_time_s": 100.0, "stall_s": 29.0})
    assert stalled({"train_time_s": 100.0, "stall_s": 31.0})
    assert not stalled({"train_time_s": 5000.0, "stall_s": 200.0})      # 4%
    assert stalled({"train_time_s": 5000.0, "stall_s": 300.0})


def test_training_time_ratio_pairs_runs_of_one_rate_point_and_one_thread_count():
    from baseline.eval.report import train_time_pairs
    res = stored_results()
    by = {(r["method"], r["lmbda"]): r for r in res["runs"]}
    for lm, t in zip(LAMBDAS, (1000.0, 2000.0, 4000.0)):
        by[("baseline", lm)]["train_time_s"] = t
        by[("predict-gs", lm)]["train_time_s"] = 1.5 * t
    # one Predict-GS run resumed at another thread count, one trained at another count: neither
    # compares, and the ratio is over the remaining pair alone
    slow = by[("predict-gs", LAMBDAS[0])]
    slow["threads_by_iteration"] = [[0, 1], [500, 2]]
    slow["train_time_s"] = 99999.0
    by[("predict-gs", LAMBDAS[1])]["threads"] = 1
    pairs, left = train_time_pairs(res, "predict-gs", "baseline")
    assert [(r["lmbda"], b["lmbda"]) for r, b in pairs] == [(LAMBDAS[2], LAMBDAS[2])]
    assert sorted(r["lmbda"] for r, _ in left) == sorted(LAMBDAS[:2])
    # a rate point the baseline has no run at is neither paired nor left out
    extra = dict(by[("predict-gs", LAMBDAS[2])], lmbda=0.008)
    pairs2, left2 = train_time_pairs(dict(res, runs=res["runs"] + [extra]), "predict-gs",
                                     "baseline")
    assert len(pairs2) == 1 and len(left2) == 2
    line = next(x for x in verdict_lines(res) if x.startswith("Predict-GS trains"))
    assert line.startswith("Predict-GS trains in 1.50x HAC's time (6000 s vs 4000 s per run; "
                           "1 pair(s) at the same rate point, 2 thread(s) each; left out: ")
    assert f"{LAMBDAS[1]:g} (1 thread(s) against 2)" in line
    assert f"{LAMBDAS[0]:g} (its thread count changed on a resume or is unrecorded)" in line
    # a record with the one count it kept all along still pairs; no pair at all: said so
    slow["threads_by_iteration"] = [[0, 2]]
    assert len(train_time_pairs(res, "predict-gs", "baseline")[0]) == 2
    for r in res["runs"]:
        if r["method"] == "baseline":
            r["threads"] = None
    v = verdict_lines(res)
    assert "Predict-GS's training time compares with no HAC run" in "\n".join(v)
    assert not any(x.startswith("Predict-GS trains") for x in v)


def test_a_stalled_or_marked_training_time_is_named_and_left_out_of_the_ratio():
    """A run whose training time holds more than 5% in which it ran on no core (paused, or
    sharing its core), or whose record is marked untimed (a pause it could not record), neither
    enters the verdict's ratio nor passes unmarked in the speed table; 1% (a healthy run beside
    another) does not count."""
    from baseline.eval.report import speed_table, train_time_pairs, untimed
    res = stored_results()
    by = {(r["method"], r["lmbda"]): r for r in res["runs"]}
    for lm, t in zip(LAMBDAS, (1000.0, 2000.0, 4000.0)):
        by[("baseline", lm)].update(train_time_s=t, stall_s=0.01 * t)
        by[("predict-gs", lm)].update(train_time_s=1.5 * t, stall_s=0.01 * t)
    assert len(train_time_pairs(res, "predict-gs", "baseline")[0]) == 3
    assert not any(n.startswith("Train time not") for n in speed_table(res).notes)
    assert untimed(by[("baseline", LAMBDAS[0])]) is None
    by[("predict-gs", LAMBDAS[0])].update(stall_s=840.0, stall_from=3343)
    by[("baseline", LAMBDAS[1])]["stall_s"] = 200.0
    pairs, left = train_time_pairs(res, "predict-gs", "baseline")
    assert [r["lmbda"] for r, _ in pairs] == [LAMBDAS[2]]
    why = {r["lmbda"]: w for r, w in left}
    assert why[LAMBDAS[0]] == "840 s (56%, counted from iteration 3343) stalled"
    assert why[LAMBDAS[1]] == "the baseline run: 200 s (10%) stalled"
    note = next(n for n in speed_table(res).notes if n.startswith("Train time not"))
    assert f"Predict-GS {LAMBDAS[0]:g}: 840 s (56%, counted from iteration 3343) stalled" in note
    assert f"HAC {LAMBDAS[1]:g}: 200 s (10%) stalled" in note
    line = next(x for x in verdict_lines(res) if x.startswith("Predict-GS trains"))
    assert "1 pair(s)" in line and "the baseline run: 200 s (10%) stalled" in line
    # a marked record (its stall share unrecorded or low) is left out with its reason
    by[("predict-gs", LAMBDAS[2])].update(stall_s=None, untimed="paused 14 min")
    pairs, left = train_time_pairs(res, "predict-gs", "baseline")
    assert pairs == [] and dict((r["lmbda"], w) for r, w in left)[LAMBDAS[2]] == "paused 14 min"
    assert f"Predict-GS {LAMBDAS[2]:g}: paused 14 min" in next(
        n for n in speed_table(res).notes if n.startswith("Train time not"))
    assert any(x.startswith("Predict-GS's training time compares with no HAC run")
               for x in verdict_lines(res))


def test_training_times_of_two_machines_make_no_ratio():
    """Two runs' training times compare only when their records name the same machine (a
    record that names none, from before machines were kept, pairs as before); the protocol
    lists each method's machine."""
    from baseline.eval.report import protocol_lines, train_time_pairs
    res = stored_results()
    by = {(r["method"], r["lmbda"]): r for r in res["runs"]}
    for lm, t in zip(LAMBDAS, (1000.0, 2000.0, 4000.0)):
        by[("baseline", lm)].update(train_time_s=t, machine="AMD EPYC 7B13 (2 CPUs)")
        by[("predict-gs", lm)].update(train_time_s=1.5 * t, machine="AMD EPYC 7B13 (2 CPUs)")
    assert len(train_time_pairs(res, "predict-gs", "baseline")[0]) == 3
    by[("predict-gs", LAMBDAS[0])]["machine"] = "Intel(R) Xeon(R) Processor (2 CPUs)"
    del by[("predict-gs", LAMBDAS[1])]["machine"]
    pairs, left = train_time_pairs(res, "predict-gs", "baseline")
    assert sorted(r["lmbda"] for r, _ in pairs) == sorted(LAMBDAS[1:])
    assert left == [(by[("predict-gs", LAMBDAS[0])],
                     "trained on Intel(R) Xeon(R) Processor (2 CPUs), the baseline run on "
                     "AMD EPYC 7B13 (2 CPUs)")]
    machine = dict(protocol_lines(res))["machine"]
    assert "Intel(R) Xeon(R) Processor (2 CPUs) (Predict-GS" in machine
    assert f"- (Predict-GS {LAMBDAS[1]:g}, " in machine


def test_training_times_of_two_codes_make_no_ratio():
    """Two runs' training times compare only when their records name the same code (a
    same-numbers speed-up changes no result, only the time): a record from before codes were
    kept pairs only with another such record; the protocol lists each method's code."""
    from baseline.eval.report import protocol_lines, train_time_pairs
    res = stored_results()
    by = {(r["method"], r["lmbda"]): r for r in res["runs"]}
    for lm, t in zip(LAMBDAS, (1000.0, 2000.0, 4000.0)):
        by[("baseline", lm)].update(train_time_s=t, code="0123456789ab")
        by[("predict-gs", lm)].update(train_time_s=1.5 * t, code="0123456789ab")
    assert len(train_time_pairs(res, "predict-gs", "baseline")[0]) == 3
    by[("predict-gs", LAMBDAS[0])]["code"] = "ba9876543210+modified"
    del by[("predict-gs", LAMBDAS[1])]["code"]
    pairs, left = train_time_pairs(res, "predict-gs", "baseline")
    assert [r["lmbda"] for r, _ in pairs] == [LAMBDAS[2]]
    assert sorted(why for _, why in left) == [
        "trained by code ba9876543210+modified, the baseline run by 0123456789ab",
        "trained by code unrecorded, the baseline run by 0123456789ab"]
    code = dict(protocol_lines(res))["code"]
    assert "ba9876543210+modified (Predict-GS" in code and "0123456789ab (HAC" in code


def test_pgs_train_names_a_stalled_training_time(capsys):
    from baseline.cli import _print_results
    run = {"iterations": 10, "train_time_s": 100.0, "s_per_it": 10.0, "threads": 1, "anchors": 5}
    run["train_time_s"] = 400.0
    for stall, named in ((40.0, True), (1.0, False), (None, False)):
        _print_results(dict(run, **({} if stall is None else {"stall_s": stall})))
        out = capsys.readouterr().out
        assert ("40.0 s of it stalled: paused or sharing its core" in out) == named, out
    _print_results(dict(run, machine="AMD EPYC 7B13 (2 CPUs)"))
    assert "1 threads on AMD EPYC 7B13 (2 CPUs)" in capsys.readouterr().out


def test_a_thin_psnr_overlap_is_shown_and_named_in_the_verdict():
    res = stored_results()
    full = {b["method"]: b for b in compute_bd(res)}["predict-gs"]
    assert full["psnr_overlap"] == pytest.approx([25.1, 27.0, 1.0])
    assert not any("thin overlap" in line for line in verdict_lines(res))
    # the contender's curve shifted up until it meets the baseline's over 0.3 of 1.9 dB
    for r in res["runs"]:
        if r["method"] == "predict-gs":
            r["psnr"] += 1.6
    b = {b["method"]: b for b in compute_bd(res)}["predict-gs"]
    assert b["bd_rate"] is not None
    assert b["psnr_overlap"] == pytest.approx([26.7, 27.0, 0.3 / 1.9])
    line = next(l for l in verdict_lines(res) if l.startswith("Predict-GS is"))
    assert "thin overlap" in line and "26.70-27.00 dB" in line
    assert "(16%, thin)" in format_report(res)


def test_a_curve_that_does_not_rise_with_size_is_named():
    res = stored_results()
    assert not any(b["non_monotone"] for b in compute_bd(res))
    low = next(r for r in res["runs"] if r["method"] == "baseline" and r["lmbda"] == 0.002)
    low["psnr"] = 25.0                       # more bytes than the 0.004 point, less PSNR
    b = {b["method"]: b for b in compute_bd(res)}["predict-gs"]
    assert b["non_monotone"] and "baseline's curve does not rise" in b["note"]
    assert "25.000 dB" in b["note"]
    line = next(l for l in verdict_lines(res) if l.startswith("Predict-GS"))
    assert "does not rise with size" in line


def test_methods_with_rate_points_of_their_own():
    """``--lambda-for``: the baseline has a point at a lambda the contender lacks and the other
    way round; each curve uses all of its points, equal-lambda pairs only the shared ones."""
    from baseline.eval.report import seed_mean_points

    res = seeded_results()
    extra = []
    for r in res["runs"]:
        if r["lmbda"] == 0.004 and r["method"] == "baseline":        # a lower-rate HAC point
            q = dict(r, lmbda=0.008, psnr=r["psnr"] - 1.0, bytes=int(r["bytes"] * 0.8))
        elif r["lmbda"] == 0.0005 and r["method"] == "predict-gs":   # a higher-rate one
            q = dict(r, lmbda=0.0002, psnr=r["psnr"] + 0.5, bytes=int(r["bytes"] * 1.3))
        else:
            continue
        q["mb"] = q["bytes"] / MB
        extra.append(q)
    res["runs"] += extra
    assert [p["lmbda"] for p in seed_mean_points(res, "baseline")] == [0.0005, 0.002, 0.004, 0.008]
    assert [p["lmbda"] for p in seed_mean_points(res, "predict-gs")] == [0.0002] + LAMBDAS
    bd = {b["seed"]: b for b in compute_bd(res)}
    assert all(bd[k]["points"] == 4 and bd[k]["baseline_points"] == 4 for k in (0, 1, "mean"))
    # the shared stretch is still 0.8x / 0.9x at equal PSNR; an extra point beyond the other
    # curve only moves the end slopes of the piecewise cubic inside the overlap a little
    assert bd[0]["bd_rate"] == pytest.approx(-20.0, abs=0.3)
    assert bd[1]["bd_rate"] == pytest.approx(-10.0, abs=0.3)
    lines = " ".join(verdict_lines(res))
    assert "lambda 0.0005" in lines and "lambda 0.008" not in lines and "lambda 0.0002" not in lines
    # one section table per (lambda, seed): the unshared points hold one method's run
    pts = rate_points(res)
    assert len(pts) == 10 and sorted(len(p) for p in pts) == [1] * 4 + [2] * 6
    row = next(r for r in res["runs"] if r["lmbda"] == 0.0002)
    assert baseline_partner(res, row) is None
    text = format_report(res)
    assert "0.008 s1" in text and "0.0002 s0" in text


def test_a_method_is_also_measured_against_each_contender_it_extends(tmp_path):
    """Predict-GS+HAC++ extends Predict-GS and HAC++: besides the baseline, the report gives its
    BD-rate against each (what HAC++'s coding adds to Predict-GS, what Predict-GS adds on HAC++'s
    coding); HAC++ and Predict-GS extend no contender and are measured against HAC only."""
    base_psnr, base_bytes = [27.0, 26.2, 25.1], [10 * MB, 7 * MB, 5 * MB]
    scale = {"baseline": 1.0, "predict-gs": 0.8, "hacpp": 0.7, "predict-gs+hacpp": 0.63}
    runs = []
    for lm, p, b in zip(LAMBDAS, base_psnr, base_bytes):
        for m, k in scale.items():
            tot = int(k * b)
            runs.append(_row(m, lm, p, tot // 2, tot - tot // 2))
    res = stored_results()
    res["methods"] = [{"name": m, "patches": [] if m == "baseline" else m.split("+")}
                      for m in scale]
    res["runs"] = runs
    bd = {(b["method"], b["against"]): b for b in compute_bd(res)}
    assert set(bd) == {("predict-gs", "baseline"), ("hacpp", "baseline"),
                       ("predict-gs+hacpp", "baseline"), ("predict-gs+hacpp", "predict-gs"),
                       ("predict-gs+hacpp", "hacpp")}
    assert bd[("hacpp", "baseline")]["bd_rate"] == pytest.approx(-30.0, abs=1e-3)
    assert bd[("predict-gs+hacpp", "baseline")]["bd_rate"] == pytest.approx(-37.0, abs=1e-3)
    assert bd[("predict-gs+hacpp", "hacpp")]["bd_rate"] == pytest.approx(-10.0, abs=1e-3)
    assert bd[("predict-gs+hacpp", "predict-gs")]["bd_rate"] == pytest.approx(-21.25, abs=1e-3)
    # without the methods list the runs' records name the patches; a method known by neither
    # extends nothing and is extended by nothing
    bare = dict(res, methods=[])
    assert {(b["method"], b["against"]) for b in compute_bd(bare)} == set(bd)
    bare["runs"] = [dict(r) for r in runs]
    for r in bare["runs"]:
        if r["method"] == "hacpp":
            del r["method_patches"]
    assert {(b["method"], b["against"]) for b in compute_bd(bare)} == set(bd) - {
        ("predict-gs+hacpp", "hacpp")}
    lines = verdict_lines(res)
    assert any(l.startswith("Predict-GS+HAC++ is 10.0% smaller than HAC++ at equal quality")
               for l in lines)
    assert any(l.startswith("Predict-GS+HAC++ is 21.2% smaller than Predict-GS") for l in lines)
    assert not any(l.startswith("HAC++ is") and "than Predict-GS" in l for l in lines)
    text = format_report(res)
    assert "and the methods each extends" in text and "against" in text
    # records written before references were named: every item is against the baseline
    old = dict(res, bd=[{k: v for k, v in b.items() if k != "against"}
                        for b in compute_bd(res) if b["against"] == "baseline"])
    assert "and the methods each extends" not in format_report(old)
    write_report(res, tmp_path, plots=False)
    assert "smaller than HAC++" in (tmp_path / "report.md").read_text()


def test_a_comparison_of_one_named_seed_says_one_seed():
    res = seeded_results()
    res["runs"] = [r for r in res["runs"] if r["seed"] == 1]
    res["seeds"] = [1]
    txt = " ".join(verdict_lines(res))
    assert "(BD-rate -10.00%, one seed (1))" in txt and "curves of 1 seeds" not in txt
    # its per-run table claims no spread: no bracketed zeros, a title that says so
    from baseline.eval.report import seed_table

    tab = seed_table(res)
    assert tab.title == "Per run (one seed (1): no spread measured)"
    assert not any("(" in cell for row in tab.rows for cell in row[3:])
    assert "Seed mean and spread" not in format_report(res)
    # and one BD row per pair, named by its seed (not a seed row beside an equal mean row)
    from baseline.eval.report import bd_table

    bt = bd_table(res)
    assert [r[1] for r in bt.rows] == ["seed 1"] and "no spread measured" in " ".join(bt.notes)


def test_each_point_is_read_against_the_other_curves():
    """Predict-GS has 0.8x the baseline's bytes at the baseline's PSNRs: at each point's PSNR the
    baseline's curve needs 1/0.8 its size (-20%), and the baseline's points read +25% against
    Predict-GS's curve; a point outside a curve reads '-'."""
    import math

    from baseline.eval.report import point_readings, point_table

    res = stored_results()
    pr = {it["lmbda"]: it for it in point_readings(res, "predict-gs", "baseline")}
    for lm in LAMBDAS:
        assert pr[lm]["size_change"] == pytest.approx(-20.0, abs=1e-4)
    # PSNR at equal size, by hand: 0.002's 5.6 MB lies between the baseline's 5 MB and 7 MB
    u = math.log(0.8 * 7 / 5) / math.log(7 / 5)
    assert pr[0.002]["psnr_change"] == pytest.approx(26.2 - (25.1 + u * 1.1), abs=1e-5)
    assert pr[0.004]["ref_psnr"] is None and pr[0.004]["psnr_change"] is None   # 4 MB < 5 MB
    back = {it["lmbda"]: it for it in point_readings(res, "baseline", "predict-gs")}
    assert back[0.002]["size_change"] == pytest.approx(25.0, abs=1e-4)
    tab = point_table(res)
    assert tab is not None and "-20.0%" in tab.text() and "+25.0%" in tab.text()
    assert "Each rate point against the other curves" in format_report(res)


def test_a_curve_too_short_for_a_bd_rate_is_read_point_by_point():
    res = stored_results()
    res["runs"] = [r for r in res["runs"]
                   if not (r["method"] == "predict-gs" and r["lmbda"] == 0.004)]
    txt = "\n".join(verdict_lines(res))
    assert "Predict-GS vs HAC: no BD-rate" in txt
    line = [ln for ln in txt.splitlines() if "point by point against HAC's curve" in ln]
    assert len(line) == 1 and "lambda 0.002 20.0% smaller at equal PSNR" in line[0]
    assert "lambda 0.0005 20.0% smaller at equal PSNR" in line[0]


def test_points_outside_every_curve_make_no_point_table():
    from baseline.eval.report import point_table

    res = stored_results()
    res["runs"] = [r for r in res["runs"] if r["lmbda"] == 0.004]     # one point per method
    assert point_table(res) is None
    assert "Each rate point against" not in format_report(res)


def test_bd_rate_and_bd_psnr_of_opposite_verdicts_are_named():
    """Fewer bytes at equal PSNR but less PSNR at equal size: the deltas contradict each other
    (curves that cross or run through noise), and the verdict and the BD table say so."""
    from baseline.eval.report import bd_table

    res = stored_results()
    res["bd"] = [{"method": "predict-gs", "against": "baseline", "seed": None, "points": 3,
                  "baseline_points": 3, "bd_rate": -31.8, "bd_psnr": -0.121, "note": "",
                  "psnr_overlap": [26.27, 26.44, 0.5], "non_monotone": False}]
    txt = "\n".join(verdict_lines(res))
    assert "31.8% smaller than HAC at equal quality" in txt and "disagree in sign" in txt
    assert "disagree in sign" in " ".join(bd_table(res).notes)
    res["bd"][0]["bd_psnr"] = 0.121                        # agreeing signs: no such caveat
    assert "disagree in sign" not in "\n".join(verdict_lines(res))
