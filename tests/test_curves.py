"""The training-curve summary of a run (baseline.eval.report.curves) and its report table."""
import json

import pytest

from baseline.eval.report.curves import summarize, train_curve


def _log(its, bits_from=None):
    """Log lines every 10 iterations: l1 = it / 1000, bits once ``it > bits_from``."""
    out = []
    for it in its:
        d = {"it": it, "l1": it / 1000.0, "gaussians": 2 * it, "anchors": it + 1}
        if bits_from is not None and it > bits_from:
            d["bpp"] = 3.0
        out.append(d)
    return out


def test_summarize_windows_the_schedule():
    s = summarize(_log(range(10, 601, 10), bits_from=400), iterations=600)
    assert s["bounds"] == [0, 100, 200, 300, 400, 500, 600]
    # window 1 holds it 10..100: mean l1 = mean(10..100 step 10) / 1000 = 0.055
    assert s["l1"][0] == pytest.approx(0.055)
    assert s["l1"][-1] == pytest.approx(0.555)
    assert s["bits_per_value"] == [None, None, None, None, 3.0, 3.0]
    assert s["anchors"] == [101, 201, 301, 401, 501, 601]
    assert s["gaussians"][2] == pytest.approx(2 * 255.0)


def test_summarize_marks_empty_windows_and_defaults_to_the_last_iteration():
    s = summarize(_log([10, 20, 290, 300]), windows=3)
    assert s["iterations"] == 300 and s["bounds"] == [0, 100, 200, 300]
    assert s["l1"][1] is None and s["anchors"][1] is None and s["gaussians"][1] is None
    assert summarize([]) is None
    with pytest.raises(ValueError, match="windows"):
        summarize(_log([10]), windows=0)


def test_train_curve_reads_the_log_up_to_a_torn_line(tmp_path):
    assert train_curve(tmp_path) is None                    # no log: no curve
    lines = [json.dumps(d) for d in _log(range(10, 61, 10))]
    (tmp_path / "train_log.jsonl").write_text("\n".join(lines[:3]) + '\n{"it": 40, "l1' + "\n"
                                              + "\n".join(lines[4:]) + "\n")
    c = train_curve(tmp_path, iterations=60, windows=2)
    assert c["l1"] == [pytest.approx(0.02), None]          # only it 10..30 before the torn line


def test_curve_table_gives_each_span_beside_the_baselines():
    from baseline.eval.report import format_report
    from tests.test_report import _rows_of, _with_counts, stored_results

    res = _with_counts(stored_results())
    assert "Training curves" not in format_report(res)
    for r in res["runs"]:
        if r["method"] == "entropy-factorized":
            continue
        pgs = r["method"] == "predict-gs"
        l1 = [0.06, 0.05, 0.04, 0.035, 0.03, 0.025]
        r["train_curve"] = {"iterations": 600, "bounds": [0, 100, 200, 300, 400, 500, 600],
                            "l1": [v * (1.1 if pgs else 1.0) for v in l1],
                            "bits_per_value": [None, None, None, 2.0, 2.0, 2.0 if pgs else 1.5],
                            "gaussians": [1.0] * 6, "anchors": [1] * 6}
    txt = format_report(res)
    rows = {(r[0], r[1]): r for r in _rows_of(txt, "Training curves")}
    assert set(rows) == {("HAC", f"{lm:g}") for lm in (0.0005, 0.002, 0.004)} | \
        {("Predict-GS", f"{lm:g}") for lm in (0.0005, 0.002, 0.004)}
    assert rows[("HAC", "0.004")][2:] == ["0.0600", "0.0500", "0.0400", "0.0350", "0.0300",
                                         "0.0250", "120.0"]       # 1.5 bits x 80 values
    p = rows[("Predict-GS", "0.004")]
    assert p[2:4] == ["0.0660", "(+10.0%)"]
    # 2.0 bits x 55 coded values per anchor = 110 against HAC's 120
    assert p[-2:] == ["110.0", "(-8.3%)"]
    assert "L1 it 1-100" in txt
    assert "progressive training renders downsampled views" in txt    # a Predict-GS run is shown
    assert ("not shown (records archived before the training curve was kept): "
            "HAC+entropy-factorized") in txt


def _run_dir(path, its, iterations=60, l1_scale=1.0, attrs_dims=None):
    path.mkdir()
    (path / "config.toml").write_text(f"[train]\niterations = {iterations}\n")
    log = _log(its, bits_from=30)
    for d in log:
        d["l1"] *= l1_scale
    (path / "train_log.jsonl").write_text("".join(json.dumps(d) + "\n" for d in log))
    if attrs_dims:
        (path / "compare.json").write_text(json.dumps(
            {"encode": {"attributes": [{"dims": d} for d in attrs_dims]}}))
    return path


def test_pgs_curves_compares_runs_and_leaves_a_running_ones_later_spans_empty(tmp_path, capsys):
    from baseline.cli import main

    a = _run_dir(tmp_path / "a", range(10, 61, 10), attrs_dims=[50, 6, 30])
    b = _run_dir(tmp_path / "b", range(10, 41, 10), l1_scale=1.2)      # still training at it 40
    assert main(["curves", str(a), str(b), "--windows", "3"]) == 0
    out = capsys.readouterr().out
    assert "L1 it 1-20" in out and "L1 it 41-60" in out           # spans of the configured schedule
    l1_table = out.split("Anchors and Gaussians")[0]
    rows = {ln.split()[0]: ln.split()[1:] for ln in l1_table.splitlines() if ln.startswith(("a ", "b "))}
    assert rows["a"] == ["0.0150", "0.0350", "0.0550", "258.0"]     # 3 bits x 86 values
    assert rows["b"] == ["0.0180", "(+20.0%)", "0.0420", "(+20.0%)", "-", "-"]
    assert main(["curves", str(tmp_path)]) == 2                     # no log: a clear error
    assert "no training log" in capsys.readouterr().err


def test_summarize_over_given_span_ends():
    from baseline.eval.report.curves import span_bounds

    s = summarize(_log(range(10, 601, 10), bits_from=400), iterations=600, ends=[100, 400, 450])
    assert s["bounds"] == [0, 100, 400, 450] and s["iterations"] == 450
    assert s["l1"][1] == pytest.approx(0.255)                 # it 110..400
    assert s["anchors"] == [101, 401, 451]
    assert s["bits_per_value"] == [None, None, 3.0]
    for bad in ([], [0, 10], [20, 10], [10, 10]):
        with pytest.raises(ValueError, match="increasing"):
            span_bounds(bad)


def test_pgs_curves_at_span_ends_prints_growth_and_reads_an_archived_record(tmp_path, capsys):
    from baseline.cli import main

    a = _run_dir(tmp_path / "a", range(10, 61, 10), attrs_dims=[50, 6, 30])
    log = _log(range(10, 61, 10))
    for d in log:                       # counts in the thousands, as the table prints them
        d["anchors"], d["gaussians"] = 100 * d["it"] + 50, 200 * d["it"]
    (a / "train_log.jsonl").write_text("".join(json.dumps(d) + "\n" for d in log))
    assert main(["curves", str(a), "--at", "20", "60"]) == 0
    out = capsys.readouterr().out
    assert "L1 it 1-20" in out and "L1 it 21-60" in out and "Anchors and Gaussians" in out
    assert "it 1-20" in out.split("Anchors and Gaussians")[1]      # spans without "L1"
    row = [ln for ln in out.splitlines() if ln.startswith("a ")][-1].split()
    # anchors at it 20 (2,050) and 60 (6,050); Gaussians 200 x it, span means 3,000 and 9,000
    assert row[1:] == ["2.0k", "/", "3.0k", "6.0k", "/", "9.0k"]
    # an archived run: no log, its record's spans
    b = tmp_path / "b"
    b.mkdir()
    (b / "compare.json").write_text(json.dumps({"train_curve": {
        "iterations": 60, "bounds": [0, 30, 60], "l1": [0.5, 0.25], "bits_per_value": [None, 2.0],
        "gaussians": [1500.0, 2500.0], "anchors": [1200, 3400]}}))
    assert main(["curves", str(b), "--windows", "2"]) == 0
    out = capsys.readouterr().out
    assert "0.5000" in out and "1.2k / 1.5k" in out and "3.4k / 2.5k" in out
    assert main(["curves", str(b), "--at", "30", "60"]) == 0
    capsys.readouterr()
    assert main(["curves", str(b)]) == 2                     # 6 spans asked, 2 stored
    assert "holds only the spans ending at 30 60 (--windows 2)" in capsys.readouterr().err
    (b / "compare.json").write_text(json.dumps({"train_curve": {"bounds": [0, 30, 60], "l1": [0.5]}}))
    assert main(["curves", str(b), "--windows", "2"]) == 2   # a torn record: no curve
    assert "no training log" in capsys.readouterr().err
    assert main(["curves", str(a), "--at", "20", "10"]) == 2
    assert "increasing" in capsys.readouterr().err


def test_summarize_and_pgs_curves_split_the_anchor_count_into_grown_and_pruned(tmp_path, capsys):
    from baseline.cli import main

    log = _log(range(10, 61, 10))
    for d in log:                       # running counts: 1,000 grown and 200 pruned per 10 its
        d["grown"], d["pruned"] = 100 * d["it"], 20 * d["it"]
    s = summarize(log, iterations=60, ends=[20, 60])
    assert s["grown"] == [2000, 4000] and s["pruned"] == [400, 800]
    assert summarize(_log(range(10, 61, 10)), iterations=60, windows=2)["grown"] == [None, None]
    gap = summarize(log, iterations=90, windows=3)          # nothing logged in 61..90
    assert gap["grown"] == [3000, 3000, None]
    a = _run_dir(tmp_path / "a", range(10, 61, 10))
    (a / "train_log.jsonl").write_text("".join(json.dumps(d) + "\n" for d in log))
    b = _run_dir(tmp_path / "b", range(10, 61, 10))      # a log without the counts
    assert main(["curves", str(a), str(b), "--at", "20", "60"]) == 0
    table = capsys.readouterr().out.split("Growing and pruning")[1]
    rows = {ln.split()[0]: ln.split()[1:] for ln in table.splitlines() if ln.startswith(("a ", "b "))}
    assert rows["a"] == ["+2.0k", "/", "-0.4k", "+4.0k", "/", "-0.8k"]
    assert rows["b"] == ["-", "-"]
    assert main(["curves", str(b), "--at", "20", "60"]) == 0
    assert "Growing and pruning" not in capsys.readouterr().out
